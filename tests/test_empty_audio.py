"""Empty audio is a clear answer everywhere: `end` over the WebSocket, exit 2 with a message from the CLIs."""

import os
import sys
import wave

import numpy as np
from helpers import warm
from helpers.clients import REPO, live_server, run_client
import pytest


def empty_wav(path, samples=0):
    with wave.open(str(path), "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(16000)
        w.writeframes(np.zeros(samples, "<i2").tobytes())
    return path


@pytest.mark.timeout(120)
def test_python_client_with_an_empty_wav_gets_end(tmp_path, checkpoint):
    wav = empty_wav(tmp_path / "empty.wav")
    with live_server(tmp_path, "ws", checkpoint) as server:
        r = run_client("--url", server.ws_url, "--wav", str(wav), "--fast", timeout=60)  # used to hang forever
    assert "end:" in r.stdout and "received 0 frames" in r.stderr


@pytest.mark.parametrize("samples", [0, 100])
def test_generate_refuses_audio_shorter_than_a_frame(tmp_path, checkpoint, samples):
    wav, out = empty_wav(tmp_path / "short.wav", samples), tmp_path / "out.bvh"
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "generate", "--checkpoint", str(checkpoint),
                  "--audio", str(wav), "--out", str(out)], cwd=REPO, capture_output=True, text=True,
                 env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=120)
    assert r.returncode == 2 and "nothing to generate" in r.stderr and str(wav) in r.stderr, r.stderr
    assert not out.exists()


def test_serve_refuses_an_empty_wav(tmp_path):
    wav = empty_wav(tmp_path / "empty.wav")
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "serve", "--source", str(wav), "--no-ws"], cwd=REPO,
                 capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "no audio samples" in r.stderr
