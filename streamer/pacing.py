"""Pacing: release timestamped items at their presentation time, recovering from any stall.

Every paced output (the VMC sink; anything that sleeps until a pts) asks one `Pacer` what to do with
the item at the head of its queue. The pacer keeps a playout clock, `anchor + pts`, that sits a jitter
buffer (`buffer_s`) behind the earliest the producer delivers:

- an item that is due is sent; one that is early waits; one more than `tolerance_s` late is dropped
  and counted, so a backlog after a stall is never sent in a burst and never moves the clock;
- the clock follows the producer, not the sink: `arrived(pts, now)` records how late each item came
  (its offset, arrival - pts). Only when every item for `resync_s` came later than the clock (the
  producer now runs behind, e.g. a live source that lost audio) or every item waited more than a jitter
  buffer (the producer got faster) does the clock move, to the best offset of that period plus the
  buffer. Later: at once (those items are lost anyway), unless the producer is catching up (a backlog
  going through after a stall, on a slow or busy machine) fast enough to be on time within
  `catchup_s`: then the clock stays and the late items keep being dropped, since a clock moved later
  would keep the lag for as long as pulling it back takes. Earlier: by playing `pull_rate` faster
  until it is there (nothing dropped, no burst), or, when the clock is more than `skip_s` behind, at
  once (the items in between are dropped: a skip, as a live video player seeks to the live edge).
  So after any stall the output is back to full rate within `resync_s` of the producer being on
  time, and the lag it keeps is at most the jitter buffer.

The pacer does no I/O and reads no clock: callers pass `now`, so it is tested without sleeping.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PacerStats:
    dropped_late: int = 0   # items more than tolerance_s late at the head of the queue
    resyncs: int = 0        # times the clock moved to follow the producer
    skips: int = 0          # of those, moves earlier made at once (more than skip_s)


class Pacer:
    """One playout clock: `arrived()` when an item is queued, `wait()` for the item at the head."""

    def __init__(self, buffer_s: float = 0.25, tolerance_s: float = 0.1, resync_s: float = 1.0,
                 pull_rate: float = 0.2, catchup_s: float = 3.0, skip_s: float = 1.5):
        if (buffer_s < 0 or tolerance_s < 0 or resync_s <= 0 or not 0 < pull_rate < 1 or catchup_s < 0
                or skip_s < 0):
            raise ValueError(f"need buffer_s >= 0, tolerance_s >= 0, resync_s > 0, 0 < pull_rate < 1, catchup_s >= 0, "
                             f"skip_s >= 0; got {buffer_s}, {tolerance_s}, {resync_s}, {pull_rate}, {catchup_s}, {skip_s}")
        self.buffer_s, self.tolerance_s, self.resync_s, self.pull_rate = buffer_s, tolerance_s, resync_s, pull_rate
        self.catchup_s, self.skip_s = catchup_s, skip_s
        self.stats = PacerStats()
        self.reset()

    def reset(self) -> None:
        """A new stream (pts restart at 0): the next item starts the clock afresh."""
        self.anchor: float | None = None  # monotonic time at which pts 0 is shown
        self._run: list[tuple[float, float]] = []  # (arrival, offset) of the current run of late or early items
        self._run_late = False
        self._target: float | None = None  # where an earlier clock is being pulled to
        self._last_wait: float | None = None

    def arrived(self, pts: float, now: float) -> None:
        """An item with presentation time pts was queued at `now`: start or adjust the clock.

        The clock is set so the latest-arriving item of a burst (the first of an inference window) is
        shown a jitter buffer after it arrived; the others wait longer, by up to a window.
        """
        offset = now - pts
        if self.anchor is None:
            self.anchor = offset + self.buffer_s
            return
        clock = self._target if self._target is not None else self.anchor
        late = offset > self.anchor + self.tolerance_s               # came too late to be shown
        early = offset < clock - self.buffer_s - self.tolerance_s    # waits more than a jitter buffer
        if not (late or early):
            self._run = []
            return
        if not self._run or self._run_late != late:
            self._run, self._run_late = [], late
        self._run.append((now, offset))
        if now - self._run[0][0] < self.resync_s:
            return
        if late and self._catching_up(now):
            return
        # A whole resync_s of it: follow the producer. Late: from the recent half of the run (after the
        # backlog of a stall has gone through); early: from all of it.
        recent = [o for t, o in self._run if t >= now - self.resync_s / 2] if late else [o for _, o in self._run]
        self._move(max(recent) + self.buffer_s)

    def _catching_up(self, now: float) -> bool:
        """Whether the late run's producer will be on time within catchup_s at the pace it is catching up.

        Items come in bursts (an inference window each, all arriving at one `now`); the latest of a burst
        (its largest offset) is what the clock is set by, so the pace is the least-squares slope of
        each burst's largest offset over the arrival times of the run.
        """
        bursts: dict[float, float] = {}
        for t, o in self._run:
            bursts[t] = max(o, bursts.get(t, o))
        if len(bursts) < 2:
            return False
        t = list(bursts)
        o = list(bursts.values())
        tm, om = sum(t) / len(t), sum(o) / len(o)
        var = sum((x - tm) ** 2 for x in t)
        slope = sum((x - tm) * (y - om) for x, y in zip(t, o)) / var  # seconds of lag per second; < 0: catching up
        if slope >= 0:
            return False
        late_by = om + slope * (now - tm) - (self.anchor + self.tolerance_s)
        return late_by / -slope <= self.catchup_s

    def _move(self, anchor: float) -> None:
        if anchor > self.anchor or self.anchor - anchor > self.skip_s:
            self.stats.skips += anchor < self.anchor
            self.anchor, self._target = anchor, None
        else:
            self._target = anchor
        self.stats.resyncs += 1
        self._run = []

    def due(self, pts: float) -> float:
        """The monotonic time at which the item with this pts is shown (the clock must be started)."""
        assert self.anchor is not None, "arrived() starts the clock"
        return self.anchor + pts

    def wait(self, pts: float, now: float) -> float | None:
        """Seconds to wait before sending the head item (0: send now), or None: drop it, it is late."""
        if self.anchor is None:
            self.arrived(pts, now)
        if self._target is not None and self._last_wait is not None:  # play a little faster until there
            self.anchor = max(self._target, self.anchor - self.pull_rate * max(0.0, now - self._last_wait))
            if self.anchor == self._target:
                self._target = None
        self._last_wait = now
        delay = self.due(pts) - now
        if delay < -self.tolerance_s:
            self.stats.dropped_late += 1
            return None
        return max(0.0, delay)
