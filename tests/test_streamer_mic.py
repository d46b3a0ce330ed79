"""The live microphone for real: PortAudio captures a virtual sound card (a private PulseAudio daemon,
tests/helpers/virtual_mic.py) through `dimgestor devices` and `dimgestor serve --source mic`, as a user runs them."""

import asyncio
import json
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from websockets.asyncio.client import connect
from helpers import warm
from helpers.serve import REPO, Serve
from helpers.clients import joint_speed
from helpers.virtual_mic import speech_then_silence, virtual_mic

pytestmark = pytest.mark.timeout(180)
SPEECH_S, SILENCE_S = 5.0, 4.5


@pytest.fixture(scope="module")
def vmic(tmp_path_factory):
    with virtual_mic(tmp_path_factory.mktemp("vmic")) as mic:
        yield mic


def dimgestor(vmic, *args: str) -> subprocess.CompletedProcess:
    return warm.run([sys.executable, "-m", "dimgestor_app.cli", *args], cwd=REPO, env={**vmic.env, "OMP_NUM_THREADS": "1"},
                    capture_output=True, text=True, timeout=120)


def test_devices_lists_the_virtual_microphones_with_their_rates(vmic):
    r = dimgestor(vmic, "devices")
    assert r.returncode == 0, r.stderr
    rows = re.findall(r"^([* ])\s*(\d+)\s+(\S+)\s+\((\w+), (\d+) ch, (\d+) Hz\)$", r.stdout, re.M)
    names = {name: (mark, api, int(rate)) for mark, _, name, api, _, rate in rows}
    assert {"pulse", "vmic44", "vmic_quiet", "default"} <= set(names), r.stdout
    assert "vspeaker" not in names  # playback only: not an input
    assert names["vmic44"][1] == "ALSA" and names["vmic44"][2] in (44100, 48000)
    assert [name for name, (mark, _, _) in names.items() if mark == "*"] == ["default"]


async def watch_while_playing(url: str, vmic, wav, sink: str, seconds: float):
    """A WebSocket client: hello, then frames and status with their arrival times; plays `wav` into the
    virtual microphone's `sink` once frames flow."""
    got, t_play = [], None
    async with connect(url) as c:
        hello = json.loads(await asyncio.wait_for(c.recv(), 60))
        while t_play is None or time.monotonic() < t_play + seconds:
            msg = json.loads(await asyncio.wait_for(c.recv(), 30))
            got.append((time.monotonic(), msg))
            if t_play is None and msg["type"] == "frame":
                vmic.play(wav, sink)
                t_play = time.monotonic()
    return hello, got, t_play


@pytest.mark.parametrize("device, rate, sink", [("pulse", 48000, "mic48"), ("vmic44", 44100, "mic44")])
def test_serve_mic_gestures_while_speech_plays_and_rests_in_silence(vmic, tmp_path, device, rate, sink):
    """`--input-device pulse --rate 48000` and `--input-device vmic44` (its own rate, 44.1 kHz): captured through PortAudio,
    resampled to 16 kHz as it streams, the embedded default model's avatar moves faster while speech plays
    than in the silence played after it; latency stays low, no audio is dropped, Ctrl-C ends cleanly."""
    wav = speech_then_silence(tmp_path / "talk.wav", SPEECH_S, SILENCE_S)
    rate_args = ["--rate", str(rate)] if device == "pulse" else []
    s = Serve("--source", "mic", "--input-device", device, *rate_args, "--ws", "127.0.0.1:0", "--status-every", "0.5",
              env=vmic.env)
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    assert f"microphone {device!r} at {rate} Hz" in s.output
    hello, got, t_play = asyncio.run(watch_while_playing(url, vmic, wav, sink, SPEECH_S + SILENCE_S + 0.5))
    s.proc.send_signal(signal.SIGINT)
    assert s.finish(30) == 0, s.output
    assert "source ended after" in s.output and "Traceback" not in s.output

    frames = [(t, m) for t, m in got if m["type"] == "frame"]
    idx = [m["index"] for _, m in frames]
    assert idx == list(range(idx[0], idx[0] + len(idx)))  # nothing skipped on the way
    fps = hello["fps"]
    speed = joint_speed([m for _, m in frames], fps)
    t = np.array([t for t, _ in frames[1:]]) - t_play  # frame arrival, seconds after the speech started playing
    # generous margins for the playback start, the model's lookahead and the output smoothing
    talking = speed[(t > 1.0) & (t < SPEECH_S)]
    resting = speed[(t > SPEECH_S + 2.0) & (t < SPEECH_S + SILENCE_S)]
    assert len(talking) > 2.5 * fps and len(resting) > 1.5 * fps, (len(talking), len(resting))
    assert np.median(talking) > 2 * np.median(resting), (np.median(talking), np.median(resting))

    status = [m for _, m in got if m["type"] == "status"]
    assert status, "no status messages"
    latency = [m["latency_ms"] for m in status if m.get("latency_ms") is not None]
    assert latency and np.median(latency) < 1500, latency
    assert status[-1]["audio_dropped_s"] < 0.5, status[-1]
    lines = re.findall(r"latency\s+(\d+)ms .*\| mic\s+(-?\d+) dBFS \| mic dropped ([\d.]+)s", s.output)
    assert lines, s.output
    assert max(int(level) for _, level, _ in lines) > -40  # the meter heard the speech
    assert float(lines[-1][2]) < 0.5


def test_a_silent_microphone_warns_no_signal(vmic):
    """Once 3 s of silence are captured (however long a loaded machine takes to start capturing: a fixed
    --max-seconds 6 once ended after 2.7 s of audio), the warning is printed and the status line says so."""
    s = Serve("--source", "mic", "--input-device", "vmic_quiet", "--no-ws", "--status-every", "0.5", env=vmic.env)
    try:
        s.wait_for(r"no signal from microphone 'vmic_quiet' for 3 s: is it muted")
        s.wait_for(r"mic NO SIGNAL for")
    finally:
        s.proc.send_signal(signal.SIGINT)
    assert s.finish(30) == 0, s.output
    assert s.output.count("no signal from microphone") == 1, s.output  # said once, not at every block


def _index_of(vmic, name: str) -> int:
    code = f"import sounddevice as sd; print([d['name'] for d in sd.query_devices()].index({name!r}))"
    r = subprocess.run([sys.executable, "-c", code], env=vmic.env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return int(r.stdout)


@pytest.mark.parametrize("how", ["name", "index"])
def test_a_device_without_input_channels_exits_2_with_one_clear_line(vmic, how):
    device = "vspeaker" if how == "name" else str(_index_of(vmic, "vspeaker"))
    r = dimgestor(vmic, "serve", "--source", "mic", "--input-device", device, "--no-ws")
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "dimgestor: No input device: 'vspeaker' has no input channels (an output device?); "
        "list the inputs with `dimgestor devices`"], r.stderr


@pytest.mark.parametrize("args, says", [
    (["--input-device", "vmic44", "--rate", "1000000"], "dimgestor: Input device 'vmic44' cannot capture at 1000000 Hz"),
    (["--input-device", "vmic"], "dimgestor: No input device 'vmic': Multiple input devices found for 'vmic'"),
    (["--input-device", "no such mic"], "dimgestor: No input device 'no such mic'"),
])
def test_a_device_that_cannot_be_used_exits_2_with_one_clear_line(vmic, args, says):
    r = dimgestor(vmic, "serve", "--source", "mic", "--no-ws", *args)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(says), r.stderr
