"""The browser sound tests' judge (tests/helpers/av_sync.py): a recording is what the page scheduled
(source-audio.js `played`), holds, lateness and stops included, and nothing else."""

import numpy as np
import pytest

from helpers.av_sync import assert_played_as_scheduled, as_scheduled, streams


def piece(at, pts, dur, late=0.0, stop=None):
    return {"at": at, "pts": pts, "dur": dur, "late": late, "stop": stop}


# The page's log: a drop played 0.15 s, held 0.5 s (an underrun), came back 20 ms late (skipped), then a piece
# stopped at a second drop, which plays from its start (its first 10 ms skipped whole: the page came late).
PIECES = [piece(1.0, 0.0, 0.1), piece(1.1, 0.1, 0.05), piece(1.7, 0.17, 0.2, late=0.02),
          piece(1.9, 0.37, 1.2, stop=2.8), piece(2.9, 0.0, 0.0, late=0.01), piece(2.91, 0.01, 1.0)]
START_S = 0.5  # the recording's first sample, on the context's clock


def recording(source, pieces, n=16000 * 4):
    """What an output that plays `pieces` exactly records (a stopped piece stops 10 ms after the page's stop)."""
    out = np.zeros(n, np.float32)
    for p in pieces:
        end = p["at"] + p["dur"] if p["stop"] is None else p["stop"] + 0.01
        a, b, k = round((p["at"] - START_S) * 16000), round((end - START_S) * 16000), round(p["pts"] * 16000)
        out[a:b] += source[k : k + b - a]
    return out


def test_a_recording_of_what_the_page_scheduled_passes_and_anything_else_fails():
    source = (0.3 * np.random.default_rng(0).standard_normal(16000 * 3)).astype(np.float32)
    played = recording(source, PIECES)
    assert [len(s) for s in streams(PIECES)] == [4, 2]
    # scheduled 3 s ahead, then again from the pts heard (the clock moved): one stream; a drop after it, another
    rescheduled = [piece(1.0, 0.0, 3.0, stop=2.0), piece(2.0, 1.0, 2.0), piece(4.0, 0.0, 1.0)]
    assert [len(s) for s in streams(rescheduled)] == [2, 1]
    expected, sure, covered = as_scheduled(PIECES, START_S, len(played), source)
    assert np.allclose(expected[sure], played[sure])
    assert covered.sum() == round(16000 * 2.28)  # (the stopped piece: to 30 ms after its stop)
    assert assert_played_as_scheduled(played, START_S, PIECES, source, 0.9, 3.0) > 0.99
    # not what the page says: the sound resumed after the hold where it stopped, not 20 ms on
    resumed = recording(source, PIECES[:2] + [piece(1.7, 0.15, 0.2)] + PIECES[3:])
    with pytest.raises(AssertionError, match="not what the page scheduled"):
        assert_played_as_scheduled(resumed, START_S, PIECES, source, 0.9, 1.2)
    # ... or the first drop went on after the second began
    went_on = recording(source, PIECES[:3] + [piece(1.9, 0.37, 1.2)] + PIECES[4:])
    with pytest.raises(AssertionError, match="not what the page scheduled"):
        assert_played_as_scheduled(went_on, START_S, PIECES, source, 2.7, 0.6)
    # ... or 30 ms late throughout
    late = np.concatenate([np.zeros(480, np.float32), played[:-480]])
    with pytest.raises(AssertionError, match="not what the page scheduled"):
        assert_played_as_scheduled(late, START_S, PIECES, source, 0.9, 3.0)
    # a piece asked for 5 ms ahead may start later than asked (the audio thread heard of it late): not compared
    tight = PIECES[:4] + [piece(2.9, 0.0, 0.0, late=0.01), piece(2.91, 0.01, 0.1) | {"ahead": 0.005},
                          piece(3.01, 0.11, 0.9) | {"ahead": 0.105}]
    started_late = recording(source, tight[:5] + [piece(2.93, 0.01, 0.1)] + tight[6:])
    assert assert_played_as_scheduled(started_late, START_S, tight, source, 2.85, 0.5) > 0.99
    with pytest.raises(AssertionError, match="not what the page scheduled"):
        assert_played_as_scheduled(started_late, START_S, PIECES, source, 2.85, 0.5)
    # where the recorder missed blocks nothing is compared
    gap = played.copy()
    gap[8000:12000] = 0
    assert assert_played_as_scheduled(gap, START_S, PIECES, source, 0.9, 3.0, missed=[(8000, 12000)]) > 0.99
