"""The frame every sink receives: one motion frame on the audio clock, a pose plus named channels. Pure data
(no threads, no model), so the protocol encoder, the VMC encoder and the recorder depend on it alone, not on
the inference engine.

A channel is any per-frame vector beside the pose (e.g. the face's blendshape weights): the producer puts it in
`Frame.channels` under its `Channel.name`, and each sink sends the channels named in its own map
(`streamer.protocol.WS_CHANNELS`, `streamer.vmc.VMC_CHANNELS`, `streamer.record.RECORD_CHANNELS`); a sink
ignores the channels its map does not name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

__all__ = ["Channel", "Frame", "channel_values"]


@dataclass(frozen=True)
class Channel:
    """What one channel of a frame holds: `size` float values per frame, optionally one label per value."""

    name: str
    size: int
    description: str = ""
    labels: tuple[str, ...] = ()  # e.g. blendshape names; empty: the values are unnamed
    # A sink's view of a frame channel: the values of frame channel `source` (default: this name) through
    # `derive` (e.g. the canonical face as ARKit's 52 names); None: as the frame has them.
    source: str = ""
    derive: Callable[[np.ndarray], np.ndarray] | None = field(default=None, compare=False)

    def __post_init__(self):
        if not self.name or not self.name.replace("_", "").isalnum() or not self.name.isascii():
            raise ValueError(f"a channel name is letters, digits and '_', got {self.name!r}")
        if not isinstance(self.size, int) or isinstance(self.size, bool) or self.size < 1:
            raise ValueError(f"channel {self.name}: size must be a positive integer, got {self.size!r}")
        if self.labels and len(self.labels) != self.size:
            raise ValueError(f"channel {self.name}: {len(self.labels)} labels for {self.size} values")


@dataclass(frozen=True)
class Frame:
    index: int
    pts: float              # seconds on the audio clock: index / fps
    root_pos: np.ndarray    # (3,) BVH space, file units
    rotations: np.ndarray   # (J, 4) local, wxyz
    features: np.ndarray    # (D,) denormalized motion features (what --record writes)
    channels: Mapping[str, np.ndarray] = field(default_factory=dict)  # name -> (Channel.size,) values


def channel_values(frame: Frame, channel: Channel) -> np.ndarray:
    """The frame's values of `channel` as float64 (size,): zeros when the frame lacks it (e.g. a rest pose)."""
    values = frame.channels.get(channel.source or channel.name)
    if values is None:
        return np.zeros(channel.size)
    values = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if channel.derive is not None:
        values = np.atleast_1d(np.asarray(channel.derive(values), dtype=np.float64))
    if values.shape != (channel.size,):
        raise ValueError(f"frame {frame.index}: channel {channel.name} has shape {values.shape}, "
                         f"its spec says ({channel.size},)")
    return values
