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

import numpy as np

__all__ = ["OneEuroFilter"]


class OneEuroFilter:
    """Filters (n, D) frames sampled at `fps`, one call after another; the first frame passes unchanged."""

    def __init__(self, fps: float, min_cutoff_hz: float, beta: float = 0.0, d_cutoff_hz: float = 1.0):
        if fps <= 0 or min_cutoff_hz <= 0 or d_cutoff_hz <= 0 or beta < 0:
            raise ValueError(f"OneEuroFilter needs fps, min_cutoff_hz and d_cutoff_hz > 0 and beta >= 0, got "
                             f"fps={fps}, min_cutoff_hz={min_cutoff_hz}, beta={beta}, d_cutoff_hz={d_cutoff_hz}")
        self.fps, self.min_cutoff_hz, self.beta, self.d_cutoff_hz = float(fps), float(min_cutoff_hz), float(beta), float(d_cutoff_hz)
        self._x: np.ndarray | None = None  # last filtered frame (float64)
        self._dx: np.ndarray | None = None  # last filtered derivative (units per second)

    def _alpha(self, cutoff_hz):
        tau = 1.0 / (2.0 * math.pi * cutoff_hz)
        return 1.0 / (1.0 + tau * self.fps)

    @property
    def delay_s(self) -> float:
        """Time constant at rest: how far a slow signal lags behind."""
        return 1.0 / (2.0 * math.pi * self.min_cutoff_hz)

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        frames = np.asarray(frames)
        if frames.ndim != 2:
            raise ValueError(f"OneEuroFilter filters (n, D) frames, got shape {frames.shape}")
        dtype = frames.dtype if np.issubdtype(frames.dtype, np.floating) else np.float32
        if self.beta == 0.0 and len(frames):
            return self._fixed(frames.astype(np.float64)).astype(dtype)
        out = np.empty(frames.shape, np.float64)
        a_d = self._alpha(self.d_cutoff_hz)
        for i, x in enumerate(frames.astype(np.float64)):
            if self._x is None:
                self._x, self._dx = x.copy(), np.zeros_like(x)
            else:
                self._dx = self._dx + a_d * ((x - self._x) * self.fps - self._dx)
                a = self._alpha(self.min_cutoff_hz + self.beta * np.abs(self._dx))
                self._x = self._x + a * (x - self._x)
            out[i] = self._x
        return out.astype(dtype)

    def _fixed(self, x: np.ndarray) -> np.ndarray:
        """beta = 0: a fixed first-order low-pass, y_n = y_{n-1} + a (x_n - y_{n-1}), as one lfilter call."""
        from scipy.signal import lfilter

        if self._x is None:  # the first frame passes unchanged
            self._x, self._dx = x[0].copy(), np.zeros_like(x[0])
            x = x[1:]
            head = self._x[None]
        else:
            head = x[:0]
        if len(x):
            a = self._alpha(self.min_cutoff_hz)
            y, _ = lfilter([a], [1.0, a - 1.0], x, axis=0, zi=((1.0 - a) * self._x)[None])
            self._x = y[-1].copy()
            return np.concatenate([head, y])
        return head
