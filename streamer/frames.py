"""The frame every sink receives: one motion frame on the audio clock. Pure data (no threads, no model), so
the protocol encoder, the VMC encoder and the recorder depend on it alone, not on the inference engine."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Frame"]


@dataclass(frozen=True)
class Frame:
    index: int
    pts: float              # seconds on the audio clock: index / fps
    root_pos: np.ndarray    # (3,) BVH space, file units
    rotations: np.ndarray   # (J, 4) local, wxyz
    features: np.ndarray    # (D,) denormalized motion features (what --record writes)
