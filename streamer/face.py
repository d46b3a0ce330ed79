"""The face as the sinks send it: the frame channel "face" (the canonical vector, `dimgestor.face.FACE_LABELS`)
seen through a name set ("vrm0", "vrm1", "arkit", "oculus": `dimgestor.face.names`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

from dimgestor.face import FaceOptions
from dimgestor.face.names import DEFAULT_NAMES, check_name_set, convert, names_of
from streamer.frames import Channel

__all__ = ["FACE", "ServeFace", "face_channel"]

FACE = "face"  # the frame channel's name


def face_channel(name_set: str = DEFAULT_NAMES) -> Channel:
    """A sink channel of the face in `name_set`'s names (ValueError listing the known sets for another)."""
    names = names_of(name_set)
    return Channel(FACE, len(names), f"face blendshape weights 0..1, {name_set} names", labels=names,
                   source=FACE, derive=partial(convert, name_set=name_set))


@dataclass(frozen=True)
class ServeFace:
    """`serve`'s face, resolved once at start (from --face, --smile and --seed, on a machine that has its listener)
    and handed to everything that makes or sends one: the name set its frames carry unless a client asks another
    (the hello, the WebSocket clients' terms, VMC), and how every session makes it. No face: None, not a value."""

    names: str = DEFAULT_NAMES  # "vrm0", "vrm1", "arkit" or "oculus"
    options: FaceOptions = field(default_factory=FaceOptions)

    def __post_init__(self):
        check_name_set(self.names)
