"""The worker thread that takes client audio in (decode, channel mix, resample) and encodes frames, shared fairly.

Fair shares of it are counted in compute, not in audio seconds: a second of 192 kHz stereo float32 costs ~100x
a second of 16 kHz PCM16 to take in (~30 ms of CPU against ~0.3 ms). Every job of a client runs under its
`Account`, which sums the thread's CPU time the job took, and:
- `FairWorker` runs the job of the account that has used the thread least first (start-time fair queueing on
  that CPU time), so a real-time talker's small jobs never queue behind a fast sender's big ones;
- `ComputeBudget` turns an account's CPU time into how long its socket is not read (TCP back pressure) once it
  uses more than `share` of the thread, and says when it is over its share (`slow_down`) and back (`resume`).
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections import deque
from concurrent.futures import Executor, Future
from typing import Callable

__all__ = ["Account", "FairWorker", "ComputeBudget", "submit_for", "INTAKE_SHARE"]

INTAKE_SHARE = 0.1  # of the worker thread, per client: 192 kHz stereo float32 in real time takes 0.03-0.06 here
INTAKE_BURST_S = 0.25  # CPU seconds a client may take at once before its share holds (~6 s of 192 kHz stereo)


class Account:
    """The worker thread's CPU time spent on one client (`spent_s`), and its place in `FairWorker`'s queue."""

    def __init__(self):
        self.spent_s = 0.0
        self.jobs: deque[tuple[Future, Callable, tuple, dict]] = deque()  # waiting in a FairWorker
        self.running = False
        self.finish = 0.0  # virtual time its last job ended (FairWorker)

    def run(self, fn: Callable, *args, **kwargs):
        """fn(*args, **kwargs), its CPU time added to `spent_s` (on any executor's thread)."""
        t = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            self.spent_s += time.thread_time() - t


class FairWorker(Executor):
    """One thread; of the accounts with jobs waiting, the one that has used it least goes next.

    Start-time fair queueing with CPU time as the cost: an account's next job is tagged max(V, the virtual time
    its last job ended), V being the tag of the job in service; the lowest tag runs. An account that was idle
    starts at V (it saves up no credit); one that keeps the thread busy falls behind by what it took. `submit`
    (the server's own jobs: a hand-over's snapshot, a resume's restore, trims) runs under an account of the server's.
    """

    def __init__(self, name: str = "ws-prep"):
        self.name = name
        self._cv = threading.Condition()
        self._ready: list[tuple[float, int, Account]] = []  # (start tag, order, account), a heap
        self._order = itertools.count()
        self._v = 0.0
        self._server = Account()
        self._running: Account | None = None  # the account whose job runs now
        self._thread: threading.Thread | None = None
        self._shutdown = False

    def submit(self, fn: Callable, /, *args, **kwargs) -> Future:
        return self.submit_for(self._server, fn, *args, **kwargs)

    def submit_for(self, account: Account, fn: Callable, /, *args, **kwargs) -> Future:
        future: Future = Future()
        with self._cv:
            if self._shutdown:
                raise RuntimeError("cannot schedule new futures after shutdown")
            account.jobs.append((future, fn, args, kwargs))
            if len(account.jobs) == 1 and not account.running:
                self._queue(account)
            if self._thread is None:
                self._thread = threading.Thread(target=self._work, name=self.name, daemon=True)
                self._thread.start()
            self._cv.notify()
        return future

    def _queue(self, account: Account) -> None:  # (under the lock)
        heapq.heappush(self._ready, (max(self._v, account.finish), next(self._order), account))

    def _work(self) -> None:
        while True:
            with self._cv:
                while not self._ready and not self._shutdown:
                    self._cv.wait()
                if not self._ready:
                    return
                start, _, account = heapq.heappop(self._ready)
                self._v = start
                future, fn, args, kwargs = account.jobs.popleft()
                account.running, self._running = True, account
            result, error, t = None, None, time.thread_time()
            if future.set_running_or_notify_cancel():
                try:
                    result = fn(*args, **kwargs)
                except BaseException as e:  # (handed to whoever awaits it)
                    error = e
            cost = time.thread_time() - t
            with self._cv:
                account.spent_s += cost  # (before the result: its owner sees the cost once it has the result)
                account.finish = start + cost
                account.running, self._running = False, None
                if account.jobs:
                    self._queue(account)
            if future.running():
                if error is not None:
                    future.set_exception(error)
                else:
                    future.set_result(result)
            del future, fn, args, kwargs, result, error

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        with self._cv:
            self._shutdown = True
            if cancel_futures:
                for account in [a for _, _, a in self._ready] + [self._running] * (self._running is not None):
                    while account.jobs:
                        account.jobs.popleft()[0].cancel()
                self._ready.clear()
            self._cv.notify_all()
            thread = self._thread
        if wait and thread is not None and thread is not threading.current_thread():
            thread.join()


def submit_for(executor: Executor, account: Account, fn: Callable, /, *args) -> Future:
    """fn(*args) on `executor` for `account`: in its fair order on a `FairWorker`, measured on any other."""
    if isinstance(executor, FairWorker):
        return executor.submit_for(account, fn, *args)
    return executor.submit(account.run, fn, *args)


class ComputeBudget:
    """A client's share of the worker thread: `share` CPU seconds per second, bursts of `burst_s`, charged with
    what its `account` spent. Over budget, its socket is read only after `wait_s` (TCP back pressure); it is
    `over` from the moment it is in debt until the budget has refilled to half (`refilled_in`)."""

    def __init__(self, account: Account, share: float = INTAKE_SHARE, burst_s: float = INTAKE_BURST_S):
        self.account, self.share, self.burst_s = account, share, burst_s
        self.tokens, self.t, self.charged = burst_s, time.monotonic(), 0.0
        self.over = False

    def _update(self, now: float) -> None:
        spent = self.account.spent_s - self.charged
        self.charged += spent
        self.tokens = min(self.burst_s, self.tokens + (now - self.t) * self.share) - spent
        self.t = now
        if self.tokens < 0:
            self.over = True
        elif self.tokens >= self.burst_s / 2:
            self.over = False

    def wait_s(self, now: float) -> float:
        """How long to leave the socket unread for what was spent so far."""
        self._update(now)
        return max(0.0, -self.tokens / self.share)

    def refilled_in(self, now: float) -> float:
        """Seconds until it is no longer `over` if it spends nothing more (0: not over now)."""
        self._update(now)
        return max(0.0, (self.burst_s / 2 - self.tokens) / self.share) if self.over else 0.0
