"""Causal output smoothing: the One Euro filter (Casiez, Roussel and Vogel, CHI 2012).

The standard jitter filter of live tracking and avatar tools: a first-order low-pass whose cutoff
rises with the signal's speed, so slow motion is smoothed hard and fast motion lags little. Here it
runs on the model's normalized motion features (every column has unit variance, so one `beta` suits
all of them). It is causal and carries its state, so a stream filtered window by window equals the
whole recording filtered at once, and `GestureStream` still equals `generate_offline`.

The delay it adds at rest is the time constant 1 / (2 pi min_cutoff_hz): 53 ms at 3 Hz.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["OneEuroFilter", "OneEuroState"]


class OneEuroState(NamedTuple):
    """What the filter carries from one call to the next (a value; None before the first frame)."""

    x: np.ndarray  # (D,) the last filtered frame (float64)
    dx: np.ndarray  # (D,) the last filtered derivative, units per second


class OneEuroFilter:
    """Filters (n, D) frames sampled at `fps`, one call after another; the first frame passes unchanged.

    `step(state, frames) -> (filtered, state)` is the filter (what `GestureStream` carries in its state);
    calling the filter runs `step` on a state it keeps itself.
    """

    def __init__(self, fps: float, min_cutoff_hz: float, beta: float = 0.0, d_cutoff_hz: float = 1.0):
        if fps <= 0 or min_cutoff_hz <= 0 or d_cutoff_hz <= 0 or beta < 0:
            raise ValueError(f"OneEuroFilter needs fps, min_cutoff_hz and d_cutoff_hz > 0 and beta >= 0, got "
                             f"fps={fps}, min_cutoff_hz={min_cutoff_hz}, beta={beta}, d_cutoff_hz={d_cutoff_hz}")
        self.fps, self.min_cutoff_hz, self.beta, self.d_cutoff_hz = float(fps), float(min_cutoff_hz), float(beta), float(d_cutoff_hz)
        self.state: OneEuroState | None = None  # what `__call__` carries

    def _alpha(self, cutoff_hz):
        tau = 1.0 / (2.0 * math.pi * cutoff_hz)
        return 1.0 / (1.0 + tau * self.fps)

    @property
    def delay_s(self) -> float:
        """Time constant at rest: how far a slow signal lags behind."""
        return 1.0 / (2.0 * math.pi * self.min_cutoff_hz)

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        out, self.state = self.step(self.state, frames)
        return out

    def step(self, state: OneEuroState | None, frames: np.ndarray) -> tuple[np.ndarray, OneEuroState | None]:
        """Filter the frames that follow `state` (None: the first frame passes unchanged) -> (filtered, new state)."""
        frames = np.asarray(frames)
        if frames.ndim != 2:
            raise ValueError(f"OneEuroFilter filters (n, D) frames, got shape {frames.shape}")
        dtype = frames.dtype if np.issubdtype(frames.dtype, np.floating) else np.float32
        if self.beta == 0.0 and len(frames):
            out, state = self._fixed(state, frames.astype(np.float64))
            return out.astype(dtype), state
        out = np.empty(frames.shape, np.float64)
        a_d = self._alpha(self.d_cutoff_hz)
        for i, x in enumerate(frames.astype(np.float64)):
            if state is None:
                state = OneEuroState(x.copy(), np.zeros_like(x))
            else:
                dx = state.dx + a_d * ((x - state.x) * self.fps - state.dx)
                a = self._alpha(self.min_cutoff_hz + self.beta * np.abs(dx))
                state = OneEuroState(state.x + a * (x - state.x), dx)
            out[i] = state.x
        return out.astype(dtype), state

    def _fixed(self, state: OneEuroState | None, x: np.ndarray) -> tuple[np.ndarray, OneEuroState]:
        """beta = 0: a fixed first-order low-pass, y_n = y_{n-1} + a (x_n - y_{n-1}), computed as
        y_n = a x_n + (1 - a) y_{n-1}: the sums scipy.signal.lfilter([a], [1, a - 1]) makes, bit for bit
        (tests/test_smoothing.py), without importing scipy.signal (~1 s of CPU, paid by a server's first frames)."""
        if state is None:  # the first frame passes unchanged
            state = OneEuroState(x[0].copy(), np.zeros_like(x[0]))
            x = x[1:]
            head = state.x[None]
        else:
            head = x[:0]
        if len(x):
            a = self._alpha(self.min_cutoff_hz)
            y, keep = np.empty_like(x), 1.0 - a
            prev = state.x
            for n in range(len(x)):
                prev = y[n] = keep * prev + a * x[n]
            return np.concatenate([head, y]), OneEuroState(y[-1].copy(), state.dx)
        return head, state
