"""Live input conditioning: a level meter that notices a dead input, input gain, and a noise gate.

A muted or wrong microphone is the first thing a user at a live mic meets, so the meter tracks how long the
input has stayed below `SILENCE_DBFS` (muted inputs give exact zeros or a -90 dBFS noise floor; a quiet
room through a live microphone peaks above -65 dBFS). The gate exists because the model gestures to
whatever it hears: a fan's hiss at -45 dBFS is not speech and should leave the avatar at rest.
"""

from __future__ import annotations

from collections import deque

import numpy as np

SILENCE_DBFS = -70.0  # an input whose peak stays below this is "no signal"
NO_SIGNAL_S = 3.0     # ... for this long (a speaker's pauses are shorter)
METER_S = 1.0         # the level shown is the rms over this last stretch of input


def dbfs(amplitude: float) -> float:
    """Amplitude (1.0 = full scale) in dB relative to full scale; -inf dB is reported as -120."""
    return 20.0 * float(np.log10(max(float(amplitude), 1e-6)))


class LevelMeter:
    """rms over the last `METER_S` seconds, and how long the input has stayed silent (peak < `SILENCE_DBFS`)."""

    def __init__(self, rate: int, silence_dbfs: float = SILENCE_DBFS, no_signal_s: float = NO_SIGNAL_S):
        self.rate, self.no_signal_s = rate, no_signal_s
        self.silence = 10.0 ** (silence_dbfs / 20.0)
        self.blocks: deque[tuple[int, float]] = deque()  # (samples, sum of squares), newest last
        self.window_n = 0
        self.silent_s = 0.0  # length of the current silent stretch
        self.total_s = 0.0

    def update(self, x: np.ndarray) -> None:
        n = len(x)
        if n == 0:
            return
        self.blocks.append((n, float(np.dot(x, x))))
        self.window_n += n
        while self.window_n - self.blocks[0][0] >= METER_S * self.rate:
            self.window_n -= self.blocks.popleft()[0]
        self.silent_s = self.silent_s + n / self.rate if float(np.abs(x).max()) < self.silence else 0.0
        self.total_s += n / self.rate

    @property
    def level_dbfs(self) -> float:
        if not self.window_n:
            return dbfs(0.0)
        return dbfs(np.sqrt(sum(s for _, s in self.blocks) / self.window_n))

    @property
    def no_signal(self) -> bool:
        return self.silent_s >= self.no_signal_s

    def describe(self) -> str:
        """For the status line: `mic -23 dBFS`, or the warning while the input is dead."""
        if self.no_signal:
            return f"mic NO SIGNAL for {self.silent_s:.0f}s (muted? wrong --input-device?)"
        return f"mic {self.level_dbfs:4.0f} dBFS"


class NoiseGate:
    """Mutes the input while its level stays under `threshold_dbfs`.

    Decided per 10 ms piece on its rms: the gate opens on the first loud piece and closes after `hold_s`
    of quiet pieces (so a word's soft ending and short pauses pass), with a linear ramp over each piece
    whose gain changes (no clicks). Adds no latency: nothing is buffered.
    """

    def __init__(self, rate: int, threshold_dbfs: float, hold_s: float = 0.3):
        self.threshold = 10.0 ** (threshold_dbfs / 20.0)
        self.piece = max(1, rate // 100)
        self.hold = int(hold_s * rate)
        self.quiet = self.hold  # samples since the last loud piece: start closed
        self.gain = 0.0

    def process(self, x: np.ndarray) -> np.ndarray:
        y = np.empty_like(x)
        for i in range(0, len(x), self.piece):
            p = x[i : i + self.piece]
            loud = np.sqrt(np.mean(np.square(p, dtype=np.float64))) >= self.threshold
            self.quiet = 0 if loud else self.quiet + len(p)
            target = 1.0 if self.quiet <= self.hold else 0.0
            if target == self.gain:
                y[i : i + len(p)] = p * target
            else:
                ramp = np.linspace(self.gain, target, len(p) + 1, dtype=np.float32)[1:]
                y[i : i + len(p)] = p * ramp
                self.gain = target
        return y
