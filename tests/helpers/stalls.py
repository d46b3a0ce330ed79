"""How long this test process's own event loop stalled: tests that bound gaps between frames a server sends
measure them where they arrive, in a process that shares CI's cores with other work; a stall of its own is
not the server's doing."""
import asyncio
import time


class LoopStalls:
    """Run `watch()` as a task beside the clients; `worst` is the longest this loop ran late, in seconds;
    `within(t0, t1)` how long in all it ran late in that span (stalls that follow each other add up)."""

    def __init__(self, period_s: float = 0.02):
        self.period_s, self.worst = period_s, 0.0
        self.late: list[tuple[float, float]] = []  # (when it woke, how late), each late wake

    async def watch(self) -> None:
        while True:
            before = time.monotonic()
            await asyncio.sleep(self.period_s)
            now = time.monotonic()
            late = now - before - self.period_s
            self.worst = max(self.worst, late)
            if late > 0:
                self.late.append((now, late))

    def within(self, t0: float, t1: float) -> float:
        """Seconds this loop ran late between t0 and t1 (monotonic), the stall that ended just after t1 included."""
        return sum(late for woke, late in self.late if t0 <= woke and woke - late <= t1)
