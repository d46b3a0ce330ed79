"""How long this test process's own event loop stalled: tests that bound gaps between frames a server sends
measure them where they arrive, in a process that shares CI's cores with other work; a stall of its own is
not the server's doing."""
import asyncio
import time


class LoopStalls:
    """Run `watch()` as a task beside the clients; `worst` is the longest this loop ran late, in seconds."""

    def __init__(self, period_s: float = 0.02):
        self.period_s, self.worst = period_s, 0.0

    async def watch(self) -> None:
        while True:
            before = time.monotonic()
            await asyncio.sleep(self.period_s)
            self.worst = max(self.worst, time.monotonic() - before - self.period_s)
