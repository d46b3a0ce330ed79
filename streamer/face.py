"""The face as the sinks send it: the frame channel "face" (the canonical vector, `dimgestor.face.FACE_LABELS`)
seen through a name set ("vrm0", "vrm1", "arkit", "oculus": `dimgestor.face.names`)."""

from __future__ import annotations

from functools import partial

from dimgestor.face.names import DEFAULT_NAMES, convert, names_of
from streamer.frames import Channel

__all__ = ["FACE", "face_channel"]

FACE = "face"  # the frame channel's name


def face_channel(name_set: str = DEFAULT_NAMES) -> Channel:
    """A sink channel of the face in `name_set`'s names (ValueError listing the known sets for another)."""
    names = names_of(name_set)
    return Channel(FACE, len(names), f"face blendshape weights 0..1, {name_set} names", labels=names,
                   source=FACE, derive=partial(convert, name_set=name_set))
