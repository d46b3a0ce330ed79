"""`dimgestor serve` as a user runs it: a subprocess, real websockets/python-osc clients, loopback only."""

import asyncio
import json
import os
import re
import signal
import sys
import urllib.error
import urllib.request

import numpy as np
import pytest

from dimgestor.bvh import read_bvh
from streamer.pose import HUMAN_BODY_BONES
from helpers import warm
from helpers.serve import REPO, WAV_SECONDS as SECONDS, follow, serve
from helpers.vmc import bundles, check_vmc_bundle, osc_server

pytestmark = pytest.mark.timeout(180)


def test_wav_file_to_websocket_client_and_vmc(tiny_checkpoint, wav, tmp_path):
    server, rec = osc_server()
    s = serve(tiny_checkpoint, "--source", str(wav), "--fast", "--wait-client",
              "--vmc", f"127.0.0.1:{server.server_address[1]}")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    hello, msgs = asyncio.run(follow(url))
    assert s.finish() == 0, s.output
    server.shutdown()

    assert hello["type"] == "hello" and hello["protocol"] == 1 and hello["fps"] == 20
    J = len(hello["skeleton"]["joints"])
    assert set(hello["humanoid"]) <= set(HUMAN_BODY_BONES) and hello["humanoid"]
    frames = [m for m in msgs if m["type"] == "frame"]
    end = [m for m in msgs if m["type"] == "end"]
    assert len(frames) == int(SECONDS * 20) and end == [{"type": "end", "frames": len(frames)}]
    assert msgs[-1]["type"] == "end"  # nothing after the end
    assert [f["index"] for f in frames] == list(range(len(frames)))
    pts = np.array([f["pts"] for f in frames])
    assert np.all(np.diff(pts) > 0) and np.allclose(np.diff(pts), 1 / 20)
    rot = np.array([f["rotations"] for f in frames])
    assert rot.shape == (len(frames), J, 4) and np.allclose(np.linalg.norm(rot, axis=-1), 1, atol=1e-5)
    assert np.array([f["root"] for f in frames]).shape == (len(frames), 3)

    got = bundles(rec.packets)
    assert len(got) == len(frames)
    for msgs in got:
        check_vmc_bundle(msgs, bones_expected=hello["humanoid"])
    assert re.search(r"latency\s+\d+ms \| rtf \d", s.output)


@pytest.mark.parametrize("root,guidance", [("free", None), ("tether", None), ("tether", "2.5")])
def test_record_equals_offline_generate(tiny_checkpoint, wav, tmp_path, root, guidance):
    """Streaming (--record, window 150 ms) == `dimgestor generate` on the same file, seed, steps, root mode and
    guidance scale; the face track beside the recording == `generate --face-csv`'s, row for row (one per BVH frame)."""
    out_stream, out_offline = tmp_path / "stream.bvh", tmp_path / "offline.bvh"
    extra = ["--guidance", guidance] if guidance else []
    s = serve(tiny_checkpoint, "--source", str(wav), "--fast", "--no-ws", "--seed", "7", "--steps", "3",
              "--window-ms", "150", "--record", str(out_stream), "--root", root, "--tether-s", "0.5", *extra)
    assert s.finish() == 0, s.output
    assert f"root {root}" in s.output and (f"guidance {guidance}" in s.output) == bool(guidance)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "generate", "--checkpoint", str(tiny_checkpoint),
                  "--audio", str(wav), "--out", str(out_offline), "--steps", "3", "--seed", "7",
                  "--face-csv", str(tmp_path / "offline.csv"),
                  "--root", root, "--tether-s", "0.5", *extra],
                 cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    a, b = read_bvh(out_stream), read_bvh(out_offline)
    assert a.values.shape == b.values.shape and a.num_frames == int(SECONDS * 20)
    assert a.frame_time == pytest.approx(b.frame_time)
    assert np.abs(a.values - b.values).max() < 1e-3
    face = (tmp_path / "stream.face.csv").read_text()
    assert face == (tmp_path / "offline.csv").read_text()
    assert face.startswith("time,A,I,U,E,O,Blink,Blink_L,Blink_R,Joy,eyeBlinkLeft,")
    assert face.count("\n") == 1 + a.num_frames


def test_ctrl_c_stops_cleanly_and_finishes_the_recording(tiny_checkpoint, wav, tmp_path):
    out = tmp_path / "partial.bvh"
    s = serve(tiny_checkpoint, "--source", str(wav), "--loop", "--record", str(out))  # real time, forever
    m = s.wait_for(r"\[dimgestor\s+([\d.]+)s\] \| audio\s+([\d.]+)s \| frames [1-9].* \| batch ([\d.]+) streams")
    assert float(m.group(2)) <= float(m.group(1))  # paced in real time, not as fast as possible
    assert float(m.group(3)) == 1.0  # batched inference by default; one stream here
    s.proc.send_signal(signal.SIGINT)
    assert s.finish(30) == 0, s.output
    assert "wrote" in s.output
    motion = read_bvh(out)
    assert motion.num_frames > 0 and np.isfinite(motion.values).all()


def test_the_viewer_is_served_on_the_websocket_port_and_http_is_a_deprecated_alias(tiny_checkpoint):
    s = serve(tiny_checkpoint, "--source", "ws", "--http", "0", "--token", "t0k", "--max-seconds", "20")
    ws_url = s.wait_for(r"WebSocket\s+(ws://\S+?)\?").group(1)
    viewer_url = s.wait_for(r"web viewer (http://\S+)").group(1)
    assert viewer_url == "http" + ws_url[2:]  # one port: the page, its assets and the WebSocket
    page = urllib.request.urlopen(viewer_url, timeout=10).read().decode()
    assert "<html" in page.lower()
    assert "text/javascript" in urllib.request.urlopen(viewer_url + "viewer.js", timeout=10).headers["Content-Type"]
    with pytest.raises(urllib.error.HTTPError) as e:  # no /config.json: the page connects to its own origin
        urllib.request.urlopen(viewer_url + "config.json", timeout=10)
    assert e.value.code == 404
    # --http: still the viewer, and the WebSocket beside it (its pages connect to their own origin), with a warning
    alias = s.wait_for(r"--http is deprecated: .* on port (\d+) too").group(1)
    assert alias != ws_url.rsplit(":", 1)[1].strip("/")
    assert "<html" in urllib.request.urlopen(f"http://127.0.0.1:{alias}/", timeout=10).read().decode().lower()
    assert asyncio.run(first_message(f"ws://127.0.0.1:{alias}/?token=t0k"))["type"] == "hello"
    s.proc.send_signal(signal.SIGTERM)
    assert s.finish(30) == 0, s.output


async def first_message(url: str) -> dict:
    """The first message of a WebSocket opened as a page of the viewer at that address would (its Origin)."""
    from websockets.asyncio.client import connect

    async with connect(url, origin=url.replace("ws://", "http://").split("/?")[0]) as c:
        return json.loads(await asyncio.wait_for(c.recv(), 30))


def test_mic_without_an_input_device_exits_with_a_clear_message():
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "serve", "--source", "mic", "--no-ws"],
                 cwd=REPO, capture_output=True, text=True, timeout=60)
    try:
        import sounddevice as sd

        sd.query_devices(kind="input")
        pytest.skip("this machine has an input device")
    except Exception:
        pass
    assert r.returncode == 2
    assert re.search(r"No input device|PortAudio library not found", r.stderr), r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("args, message", [
    (["--checkpoint", "/nonexistent/ckpt"], "cannot load"),
    (["--source", "/nonexistent.wav"], "audio file not found"),
    (["--window-ms", "3"], "window-ms"),
    (["--record", "/nonexistent/dir/out.bvh"], "does not exist"),
    (["--smooth", "-1"], "--smooth must be >= 0"),
    (["--steps", "0"], "--steps must be >= 1"),
    (["--tether-s", "0"], "--tether-s must be > 0"),
    (["--guidance", "-1"], "--guidance: guidance scale must be"),
])
def test_bad_arguments_exit_2_with_a_message(args, message):
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "serve", "--no-ws", *args],
                 cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_zeggs_skeleton_maps_every_humanoid_bone(zeggs_dir, wav, tmp_path):
    """On the real training skeleton (random tiny weights) the hello and VMC carry all 52 mapped bones."""
    import torch

    from dimgestor.config import get_preset
    from dimgestor.features import FeatureSpec
    from dimgestor.model.network import DiMGestor
    from dimgestor.streaming.checkpoint import save_checkpoint

    sk = read_bvh(next(zeggs_dir.glob("*.bvh"))).skeleton
    spec = FeatureSpec.for_skeleton(sk)
    torch.manual_seed(0)
    model = DiMGestor(get_preset("tiny", motion_dim=spec.dim)).eval()
    ckpt = save_checkpoint(tmp_path / "zeggs_tiny", model, spec, sk, np.zeros(spec.dim), np.full(spec.dim, 0.1))

    server, rec = osc_server()
    s = serve(ckpt, "--source", str(wav), "--fast", "--wait-client", "--vmc", f"127.0.0.1:{server.server_address[1]}")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    hello, msgs = asyncio.run(follow(url))
    assert s.finish() == 0, s.output
    server.shutdown()
    assert hello["skeleton"]["joints"] == sk.names and len(hello["humanoid"]) == 52
    assert hello["humanoid"]["LeftUpperArm"] == "LeftArm" and hello["humanoid"]["LeftLittleProximal"] == "LeftHandPinky1"
    got = bundles(rec.packets)
    assert len(got) == int(SECONDS * 20)
    for b in got:
        check_vmc_bundle(b, bones_expected=hello["humanoid"])

