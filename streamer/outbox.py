"""A connection's outgoing side: one bounded queue and one sender task per client, and its read budget.

A broadcast frame put in a full queue drops the oldest droppable message and is counted, so broadcasting never
awaits a slow client; a client's own frames are never dropped: its session waits for room instead.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass

from websockets.asyncio.server import ServerConnection

DROPPABLE = ("frame", "note", "audio")  # broadcast frames; status, pong and error replies; source audio


class MessageBudget:
    """Token bucket on a client's messages: `rate` per second, bursts of `burst`; a text message also costs
    one token per KiB (parsing is the event loop's work). Over budget, the client is read more slowly."""

    def __init__(self, rate: float = 250.0, burst: float = 500.0):
        self.rate, self.burst = rate, burst
        self.tokens, self.t = burst, time.monotonic()

    def wait_s(self, message: str | bytes) -> float:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
        self.t = now
        self.tokens -= 1 + (len(message) / 1024 if isinstance(message, str) else 0)
        return max(0.0, -self.tokens / self.rate)


@dataclass
class FrameTotals:
    """Frames sent and dropped over all clients, past and present (the metrics' `sink="ws"` counts)."""

    sent: int = 0
    dropped: int = 0


class Outbox:
    """The messages waiting for one client, the task that sends them, and what was sent and dropped."""

    def __init__(self, ws: ServerConnection, max_queue: int, totals: FrameTotals | None = None):
        self.ws = ws
        self.queue: deque[tuple[str, str | bytes]] = deque()  # (kind, message)
        self.max_queue = max_queue
        self.ready = asyncio.Event()  # something to send
        self.room = asyncio.Event()  # the queue has room
        self.frames_sent = 0
        self.dropped = 0
        self.totals = totals if totals is not None else FrameTotals()  # the server's, shared by all its clients
        self.sending = False  # send_loop is handing a message to the socket

    def put(self, message: str | bytes, kind: str = "ctl") -> None:
        """Queue a message. "ctl" (hello, end) and "own" frames always go in; a droppable one ("frame",
        "note") finds a full queue -> the oldest droppable message goes (itself if none is older)."""
        if len(self.queue) >= self.max_queue and kind in DROPPABLE:
            victim = next((i for i, (k, _) in enumerate(self.queue) if k in DROPPABLE), None)
            lost = kind == "frame" if victim is None else self.queue[victim][0] == "frame"
            self.dropped += lost
            self.totals.dropped += lost
            if victim is None:
                return
            del self.queue[victim]
        self.queue.append((kind, message))
        self.ready.set()

    def note(self, message: str) -> None:
        self.put(message, "note")

    async def put_own(self, messages: list[str | bytes]) -> None:
        """This client's own frames: wait (bounded by the client reading) for room, never drop."""
        while len(self.queue) >= self.max_queue:
            self.room.clear()
            await self.room.wait()
        for m in messages:
            self.put(m, "own")

    async def send_loop(self) -> None:
        while True:
            while not self.queue:
                self.ready.clear()
                await self.ready.wait()
            kind, message = self.queue.popleft()
            self.room.set()
            self.sending = True
            try:
                await self.ws.send(message)
            finally:
                self.sending = False
            sent = kind in ("frame", "own")
            self.frames_sent += sent
            self.totals.sent += sent

    @property
    def awaits_reading(self) -> bool:
        """Something waits for the client to read it: messages queued, or one being sent (blocked while the
        client's socket is full)."""
        return bool(self.queue) or self.sending

    async def drained(self, deadline: float) -> None:
        """Wait until everything queued so far has been handed to the socket, or the loop time `deadline`."""
        loop = asyncio.get_running_loop()
        while self.queue and loop.time() < deadline:
            await asyncio.sleep(0.01)
