"""The embedded default model: it is there, `streamer serve` and `dimgestor generate` use it with no
--checkpoint, and what it generates for the demo clips moves visibly and within human speeds."""

import asyncio
import os
import sys

import numpy as np
import pytest

from dimgestor.audio import load_wav, save_wav
from dimgestor.bvh import forward_kinematics, read_bvh
from streamer.sources import DEMO_WAV
from helpers import warm
from helpers.serve import REPO, Serve, follow
from helpers.vmc import bundles, check_vmc_bundle, osc_server

DEFAULT_MODEL = REPO / "dimgestor" / "default_model"
pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]


def test_the_default_model_is_embedded():
    for name in ("model.safetensors", "config.json"):
        assert (DEFAULT_MODEL / name).is_file(), f"{DEFAULT_MODEL / name} is missing: run `make default-model`"
    assert sum(f.stat().st_size for f in DEFAULT_MODEL.iterdir()) < 20e6  # small enough to live in git


@pytest.mark.parametrize("clip", ["demo_en.wav", "demo_zh.wav"])
def test_default_model_generates_visible_motion_within_human_speeds(tmp_path, clip):
    """`dimgestor generate` as a user runs it (embedded model, its default steps and smoothing)."""
    from dimgestor.bvh import forward_kinematics
    from dimgestor_app.render import motion_stats

    wav, out = DEMO_WAV.parent / clip, tmp_path / "demo.bvh"
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "generate", "--audio", str(wav), "--out", str(out)],
                 cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True,
                 timeout=240)
    assert r.returncode == 0, r.stderr
    motion = read_bvh(out)
    assert motion.num_frames == len(load_wav(wav)) * 20 // 16000
    # the ZEGGS skeleton is in centimetres: check that before reading speeds in cm/s
    rest = forward_kinematics(motion.skeleton, np.tile([1.0, 0, 0, 0], (1, motion.skeleton.num_joints, 1)))[0]
    height = np.ptp(rest[:, 1])
    assert 140 < height < 210, f"skeleton height {height:.1f}: not a human in centimetres"
    stats = motion_stats(motion)
    # visible gesture: each hand moves (relative to the body) by more than a few centimetres
    assert len(stats["hand_travel_rel_root"]) == 2
    assert min(stats["hand_travel_rel_root"].values()) > 5.0, stats["hand_travel_rel_root"]
    # no explosions: speeds stay in the range of real gesture capture. The ZEGGS training clip itself,
    # through the same 20 fps features: p99 over frames of the fastest joint 5.0 m/s, max 8.5 m/s
    assert stats["joint_speed_p99"] < 700.0, stats["joint_speed_p99"]
    assert stats["max_joint_speed"] < 1000.0, (stats["max_joint_speed"], stats["max_joint_speed_joint"])


def test_default_model_streams_the_demo_like_offline_generate(tmp_path):
    clip = tmp_path / "demo4s.wav"
    save_wav(clip, load_wav(DEMO_WAV)[: 4 * 16000], 16000)
    rec_path, off_path = tmp_path / "stream.bvh", tmp_path / "offline.bvh"
    server, rec = osc_server()
    s = Serve("--source", str(clip), "--fast", "--wait-client", "--ws", "127.0.0.1:0", "--steps", "4", "--seed", "2",
              "--record", str(rec_path), "--vmc", f"127.0.0.1:{server.server_address[1]}")
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

    # serve tethers the root by default: generate does the same when asked
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "generate", "--audio", str(clip), "--out",
                  str(off_path), "--steps", "4", "--seed", "2", "--root", "tether"], cwd=REPO,
                 env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    a, b = read_bvh(rec_path), read_bvh(off_path)
    assert a.values.shape == b.values.shape == (80, a.skeleton.num_channels)
    # the same motion: every joint within 1e-3 cm of the offline one (FK of the written files), and every channel
    # within 0.01 degree (a large unwrapped Euler angle, e.g. -266 degrees, carries float32 rounding of ~1e-5 of it)
    assert np.abs(forward_kinematics(a) - forward_kinematics(b)).max() < 1e-3
    assert np.abs(a.values - b.values).max() < 1e-2
