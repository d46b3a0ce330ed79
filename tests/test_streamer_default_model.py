"""`streamer serve` with no --checkpoint: the embedded default model, on the demo clip, end to end."""

import asyncio
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dimgestor.audio import load_wav, save_wav
from dimgestor.bvh import read_bvh
from streamer.sources import DEMO_WAV
from test_streamer_cli import REPO, follow, osc_server, bundles, check_vmc_bundle, Serve

DEFAULT_MODEL = REPO / "dimgestor" / "default_model"
pytestmark = [pytest.mark.timeout(300), pytest.mark.slow,
              pytest.mark.skipif(not (DEFAULT_MODEL / "model.safetensors").is_file(),
                                 reason=f"no embedded default model at {DEFAULT_MODEL} yet")]


def test_default_model_streams_the_demo_like_offline_generate(tmp_path):
    clip = tmp_path / "demo4s.wav"
    save_wav(clip, load_wav(DEMO_WAV)[: 4 * 16000], 16000)
    rec_path, off_path = tmp_path / "stream.bvh", tmp_path / "offline.bvh"
    server, rec = osc_server()
    s = Serve("--source", str(clip), "--fast", "--wait-client", "--ws", "127.0.0.1:0", "--steps", "4", "--seed", "2",
              "--record", str(rec_path), "--osc", f"127.0.0.1:{server.server_address[1]}")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    hello, msgs = asyncio.run(follow(url))
    assert s.finish() == 0, s.output
    server.shutdown()

    frames = [m for m in msgs if m["type"] == "frame"]
    assert len(frames) == 80 and msgs[-1] == {"type": "end", "frames": 80}
    assert hello["lookahead_s"] > 0 and len(hello["humanoid"]) >= 20
    rot = np.array([f["rotations"] for f in frames])
    assert np.allclose(np.linalg.norm(rot, axis=-1), 1, atol=1e-5)
    got = bundles(rec.packets)
    assert len(got) == 80
    for b in got:
        check_vmc_bundle(b, bones_expected=hello["humanoid"])

    r = subprocess.run([sys.executable, "-m", "dimgestor.cli", "generate", "--audio", str(clip), "--out",
                        str(off_path), "--steps", "4", "--seed", "2"], cwd=REPO,
                       env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    a, b = read_bvh(rec_path), read_bvh(off_path)
    assert a.values.shape == b.values.shape == (80, a.skeleton.num_channels)
    assert np.abs(a.values - b.values).max() < 1e-3
