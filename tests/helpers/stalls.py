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


def runnable_waiting_s(pid: int) -> float:
    """Seconds the main thread of process `pid` has spent runnable but waiting for a CPU (Linux schedstat): how
    long the machine's other work held it up. 0.0 where that is not known (another OS, or the process is gone)."""
    try:
        return int(open(f"/proc/{pid}/schedstat").read().split()[1]) / 1e9
    except (OSError, ValueError, IndexError):
        return 0.0


def wait_counting_cpu_waits(proc, since: float, timeout: float = 10.0) -> float:
    """Wait for `proc` to exit; return how long its main thread waited for a CPU since `since` (a reading of
    runnable_waiting_s), read every 20 ms until it exited."""
    waited, deadline = 0.0, time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < deadline:
        waited = max(waited, runnable_waiting_s(proc.pid) - since)
        time.sleep(0.02)
    proc.wait(max(0.0, deadline - time.monotonic()))
    return waited
