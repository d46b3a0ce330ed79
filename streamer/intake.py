"""The worker thread that takes client audio in (decode, channel mix, resample) and encodes frames, shared fairly.

Fair shares of it are counted in compute, not in audio seconds: a second of 192 kHz stereo float32 costs ~100x
a second of 16 kHz PCM16 to take in (~30 ms of CPU against ~0.3 ms). Every job of a client runs under its
`Account`, which sums the thread's CPU time the job took, and:
- `FairWorker` runs the job of the account that has used the thread least first (start-time fair queueing on
  that CPU time), so a real-time talker's small jobs never queue behind a fast sender's big ones;
- `ComputeBudget` turns an account's CPU time into how long its socket is not read (TCP back pressure) once it
  uses more than its share of the thread, and says when it is over its share (`slow_down`) and back (`resume`).

A fixed share cannot say what real time is: 192 kHz stereo in real time takes 0.03-0.06 of the thread on the
machine this was built on, over 0.1 on a slower or busier one (issue 47: a client paced in real time was told
`slow_down`). So a client's share is the larger of `INTAKE_SHARE` and `REAL_TIME_HEADROOM` times what a second of
its own audio has cost it lately (CPU time over audio seconds taken in, measured on this machine as it goes):
a client sending in real time spends 1/`REAL_TIME_HEADROOM` of its share on any machine that can serve it,
while one sending faster than that still goes over it, whatever its format costs.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections import deque
from concurrent.futures import Executor, Future
from typing import Callable

__all__ = ["Account", "FairWorker", "ComputeBudget", "submit_for", "INTAKE_SHARE", "REAL_TIME_HEADROOM", "MAX_SHARE"]

INTAKE_SHARE = 0.1  # of the worker thread, per client, at least (16 kHz PCM16 in real time takes ~0.0003)
REAL_TIME_HEADROOM = 1.5  # ...or this many times what its own audio in real time costs here, if more
MAX_SHARE = 0.5  # ...but never more than half the thread, however costly a client makes its audio look
INTAKE_BURST_S = 0.25  # CPU seconds a client may take at once before its share holds (~6 s of 192 kHz stereo here)
INTAKE_BURST_AUDIO_S = 4.0  # ...or what this much of its own audio costs, if more (a slower machine)
COST_HALF_LIFE_S = 5.0  # how fast the measured cost of a second of its audio follows the machine's load
COST_MIN_AUDIO_S = 1.0  # recent audio seconds the measured cost needs before it counts (one message says little)


class Account:
    """The worker thread's CPU time spent on one client (`spent_s`), the audio it took in (`audio_s`, counted by
    its owner), and its place in `FairWorker`'s queue."""

    def __init__(self):
        self.spent_s = 0.0
        self.audio_s = 0.0  # seconds of the client's audio taken in (decoded)
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
    """A client's share of the worker thread, charged with what its `account` spent: `rate()` CPU seconds per
    second, bursts of `cap()`. Both grow with what a second of its own audio costs here (`per_audio_s`): the share
    is at least `headroom` x that cost (real time with room to spare), the burst at least `burst_audio_s` of it.
    Over budget, its socket is read only after `wait_s` (TCP back pressure); it is `over` from the moment it is in
    debt until the budget has refilled to half (`refilled_in`)."""

    def __init__(self, account: Account, share: float = INTAKE_SHARE, burst_s: float = INTAKE_BURST_S,
                 headroom: float = REAL_TIME_HEADROOM, burst_audio_s: float = INTAKE_BURST_AUDIO_S,
                 half_life_s: float = COST_HALF_LIFE_S, now: float | None = None, max_share: float = MAX_SHARE):
        self.account, self.share, self.burst_s, self.max_share = account, share, burst_s, max_share
        self.headroom, self.burst_audio_s, self.half_life_s = headroom, burst_audio_s, half_life_s
        self.tokens, self.charged, self.heard = burst_s, 0.0, 0.0
        self.t = time.monotonic() if now is None else now
        self.recent_cpu_s = self.recent_audio_s = 0.0  # spent and taken in lately (halved every half_life_s)
        self.over = False

    @property
    def per_audio_s(self) -> float | None:
        """CPU seconds a second of its audio has cost lately (None: too little audio lately to say)."""
        return self.recent_cpu_s / self.recent_audio_s if self.recent_audio_s >= COST_MIN_AUDIO_S else None

    def rate(self) -> float:
        """Its share now: CPU seconds per second (at most `max_share` of the thread: a client whose audio costs more
        than that in real time, such as one that asks for a new resampler with every message, cannot be served
        beside others and is held to it)."""
        cost = self.per_audio_s
        return self.share if cost is None else max(self.share, min(self.max_share, self.headroom * cost))

    def cap(self) -> float:
        """The CPU seconds it may take at once now."""
        cost = self.per_audio_s
        return self.burst_s if cost is None else max(self.burst_s, self.burst_audio_s * cost)

    def _update(self, now: float) -> None:
        spent, audio = self.account.spent_s - self.charged, self.account.audio_s - self.heard
        self.charged += spent
        self.heard += audio
        keep = 0.5 ** (max(0.0, now - self.t) / self.half_life_s)
        self.recent_cpu_s = self.recent_cpu_s * keep + spent
        self.recent_audio_s = self.recent_audio_s * keep + audio
        self.tokens = min(self.cap(), self.tokens + (now - self.t) * self.rate()) - spent
        self.t = now
        if self.tokens < 0:
            self.over = True
        elif self.tokens >= self.cap() / 2:
            self.over = False

    def wait_s(self, now: float) -> float:
        """How long to leave the socket unread for what was spent so far."""
        self._update(now)
        return max(0.0, -self.tokens / self.rate())

    def refilled_in(self, now: float) -> float:
        """Seconds until it is no longer `over` if it spends nothing more (0: not over now)."""
        self._update(now)
        return max(0.0, (self.cap() / 2 - self.tokens) / self.rate()) if self.over else 0.0
