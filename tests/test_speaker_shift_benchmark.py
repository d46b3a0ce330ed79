"""benchmarks/speaker_shift.py: its measures on cases with known answers."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import speaker_shift  # noqa: E402


def test_shift_is_the_mean_move_in_pooled_standard_deviations():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(20000, 3))
    assert speaker_shift.shift(a, rng.normal(size=(20000, 3))) < 0.03
    b = rng.normal(size=(20000, 3)) + np.array([0.5, 0.0, 1.0])
    assert speaker_shift.shift(a, b) == pytest.approx(0.5, abs=0.03)
    assert speaker_shift.shift(np.c_[a, np.ones(len(a))], np.c_[b, np.ones(len(b))]) == pytest.approx(0.5, abs=0.03)


def test_probe_tells_apart_only_what_differs():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(4000, 5)), rng.normal(size=(4000, 5))
    assert abs(speaker_shift.probe(a, b) - 0.5) < 0.05  # the same distribution: chance
    assert speaker_shift.probe(a, b + np.array([3.0, 0, 0, 0, 0])) > 0.9  # one channel apart: found


def test_nmse_and_levels():
    x = np.sin(np.arange(16000) / 50.0).astype(np.float32)
    f = np.c_[x, 2 * x]
    assert speaker_shift.nmse(f, f) == 0.0
    assert speaker_shift.nmse(f + 0.1, f) == pytest.approx(0.01 / f.var(0).mean(), rel=1e-6)
    from dimgestor.training.augment import active_level

    for dbfs in (-35.0, -10.0):  # the active level is a mean power
        assert 10 * np.log10(active_level(speaker_shift.at_level(x, dbfs), 16000)) == pytest.approx(dbfs, abs=0.01)
