"""The embedded live model (`--checkpoint live`): the default model's recipe with 150 ms of audio lookahead
instead of 300, so a live microphone's gestures come 150 ms sooner. It is found by name, streams exactly like
offline generation, and its motion is smooth, speech-driven and calm in silence (MODEL_CARD.md, "The live model")."""

import asyncio
import os
import sys

import numpy as np
import pytest

from dimgestor.audio import load_wav, save_wav
from dimgestor.bvh import forward_kinematics, read_bvh
from dimgestor.streaming.checkpoint import (DEFAULT_MODEL_DIR, LIVE_MODEL_DIR, CheckpointError, load_checkpoint,
                                            resolve_checkpoint)
from dimgestor.evaluation import metrics
from dimgestor.evaluation.eval import clip_stats, joint_positions
from dimgestor.streaming.stream import generate_offline
from streamer.sources import DEMO_WAV
from helpers import warm
from helpers.serve import REPO, Serve, follow

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]
REAL_HAND_JERK = 21680.0  # the real capture's held-out wrist jerk (tests/test_default_model_motion.py)


@pytest.fixture(scope="module")
def live():
    b = load_checkpoint("live")
    b.model.eval()
    return b


def test_the_live_model_is_embedded_and_found_by_name(tmp_path, monkeypatch):
    assert sum(f.stat().st_size for f in LIVE_MODEL_DIR.iterdir()) < 20e6  # small enough to live in git
    assert resolve_checkpoint("live") == LIVE_MODEL_DIR and resolve_checkpoint("default") == DEFAULT_MODEL_DIR
    monkeypatch.chdir(tmp_path)
    (tmp_path / "live").mkdir()  # a folder of that name is what the user means: the path wins over the name
    with pytest.raises(CheckpointError, match="live is neither a checkpoint folder"):
        resolve_checkpoint("live")


def test_the_live_model_answers_150_ms_sooner(live):
    default = load_checkpoint(None)
    assert live.config.frontend == default.config.frontend == "speech"
    assert (live.config.lookahead_ms, default.config.lookahead_ms) == (150, 300)
    assert live.model.lookahead_s == pytest.approx(0.2) and default.model.lookahead_s == pytest.approx(0.35)
    # both 2-step students (`distill --steps 2`) of 4-step students with their teacher's guidance 1.25 folded in
    # (`distill --steps 4`): one network row a step, two steps
    for b in (live, default):
        assert (b.config.sample_steps, b.config.guidance, b.config.smooth_hz or 0) == (2, 1.0, 0)
        assert b.config.ddim_timesteps == (7, 2) and b.info["method"] == "progressive"
        assert (b.info["teacher"]["sample_steps"], b.info["teacher"]["guidance"]) == (4, 1.0)


@pytest.mark.parametrize("clip", ["demo_en.wav", "demo_zh.wav"])
def test_the_live_model_is_smooth_and_keeps_facing_the_camera(live, clip):
    audio = load_wav(DEMO_WAV.parent / clip)
    raw = np.asarray(live.denormalize(generate_offline(live.model, audio, seed=0, smoothing=None)))
    s = clip_stats(raw, audio, live.skeleton, live.feature_spec)
    assert 0.5 < s["hand_jerk"] / REAL_HAND_JERK < 2.0, s["hand_jerk"]
    assert abs(s["net_yaw_deg"]) < 45.0, s["net_yaw_deg"]


def test_the_live_model_rests_in_silence(live):
    audio = load_wav(DEMO_WAV)
    cut = 6 * 16000
    with_pause = np.concatenate([audio[:cut], np.zeros(5 * 16000, np.float32), audio[cut:]])
    raw = np.asarray(live.denormalize(generate_offline(live.model, with_pause, seed=0, smoothing=None)))
    pos = joint_positions(raw, live.skeleton, live.feature_spec)[:, metrics.hand_joints(live.skeleton.names)]
    speed = metrics.joint_speed(pos, 20.0).mean(axis=1)
    pause = speed[6 * 20 + 15: 11 * 20]  # the inserted 5 s, after 0.75 s to finish the last gesture
    speech = np.concatenate([speed[20: 6 * 20], speed[11 * 20 + 15:]])
    assert speech.mean() > 2.0 * pause.mean(), (speech.mean(), pause.mean())


def test_serve_with_the_live_model_streams_like_generate(tmp_path):
    clip, rec, off = tmp_path / "demo3s.wav", tmp_path / "stream.bvh", tmp_path / "offline.bvh"
    save_wav(clip, load_wav(DEMO_WAV)[: 3 * 16000], 16000)
    s = Serve("--checkpoint", "live", "--source", str(clip), "--fast", "--wait-client", "--ws", "127.0.0.1:0",
              "--window-ms", "100", "--seed", "3", "--record", str(rec))
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    hello, msgs = asyncio.run(follow(url))
    assert s.finish() == 0, s.output
    assert hello["lookahead_s"] == pytest.approx(0.2) and msgs[-1] == {"type": "end", "frames": 60}
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "generate", "--checkpoint", "live", "--audio",
                  str(clip), "--out", str(off), "--seed", "3", "--root", "tether"], cwd=REPO,
                 env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    a, b = read_bvh(rec), read_bvh(off)
    assert a.values.shape == b.values.shape == (60, a.skeleton.num_channels)
    assert np.abs(forward_kinematics(a) - forward_kinematics(b)).max() < 1e-3
