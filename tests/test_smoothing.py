"""The One Euro output filter: known responses, state carried across calls, streaming still equals offline."""
import math

import numpy as np
import pytest

from dimgestor.smoothing import OneEuroFilter
from dimgestor.streaming.stream import GestureStream, generate_offline
from helpers.stream import noise_audio as _audio, random_tiny_model as _model, stream_in_pieces as _stream


def test_constant_signal_passes_unchanged_and_first_frame_is_kept():
    x = np.tile(np.array([[1.5, -2.0, 0.0]], np.float32), (30, 1))
    assert np.array_equal(OneEuroFilter(20, 3.0, 0.5)(x), x)


def test_beta_zero_is_the_first_order_low_pass_with_the_documented_time_constant():
    fps, fc = 20.0, 2.0
    f = OneEuroFilter(fps, fc)
    step = np.ones((200, 1))
    step[0] = 0.0
    y = f(step)[:, 0]
    alpha = 1 / (1 + fps / (2 * math.pi * fc))
    expected = 1 - (1 - alpha) ** np.arange(200)  # y_n = y_{n-1} + alpha (1 - y_{n-1}), y_0 = 0
    assert np.allclose(y, expected, atol=1e-12)
    # ~63 % of a step after about one time constant (discretisation makes it slightly later)
    n63 = int(np.argmax(y >= 1 - math.exp(-1)))
    assert abs(n63 / fps - f.delay_s) <= 1.5 / fps


def test_beta_lets_fast_motion_through_with_less_lag():
    t = np.arange(100) / 20.0
    ramp = (t * 5.0)[:, None]  # fast, steady motion
    slow, adaptive = OneEuroFilter(20, 1.0, 0.0)(ramp), OneEuroFilter(20, 1.0, 1.0)(ramp)
    lag = lambda y: (ramp - y)[-20:].mean()
    assert lag(adaptive) < 0.5 * lag(slow)


def test_jitter_is_damped():
    rng = np.random.default_rng(0)
    smooth = np.sin(np.arange(400) / 20.0 * 2 * math.pi * 0.5)[:, None]
    noisy = smooth + 0.2 * rng.standard_normal((400, 1))
    y = OneEuroFilter(20, 3.0)(noisy)
    jerk = lambda s: np.abs(np.diff(s, 3, axis=0)).mean()
    assert jerk(y) < 0.5 * jerk(noisy)
    assert np.abs(y - smooth)[40:].mean() < np.abs(noisy - smooth)[40:].mean()


@pytest.mark.parametrize("beta", [0.0, 0.3])
def test_calls_in_pieces_equal_one_call(beta):
    x = np.random.default_rng(1).standard_normal((57, 4)).astype(np.float32)
    whole = OneEuroFilter(20, 2.5, beta)(x)
    f = OneEuroFilter(20, 2.5, beta)
    parts = np.concatenate([f(x[:1]), f(x[1:1]), f(x[1:20]), f(x[20:])])
    assert np.allclose(parts, whole, atol=1e-6)
    assert OneEuroFilter(20, 2.5, beta)(x[:0]).shape == (0, 4)


def test_fixed_cutoff_fast_path_equals_the_per_frame_recursion():
    x = np.random.default_rng(2).standard_normal((40, 3))
    fast = OneEuroFilter(20, 2.0, 0.0)(x)
    slow = OneEuroFilter(20, 2.0, 1e-300)(x)  # beta > 0 takes the per-frame loop; 1e-300 changes nothing
    assert np.allclose(fast, slow, atol=1e-12)


def test_bad_settings_are_clear_errors():
    with pytest.raises(ValueError, match="min_cutoff_hz"):
        OneEuroFilter(20, 0.0)
    with pytest.raises(ValueError, match=r"\(n, D\)"):
        OneEuroFilter(20, 1.0)(np.zeros(5))


def test_streaming_with_smoothing_equals_offline_and_the_config_default_applies():
    model = _model(smooth_hz=3.0, smooth_beta=0.2)
    audio = _audio(2.0)
    smoothed = generate_offline(model, audio, steps=4, seed=1)
    raw = generate_offline(model, audio, steps=4, seed=1, smoothing=None)
    assert not np.allclose(smoothed, raw)
    assert np.allclose(smoothed, OneEuroFilter(20, 3.0, 0.2)(raw), atol=1e-6)
    assert np.abs(_stream(model, audio, [777] * (len(audio) // 777) + [len(audio) % 777], steps=4, seed=1)
                  - smoothed).max() < 1e-4
    assert np.allclose(generate_offline(model, audio, steps=4, seed=1, smoothing=(1.0, 0.0)),
                       OneEuroFilter(20, 1.0)(raw), atol=1e-6)
    assert GestureStream(model, smoothing=0).smoother is None
    with pytest.raises(ValueError, match="smoothing must be"):
        GestureStream(model, smoothing="heavy")


def test_the_checkpoint_defaults_drive_steps_and_smoothing():
    from dimgestor.cli_help import smoothing_from_flag
    model = _model(sample_steps=2, smooth_hz=2.0)
    audio = _audio(1.0)
    assert np.array_equal(generate_offline(model, audio), generate_offline(model, audio, steps=2, smoothing=2.0))
    assert not np.allclose(generate_offline(model, audio), generate_offline(model, audio, steps=8))
    assert len(GestureStream(model).pairs) == 2
    assert smoothing_from_flag(None) == "config" and smoothing_from_flag(0) is None and smoothing_from_flag(4) == 4
    with pytest.raises(ValueError, match="--smooth"):
        smoothing_from_flag(-1)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_beta_zero_adds_as_scipy_lfilter_does_bit_for_bit(dtype):
    """The fixed low-pass is a loop of numpy (no scipy.signal import, ~1 s of CPU); its sums are lfilter's, in the
    same order, so a filtered stream is what it was: from the first frame and from a carried state."""
    from scipy.signal import lfilter

    f = OneEuroFilter(20.0, 1.5)
    a = f._alpha(f.min_cutoff_hz)
    x = np.random.default_rng(1).normal(size=(300, 42)).astype(dtype)
    out, state = f.step(None, x)
    want = lfilter([a], [1.0, a - 1.0], x[1:].astype(np.float64), axis=0, zi=((1.0 - a) * x[0].astype(np.float64))[None])[0]
    assert out.dtype == dtype and np.array_equal(out[0], x[0]) and np.array_equal(out[1:], want.astype(dtype))
    more = np.random.default_rng(2).normal(size=(50, 42)).astype(dtype)
    out2, _ = f.step(state, more)
    want2 = lfilter([a], [1.0, a - 1.0], more.astype(np.float64), axis=0, zi=((1.0 - a) * state.x)[None])[0]
    assert np.array_equal(out2, want2.astype(dtype))
