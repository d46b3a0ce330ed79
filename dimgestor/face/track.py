"""The face track as a file: one CSV that any rig's names can be read from, written by `dimgestor generate --face-csv`
and beside a `serve --record` BVH.

    time,A,I,U,E,O,Blink,Blink_L,Blink_R,Joy,eyeBlinkLeft,...,tongueOut
    0.0000,0.0000,...

`time` is the frame's time in seconds (index / fps); then the VRM 0 presets, then ARKit's 52 blendshapes, each a
weight 0..1 with 4 decimals (as the WebSocket frames carry them). One row per body frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dimgestor.face.names import convert, names_of

__all__ = ["TRACK_SETS", "TRACK_NAMES", "track_header", "track_rows", "write_track"]

TRACK_SETS = ("vrm0", "arkit")  # the name sets of the columns, in order
TRACK_NAMES = tuple(n for s in TRACK_SETS for n in names_of(s))


def track_header() -> str:
    """The CSV's first line, newline included."""
    return ",".join(("time", *TRACK_NAMES)) + "\n"


def track_rows(face: np.ndarray, fps: float, first: int = 0) -> list[str]:
    """Canonical face frames (T, len(FACE_LABELS)), the first one frame `first` -> T CSV lines (newline included)."""
    face = np.atleast_2d(np.asarray(face, dtype=np.float64))
    if len(face) == 0:
        return []
    values = np.concatenate([convert(face, s) for s in TRACK_SETS], axis=1) + 0.0  # (T, len(TRACK_NAMES)); no -0.0
    return [f"{(first + i) / fps:.4f}," + ",".join(f"{v:.4f}" for v in row) + "\n" for i, row in enumerate(values)]


def write_track(path: str | Path, face: np.ndarray, fps: float) -> Path:
    """The whole track at once (header + one row per frame)."""
    path = Path(path)
    path.write_text(track_header() + "".join(track_rows(face, fps)))
    return path
