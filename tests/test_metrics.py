"""Metrics on cases with known answers."""

import numpy as np
import pytest

from dimgestor.evaluation import metrics

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


# ---------------------------------------------------------------- speech-drivenness

SR, FPS = 16000, 20


def _speech_like(seconds: float = 60.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Syllables (voiced tone bursts of random length and loudness) in phrases separated by random pauses,
    and the syllable onset times (s)."""
    rng = np.random.default_rng(seed)
    audio, onsets, t = np.zeros(int(seconds * SR), np.float32), [], 0.5
    while t < seconds - 2.0:
        for _ in range(rng.integers(3, 12)):  # a phrase
            if t > seconds - 1.0:
                break
            dur = rng.uniform(0.12, 0.3)
            n, start = int(dur * SR), int(t * SR)
            env = np.hanning(n) * rng.uniform(0.05, 0.5)
            audio[start:start + n] += (env * np.sin(2 * np.pi * rng.uniform(100, 250) * np.arange(n) / SR)).astype(np.float32)
            onsets.append(t)
            t += dur + rng.uniform(0.03, 0.15)
        t += rng.uniform(0.4, 2.0)  # a pause
    return audio, np.asarray(onsets)


def test_loudness_db_of_a_sine_and_of_silence():
    t = np.arange(2 * SR) / SR
    audio = np.where(t < 1, 0.5 * np.sin(2 * np.pi * 200 * t), 0.0)
    loud = metrics.loudness_db(audio, SR, FPS)
    assert loud.shape == (40,)
    np.testing.assert_allclose(loud[:20], 20 * np.log10(0.5 / np.sqrt(2)), atol=0.01)  # 200 Hz: 10 periods a frame
    assert (loud[20:] == metrics.LOUDNESS_FLOOR_DB).all()
    assert metrics.loudness_db(audio, SR, FPS, n_frames=45)[40:].tolist() == [metrics.LOUDNESS_FLOOR_DB] * 5


def test_hands_that_follow_the_loudness_couple_far_above_the_shifted_baseline():
    audio, _ = _speech_like()
    loud = metrics.loudness_db(audio, SR, FPS)
    speed = 10.0 + np.maximum(loud, -60.0)  # speed as an affine function of the clipped loudness: r ~ 1
    r = metrics.speech_coupling(speed, audio, SR, FPS)
    mean, sd = metrics.shifted_coupling(speed, audio, SR, FPS)
    assert r > 0.9
    assert abs(mean) < 0.2 and 0 < sd < 0.2
    assert r > mean + 2 * sd


def test_coupling_finds_a_lag_within_the_window_and_not_beyond():
    audio, _ = _speech_like(seed=1)
    speed = np.maximum(metrics.loudness_db(audio, SR, FPS), -60.0)
    late = np.concatenate([np.full(3, speed[0]), speed[:-3]])  # the hands 150 ms after the sound
    much_later = np.concatenate([np.full(20, speed[0]), speed[:-20]])  # 1 s after
    assert metrics.speech_coupling(late, audio, SR, FPS) > 0.9
    assert metrics.lagged_correlation(late, speed, 4)[1] == 3
    assert metrics.speech_coupling(much_later, audio, SR, FPS) < 0.5


def test_random_hand_speed_couples_at_its_baseline():
    audio, _ = _speech_like(seed=2)
    rng = np.random.default_rng(3)
    speed = np.abs(np.convolve(rng.standard_normal(len(audio) // 800 + 20), np.ones(5) / 5, mode="same"))[:len(audio) // 800]
    r = metrics.speech_coupling(speed, audio, SR, FPS)
    mean, sd = metrics.shifted_coupling(speed, audio, SR, FPS)
    assert abs(r - mean) < 3 * sd and abs(r - mean) < 0.3


def test_coupling_of_a_still_body_is_undefined():
    audio, _ = _speech_like(seconds=10.0)
    assert np.isnan(metrics.speech_coupling(np.zeros(200), audio, SR, FPS))
    assert all(np.isnan(metrics.shifted_coupling(np.zeros(200), audio, SR, FPS)))


def _bumps(times_s: np.ndarray, n_frames: int, width_s: float = 0.08) -> np.ndarray:
    t = np.arange(n_frames) / FPS
    return 1.0 + sum(5.0 * np.exp(-0.5 * ((t - c) / width_s) ** 2) for c in times_s)


def test_peaks_after_each_onset_align_and_random_peaks_score_as_shuffled():
    audio, onsets = _speech_like(seed=4)
    n = len(audio) // 800
    speech = metrics.speech_mask(audio, SR, FPS, n) == 1
    # sparse onsets (every 4th syllable) so that each gets its own peak
    onsets = onsets[::4]
    following = _bumps(onsets + 0.1, n)
    assert metrics.onset_alignment(onsets, following, FPS) == 1.0
    shuffled = metrics.shuffled_onset_alignment(len(onsets), following, FPS, speech, draws=20)
    assert shuffled < 0.75
    # peaks 0.5 s after the onsets are outside the stated window
    assert metrics.onset_alignment(onsets, _bumps(onsets + 0.5, n), FPS, window_s=(-0.1, 0.3)) < shuffled
    assert metrics.onset_alignment(onsets, _bumps(onsets + 0.5, n), FPS, window_s=(0.4, 0.6)) == 1.0

    rng = np.random.default_rng(5)
    random_peaks = _bumps(np.sort(rng.choice(np.flatnonzero(speech), len(onsets)) / FPS), n)
    aligned = metrics.onset_alignment(onsets, random_peaks, FPS)
    assert abs(aligned - metrics.shuffled_onset_alignment(len(onsets), random_peaks, FPS, speech, draws=20)) < 0.12


def test_speed_peaks_need_to_rise_above_the_clip_mean():
    speed = np.array([0, 1, 0, 0.1, 0.2, 0.1, 0, 3, 0, 0], float)
    assert metrics.speed_peaks(speed).tolist() == [1, 7]  # the 0.2 wobble is below the mean (0.44)
    assert metrics.speed_peaks(speed, threshold=0.0).tolist() == [1, 4, 7]
    assert np.isnan(metrics.onset_alignment(np.zeros(0), speed, FPS))
    assert metrics.onset_hits(np.array([0.3]), np.zeros(10), FPS).tolist() == [False]  # no peaks, no hits


def test_shuffled_onset_alignment_is_deterministic_for_a_seed():
    audio, onsets = _speech_like(seconds=20.0, seed=6)
    n = len(audio) // 800
    speed = _bumps(onsets[::3] + 0.1, n)
    speech = metrics.speech_mask(audio, SR, FPS, n) == 1
    a = metrics.shuffled_onset_alignment(30, speed, FPS, speech, seed=7)
    assert a == metrics.shuffled_onset_alignment(30, speed, FPS, speech, seed=7)
    times = metrics.shuffled_onsets(500, speech, FPS, np.random.default_rng(0))
    assert speech[(times * FPS).astype(int)].all()  # relocated inside speech only


def test_insert_silence_puts_exact_zeros_where_asked_and_keeps_the_rest():
    audio = np.random.default_rng(8).uniform(0.1, 0.9, 5 * SR).astype(np.float32)  # no zeros of its own
    out = metrics.insert_silence(audio, SR, at_s=2.0, seconds=6.0)
    assert len(out) == len(audio) + 6 * SR
    assert (out[2 * SR:8 * SR] == 0).all()
    np.testing.assert_array_equal(out[:2 * SR], audio[:2 * SR])
    np.testing.assert_array_equal(out[8 * SR:], audio[2 * SR:])
    noisy = metrics.insert_silence(audio, SR, at_s=2.0, seconds=6.0, noise_dbfs=-60.0)
    gap = noisy[2 * SR:8 * SR].astype(np.float64)
    assert 20 * np.log10(np.sqrt(np.mean(gap**2))) == pytest.approx(-60.0, abs=0.1)
    np.testing.assert_array_equal(noisy[8 * SR:], audio[2 * SR:])
    with pytest.raises(ValueError, match="outside"):
        metrics.insert_silence(audio, SR, at_s=6.0, seconds=1.0)


def test_inserted_silence_speeds_and_quietest_point():
    audio, _ = _speech_like(seconds=30.0, seed=9)
    at = metrics.quietest_point(audio, SR, 10.0, 20.0)
    assert 10.0 <= at < 20.0 and metrics.loudness_db(audio, SR, FPS)[int(at * FPS)] == metrics.LOUDNESS_FLOOR_DB
    gapped = metrics.insert_silence(audio, SR, at, 6.0)
    n = len(gapped) // 800
    t = np.arange(n) / FPS
    speed = np.where((t >= at) & (t < at + 6.0), 2.0, 10.0)  # calm in the inserted silence, busy elsewhere
    speaking, silent = metrics.inserted_silence_speeds(speed, gapped, SR, FPS, at, 6.0)
    assert (speaking, silent) == (10.0, 2.0)


def test_stressed_onsets_are_the_strongest_onsets_in_time_order():
    audio, _ = _speech_like(seconds=20.0, seed=10)
    every = metrics.audio_onsets(audio, SR)
    strong = metrics.stressed_onsets(audio, SR, keep=0.4)
    assert len(strong) == round(0.4 * len(every)) and np.all(np.diff(strong) > 0) and set(strong) <= set(every)
    env, rate = metrics.onset_strength(audio, SR)
    at = lambda t: env[np.round(np.asarray(t) * rate).astype(int)]  # noqa: E731
    weaker = np.setdiff1d(every, strong)
    assert at(strong).min() >= at(weaker).max()
    assert metrics.stressed_onsets(np.zeros(SR, np.float32), SR).size == 0


def test_onset_locked_speed_sizes_the_movement_after_onsets_not_any_nearby_peak():
    fps, T = 20.0, 400
    speech = np.ones(T, dtype=bool)
    onsets = np.arange(1.0, 19.0, 1.0)
    busy = 1.0 + 0.2 * np.sin(np.arange(T) * 2 * np.pi / 4)  # a small peak every 0.2 s: near every onset
    strokes = np.ones(T)
    for t in onsets:
        strokes[int(t * fps) : int(t * fps) + 6] = 3.0  # a large movement in the 0.3 s after each onset
    assert metrics.onset_alignment(onsets, busy, fps) == 1.0  # the hit rate cannot tell them apart
    assert abs(metrics.onset_locked_speed(onsets, busy, fps, speech) - 1.0) < 0.05
    assert metrics.onset_locked_speed(onsets, strokes, fps, speech) > 1.5  # (2.5 / 1.54)
    late = onsets + 0.5  # the same strokes 0.5 s before these onsets end before the window opens
    assert metrics.onset_locked_speed(late, strokes, fps, speech) < 1.0
    assert np.isnan(metrics.onset_locked_speed(np.zeros(0), strokes, fps, speech))


def test_nearest_window_distances_find_a_replayed_stretch_and_measure_a_new_one():
    """Variety (issue "real voices"): motion that replays a stretch of the reference is at distance 0 from it;
    the same motion moved by 5 units is 5 away (mean joint distance); windows never span two reference stretches."""
    from dimgestor.evaluation.metrics import nearest_window_distances

    rng = np.random.default_rng(0)
    ref = np.cumsum(rng.normal(scale=10.0, size=(200, 4, 3)), axis=0)  # a random walk: no two windows alike
    copy = ref[37:117]
    assert np.allclose(nearest_window_distances(copy, ref, 20.0), 0.0)
    assert np.allclose(nearest_window_distances(copy + np.array([3.0, 4.0, 0.0]), ref, 20.0), 5.0)
    d = nearest_window_distances(copy, ref, 20.0, window_s=1.0, query_hop_s=0.25)
    assert len(d) == (80 - 20) // 5 + 1
    # two stretches: a window made of the end of one and the start of the other is not in the reference
    joined = np.concatenate([ref[80:100], ref[0:20]])[10:30]
    assert nearest_window_distances(joined, [ref[:100], ref[100:]], 20.0).min() > 0.5
    with pytest.raises(ValueError, match="at least 20 frames"):
        nearest_window_distances(ref[:10], ref, 20.0)


def _nearest_window_distances_reference(query, reference, fps, window_s=1.0, query_hop_s=0.25):
    """The definition, window pair by window pair: every query window against every reference window."""
    from dimgestor.evaluation.metrics import window_stack

    n = int(round(window_s * fps))
    q = window_stack(np.asarray(query, np.float64), n, max(1, int(round(query_hop_s * fps))))
    stretches = list(reference) if isinstance(reference, (list, tuple)) else [reference]
    r = np.concatenate([window_stack(np.asarray(x, np.float64), n, 1) for x in stretches])
    return np.linalg.norm(q[:, None] - r[None], axis=-1).mean(axis=(2, 3)).min(axis=1)


@pytest.mark.parametrize("chunk", [1, 7, 512])
def test_nearest_window_distances_equal_the_window_by_window_definition(chunk):
    """The diagonal-sum fast path equals comparing every pair of windows, for reference chunks that split the
    windows anywhere, stretches shorter than a window, odd lengths and hops."""
    from dimgestor.evaluation.metrics import nearest_window_distances

    rng = np.random.default_rng(1)
    query = np.cumsum(rng.normal(scale=3.0, size=(53, 5, 3)), axis=0)
    stretches = [np.cumsum(rng.normal(scale=3.0, size=(t, 5, 3)), axis=0) for t in (31, 6, 20, 47)]
    for ref, fps, hop in ((stretches[0], 20.0, 0.25), (stretches, 20.0, 0.25), (stretches, 13.0, 0.1),
                          (stretches[3], 9.0, 0.5)):
        got = nearest_window_distances(query, ref, fps, query_hop_s=hop, chunk=chunk)
        np.testing.assert_allclose(got, _nearest_window_distances_reference(query, ref, fps, query_hop_s=hop),
                                   rtol=1e-12, atol=1e-12)
