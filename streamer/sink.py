"""The one interface of everything the server source's frames go to.

`WsServer` (WebSocket clients, `streamer/ws.py`), `VmcSink` (VMC/OSC over UDP, `streamer/vmc.py`) and
`RecordingSink` (a BVH file, `streamer/record.py`) implement it; `streamer.server.build` picks them from
the options and `run` drives them all alike. A new output (another protocol, a file format) is one more
class with these five methods and one more entry in the sinks `build` makes.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from streamer.frames import Frame


@runtime_checkable
class Sink(Protocol):
    async def open(self) -> None:
        """Take what it needs (a port, a socket, a file) before anything streams; an OSError says why not,
        in a message that names what failed."""

    def send(self, frames: list[Frame]) -> None:
        """Frames of the server's source, in order, as inference makes them (a burst per window). Must not
        block the event loop: a sink that paces or writes slowly queues, bounded, and counts what it drops."""

    async def close(self, drain: bool = True) -> None:
        """Stop. drain: the source ended, deliver what is queued (within a bound); else stop now (Ctrl-C)."""

    def describe(self) -> str:
        """Where its output goes, for the lines printed at start."""

    def status(self) -> str:
        """Its part of the periodic status line ("" for none)."""
