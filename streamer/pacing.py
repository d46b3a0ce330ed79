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
  buffer. So after any stall the output is back to full rate within `resync_s`, and the lag it keeps
  is at most the jitter buffer.

The pacer does no I/O and reads no clock: callers pass `now`, so it is tested without sleeping.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PacerStats:
    dropped_late: int = 0   # items more than tolerance_s late at the head of the queue
    resyncs: int = 0        # times the clock moved to follow the producer


class Pacer:
    """One playout clock: `arrived()` when an item is queued, `wait()` for the item at the head."""

    def __init__(self, buffer_s: float = 0.25, tolerance_s: float = 0.05, resync_s: float = 1.0):
        if buffer_s < 0 or tolerance_s < 0 or resync_s <= 0:
            raise ValueError(f"need buffer_s >= 0, tolerance_s >= 0, resync_s > 0; got {buffer_s}, {tolerance_s}, {resync_s}")
        self.buffer_s, self.tolerance_s, self.resync_s = buffer_s, tolerance_s, resync_s
        self.stats = PacerStats()
        self.reset()

    def reset(self) -> None:
        """A new stream (pts restart at 0): the next item starts the clock afresh."""
        self.anchor: float | None = None  # monotonic time at which pts 0 is shown
        self._late_since: float | None = None   # first arrival of the current run of late arrivals
        self._late_best = 0.0                   # smallest offset in that run
        self._early_since: float | None = None  # first arrival of the current run of over-buffered arrivals
        self._early_best = 0.0

    def arrived(self, pts: float, now: float) -> None:
        """An item with presentation time pts was queued at `now`: start or adjust the clock."""
        offset = now - pts
        if self.anchor is None:
            self.anchor = offset + self.buffer_s
            return
        if offset > self.anchor + self.tolerance_s:  # came too late to be shown
            self._early_since = None
            if self._late_since is None:
                self._late_since, self._late_best = now, offset
            self._late_best = min(self._late_best, offset)
            if now - self._late_since >= self.resync_s:
                self._move(self._late_best + self.buffer_s)
        elif offset < self.anchor - self.buffer_s - self.tolerance_s:  # waits longer than a jitter buffer
            self._late_since = None
            if self._early_since is None:
                self._early_since, self._early_best = now, offset
            self._early_best = min(self._early_best, offset)
            if now - self._early_since >= self.resync_s:
                self._move(self._early_best + self.buffer_s)
        else:
            self._late_since = self._early_since = None

    def _move(self, anchor: float) -> None:
        self.anchor = anchor
        self.stats.resyncs += 1
        self._late_since = self._early_since = None

    def due(self, pts: float) -> float:
        """The monotonic time at which the item with this pts is shown (the clock must be started)."""
        assert self.anchor is not None, "arrived() starts the clock"
        return self.anchor + pts

    def wait(self, pts: float, now: float) -> float | None:
        """Seconds to wait before sending the head item (0: send now), or None: drop it, it is late."""
        if self.anchor is None:
            self.arrived(pts, now)
        delay = self.due(pts) - now
        if delay < -self.tolerance_s:
            self.stats.dropped_late += 1
            return None
        return max(0.0, delay)
