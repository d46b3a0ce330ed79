"""Metrics on cases with known answers."""

import numpy as np
import pytest

from dimgestor import metrics

# ---------------------------------------------------------------- Fréchet distance


def test_fgd_of_a_set_with_itself_is_zero():
    x = np.random.default_rng(0).normal(size=(500, 8))
    assert metrics.fgd(x, x) == pytest.approx(0.0, abs=1e-8)


def test_fgd_of_shifted_samples_is_the_squared_shift():
    # Same covariance, so the trace term vanishes exactly and only ||mu1 - mu2||^2 is left.
    x = np.random.default_rng(1).normal(size=(400, 5)) @ np.random.default_rng(2).normal(size=(5, 5))
    shift = np.array([0.5, -1.0, 2.0, 0.0, 0.25])
    assert metrics.fgd(x, x + shift) == pytest.approx(shift @ shift, rel=1e-6)


def test_frechet_distance_closed_form_for_diagonal_gaussians():
    mu1, mu2 = np.array([0.0, 1.0, 2.0]), np.array([1.0, 1.0, -1.0])
    a, b = np.array([1.0, 4.0, 0.25]), np.array([9.0, 1.0, 0.25])
    expected = np.sum((mu1 - mu2) ** 2) + np.sum(a + b - 2 * np.sqrt(a * b))
    assert metrics.frechet_distance(mu1, np.diag(a), mu2, np.diag(b)) == pytest.approx(expected, rel=1e-9)


def test_frechet_distance_matches_symmetric_form_for_full_covariances():
    # Tr sqrt(S1 S2) = Tr sqrt(S1^1/2 S2 S1^1/2), computed here by eigendecompositions only.
    rng = np.random.default_rng(3)
    m1, m2 = rng.normal(size=(6, 6)), rng.normal(size=(6, 6))
    s1, s2 = m1 @ m1.T + 0.1 * np.eye(6), m2 @ m2.T + 0.1 * np.eye(6)
    w, v = np.linalg.eigh(s1)
    s1_half = v @ np.diag(np.sqrt(w)) @ v.T
    inner = np.linalg.eigvalsh(s1_half @ s2 @ s1_half)
    mu1, mu2 = rng.normal(size=6), rng.normal(size=6)
    expected = np.sum((mu1 - mu2) ** 2) + np.trace(s1) + np.trace(s2) - 2 * np.sum(np.sqrt(inner))
    assert metrics.frechet_distance(mu1, s1, mu2, s2) == pytest.approx(expected, rel=1e-7)


def test_fgd_of_sampled_gaussians_approaches_the_closed_form():
    rng = np.random.default_rng(4)
    x = rng.normal(0.0, 1.0, size=(20000, 3))
    y = rng.normal(1.0, 2.0, size=(20000, 3))
    expected = 3 * 1.0 + 3 * (1 + 4 - 2 * 2)  # ||mu||^2 + Tr(I + 4I - 2 * 2I)
    assert metrics.fgd(x, y) == pytest.approx(expected, rel=0.05)


def test_fgd_is_finite_for_rank_deficient_covariances():
    # Fewer samples than dimensions: singular covariances need the regularised retry.
    rng = np.random.default_rng(5)
    value = metrics.fgd(rng.normal(size=(4, 10)), rng.normal(size=(4, 10)) + 1.0)
    assert np.isfinite(value) and value > 0


def test_frechet_distance_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="shape mismatch"):
        metrics.frechet_distance(np.zeros(2), np.eye(2), np.zeros(3), np.eye(3))


# ---------------------------------------------------------------- feature space


def _wavy_motion(rng, frames, dim, freq):
    t = np.arange(frames)[:, None] / 20.0
    return np.sin(2 * np.pi * freq * t + rng.uniform(0, 6.3, size=dim)) + 0.05 * rng.normal(size=(frames, dim))


def test_motion_chunks_shapes():
    chunks = metrics.motion_chunks(np.arange(100 * 2, dtype=np.float32).reshape(100, 2), chunk=34, stride=17)
    assert chunks.shape == (4, 34, 2)
    np.testing.assert_array_equal(chunks[1, 0], [34.0, 35.0])
    assert metrics.motion_chunks(np.zeros((10, 2)), chunk=34).shape == (0, 34, 2)


def test_autoencoder_learns_and_separates_distributions(tmp_path):
    rng = np.random.default_rng(6)
    slow = metrics.motion_chunks(_wavy_motion(rng, 1200, 6, 0.5), chunk=34, stride=8)
    fast = metrics.motion_chunks(_wavy_motion(rng, 1200, 6, 3.0), chunk=34, stride=8)
    import torch

    ae = metrics.train_motion_autoencoder(slow, latent=8, width=32, steps=150, batch=32)
    with torch.no_grad():
        trained_loss = ae.loss(torch.from_numpy(slow)).item()
    untrained = metrics.MotionAutoencoder(6, 34, 8, 32)
    untrained.load_state_dict({**untrained.state_dict(), "mean": ae.mean, "std": ae.std})
    with torch.no_grad():
        assert trained_loss < 0.7 * untrained.loss(torch.from_numpy(slow)).item()

    half = len(slow) // 2
    same = metrics.feature_fgd(ae, slow[:half], slow[half:])
    different = metrics.feature_fgd(ae, slow, fast)
    assert metrics.feature_fgd(ae, slow, slow) == pytest.approx(0.0, abs=1e-6)
    assert different > 5 * same

    ae.save(tmp_path)
    loaded = metrics.MotionAutoencoder.load(tmp_path)
    np.testing.assert_allclose(loaded.embed(fast), ae.embed(fast), atol=1e-6)


def test_autoencoder_rejects_wrong_chunk_shape():
    ae = metrics.MotionAutoencoder(4, 34)
    with pytest.raises(ValueError, match="expected chunks"):
        ae.embed(np.zeros((2, 20, 4)))


# ---------------------------------------------------------------- BeatAlign

SR, FPS = 16000, 20


def _audio_with_bursts(times, duration, seed=0):
    """Silence with short decaying noise bursts starting at `times` (s)."""
    rng = np.random.default_rng(seed)
    audio = 0.001 * rng.normal(size=int(duration * SR))
    n = int(0.08 * SR)
    for t in times:
        i = int(t * SR)
        audio[i : i + n] += 0.5 * rng.normal(size=n)[: len(audio) - i] * np.exp(-np.arange(n) / (0.02 * SR))[: len(audio) - i]
    return audio.astype(np.float32)


def _motion_with_beats_at(times, duration, joints=3):
    """Positions (T, J, 3) whose speed swings between 1 and 0.2, slowest exactly at each time in `times`."""
    t = np.arange(int(duration * FPS)) / FPS
    knots = np.concatenate([[-0.5], times, [duration + 0.5]])
    k = np.searchsorted(knots, t, side="right") - 1
    phase = (t - knots[k]) / (knots[k + 1] - knots[k])
    speed = 0.2 + 0.8 * np.sin(np.pi * phase) ** 2
    x = np.cumsum(speed) / FPS
    pos = np.zeros((len(t), joints, 3))
    for j in range(joints):
        pos[:, j, 0] = x * (j + 1)
        pos[:, j, 1] = 10.0 * j
    return pos


def _beat_times(seed, duration):
    gaps = np.random.default_rng(seed).uniform(0.6, 1.4, size=int(duration))
    times = 0.5 + np.cumsum(gaps)
    return times[times < duration - 0.5]


def test_audio_onsets_find_the_bursts():
    times = _beat_times(7, 20.0)
    onsets = metrics.audio_onsets(_audio_with_bursts(times, 20.0), SR)
    assert len(onsets) == len(times)
    np.testing.assert_allclose(onsets, times, atol=0.03)


def test_motion_beats_are_the_speed_minima():
    times = _beat_times(8, 20.0)
    beats = metrics.motion_beats(_motion_with_beats_at(times, 20.0), FPS)
    np.testing.assert_allclose(beats, times, atol=1.5 / FPS)  # frame grid + half a frame from integrating speed


def test_beat_align_is_near_one_for_motion_hitting_every_onset_and_lower_when_shuffled():
    times = _beat_times(9, 30.0)
    audio = _audio_with_bursts(times, 30.0)
    aligned = metrics.beat_align_score(audio, SR, _motion_with_beats_at(times, 30.0), FPS)
    # Same beat intervals in a shuffled order: same rhythm statistics, wrong times.
    gaps = np.diff(np.concatenate([[0.0], times]))
    shuffled_times = np.cumsum(np.random.default_rng(10).permutation(gaps))
    shuffled = metrics.beat_align_score(audio, SR, _motion_with_beats_at(shuffled_times, 30.0), FPS)
    assert aligned > 0.95
    assert shuffled < aligned - 0.2


def test_beat_align_edge_cases():
    assert metrics.beat_align(np.array([1.0, 2.0]), np.array([1.0, 2.0])) == pytest.approx(1.0)
    assert metrics.beat_align(np.array([1.0]), np.array([1.3]), sigma=0.3) == pytest.approx(np.exp(-0.5))
    assert metrics.beat_align(np.array([1.0]), np.zeros(0)) == 0.0
    assert np.isnan(metrics.beat_align(np.zeros(0), np.array([1.0])))
    still = np.zeros((100, 4, 3))
    assert metrics.motion_beats(still, FPS).size == 0


# ---------------------------------------------------------------- jerk


def test_jerk_of_cubic_motion_is_six_times_the_cubic_coefficient():
    t = np.arange(60)[:, None] / FPS  # (T, 1)
    a = np.array([[1.0, -2.0, 0.5], [0.0, 3.0, 0.0]])  # cubic coefficient per joint (J, 3)
    pos = a[None] * t[:, :, None] ** 3 + 0.7 * t[:, :, None] ** 2 - 2.0 * t[:, :, None] + 5.0
    expected = np.mean(6 * np.linalg.norm(a, axis=1))
    assert metrics.jerk(pos, FPS) == pytest.approx(expected, rel=1e-6)
    np.testing.assert_allclose(metrics.jerk_magnitude(pos, FPS), np.broadcast_to(6 * np.linalg.norm(a, axis=1), (57, 2)), rtol=1e-6)


def test_jerk_of_linear_motion_is_zero():
    t = np.arange(30)[:, None, None] / FPS
    assert metrics.jerk(np.concatenate([t, 2 * t, -t], axis=2), FPS) == pytest.approx(0.0, abs=1e-6)


def test_upper_body_joints_skip_fingers_and_legs():
    names = ["Hips", "Spine", "Neck", "Head", "HeadEnd", "RightShoulder", "RightArm", "RightForeArm", "RightHand",
             "RightHandThumb1", "RightUpLeg", "RightLeg", "RightFoot"]
    assert [names[i] for i in metrics.upper_body_joints(names)] == [
        "Spine", "Neck", "Head", "RightShoulder", "RightArm", "RightForeArm", "RightHand"]
