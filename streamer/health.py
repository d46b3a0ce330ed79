"""Liveness and readiness of a worker: `/healthz`, `/readyz` and where `/metrics` is answered.

`/healthz` says the process is alive and its event loop answers (200, always). `/readyz` says whether a load
balancer or an orchestrator should send it new sessions: 503 while draining (after SIGTERM, until it exits) and
while its inference cannot keep real time, by this rule (`Readiness`); a worker whose state store does not
answer stays ready (200) and says "degraded: ..." in the body: it serves every session, without hand-over.

    not ready  <=>  real-time load > max_load (0.9)  or  a real-time session is behind,
    real-time load = seconds the inference thread(s) spent computing real-time work (a cycle of windows ranked
                     real time, or a stream's finish) within the last window_s (10 s) of wall time,
                     / (window_s x threads); a call still running counts up to now;
    behind         = a client's audio waits more than max_backlog_s (1 s) to be inferred while it comes no faster
                     than real time (received audio <= wall time since its first audio + max_backlog_s).

The load is what the inference thread(s) spend; being behind is what a client gets, whatever held it up (work the
load does not count, such as faces on their own thread, or a machine busy with other processes): a worker whose
real-time clients' audio piles up is never ready, however idle its inference thread looks.

A batch cycle of only backlog windows (fast senders ahead of real time, `streamer.sessions.AudioClock`) does
not count: a backlog takes whatever real time leaves, so a worker busy with one still serves a new talker in
real time. Time before the worker started counts as idle (no false alarm at start). Above 0.9 the windows of
real-time streams are computed back to back: one more stream and each would fall behind its audio.

The three paths are answered without the token (probes and Prometheus scrape without one; they reveal counts,
never audio, frames, addresses or the token), GET and HEAD only, after the same checks of the request target
as the viewer's files (`streamer.request_checks`).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from http import HTTPStatus
from typing import Callable

from streamer import request_checks as RC
from streamer.viewer import Answer

HEALTH, READY, METRICS = "/healthz", "/readyz", "/metrics"
READY_WINDOW_S = 10.0
READY_MAX_LOAD = 0.9
READY_MAX_BACKLOG_S = 1.0


class RealtimeLoad:
    """Busy time of the inference thread(s) on real-time work over a recent window of wall time.

    `began(realtime)` and `ended()` bracket each inference call on the thread that runs it (any thread; a lock
    guards the intervals). `now` is the clock (a fake one in tests)."""

    def __init__(self, window_s: float = READY_WINDOW_S, threads: int = 1, now: Callable[[], float] = time.monotonic):
        self.window_s, self.threads, self.now = window_s, threads, now
        self._done: deque[tuple[float, float]] = deque()  # (start, end) of finished real-time calls, oldest first
        self._running: dict[int, tuple[float, bool]] = {}  # thread id -> (start, realtime) of its call under way
        self._lock = threading.Lock()

    def began(self, realtime: bool) -> None:
        with self._lock:
            self._running[threading.get_ident()] = (self.now(), realtime)

    def ended(self) -> tuple[float, bool]:
        """The call on this thread is done -> (how long it took in seconds, whether it was real-time work)."""
        with self._lock:
            now = self.now()
            start, realtime = self._running.pop(threading.get_ident(), (now, False))
            if realtime:
                self._done.append((start, now))
            self._forget(now)
            return now - start, realtime

    def value(self) -> float:
        """The real-time load: busy seconds on real-time work per second and thread, over the last window."""
        with self._lock:
            now = self.now()
            self._forget(now)
            since = now - self.window_s
            calls = [*self._done, *((s, now) for s, rt in self._running.values() if rt)]
            busy = sum(max(0.0, end - max(start, since)) for start, end in calls)
            return busy / (self.window_s * self.threads)

    def _forget(self, now: float) -> None:
        while self._done and self._done[0][1] <= now - self.window_s:
            self._done.popleft()


def behind(lags, now: float, max_backlog_s: float = READY_MAX_BACKLOG_S) -> list[float]:
    """Of the clients' `lags` ((time.monotonic() of its first audio, seconds of audio received, seconds of it not yet
    inferred), or None for a client without audio), the seconds not yet inferred of those behind: more than
    `max_backlog_s` while their audio comes no faster than real time (a fast sender, a file sent at once, is ahead
    of real time: its backlog is its own)."""
    out = []
    for lag in lags:
        if lag is None:
            continue
        first_at, received_s, waiting_s = lag
        if waiting_s > max_backlog_s and received_s <= now - first_at + max_backlog_s:
            out.append(waiting_s)
    return out


class Readiness:
    """Whether the worker takes new sessions: not while `draining`, nor while its real-time load is over
    `max_load` or a real-time session is `behind` (the module's rule)."""

    def __init__(self, load: RealtimeLoad | None = None, max_load: float = READY_MAX_LOAD,
                 max_backlog_s: float = READY_MAX_BACKLOG_S):
        self.load = load if load is not None else RealtimeLoad()
        self.max_load, self.max_backlog_s = max_load, max_backlog_s
        self.draining = False  # set once on SIGTERM / shutdown; never cleared (the process is on its way out)
        self.store = None  # a `streamer.store_link.StoreLink` (its `health()`), if the worker has a state store
        self.lags: Callable[[], list] = lambda: []  # the clients' lags now (`behind`; the WebSocket server's)
        self.faces_left: Callable[[], int | None] | None = None  # `streamer.capacity.Admission.faces_left`

    def check(self) -> tuple[bool, str]:
        """(ready, why): the reason is one line, the body of the `/readyz` answer."""
        if self.draining:
            return False, "not ready: draining (shutting down)"
        load = self.load.value()
        late = behind(self.lags(), self.load.now(), self.max_backlog_s)
        why = []
        if load > self.max_load:
            why.append(f"real-time load {load:.2f} over the last {self.load.window_s:g} s (limit {self.max_load:g})")
        if late:
            why.append(f"{len(late)} real-time client{'s' if len(late) > 1 else ''} {max(late):.1f} s behind "
                       f"(limit {self.max_backlog_s:g} s)")
        if why:
            return False, f"not ready: {'; '.join(why)}: inference cannot keep real time"
        degraded = self.store.health() if self.store is not None else None
        note = self.store.note() if self.store is not None else ""
        note = f"; {note}" if note else ""
        left = self.faces_left() if self.faces_left is not None else None
        if left is not None:
            note = f"; room for {left} more face{'' if left == 1 else 's'}{note}"
        if degraded is not None:  # still ready: it serves every session, only without hand-over
            return True, f"degraded: {degraded}; real-time load {load:.2f}{note}"
        return True, f"ready: real-time load {load:.2f}{note}"


def answer(method: str, target: str, readiness: Readiness, metrics=None) -> Answer | None:
    """The answer to a request for one of the three paths, or None when `target` is not one of them (the viewer's
    files answer it then). `metrics`: a `streamer.metrics.ServerMetrics`, or None: `/metrics` is not served."""
    parts = RC.split_target(target) if isinstance(target, str) else None
    path = parts[0] if parts is not None else None
    if path not in (HEALTH, READY) and not (path == METRICS and metrics is not None):
        return None
    head_only = method == "HEAD"
    if method not in ("GET", "HEAD"):
        return Answer(HTTPStatus.METHOD_NOT_ALLOWED, b"only GET and HEAD\n")
    if path == HEALTH:
        return Answer(HTTPStatus.OK, b"ok\n", head_only=head_only)
    if path == READY:
        ready, why = readiness.check()
        return Answer(HTTPStatus.OK if ready else HTTPStatus.SERVICE_UNAVAILABLE, why.encode() + b"\n",
                      head_only=head_only)
    body, content_type = metrics.exposition()
    return Answer(HTTPStatus.OK, body, content_type, head_only)
