"""The state store reached off the real-time path: its blocking calls on a thread of their own.

A store (`streamer.handover`: Redis for a cluster) only serves the hand-over; a store that is slow, paused or
dead must never hold a frame. So every call a connection makes (`put`, `take`, ... by name) goes to
`StoreLink.call`, which
- queues it for the link's own thread (never the `prep` thread that decodes audio and encodes frames), in a
  bounded queue: a full queue refuses the call at once (`StoreBusy`, counted);
- gives it a deadline (`SAVE_DEADLINE_S` for a save, `TAKE_DEADLINE_S` for a take, or the caller's, e.g. the
  drain's): the caller gets `StoreTimeout` at its deadline whatever the store does, and a call still queued
  then is dropped unrun (counted);
- fails at once while the store is known down (`StoreDown`; a circuit breaker): a failed or timed-out call
  marks it down, and the thread pings it every `PING_EVERY_S` until it answers, then calls go on (the client
  library reconnects by itself). The thread also pings an idle store, so a store that dies while nobody saves
  is seen too (`/readyz` says "degraded" meanwhile: the worker serves, without hand-over).

Counts and the state are read by `streamer.metrics` and `streamer.health` (`StoreLink.health`).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field

from streamer.handover import StoreAnswer
from streamer.log_limit import ErrorLog

log = logging.getLogger("dimgestor.store")

MAX_QUEUE = 32  # calls waiting for the store (a save holds a state of ~1 MB: 32 MB at most)
SAVE_DEADLINE_S = 2.0  # a periodic save that waits longer is dropped: the next one comes S seconds later
TAKE_DEADLINE_S = 1.5  # a resume: the client waits for `session_resumed` (or `resume_failed` and a fresh stream)
PING_EVERY_S = 1.0  # a down store is pinged this often; an idle one too
DELAYED_S = 0.5  # a call that took longer than this (queue + store) is counted as delayed
STUCK_S = 3.0  # a call or ping still running after this long marks the store down (a client without timeouts)


class StoreError(Exception):
    """The store could not serve a call; the message says why in words a client may read."""


class StoreBusy(StoreError):
    pass


class StoreTimeout(StoreError):
    pass


class StoreDown(StoreError):
    pass


@dataclass
class _Call:
    name: str
    args: tuple
    deadline: float  # time.monotonic()
    future: asyncio.Future
    loop: asyncio.AbstractEventLoop
    queued: float = field(default_factory=time.monotonic)


class StoreLink:
    """A store's calls on its own thread, bounded, with deadlines and a circuit breaker (the module's rules)."""

    def __init__(self, store, max_queue: int = MAX_QUEUE, ping_every_s: float = PING_EVERY_S):
        self.store, self.max_queue, self.ping_every_s = store, max_queue, ping_every_s
        self.down_since: float | None = None  # time.monotonic() when the store was last seen failing; None: up
        self.down_reason = ""
        self.outages = 0
        # (name, outcome) -> count; outcome: ok, refused, late, failed, timeout, dropped, busy, down
        self.calls = Counter()
        self.delayed = Counter()  # name -> calls that took over DELAYED_S
        # one line when it goes down, one when it is back; a flapping store: at most one of each per 30 s
        self._down_log = ErrorLog("state store", every_s=30.0, what="outages", logger=log)
        self._up_log = ErrorLog("state store", every_s=30.0, what="recoveries", logger=log)
        self._lock = threading.Lock()  # (the counts are written by both threads)
        self._queue: deque[_Call] = deque()
        self._wake = threading.Condition()
        self._closed = False
        self._started: float | None = None  # when the thread's call or ping under way began
        self._thread = threading.Thread(target=self._run, name="store-link", daemon=True)  # (a hung call never
        self._thread.start()                                                              # holds the exit)

    # ---- the event loop's side -------------------------------------------------------------------

    @property
    def up(self) -> bool:
        started = self._started
        if self.down_since is None and started is not None and time.monotonic() - started > STUCK_S:
            self._went_down(f"a call has not returned for {time.monotonic() - started:.0f} s")
        return self.down_since is None

    @property
    def queued(self) -> int:
        return len(self._queue)

    async def call(self, name: str, *args, deadline_s: float | None = None):
        """The store's method `name`(*args), done on the link's thread within `deadline_s` (default: by name)."""
        if deadline_s is None:
            deadline_s = TAKE_DEADLINE_S if name == "take" else SAVE_DEADLINE_S
        if not self.up:
            self._count(name, "down")
            raise StoreDown(f"the state store is unreachable ({self._down_for()})")
        loop = asyncio.get_running_loop()
        job = _Call(name, args, time.monotonic() + max(0.0, deadline_s), loop.create_future(), loop)
        with self._wake:
            if len(self._queue) >= self.max_queue:
                self._count(name, "busy")
                raise StoreBusy(f"the state store's queue is full ({self.max_queue} calls waiting)")
            self._queue.append(job)
            self._wake.notify()
        try:  # (a timeout or the caller's cancellation cancels the job: the thread drops it, or its result)
            return await asyncio.wait_for(job.future, max(0.0, job.deadline - time.monotonic()))
        except asyncio.TimeoutError:
            self._count(name, "timeout")
            self._went_down(f"a {name} took over {deadline_s:g} s")
            raise StoreTimeout(f"the state store did not answer within {deadline_s:g} s") from None
        finally:
            if time.monotonic() - job.queued > DELAYED_S:
                with self._lock:
                    self.delayed[name] += 1

    def health(self) -> str | None:
        """None while the store answers; else why the worker serves without hand-over (`/readyz`'s body)."""
        if self.up:
            return None
        return f"state store unreachable ({self._down_for()}): sessions go on without hand-over"

    def _down_for(self) -> str:
        since = self.down_since  # (the link's thread may clear it meanwhile)
        return f"{self.down_reason}; for {time.monotonic() - since:.0f} s" if since is not None else "back now"

    def note(self) -> str:
        """The saves that did not go as usual so far, for `/readyz`'s body ("" if none)."""
        calls, delayed = self.counts()
        lost = sum(n for (name, outcome), n in calls.items() if name == "put" and outcome not in ("ok", "late"))
        slow = delayed.get("put", 0)
        return f"state store: {lost} saves not made, {slow} delayed" if lost or slow else ""

    def counts(self) -> tuple[dict, dict]:
        """({(call, outcome): calls}, {call: calls delayed}), as they are now (for the metrics)."""
        with self._lock:
            return dict(self.calls), dict(self.delayed)

    def _count(self, name: str, outcome: str) -> None:
        with self._lock:
            self.calls[name, outcome] += 1

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._wake.notify()

    # ---- the link's thread -----------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._wake:
                if not self._queue and not self._closed:
                    self._wake.wait(self.ping_every_s)
                if self._closed:
                    return
                job = self._queue.popleft() if self._queue else None
            self._started = time.monotonic()
            try:
                self._next(job)
            finally:
                self._started = None

    def _next(self, job: _Call | None) -> None:
        if job is None:
            self._ping()
        elif job.future.cancelled() or time.monotonic() > job.deadline:
            self._count(job.name, "dropped")  # queued past its deadline: never run
            _post(job.loop, _cancel, job.future)
        elif not self.up:  # went down while it waited
            self._count(job.name, "down")
            _post(job.loop, _fail, job.future, StoreDown(
                f"the state store is unreachable ({self.down_reason})"))
        else:
            self._do(job)

    def _do(self, job: _Call) -> None:
        try:
            result = getattr(self.store, job.name)(*job.args)
        except StoreAnswer as e:  # a healthy store's no (a spent token, a live session, a state too large)
            self._count(job.name, "refused")
            _post(job.loop, _fail, job.future, e)
            return
        except Exception as e:
            self._count(job.name, "failed")
            self._went_down(f"{type(e).__name__}: {e}")
            _post(job.loop, _fail, job.future, StoreDown(f"the state store failed: "
                                                                       f"{type(e).__name__}: {e}"))
            return
        self._count(job.name, "ok" if not job.future.cancelled() else "late")  # late: after its caller gave up
        _post(job.loop, _succeed, job.future, result)

    def _ping(self) -> None:
        ping = getattr(self.store, "ping", None)
        if ping is None:
            return
        try:
            ping()
        except Exception as e:
            self._went_down(f"ping: {type(e).__name__}: {e}")
            return
        with self._lock:
            since, self.down_since = self.down_since, None
        if since is not None:
            self._up_log(logging.WARNING, f"answers again after {time.monotonic() - since:.1f} s: sessions are "
                                          f"saved and handed over again")

    def _went_down(self, why: str) -> None:
        with self._lock:  # (either thread)
            self.down_reason = why
            if self.down_since is not None:
                return
            self.down_since = time.monotonic()
            self.outages += 1
        self._down_log(logging.WARNING, f"unreachable ({why}): sessions go on without hand-over (no saves, no "
                                        f"resumes) until it answers again (pinged every {self.ping_every_s:g} s)")


def _post(loop: asyncio.AbstractEventLoop, fn, *args) -> None:
    try:
        loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:  # its loop has closed: nobody waits for the answer
        pass


def _succeed(f: asyncio.Future, result) -> None:
    if not f.done():
        f.set_result(result)


def _fail(f: asyncio.Future, e: Exception) -> None:
    if not f.done():
        f.set_exception(e)


def _cancel(f: asyncio.Future) -> None:
    f.cancel()
