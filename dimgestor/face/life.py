"""The rest of a speaking face, from the same audio as the mouth: blinks, brows on pitch accents, a smile.

Each is a small state machine stepped once per frame on the stream's clock, deterministic for a seed (a blink's
time is drawn from a counter-based generator keyed by the seed and the blink's number), so a stream pushed in
any pieces blinks exactly as the whole recording does.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

__all__ = ["Blinks", "Brows", "pitch_semitones"]


@lru_cache(maxsize=1024)
def _draw(seed: int, k: int, n: int = 3) -> np.ndarray:
    """n uniform numbers for the k-th blink of stream `seed`: the same whatever happened before it (read-only:
    the same array is given to every caller of the same draw, each frame asks again)."""
    out = np.random.Generator(np.random.Philox(key=[seed & 0xFFFFFFFFFFFFFFFF, k])).random(n)
    out.flags.writeable = False
    return out


def _closure(u: float) -> float:
    """Eyelid closure u seconds after a blink began: closes in 80 ms, stays 40 ms, opens over 180 ms."""
    close, hold, open_ = 0.08, 0.04, 0.18
    if u < 0:
        return 0.0
    if u < close:
        return u / close
    if u < close + hold:
        return 1.0
    return min(max(1 - (u - close - hold) / open_, 0.0), 1.0)


@dataclass
class Blinks:
    """Spontaneous blinks as people blink while talking: intervals of `min_s` plus a gamma of shape 3 (mean
    `mean_s` in all: irregular, never metronomic, rarely a stare of more than 8 s), and a blink at a phrase's end (speech of at
    least a second, then a pause) when the eyes have been open long enough. Times are continuous (not on the frame
    grid); the lids are sampled at each frame."""

    seed: int = 0
    mean_s: float = 3.6
    min_s: float = 0.6
    phrase_p: float = 0.6
    count: int = 0
    last: float = -10.0           # when the newest blink began (s)
    next_at: float | None = None  # when the next spontaneous one begins
    started: list = field(default_factory=list)  # blink onsets (s), for statistics

    def step(self, t: float, phrase_end: bool) -> tuple[float, float]:
        """The lids' closure (left, right) at time t (frames in order); `phrase_end`: a pause begins at t."""
        if self.next_at is None:
            self.next_at = t + self._interval()
        if phrase_end and t - self.last > 1.5:
            u = _draw(self.seed, self.count)
            if u[2] < self.phrase_p:
                self._begin(t + 0.05 * u[0])
        if t >= self.next_at:
            self._begin(self.next_at)
        closure = _closure(t - self.last)
        right = closure * (0.93 + 0.07 * _draw(self.seed, self.count - 1, 1)[0])  # the eyes are never identical
        return closure, right

    def _begin(self, at: float) -> None:
        self.last = at
        self.started.append(at)
        self.count += 1
        self.next_at = at + self._interval()

    def _interval(self) -> float:
        u = _draw(self.seed, self.count, 6)[3:]  # (the first three: the phrase-end blink's)
        # min_s + gamma(3), mean mean_s: the sum of three exponentials, from three uniforms. (A floor clamped on a
        # gamma(2) piled many intervals at the floor, alike; gamma(3)'s tail stares at most ~8 s, 1 in 400.)
        return self.min_s - (self.mean_s - self.min_s) / 3 * float(np.sum(np.log1p(-u)))


def pitch_semitones(x: np.ndarray, rate: int = 16000, fmin: float = 70.0, fmax: float = 400.0) -> float | None:
    """The fundamental of a short stretch of speech in semitones above 100 Hz (normalized autocorrelation);
    None where it is not clearly voiced."""
    # (numpy's reductions called directly: the numbers of np.mean, without its wrappers' cost on every frame)
    x = np.asarray(x)
    if len(x) == 0:
        return None
    x = np.asarray(x, np.float64) - x.dtype.type(np.add.reduce(x) / len(x))
    x2 = x * x
    if np.sqrt(np.add.reduce(x2) / len(x)) < 1e-3:
        return None
    lo, hi = int(rate / fmax), int(rate / fmin)
    if len(x) < 2 * hi:
        return None
    n = len(x) - hi
    a = x[:n]
    # a . x[k:k + n] for each lag k in lo..hi-1 (np.correlate: contiguous dot products, ~5x a product with the
    # lags as an overlapping strided view, the face's largest part of a batch)
    lagged = np.correlate(x[lo:hi + n - 1], a, mode="valid")
    sq = np.concatenate([[0.0], np.cumsum(x2)])
    energy = sq[lo + n:hi + n] - sq[lo:hi]
    r = lagged / np.sqrt(np.dot(a, a) * energy + 1e-12)
    k = int(np.argmax(r))
    best, lag = float(r[k]), lo + k
    if best < 0.6:
        return None
    return float(12 * np.log2(rate / lag / 100.0))


@lru_cache(maxsize=16)
def _decay(fps: int, release_s: float) -> float:
    return float(np.exp(-1.0 / (fps * release_s)))


@dataclass
class Brows:
    """Brows raised on prominent syllables, as speakers raise them on the words they stress: a vowel within a few
    dB of the voice's recent peak (stressed syllables are louder: on real speech loudness tells a stressed vowel
    from an unstressed one better than pitch does), more when its pitch also rises above the speaker's recent
    median; they settle over `release_s`."""

    fps: int = 20
    loud_db: tuple[float, float] = (-2.0, 0.0)  # below the recent peak: no raise at the first, full at the second
    rise: float = 1.0
    span: float = 3.0
    release_s: float = 0.3
    gain: float = 0.6
    level: float = 0.0
    recent: list = field(default_factory=list)  # voiced pitches of the last 5 s (semitones)

    def step(self, semitones: float | None, below_peak_db: float, vowel: bool) -> float:
        accent = 0.0
        if semitones is not None:
            self.recent.append(semitones)
            del self.recent[: max(0, len(self.recent) - int(5 * self.fps))]
        if vowel:
            lo, hi = self.loud_db
            accent = min(max(float((below_peak_db - lo) / (hi - lo)), 0.0), 1.0)
            if semitones is not None and len(self.recent) >= self.fps:  # a second of voice to know what is high
                rise = float((semitones - np.median(self.recent) - self.rise) / self.span)
                accent *= 0.6 + 0.4 * min(max(rise, 0.0), 1.0)
            else:
                accent *= 0.6
        self.level = max(accent, self.level * _decay(self.fps, self.release_s))
        return self.gain * self.level
