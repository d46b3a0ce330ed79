"""BVH recording sink: keeps the denormalized features and writes them on the training skeleton on close.

Decoding the whole recording at once with `features_to_motion` (rather than saving the streamed
poses) makes the file identical to `dimgestor generate` on the same audio, seed and steps.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from streamer.engine import Frame

log = logging.getLogger("streamer.record")


class BvhRecorder:
    def __init__(self, path: str | Path, skeleton, feature_spec, root: str = "free", tether_s: float = 5.0):
        self.path = Path(path)
        self.root, self.tether_s = root, tether_s  # the root mode the live sinks use, so the file shows what they showed
        if not self.path.parent.is_dir():
            raise FileNotFoundError(f"{self.path}: folder {self.path.parent} does not exist")
        self.skeleton, self.spec = skeleton, feature_spec
        self.parts: list[np.ndarray] = []
        self.frames = 0
        self.closed = False

    def on_frames(self, frames: list[Frame]) -> None:
        if frames:
            self.parts.append(np.stack([f.features for f in frames]))
            self.frames += len(frames)

    def close(self) -> Path | None:
        """Write the BVH (atomically: a partial file never replaces a good one); None if nothing was recorded."""
        if self.closed:
            return None
        self.closed = True
        if not self.frames:
            log.warning("%s: no frames were generated, nothing recorded", self.path)
            return None
        from dimgestor.bvh import write_bvh
        from dimgestor.features import features_to_motion

        motion = features_to_motion(np.concatenate(self.parts), self.skeleton, self.spec, root=self.root,
                                    tether_s=self.tether_s)
        tmp = self.path.with_name(self.path.name + ".part")
        write_bvh(tmp, motion)
        os.replace(tmp, self.path)
        return self.path
