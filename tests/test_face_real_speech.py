"""The face on real speech: two takes of a speaker the default model never heard and two real-world speakers, with
every phone's time from a forced alignment (`../shared/data/phone_aligned_speech`), streamed live in awkward pieces.
The mouth follows what was said (openness, vowel class, lips closed at M/B/P, rest in silence) and the eyes blink
as people do while talking (10-25 a minute, never metronomic). benchmarks/face.py measures the same and more."""

from pathlib import Path

import numpy as np
import pytest

from dimgestor.audio import load_wav
from dimgestor.face import FaceOptions, FaceStream
from dimgestor.face.evaluate import mouth_lag, mouth_scores
from dimgestor.face.textgrid import read_tiers
from dimgestor.face.visemes import V

pytestmark = pytest.mark.slow
DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "phone_aligned_speech"
TAKES = ("2_scott_0_2_2", "2_scott_0_4_4")
REAL_WORLD = ("clip000028_tCAkv4ggPgI", "clip000070_lskPN47Lo8o")
BLINK_S = 60.0


def streamed(name, listener="net", piece=1234):
    """(the clip's face frames at 20 fps, its alignment's phones, the stream), streamed in `piece`-sample pieces."""
    wav, grid = DATA / f"{name}.wav", DATA / f"{name}.TextGrid"
    if not (wav.is_file() and grid.is_file()):
        pytest.skip(f"the phone-aligned clips are not at {DATA} (they live beside the dev checkout only)")
    audio, phones = load_wav(wav), read_tiers(grid)["phones"]
    face, rows = FaceStream(20, 0.3, FaceOptions(listener=listener)), []
    for at in range(0, len(audio), piece):
        face.push(audio[at:at + piece])
        rows.append(face.take(face.frames_ready))
    face.finish()
    rows.append(face.take(face.frames_ready))
    return np.concatenate(rows), phones, face


@pytest.fixture(scope="module", params=TAKES)
def take(request):
    """A studio take through the default face (the face's own listener)."""
    return streamed(request.param)


@pytest.mark.parametrize("name", TAKES)
def test_the_pocketsphinx_mouth_meets_issue_37s_targets_on_real_speech(name):
    pytest.importorskip("pocketsphinx", reason="pocketsphinx has no wheel for this Python (pyproject.toml)")
    face, phones, _ = streamed(name, "pocketsphinx")
    s = mouth_scores(face, phones, 20)
    summary = {k: s[k] for k in ("openness_r", "vowel_top1", "vowel_mean_recall", "closures", "rest")}
    assert s["openness_r"] >= 0.65, summary         # jaw opening vs the phones' (Pearson, per frame)
    assert s["vowel_top1"] >= 0.65, summary         # the strongest of A I U E O is the vowel's (always "A": ~0.49)
    assert s["vowel_mean_recall"] >= 0.55, summary  # ... for every class, not just the frequent "A"
    assert s["closures"] >= 0.5, summary            # lips shut at M, B, P centres
    assert s["rest"] <= 0.15, summary               # the mouth rests in pauses


@pytest.mark.parametrize("name", TAKES[1:] + REAL_WORLD)
def test_the_default_mouth_on_real_voices_it_never_trained_on(name):
    """The face's own listener on the real clips it was not trained on (its weights record those it was:
    scott's take 2_2). Floors under what it measures (benchmarks/face.py: 0.63-0.68 / 0.50-0.70 / 0.40-0.62 /
    0.62-0.73 / rest 0.00-0.09); issue 49's targets are higher and not met yet, on clip000070 by pocketsphinx's
    listener either (benchmarks/README.md)."""
    from dimgestor.face.net import weights_meta

    assert name not in weights_meta()["real_train"]
    face, phones, _ = streamed(name)
    s = mouth_scores(face, phones, 20)
    summary = {k: s[k] for k in ("openness_r", "vowel_top1", "vowel_mean_recall", "closures", "rest", "always_A")}
    assert s["openness_r"] >= 0.60, summary
    assert s["vowel_top1"] >= 0.45, summary
    assert s["vowel_mean_recall"] >= 0.35, summary  # (an "always A" mouth: 0.2)
    assert s["closures"] >= 0.5, summary
    assert s["rest"] <= 0.15, summary


@pytest.mark.parametrize("name", TAKES[1:] + REAL_WORLD)
def test_both_listeners_together_open_the_mouth_closer_to_real_speech_than_either(name):
    """--face-listener net+pocketsphinx: the mean of the two mouths. On the real clips neither listener trained
    on, its openness is over issue 49's 0.65 and over each listener's alone (benchmarks/face.py: 0.68-0.72 against
    0.63-0.68 and 0.64-0.70), and its lips still shut at M, B, P."""
    pytest.importorskip("pocketsphinx", reason="pocketsphinx has no wheel for this Python (pyproject.toml)")
    scores = {lis: mouth_scores(streamed(name, lis)[0], streamed(name)[1], 20)
              for lis in ("net", "pocketsphinx", "net+pocketsphinx")}
    both = scores["net+pocketsphinx"]
    summary = {lis: {k: round(s[k], 3) for k in ("openness_r", "vowel_top1", "closures", "rest")}
               for lis, s in scores.items()}
    assert both["openness_r"] >= 0.65, summary
    assert both["openness_r"] > max(scores["net"]["openness_r"], scores["pocketsphinx"]["openness_r"]), summary
    assert both["closures"] >= 0.5 and both["rest"] <= 0.15, summary


@pytest.mark.parametrize("listener", ("pocketsphinx", "net+pocketsphinx"))
def test_a_real_voice_streamed_in_any_pieces_gives_the_face_of_the_whole_recording(listener):
    """pocketsphinx's running cepstral mean moves at the end of each call to it, so the listener calls it with the
    same blocks whatever the pieces (on this clip, pieces of 777 samples once changed three frames' mouths)."""
    pytest.importorskip("pocketsphinx", reason="pocketsphinx has no wheel for this Python (pyproject.toml)")
    whole = streamed(REAL_WORLD[1], listener, piece=10**8)[0]
    for piece in (777, 161, 5000):
        np.testing.assert_array_equal(streamed(REAL_WORLD[1], listener, piece=piece)[0], whole, err_msg=str(piece))


def test_the_mouth_shows_a_sound_within_40_ms_of_when_it_was_said(take):
    """The frame at pts t shows the sound said at t: the jaw (held over each 50 ms frame, as a 20 fps client holds
    it; half a frame is its own 25 ms) correlates best with the alignment within 40 ms of no lag."""
    face, phones, _ = take
    lag, r = mouth_lag(face, phones, 20)
    print(f"best lag {lag * 1000:.0f} ms (r {r[lag]:.3f}; at 0: {r[0.0]:.3f})")
    assert abs(lag) <= 0.04, {k: round(v, 3) for k, v in r.items() if abs(k) <= 0.1}


def test_blinks_as_people_blink_while_talking(take):
    """On the first minute of speech: 10-25 blinks a minute, consecutive intervals alike (within 50 ms) at most a
    third of the time, never a long stare; and each blink shows on both eyelids as a client sees them (closed past
    half in some frame)."""
    face, _, stream = take
    onsets = np.array([t for t in stream.blinks.started if t < BLINK_S])
    per_min = len(onsets) / BLINK_S * 60
    assert 10 <= per_min <= 25, f"{per_min:.1f} blinks a minute"
    gaps = np.diff(onsets)
    alike = np.mean(np.abs(np.diff(gaps)) < 0.05)
    assert alike <= 1 / 3, f"intervals {np.round(gaps, 2)}: {alike:.0%} alike within 50 ms"
    assert gaps.max() < 12, f"eyes open {gaps.max():.1f} s without a blink"
    for lid in ("blinkLeft", "blinkRight"):  # closed past half in a frame within 0.3 s of each onset, shut otherwise
        near = np.zeros(len(face), bool)
        for t in onsets:
            frames = np.arange(int(np.ceil(t * 20)), int(np.floor((t + 0.3) * 20)) + 1)
            assert face[frames, V[lid]].max() > 0.5, f"{lid}: the blink at {t:.2f} s never shows"
            near[frames] = True
        assert np.all(face[: int(BLINK_S * 20)][~near[: int(BLINK_S * 20)], V[lid]] < 0.5), lid
