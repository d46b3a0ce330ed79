"""Live input conditioning (streamer/level.py): the level meter, its "no signal" verdict, and the noise gate."""

import numpy as np

from streamer.level import NO_SIGNAL_S, LevelMeter, NoiseGate, dbfs

RATE = 48000


def blocks(x: np.ndarray, n: int = 960):
    return [x[i : i + n] for i in range(0, len(x), n)]


def tone(seconds: float, dbfs_rms: float, hz: float = 220.0) -> np.ndarray:
    t = np.arange(int(seconds * RATE)) / RATE
    return (np.sqrt(2) * 10 ** (dbfs_rms / 20) * np.sin(2 * np.pi * hz * t)).astype(np.float32)


def noise(seconds: float, dbfs_rms: float, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).normal(size=int(seconds * RATE)) * 10 ** (dbfs_rms / 20)).astype(np.float32)


def test_meter_reads_the_rms_of_the_last_second():
    m = LevelMeter(RATE)
    for b in blocks(np.concatenate([tone(2.0, -6.0), tone(1.0, -30.0)])):
        m.update(b)
    assert abs(m.level_dbfs - -30.0) < 0.5
    assert m.describe() == "mic  -30 dBFS"
    assert dbfs(0.0) == -120.0


def test_no_signal_after_seconds_of_silence_and_back_at_the_first_sound():
    m = LevelMeter(RATE)
    silent = np.zeros(int((NO_SIGNAL_S - 0.1) * RATE), np.float32)
    for b in blocks(silent):
        m.update(b)
    assert not m.no_signal  # a speaker's pause is not a dead microphone
    for b in blocks(noise(0.2, -100.0)):  # a muted input's dither is still no signal
        m.update(b)
    assert m.no_signal and "NO SIGNAL" in m.describe()
    m.update(tone(0.02, -50.0))
    assert not m.no_signal and m.silent_s == 0.0


def test_a_quiet_room_through_a_live_microphone_is_a_signal():
    m = LevelMeter(RATE)
    for b in blocks(noise(NO_SIGNAL_S + 1, -68.0)):
        m.update(b)
    assert not m.no_signal


def test_gate_mutes_background_noise_and_passes_speech_with_its_pauses():
    g = NoiseGate(RATE, threshold_dbfs=-40.0, hold_s=0.3)
    hiss, talk, pause = noise(1.0, -50.0), tone(1.0, -20.0), np.zeros(int(0.2 * RATE), np.float32)
    x = np.concatenate([hiss, talk, pause, talk, hiss])
    y = np.concatenate([g.process(b) for b in blocks(x, 441)])  # block length unrelated to the 10 ms pieces
    n, t, p = len(hiss), len(talk), len(pause)
    ten_ms = RATE // 100
    assert np.all(y[: n - ten_ms] == 0)  # noise alone: the avatar hears silence (the onset's piece may open early)
    np.testing.assert_array_equal(y[n + ten_ms : n + t], x[n + ten_ms : n + t])  # open from the first loud piece
    np.testing.assert_array_equal(y[n + t : n + t + p], x[n + t : n + t + p])  # a short pause does not close it
    assert np.all(y[-n + int(0.3 * RATE) + 2 * ten_ms :] == 0)  # closes after the hold
    assert np.abs(np.diff(y)).max() <= np.abs(np.diff(x)).max() + 1e-6  # ramps: no clicks


def test_gate_is_stateful_across_blocks_exactly_like_one_long_block():
    x = np.concatenate([noise(0.5, -50.0), tone(0.5, -20.0), noise(0.6, -50.0)])
    whole = NoiseGate(RATE, -40.0).process(x)
    g = NoiseGate(RATE, -40.0)
    split = np.concatenate([g.process(b) for b in blocks(x, 480)])
    np.testing.assert_allclose(split, whole)
