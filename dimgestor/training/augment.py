"""Audio augmentation for training across voices, rooms and microphones, with the timing kept exactly.

`augment(audio, sr, seed, config)` returns audio of the same length whose events sit at the same samples
(it stays aligned with the motion capture): every effect is zero-phase or keeps its direct path at lag 0,
and the pitch shift restores the duration with a time stretch whose drift is bounded by its search range.
The chain follows the signal's path from a talker to a recording: voice (pitch, formants) -> room (reverb)
-> other sound in the room (noise) -> microphone and channel (EQ, band limits) -> gain -> a peak limiter.
A seed fixes everything: `draw` turns it into an `AugmentDraw` (the parameters, readable), `apply` renders
it; each effect draws from its own child generator, so one effect's probability never moves another's draw.
"""
from __future__ import annotations

from fractions import Fraction
from typing import Literal, Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["AugmentConfig", "AugmentDraw", "augment", "draw", "apply", "active_level", "pitch_shift",
           "time_stretch", "formant_shift", "equalize", "band_limit", "reverb", "make_noise", "add_noise",
           "gain", "soft_limit"]

NoiseKind = Literal["white", "pink", "brown", "babble"]
BandKind = Literal["telephone", "lowpass", "highpass"]
Range = tuple[float, float]
MIN_SAMPLES = 4096  # shorter audio is processed padded with silence to this length


class AugmentConfig(BaseModel):
    """Probabilities and ranges of each effect (uniform within a range unless said otherwise)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    p_pitch: float = Field(0.5, ge=0, le=1)  # other voices: the commonest difference between speakers
    semitones: Range = (-4.0, 4.0)  # +-4 st spans a low male to a high female voice from a middle one
    p_formant: float = Field(0.3, ge=0, le=1)  # vocal tract length, independent of pitch
    formant_ratio: Range = (0.85, 1.18)  # log-uniform; adult vocal tracts differ by up to ~20 %
    p_reverb: float = Field(0.4, ge=0, le=1)  # users talk in rooms, the capture was made close-miked
    rt60_s: Range = (0.2, 1.0)  # a furnished office to a bare hall
    wet: Range = (0.1, 0.5)  # share of the reverberant part; 0.5 is a far microphone (direct = reverberant)
    p_noise: float = Field(0.5, ge=0, le=1)  # fans, streets, other talkers
    snr_db: Range = (5.0, 30.0)  # against the active speech level; 5 dB is hard but intelligible
    noise_kinds: tuple[NoiseKind, ...] = ("white", "pink", "brown", "babble")  # babble only with other speech
    babble_talkers: tuple[int, int] = (3, 6)  # few enough that single words poke out, as in a cafe
    p_eq: float = Field(0.5, ge=0, le=1)  # microphones and speakers colour the spectrum
    eq_bands: tuple[int, int] = (1, 3)  # random peaking/shelf filters per draw
    eq_db: Range = (-12.0, 12.0)  # each band's gain; +-12 dB is a cheap headset, not a broken one
    eq_hz: Range = (80.0, 6000.0)  # log-uniform centre / corner frequencies
    eq_q: Range = (0.5, 2.0)  # peaking bandwidths from broad tilt to a resonance
    p_band: float = Field(0.3, ge=0, le=1)  # narrow channels: phones, VoIP codecs, cheap or rumble-filtered mics
    telephone_hz: Range = (300.0, 3400.0)  # the classic narrowband telephone channel (fixed corners)
    lowpass_hz: Range = (4000.0, 7500.0)  # wideband codecs and cheap mics, up to just under 16 kHz audio's Nyquist
    highpass_hz: Range = (100.0, 300.0)  # rumble filters and small loudspeakers
    p_dynamics: float = Field(0.0, ge=0, le=1)  # speakers vary their loudness more or less than the actor
    dynamics_ratio: Range = (0.4, 1.0)  # log-uniform; how far loudness strays from its typical level, times this
    p_gain: float = Field(1.0, ge=0, le=1)  # every microphone is at some level
    gain_db: Range = (-30.0, 6.0)  # a distant laptop mic to a hot headset; the limiter catches the top
    limit_knee: float = Field(0.9, gt=0, lt=1)  # samples above this are soft-limited, the level stays
    limit_ceiling: float = Field(0.999, gt=0, le=1)  # never reached: a float32 WAV stays unclipped

    @model_validator(mode="after")
    def _check(self):
        for name in ("semitones", "formant_ratio", "rt60_s", "wet", "snr_db", "babble_talkers", "eq_bands", "eq_db",
                     "eq_hz", "eq_q", "telephone_hz", "lowpass_hz", "highpass_hz", "gain_db", "dynamics_ratio"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}: the range ({lo}, {hi}) is reversed")
        if min(self.formant_ratio + self.rt60_s + self.eq_hz + self.eq_q + self.telephone_hz + self.lowpass_hz
               + self.highpass_hz + self.dynamics_ratio) <= 0 or self.babble_talkers[0] < 1 or self.eq_bands[0] < 0:
            raise ValueError("ratios, times, frequencies and Q must be positive, babble needs a talker")
        if not 0 <= self.wet[0] <= self.wet[1] <= 1:
            raise ValueError(f"wet must lie in [0, 1], got {self.wet}")
        if self.limit_ceiling <= self.limit_knee:
            raise ValueError("limit_ceiling must be above limit_knee")
        if not self.noise_kinds:
            raise ValueError("noise_kinds is empty (set p_noise = 0 for no noise)")
        return self


class AugmentDraw(BaseModel):
    """What one seed drew: None is an effect left out. Rendering it is deterministic (`apply`)."""

    model_config = ConfigDict(frozen=True)

    semitones: float | None = None
    formant_ratio: float | None = None
    reverb: tuple[float, float] | None = None  # (rt60 s, wet)
    noise: tuple[NoiseKind, float] | None = None  # (kind, SNR dB)
    eq: tuple[tuple[str, float, float, float], ...] = ()  # (peak|lowshelf|highshelf, Hz, dB, Q)
    band: tuple[BandKind, float, float] | None = None  # (kind, low Hz, high Hz); 0 / inf where open
    gain_db: float | None = None
    dynamics: float | None = None  # loudness deviations from the typical level, times this
    noise_seed: int = 0  # the random signals (reverb tail, noise, babble picks)


def draw(seed: int | Sequence[int], config: AugmentConfig, babble: bool = False) -> AugmentDraw:
    """The effects and their parameters for `seed` (babble is possible only when other speech is given)."""
    r = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(8)]
    c, d = config, {}
    if r[0].random() < c.p_pitch:
        d["semitones"] = float(r[0].uniform(*c.semitones))
    if r[1].random() < c.p_formant:
        d["formant_ratio"] = float(np.exp(r[1].uniform(*np.log(c.formant_ratio))))
    if r[2].random() < c.p_reverb:
        d["reverb"] = (float(r[2].uniform(*c.rt60_s)), float(r[2].uniform(*c.wet)))
    kinds = [k for k in c.noise_kinds if babble or k != "babble"]
    if r[3].random() < c.p_noise and kinds:
        d["noise"] = (kinds[int(r[3].integers(len(kinds)))], float(r[3].uniform(*c.snr_db)))
    if r[4].random() < c.p_eq:
        bands = []
        for _ in range(int(r[4].integers(c.eq_bands[0], c.eq_bands[1] + 1))):
            kind = ("peak", "peak", "lowshelf", "highshelf")[int(r[4].integers(4))]
            bands.append((kind, float(np.exp(r[4].uniform(*np.log(c.eq_hz)))), float(r[4].uniform(*c.eq_db)),
                          float(r[4].uniform(*c.eq_q))))
        d["eq"] = tuple(bands)
    if r[5].random() < c.p_band:
        kind = ("telephone", "lowpass", "highpass")[int(r[5].integers(3))]
        d["band"] = {"telephone": (kind, *c.telephone_hz), "lowpass": (kind, 0.0, float(r[5].uniform(*c.lowpass_hz))),
                     "highpass": (kind, float(r[5].uniform(*c.highpass_hz)), float("inf"))}[kind]
    if r[6].random() < c.p_gain:
        d["gain_db"] = float(r[6].uniform(*c.gain_db))
    if c.p_dynamics > 0:  # (its own stream, so configs without it draw exactly as before)
        rd = np.random.default_rng(np.random.SeedSequence(seed).spawn(9)[8])
        if rd.random() < c.p_dynamics:
            d["dynamics"] = float(np.exp(rd.uniform(*np.log(c.dynamics_ratio))))
    return AugmentDraw(**d, noise_seed=int(r[7].integers(2**63)))


def apply(audio: np.ndarray, sr: int, d: AugmentDraw, config: AugmentConfig,
          babble: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Render a draw: float32 audio of the same length, events at the same samples."""
    n = len(audio)
    # the filters and the STFT need some length: short audio is padded with silence after its end, cut below
    x = np.pad(np.asarray(audio, dtype=np.float64), (0, max(0, MIN_SAMPLES - n)))
    rng = np.random.default_rng(d.noise_seed)
    if d.dynamics is not None:
        x = dynamics(x, d.dynamics, sr)
    if d.semitones is not None:
        x = pitch_shift(x, d.semitones, sr)
    if d.formant_ratio is not None:
        x = formant_shift(x, d.formant_ratio, sr)
    if d.reverb is not None:
        x = reverb(x, *d.reverb, sr, rng)
    if d.noise is not None:
        kind, snr = d.noise
        x = add_noise(x, make_noise(kind, len(x), sr, rng, babble, config.babble_talkers), snr, sr)
    if d.eq:
        x = equalize(x, d.eq, sr)
    if d.band is not None:
        x = band_limit(x, d.band[1], d.band[2], sr)
    if d.gain_db is not None:
        x = gain(x, d.gain_db)
    return soft_limit(x[:n], config.limit_knee, config.limit_ceiling).astype(np.float32)


def augment(audio: np.ndarray, sr: int, seed: int | Sequence[int], config: AugmentConfig | None = None,
            babble: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """`audio` as heard through a random voice, room, noise, microphone and level; fixed by `seed`.

    babble: other speech (any lengths, at `sr`) to make babble noise from; without it babble is never drawn.
    """
    config = config or AugmentConfig()
    has_babble = bool(babble) and any(len(b) for b in babble)
    return apply(audio, sr, draw(seed, config, has_babble), config, babble if has_babble else None)


# ---------------- levels ----------------
def active_level(x: np.ndarray, sr: int, frame_ms: float = 20.0, floor_db: float = -35.0) -> float:
    """Mean power of the active frames (within `floor_db` of the loud frames' level), so pauses do not count.

    A simplified ITU-T P.56 active speech level: 20 ms frames, the reference is the 95th percentile frame
    power. Stationary noise is active throughout, so for it this is its mean power.
    """
    f = max(1, int(sr * frame_ms / 1000))
    n = len(x) // f
    if n == 0:
        return float(np.mean(np.square(x))) if len(x) else 0.0
    p = np.mean(np.square(x[: n * f].reshape(n, f)), axis=1)
    ref = np.percentile(p, 95)
    return float(p[p >= ref * 10 ** (floor_db / 10)].mean()) if ref > 0 else 0.0


def dynamics(x: np.ndarray, ratio: float, sr: int, window_ms: float = 100.0, max_db: float = 24.0) -> np.ndarray:
    """x with its loudness contour's deviations from the typical speech level times `ratio` (< 1 flatter, as a
    monotonous speaker; > 1 livelier), the change at most `max_db`; pauses (30 dB under the speech) untouched."""
    w = max(1, int(sr * window_ms / 1000))
    power = np.convolve(np.square(x), np.hanning(2 * w) / np.hanning(2 * w).sum(), mode="same")
    db = 10 * np.log10(np.maximum(power, 1e-12))
    level = 10 * np.log10(max(active_level(x, sr), 1e-12))
    change = np.clip((db - level) * (ratio - 1.0), -max_db, max_db)
    change = np.where(db > level - 30.0, change, 0.0)
    return x * 10 ** (change / 20)


def gain(x: np.ndarray, db: float) -> np.ndarray:
    """x scaled by `db` decibels."""
    return x * 10 ** (db / 20)


def _signal():
    """scipy.signal, imported where an augmentation first needs it: the import takes ~1 s of CPU, and every
    `dimgestor train` process imports this module (for AugmentConfig), most of them never augmenting."""
    from scipy import signal

    return signal


def soft_limit(x: np.ndarray, knee: float = 0.9, ceiling: float = 0.999) -> np.ndarray:
    """Peaks above `knee` bent smoothly (tanh) towards `ceiling`; everything below passes untouched.

    A limiter rather than normalization: a quiet draw stays quiet, a hot one keeps its level and only its
    peaks are squashed, as an overdriven microphone preamp does.
    """
    a = np.abs(x)
    over = a > knee
    if not over.any():
        return x
    y = x.copy()
    y[over] = np.sign(x[over]) * (knee + (ceiling - knee) * np.tanh((a[over] - knee) / (ceiling - knee)))
    return y


# ---------------- voice ----------------
def _resample(x: np.ndarray, ratio: float, max_den: int = 100) -> np.ndarray:
    """x resampled to about len(x) * ratio samples (zero-phase polyphase filter: no delay)."""
    q = Fraction(ratio).limit_denominator(max_den)
    return _signal().resample_poly(x, q.numerator, q.denominator)


def time_stretch(x: np.ndarray, n_out: int, win: int = 512, tol: int = 128, pull: float = 0.3) -> np.ndarray:
    """WSOLA: x spread over `n_out` samples at the same pitch; output sample t comes from input ~t*len(x)/n_out.

    Hann frames at a half-window hop are overlap-added; each frame's source is searched within +-`tol` samples
    of its nominal position for the best normalized match with the natural continuation of the previous
    frame, so waveforms join in phase and the timing error never exceeds `tol` (8 ms at 16 kHz). The
    continuation always lies on one side of the nominal position, which biased the choice by 6-9 ms on the
    ZEGGS speech at +-2..4 semitones; a penalty of `pull` * |offset| / tol on the correlation brings that to
    1-3 ms without worse joins (mean best correlation 0.83 -> 0.85).
    """
    hop = win // 2
    w = _signal().windows.hann(win, sym=False)  # sums to 1 at hop win/2
    rate = len(x) / n_out
    pad = win + tol
    xp = np.concatenate([np.zeros(pad), x, np.zeros(pad + win)])
    n_frames = n_out // hop + 2
    y = np.zeros(n_frames * hop + win)
    prev = None
    penalty = pull * np.abs(np.arange(-tol, tol + 1)) / tol
    for k in range(n_frames):
        nominal = int(round(k * hop * rate)) - win // 2 + pad  # frame centre at output k*hop <- input k*hop*rate
        start = nominal
        if prev is not None:
            target = xp[prev + hop: prev + hop + win]
            region = xp[nominal - tol: nominal + tol + win]
            corr = np.correlate(region, target, mode="valid")  # (2 tol + 1,)
            c2 = np.concatenate([[0.0], np.cumsum(np.square(region))])
            energy = c2[win:] - c2[:-win]  # of each candidate, (2 tol + 1,)
            score = corr / np.sqrt(energy * np.dot(target, target) + 1e-12)  # in [-1, 1]
            start = nominal - tol + int(np.argmax(score - penalty))
        y[k * hop: k * hop + win] += w * xp[start: start + win]
        prev = start
    return y[win // 2: win // 2 + n_out]


def pitch_shift(x: np.ndarray, semitones: float, sr: int) -> np.ndarray:
    """Pitch (and formants) moved by `semitones` with the duration and timing kept.

    Resampling by r = 2^(s/12) moves every frequency by r but plays r times faster; WSOLA then stretches
    the result back to len(x) samples, which restores the timing without moving the frequencies again.
    """
    if semitones == 0:
        return x.copy()
    y = _resample(x, 2 ** (-semitones / 12))
    return time_stretch(y, len(x))


def formant_shift(x: np.ndarray, ratio: float, sr: int, n_fft: int = 512, lifter_ms: float = 2.0,
                  iterations: int = 8) -> np.ndarray:
    """Spectral envelope (formants) scaled in frequency by `ratio`, pitch and timing kept.

    Per STFT frame the envelope is a "true envelope": the log spectrum smoothed cepstrally (quefrencies under
    `lifter_ms`, below any voice's pitch period) and iterated to ride on the harmonic peaks rather than
    between them. The frame is multiplied by warped / original envelope (bounded to -40..+20 dB, so
    near-empty bands are not blown up) and resynthesized with its own phase.
    """
    if ratio == 1:
        return x.copy()
    hop = n_fft // 4
    _, _, Z = _signal().stft(x, nperseg=n_fft, noverlap=n_fft - hop, window="hann")  # (bins, frames)
    log_mag = np.log(np.abs(Z) + 1e-9)
    cut = max(1, int(lifter_ms * sr / 1000))

    def smooth(log_spec):
        cep = np.fft.irfft(log_spec, n=n_fft, axis=0)
        cep[cut: n_fft - cut + 1] = 0
        return np.fft.rfft(cep, axis=0).real

    env = smooth(log_mag)
    for _ in range(iterations):
        env = smooth(np.maximum(log_mag, env))
    src = np.arange(env.shape[0]) / ratio  # the warped envelope at bin b is the original's at b / ratio
    i0 = np.minimum(src.astype(int), env.shape[0] - 1)
    i1 = np.minimum(i0 + 1, env.shape[0] - 1)
    frac = np.clip(src - i0, 0, 1)[:, None]
    warped = (1 - frac) * env[i0] + frac * env[i1]
    Z = Z * np.exp(np.clip(warped - env, np.log(1e-2), np.log(10.0)))
    _, y = _signal().istft(Z, nperseg=n_fft, noverlap=n_fft - hop, window="hann")
    return np.pad(y, (0, max(0, len(x) - len(y))))[: len(x)]


# ---------------- room and noise ----------------
def reverb(x: np.ndarray, rt60: float, wet: float, sr: int, rng: np.random.Generator) -> np.ndarray:
    """(1 - wet) * x + wet * (x convolved with a synthetic late reverberation tail).

    The tail is Gaussian noise under an exponential decay reaching -60 dB at `rt60`, slightly low-passed
    (walls absorb highs), unit energy, starting 3-10 ms after the direct sound (the first reflections); the
    direct path is x itself at lag 0, so onsets stay where they were.
    """
    pre = int(rng.uniform(0.003, 0.010) * sr)
    n = max(1, int(rt60 * sr))
    t = np.arange(n) / sr
    tail = rng.standard_normal(n) * np.exp(-3 * np.log(10) * t / rt60)  # amplitude -60 dB at rt60
    tail = _signal().lfilter([0.6], [1, -0.4], tail)  # one-pole low-pass
    tail /= np.sqrt(np.sum(np.square(tail)))
    h = np.concatenate([np.zeros(pre), tail])
    return (1 - wet) * x + wet * _signal().fftconvolve(x, h)[: len(x)]


def _coloured(n: int, sr: int, exponent: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise with power spectrum ~ 1/f^exponent (0 white, 1 pink, 2 brown), flat below 20 Hz."""
    spec = np.fft.rfft(rng.standard_normal(n))
    f = np.maximum(np.fft.rfftfreq(n, 1 / sr), 20.0)
    y = np.fft.irfft(spec / f ** (exponent / 2), n)
    return y / (np.std(y) + 1e-12)


def _babble(n: int, sr: int, sources: Sequence[np.ndarray], talkers: tuple[int, int],
            rng: np.random.Generator) -> np.ndarray:
    """A crowd: several random stretches of other speech, each pitch-shifted by resampling (tempo moves too,
    which no one can tell in a crowd) and brought to the same active level, summed."""
    out = np.zeros(n)
    sources = [s for s in sources if len(s)]
    for _ in range(int(rng.integers(talkers[0], talkers[1] + 1))):
        src = sources[int(rng.integers(len(sources)))]
        ratio = 2 ** (rng.uniform(-4, 4) / 12)
        need = int(np.ceil(n * ratio)) + 1
        idx = (int(rng.integers(len(src))) + np.arange(need)) % len(src)  # a random offset, looped if short
        seg = np.asarray(src[idx], dtype=np.float64)
        talker = _resample(seg, 1 / ratio)
        talker = np.pad(talker, (0, max(0, n - len(talker))))[:n]
        level = active_level(talker, sr)
        if level > 0:
            out += talker / np.sqrt(level)
    return out


def make_noise(kind: NoiseKind, n: int, sr: int, rng: np.random.Generator,
               babble: Sequence[np.ndarray] | None = None, talkers: tuple[int, int] = (3, 6)) -> np.ndarray:
    """n samples of white, pink, brown or babble noise (babble needs other speech)."""
    if kind == "babble":
        if not babble:
            raise ValueError("babble noise needs other speech (pass babble=[...])")
        return _babble(n, sr, babble, talkers, rng)
    return _coloured(n, sr, {"white": 0.0, "pink": 1.0, "brown": 2.0}[kind], rng)


def add_noise(x: np.ndarray, noise: np.ndarray, snr_db: float, sr: int, silent_ref_db: float = -25.0) -> np.ndarray:
    """x plus `noise` scaled so that active level(x) / active level(noise) is `snr_db`.

    Audio without speech (a silent window) is given noise as if its speech were at `silent_ref_db` dBFS,
    a typical level, so silent stretches also learn to ignore noise.
    """
    speech = active_level(x, sr)
    if speech <= 1e-10:
        speech = 10 ** (silent_ref_db / 10)
    level = active_level(noise, sr)
    if level <= 0:
        return x.copy()
    return x + noise * np.sqrt(speech / (level * 10 ** (snr_db / 10)))


# ---------------- microphone and channel ----------------
def _biquad(kind: str, f0: float, db: float, q: float, sr: int) -> np.ndarray:
    """One second-order section (b0 b1 b2 a0 a1 a2) of a peaking or shelving EQ, after R. Bristow-Johnson's
    Audio EQ Cookbook formulas (shelves with slope 1)."""
    a = 10 ** (db / 40)
    w0 = 2 * np.pi * min(f0, 0.45 * sr) / sr
    cw, sw = np.cos(w0), np.sin(w0)
    if kind == "peak":
        al = sw / (2 * q)
        b, den = [1 + al * a, -2 * cw, 1 - al * a], [1 + al / a, -2 * cw, 1 - al / a]
    else:
        al = sw / 2 * np.sqrt(2.0)  # shelf slope S = 1
        ra = 2 * np.sqrt(a) * al
        s = 1 if kind == "lowshelf" else -1  # the high shelf is the low shelf with cos w0 negated
        b = [a * ((a + 1) - s * (a - 1) * cw + ra), 2 * s * a * ((a - 1) - s * (a + 1) * cw),
             a * ((a + 1) - s * (a - 1) * cw - ra)]
        den = [(a + 1) + s * (a - 1) * cw + ra, -2 * s * ((a - 1) + s * (a + 1) * cw), (a + 1) + s * (a - 1) * cw - ra]
    return np.array(b + den) / den[0]


def equalize(x: np.ndarray, bands: Sequence[tuple[str, float, float, float]], sr: int) -> np.ndarray:
    """x through peaking / shelving filters (kind, Hz, dB, Q), run forwards and backwards at half the gain
    each way: the stated gains with zero phase, so nothing moves in time."""
    if not bands:
        return x.copy()
    sos = np.stack([_biquad(k, f, db / 2, q, sr) for k, f, db, q in bands])
    return _signal().sosfiltfilt(sos, x)


def band_limit(x: np.ndarray, low_hz: float, high_hz: float, sr: int, order: int = 4) -> np.ndarray:
    """Butterworth high-pass at `low_hz` and/or low-pass at `high_hz` (0 / inf or Nyquist: that side open),
    zero-phase (forwards and backwards, so 2 x `order` poles and -6 dB at the corners)."""
    nyq = sr / 2
    high_hz = min(high_hz, 0.95 * nyq)
    lo, hi = low_hz > 0, high_hz < 0.95 * nyq
    if lo and hi:
        sos = _signal().butter(order, [low_hz, high_hz], btype="bandpass", fs=sr, output="sos")
    elif lo or hi:
        sos = _signal().butter(order, low_hz if lo else high_hz, btype="highpass" if lo else "lowpass", fs=sr,
                            output="sos")
    else:
        return x.copy()
    return _signal().sosfiltfilt(sos, x)
