"""The embedded default model's motion, as `dimgestor eval` measures it, with the output filter OFF and the
model's own default number of DDIM steps: as smooth as real capture, speech-driven, and facing the camera."""

from pathlib import Path

import numpy as np
import pytest

from dimgestor import metrics
from dimgestor.audio import load_wav
from dimgestor.checkpoint import load_checkpoint
from dimgestor.eval import clip_stats, joint_positions
from dimgestor.stream import generate_offline
from streamer.sources import DEMO_WAV

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]

# Wrist jerk of the real capture, as `dimgestor eval` reports it for the default model's data: the ZEGGS sample
# clip's held-out last 15 s (the reference row of `dimgestor eval --data ZEGGS --valid-seconds 15`), cm/s^3.
# The whole 69 s clip, with the actor's still pauses, has 11.9k (see MODEL_CARD.md).
# test_real_capture_reference re-measures it where the clip is present.
REAL_HAND_JERK = 21680.0


@pytest.fixture(scope="module")
def bundle():
    b = load_checkpoint(None)
    b.model.eval()
    assert b.config.sample_steps >= 2, "the default model samples with several DDIM steps"
    assert not b.config.smooth_hz or b.config.smooth_hz >= 6.0, "no output filter below 6 Hz carries the result"
    return b


def _generate(bundle, audio, seed=0):
    return np.asarray(bundle.denormalize(generate_offline(bundle.model, audio, seed=seed, smoothing=None)))


@pytest.mark.parametrize("clip", ["demo_en.wav", "demo_zh.wav"])
def test_default_model_is_smooth_and_keeps_facing_the_camera(bundle, clip):
    audio = load_wav(DEMO_WAV.parent / clip)
    raw = _generate(bundle, audio)
    s = clip_stats(raw, audio, bundle.skeleton, bundle.feature_spec)
    assert 0.5 < s["hand_jerk"] / REAL_HAND_JERK < 2.0, s["hand_jerk"]  # within 2x of the real capture's
    assert abs(s["net_yaw_deg"]) < 45.0, s["net_yaw_deg"]  # no spin away from the camera over the clip


def test_default_model_rests_in_silence(bundle):
    audio = load_wav(DEMO_WAV)
    cut = 6 * 16000
    with_pause = np.concatenate([audio[:cut], np.zeros(5 * 16000, np.float32), audio[cut:]])
    raw = _generate(bundle, with_pause)
    pos = joint_positions(raw, bundle.skeleton, bundle.feature_spec)[:, metrics.hand_joints(bundle.skeleton.names)]
    speed = metrics.joint_speed(pos, 20.0).mean(axis=1)
    pause = speed[6 * 20 + 15: 11 * 20]  # the inserted 5 s, after 0.75 s to finish the last gesture
    speech = np.concatenate([speed[20: 6 * 20], speed[11 * 20 + 15:]])
    assert speech.mean() > 1.5 * pause.mean(), (speech.mean(), pause.mean())


def test_real_capture_reference(zeggs_dir, tmp_path):
    from dimgestor.dataset import GestureDataset
    from dimgestor.eval import k_report, valid_clips

    b = load_checkpoint(None)
    valid = GestureDataset(zeggs_dir, split="valid", spec=b.feature_spec, window_s=4.0, valid_seconds=15.0,
                           cache_dir=tmp_path)
    rep = k_report(b, valid_clips(valid), [1], seeds=1, seed=0, ae=None, log=lambda *_: None)
    assert rep["reference"]["hand_jerk"] == pytest.approx(REAL_HAND_JERK, rel=1e-3)


# ---- issue "voice": the default model follows voices it never heard ----
UNSEEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "unseen_speech"


def _voices():
    yield pytest.param(DEMO_WAV.parent / "demo_en.wav", id="demo_en")
    yield pytest.param(DEMO_WAV.parent / "demo_zh.wav", id="demo_zh")
    for take in ("4_lawrence_0_19_19.wav", "4_lawrence_0_35_35.wav"):
        yield pytest.param(UNSEEN / take, id=take[:-4])


@pytest.mark.parametrize("wav", _voices())
def test_default_model_follows_an_unseen_voice(bundle, wav):
    """Over two seeds, at the default K and guidance: wrist speed follows the speech's loudness better than it
    follows the same speech shifted in time, the hands are calmer in 6 s of silence inserted into a pause than
    in speech, and the wrists stay within 1.5x the real capture's jerk."""
    from dimgestor.eval import voice_report

    if not wav.exists():
        pytest.skip(f"{wav} not found: the unseen-speaker takes are only present beside the dev checkout (../shared)")
    row = voice_report(bundle, load_wav(wav), bundle.config.sample_steps, seeds=2)
    assert row["coupling"] > row["coupling_shifted"] + 0.05, row
    assert row["silence_ratio"] > 1.5, row
    assert row["hand_jerk"] < 1.5 * REAL_HAND_JERK, row
