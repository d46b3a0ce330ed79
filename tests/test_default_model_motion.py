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
TAKES = ("4_lawrence_0_19_19.wav", "4_lawrence_0_35_35.wav")


@pytest.fixture(scope="module")
def unseen_rows(bundle):
    """voice_report (two seeds, the default K and guidance) of the demo clips and the unseen speaker's takes."""
    from dimgestor.eval import voice_report

    clips = {"demo_en": DEMO_WAV.parent / "demo_en.wav", "demo_zh": DEMO_WAV.parent / "demo_zh.wav",
             **{t[:-4]: UNSEEN / t for t in TAKES}}
    return {name: voice_report(bundle, load_wav(wav), bundle.config.sample_steps, seeds=2)
            for name, wav in clips.items() if wav.exists()}


@pytest.mark.parametrize("take", [t[:-4] for t in TAKES])
def test_default_model_follows_the_unseen_speaker(unseen_rows, take):
    """BEAT speaker lawrence (74-82 s takes): wrist speed follows the speech's loudness clearly better than the
    same speech shifted in time, and the wrists stay within 1.5x the real capture's jerk. (The 14 s demo clips
    are too short for coupling: their shifted baseline's sd is 0.13-0.16.)"""
    if take not in unseen_rows:
        pytest.skip(f"{UNSEEN / take}.wav not found: the unseen speaker is only present beside the dev checkout (../shared)")
    row = unseen_rows[take]
    assert row["coupling"] > row["coupling_shifted"] + 0.1, row
    assert row["hand_jerk"] < 1.5 * REAL_HAND_JERK, row


@pytest.mark.parametrize("clip", ["demo_en", "demo_zh"] + [t[:-4] for t in TAKES])
def test_default_model_calms_in_an_inserted_silence(unseen_rows, clip):
    """6 s of silence inserted into a pause of an unseen voice: the wrists move at least 3x faster in speech
    (issue "voice"'s target; the model measures 4.0-4.5 on these clips, the previous default 2.0-5.1)."""
    if clip not in unseen_rows:
        pytest.skip(f"{clip}.wav not found: the unseen speaker is only present beside the dev checkout (../shared)")
    assert unseen_rows[clip]["silence_ratio"] > 3.0, unseen_rows[clip]
