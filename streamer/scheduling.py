"""Where the sessions' inference runs: one scheduler interface, the policies behind it, and the window rule.

A session hands its scheduler windows of audio (`submit_push(source, samples, rank)` -> a Future of its frames)
and other jobs (`submit_ranked`: a stream's finish). The rank is how far the session's audio is ahead of real
time (rank > 0: a backlog); real time goes first, so a talker never waits behind a backlog:
- `StreamBatcher` (`streamer serve`'s default): one thread runs the due windows of all sessions as batched
  forwards, the model's weights read once per sampler step for all of them (`dimgestor.streaming.batch.push_many`);
- `RankedScheduler` (`--no-batch`): worker threads, each window a job of its own, lowest rank first;
- `PoolScheduler`: any `concurrent.futures.Executor` (None: a shared thread pool), unranked, for tools and tests.
The scheduler also says how a session's audio becomes calls (`windows` -> `WindowPolicy`).
"""

from __future__ import annotations

import atexit
import heapq
import itertools
import threading
import time
import warnings
import weakref
from abc import ABC, abstractmethod
from collections import deque
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np

from dimgestor.audio import SAMPLE_RATE

__all__ = ["WindowPolicy", "WindowSource", "Scheduler", "RankedScheduler", "StreamBatcher", "BatcherPool",
           "PoolScheduler", "BatchStats", "as_scheduler"]


class WindowSource(Protocol):
    """All a scheduler uses of whoever submits windows (a `streamer.sessions.Session` is one): the stream the
    samples are pushed into, and what makes the Future's frames of the stream's new output."""

    @property
    def stream(self) -> Any: ...

    def frames_of(self, normalized: np.ndarray) -> list: ...

    # optional: `frames_many(sources, outputs) -> [frames or exception]`, a classmethod of the sources' type that
    # makes one batch's frames together (`streamer.sessions.Session.frames_many`: their faces as one batch)


def _infer(source: WindowSource, samples: np.ndarray) -> list:
    """One window of `source`, alone, in the calling thread (a scheduler's worker)."""
    return source.frames_of(source.stream.push(samples))


@dataclass(frozen=True)
class WindowPolicy:
    """How a session's audio becomes inference calls.

    A window is due once `window` samples are buffered (or the source ended). If inference fell behind, the
    window takes what queued meanwhile, so latency recovers instead of growing, cut into calls of at most `call`
    samples: a session has at most one call queued, so short calls keep every other session's turn short. At
    most `buffer` samples wait (the source is held back beyond). whole: a window takes only the whole windows
    that queued (the rest waits for the next), and calls are whole windows: a batching scheduler's rule, so
    that the calls of sessions that fell behind share the others' batches (a batch conditions each length of
    call apart and runs the sampler again for each piece left over: benchmarks/README.md, "Whole windows").
    Elsewhere a window takes everything, so a source that comes in bursts (a TTS) has its last frames at once.
    """

    window: int
    call: int
    buffer: int
    whole: bool = False

    @classmethod
    def of(cls, window_ms: int, max_call_s: float = 1.0, max_buffer_s: float = 2.0,
           whole: bool = False) -> "WindowPolicy":
        if not 10 <= window_ms <= 5000:
            raise ValueError(f"window_ms must be in 10..5000, got {window_ms}")
        window = SAMPLE_RATE * window_ms // 1000
        call = max(window, int(max_call_s * SAMPLE_RATE))
        if whole:
            call = call // window * window
        return cls(window, call, max(window, int(max_buffer_s * SAMPLE_RATE)), whole)

    def calls(self, samples: np.ndarray) -> list[np.ndarray]:
        """A due window's samples -> the pieces inferred one call each."""
        return [samples[a:a + self.call] for a in range(0, len(samples), self.call)]


class Scheduler(Executor, ABC):
    """What a session needs from where its inference runs (an `Executor`: `submit` is a job at rank 0)."""

    def windows(self, window_ms: int, max_call_s: float = 1.0, max_buffer_s: float = 2.0) -> WindowPolicy:
        """The window rule for a session asking for `window_ms` windows."""
        return WindowPolicy.of(window_ms, max_call_s, max_buffer_s)

    @abstractmethod
    def submit_push(self, source: WindowSource, samples: np.ndarray, rank: float = 0.0) -> Future:
        """Queue one window of `source` -> a Future of its frames (`source.frames_of` the stream's new ones)."""

    @abstractmethod
    def submit_ranked(self, rank: float, fn: Callable, /, *args, **kwargs) -> Future:
        """Queue any other job of a session (its stream's finish) at its rank."""

    def submit(self, fn: Callable, /, *args, **kwargs) -> Future:
        return self.submit_ranked(0.0, fn, *args, **kwargs)


def _settle(future: Future, fn: Callable, args=(), kwargs=None) -> None:
    """Run one job into its future (unless it was cancelled while waiting)."""
    if future.set_running_or_notify_cancel():
        try:
            future.set_result(fn(*args, **(kwargs or {})))
        except BaseException as e:  # noqa: BLE001 - handed to whoever waits on the future
            future.set_exception(e)


@dataclass(order=True)
class _Job:
    rank: float
    seq: int
    future: Future = field(compare=False)
    fn: Callable = field(compare=False)
    args: tuple = field(compare=False, default=())
    kwargs: dict = field(compare=False, default_factory=dict)
    windows: int = field(compare=False, default=0)  # windows it computes (for the metrics): 1 for a push


@dataclass
class _PushJob:
    source: WindowSource
    samples: np.ndarray
    rank: float
    future: Future


_RUNNING: "weakref.WeakSet[_Threads]" = weakref.WeakSet()


@atexit.register
def _stop_all() -> None:
    """At interpreter exit: let the running jobs end and cancel the queued ones. The workers are daemon
    threads (the interpreter does not wait for them), so they must not still be inside a torch call when
    it tears down (that aborts the process: "terminate called without an active exception")."""
    for s in list(_RUNNING):
        s.shutdown(wait=True, cancel_futures=True)


class _Threads(Scheduler):
    """The worker threads, queue lock and shutdown shared by the threaded schedulers; a subclass says how jobs
    queue (`_put`, `_take`, `_queued`, `_drain`) and run (`_run`).

    observer: None, or what sees every inference call (`streamer.metrics.ServerMetrics`): `began(realtime)`
    before it and `ended(windows)` after it, on the thread that runs it."""

    observer = None

    def __init__(self, names: list[str]):
        self._seq = itertools.count()
        self._cv = threading.Condition()
        self._shutdown = False
        self._threads = [threading.Thread(target=self._work, name=name, daemon=True) for name in names]
        _RUNNING.add(self)
        for t in self._threads:
            t.start()

    def submit_ranked(self, rank: float, fn: Callable, /, *args, **kwargs) -> Future:
        return self._enqueue(_Job(rank, next(self._seq), Future(), fn, args, kwargs))

    def _enqueue(self, job) -> Future:
        with self._cv:
            if self._shutdown:
                raise RuntimeError("cannot schedule new jobs after shutdown")
            self._put(job)
            self._cv.notify()
        return job.future

    @property
    def workers(self) -> int:
        """How many threads run jobs."""
        return len(self._threads)

    def _observed(self, realtime: bool, windows: int, run: Callable[[], None]) -> None:
        if self.observer is None:
            return run()
        self.observer.began(realtime)
        try:
            run()
        finally:
            self.observer.ended(windows)

    def _work(self) -> None:
        while True:
            with self._cv:
                while (work := self._take()) is None:
                    if self._shutdown and not self._queued():
                        return
                    self._cv.wait()
            self._run(work)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        with self._cv:
            self._shutdown = True
            if cancel_futures:
                for future in self._drain():
                    future.cancel()
            self._cv.notify_all()
        if wait:
            for t in self._threads:
                if t is not threading.current_thread():
                    t.join()

    @abstractmethod
    def _put(self, job) -> None:
        """Queue a `_Job` or `_PushJob` (under the lock)."""

    @abstractmethod
    def _take(self):
        """The next work to run, or None while nothing may run (under the lock)."""

    @abstractmethod
    def _queued(self) -> bool:
        """Whether anything waits (under the lock)."""

    @abstractmethod
    def _drain(self) -> list[Future]:
        """Empty the queue -> the futures of what waited (under the lock)."""

    @abstractmethod
    def _run(self, work) -> None:
        """Run what `_take` returned (outside the lock)."""


class RankedScheduler(_Threads):
    """Worker threads that run the waiting job of lowest rank first (first come, first served among equals).

    A job ahead of real time (rank > 0) starts only while no real-time job (rank <= 0) runs, so a real-time
    session neither waits behind a backlog nor shares the CPU and the GIL with one; backlogs get whatever
    real time leaves. Each window is a job of its own (the session's stream pushed alone).
    """

    def __init__(self, max_workers: int, thread_name_prefix: str = "infer"):
        self._jobs: list[_Job] = []
        self._running_realtime = 0
        super().__init__([f"{thread_name_prefix}_{i}" for i in range(max_workers)])

    def submit_push(self, source: WindowSource, samples: np.ndarray, rank: float = 0.0) -> Future:
        return self._enqueue(_Job(rank, next(self._seq), Future(), _infer, (source, samples), windows=1))

    def queued_jobs(self) -> int:
        return len(self._jobs)

    def _put(self, job: _Job) -> None:
        heapq.heappush(self._jobs, job)

    def _take(self) -> _Job | None:
        if not (self._jobs and (self._jobs[0].rank <= 0 or not self._running_realtime)):
            return None
        job = heapq.heappop(self._jobs)
        self._running_realtime += job.rank <= 0
        return job

    def _queued(self) -> bool:
        return bool(self._jobs)

    def _drain(self) -> list[Future]:
        futures, self._jobs = [j.future for j in self._jobs], []
        return futures

    def _run(self, job: _Job) -> None:
        try:
            self._observed(job.rank <= 0, job.windows, lambda: _settle(job.future, job.fn, job.args, job.kwargs))
        finally:
            with self._cv:
                self._running_realtime -= job.rank <= 0
                self._cv.notify_all()


class BatchStats:
    """How many streams shared the recent batches (an exponential average, and the largest of a recent run)."""

    def __init__(self, alpha: float = 0.1):
        self.alpha, self.batches, self.last, self.mean, self.peak, self._peak_run = alpha, 0, 0, 0.0, 0, []

    def add(self, size: int) -> None:
        self.batches += 1
        self.last = size
        self.mean += (1.0 if self.batches == 1 else self.alpha) * (size - self.mean)
        self._peak_run = (self._peak_run + [size])[-50:]
        self.peak = max(self._peak_run)

    def describe(self) -> str:
        return f"batch {self.mean:.1f} streams (max {self.peak})" if self.batches else "batch -"


class CycleCost:
    """A running estimate of what a backlog cycle costs: seconds of compute per second of audio (an exponential
    average over measured cycles; None before the first). Measured at the size the cycles run at, so the cycles
    it sizes converge to the compute asked for even though batching makes the cost per second fall with size."""

    def __init__(self, alpha: float = 0.2):
        self.alpha, self.s_per_audio_s, self.last_s = alpha, None, 0.0

    def add(self, seconds: float, audio_s: float) -> None:
        self.last_s = seconds
        if audio_s > 0:
            x = seconds / audio_s
            old = self.s_per_audio_s
            self.s_per_audio_s = x if old is None else old + self.alpha * (x - old)

    def describe(self) -> str:
        return f"backlog cycle {1000 * self.last_s:.0f} ms" if self.s_per_audio_s is not None else ""


class StreamBatcher(_Threads):
    """One inference thread that runs the due windows of all sessions as batched forwards, real time first.

    A cycle takes every waiting window (one per session) and pushes them as one `push_many`; a session with
    nothing due is not waited for. A backlog cycle takes windows only up to `cycle_s` of estimated compute
    (`CycleCost`; `backlog_s` of audio before a measurement), so a real-time window never waits for more.
    push_many: `(streams, chunks, return_exceptions) -> frames or exception per stream`; None: torch's
    (`dimgestor.streaming.batch.push_many`); `--backend onnxruntime` gives `dimgestor.export.onnx_batch.push_many`.
    """

    def __init__(self, max_batch: int = 256, thread_name: str = "infer-batch", cycle_s: float = 0.1,
                 backlog_s: float = 4.0, clock: Callable[[], float] = time.perf_counter,
                 push_many: Callable | None = None):
        self.max_batch, self.push_many = max_batch, push_many
        self.cycle_s, self.backlog_s, self.clock = cycle_s, backlog_s, clock
        self.stats = BatchStats()
        self.cost = CycleCost()
        self.job_s: float | None = None  # what a solo job (a stream's finish) takes: an exponential average
        self._pushes: list[_PushJob] = []
        self._jobs: deque[_Job] = deque()
        super().__init__([thread_name])

    def windows(self, window_ms: int, max_call_s: float = 1.0, max_buffer_s: float = 2.0) -> WindowPolicy:
        return WindowPolicy.of(window_ms, max_call_s, max_buffer_s, whole=True)  # (batched with the others')

    def submit_push(self, source: WindowSource, samples: np.ndarray, rank: float = 0.0) -> Future:
        return self._enqueue(_PushJob(source, samples, rank, Future()))

    def _put(self, job) -> None:
        (self._pushes if isinstance(job, _PushJob) else self._jobs).append(job)

    def _queued(self) -> bool:
        return bool(self._pushes or self._jobs)

    def queued_jobs(self) -> int:
        return len(self._pushes) + len(self._jobs)

    def _drain(self) -> list[Future]:
        futures = [j.future for j in self._pushes] + [j.future for j in self._jobs]
        self._pushes, self._jobs = [], deque()
        return futures

    def _take(self) -> tuple[list[_PushJob], list[_Job]] | None:
        """The next cycle's windows (real-time ones first, one per session) and solo jobs (a stream's finish):
        a real-time cycle takes the real-time jobs, the latest first, as many as `cycle_s` of them take (at least
        one; one until one has been measured), a backlog cycle one backlog job, the least ahead first. (Every
        queued job in every cycle let a crowd of fast senders ending their sessions over and over put 30 finishes
        in front of a talker's next window: its frames 0.5-0.8 s late beside a busy loop, against 0.2. Every
        real-time job in a cycle did the same once a slower machine made that crowd late: 0.63 s against 0.09.)"""
        if not self._queued():
            return None
        pushes = sorted(self._pushes, key=lambda j: j.rank)
        realtime = (bool(pushes) and pushes[0].rank <= 0) or any(j.rank <= 0 for j in self._jobs)
        if realtime:  # real time first: a backlog waits for a cycle without any
            pushes = [j for j in pushes if j.rank <= 0]
        taken, seen, backlog = [], set(), 0
        cost = self.cost.s_per_audio_s
        most = SAMPLE_RATE * (self.backlog_s if cost is None else self.cycle_s / max(cost, 1e-6))
        for j in pushes:
            if not realtime and taken and backlog + len(j.samples) > most:
                break  # a short backlog cycle, so that the next real-time window is not kept waiting
            if len(taken) < self.max_batch and id(j.source) not in seen:
                taken.append(j)
                seen.add(id(j.source))
                backlog += len(j.samples)
        ids = {id(j) for j in taken}
        self._pushes = [j for j in self._pushes if id(j) not in ids]
        if realtime:  # the latest first, up to a cycle's worth (`cycle_s`, measured per job), at least one
            jobs = sorted((j for j in self._jobs if j.rank <= 0), key=lambda j: (j.rank, j.seq))
            each = self.job_s
            jobs = jobs[: 1 if each is None else max(1, int(self.cycle_s / max(each, 1e-6)))]
        else:
            jobs = [min(self._jobs, key=lambda j: (j.rank, j.seq))] if self._jobs else []
        ids = {id(j) for j in jobs}
        self._jobs = deque(j for j in self._jobs if id(j) not in ids)
        return taken, jobs

    def _run(self, cycle: tuple[list[_PushJob], list[_Job]]) -> None:
        pushes, jobs = cycle
        pushes = [j for j in pushes if j.future.set_running_or_notify_cancel()]
        if pushes:  # (a cycle is all real time or all backlog: `_take`)
            self._observed(pushes[0].rank <= 0, len(pushes), lambda: self._batch(pushes))
        for job in jobs:  # (a stream's finish)
            started = self.clock()
            self._observed(job.rank <= 0, 0, lambda: _settle(job.future, job.fn, job.args, job.kwargs))
            took = self.clock() - started
            self.job_s = took if self.job_s is None else self.job_s + 0.2 * (took - self.job_s)

    def _batch(self, pushes: list[_PushJob]) -> None:
        """One batched push of every taken window; a window that fails fails its own future only."""
        if (push_many := self.push_many) is None:
            from dimgestor.streaming.batch import push_many

        self.stats.add(len(pushes))
        started = self.clock()
        _faces_begin(pushes)
        try:
            results = push_many([j.source.stream for j in pushes], [j.samples for j in pushes],
                                return_exceptions=True)
        except BaseException as e:  # noqa: BLE001 - handed to every waiting session
            results = [e] * len(pushes)
        for j, r in zip(pushes, _frames(pushes, results)):
            if isinstance(r, BaseException):
                j.future.set_exception(r)
            else:
                j.future.set_result(r)
        took = self.clock() - started
        if all(j.rank > 0 for j in pushes):  # (a real-time window's cycle is not what sizes backlog cycles)
            self.cost.add(took, sum(len(j.samples) for j in pushes) / SAMPLE_RATE)


def _faces_begin(pushes: list[_PushJob]) -> None:
    """Sources that make their faces in another process start them now, beside the bodies (their `faces_begin`;
    `streamer.face_process`); a failure there is each of their faces' own, raised with its frames."""
    kinds = {type(j.source) for j in pushes}
    begin = getattr(next(iter(kinds)), "faces_begin", None) if len(kinds) == 1 else None
    if begin is not None:
        begin([j.source for j in pushes])


def _frames(pushes: list[_PushJob], results: list) -> list:
    """Each pushed window's frames (or its exception): through the sources' `frames_many` together where they
    have one (sessions make their faces as one batch), else each one's `frames_of`."""
    done = [(j.source, r) for j, r in zip(pushes, results) if not isinstance(r, BaseException)]
    kinds = {type(source) for source, _ in done}
    many = getattr(next(iter(kinds)), "frames_many", None) if len(kinds) == 1 else None
    if many is not None:
        made = iter(many([source for source, _ in done], [r for _, r in done]))
    else:
        made = iter([_frames_of(source, r) for source, r in done])
    return [r if isinstance(r, BaseException) else next(made) for r in results]


def _frames_of(source: WindowSource, normalized) -> list | BaseException:
    try:
        return source.frames_of(normalized)
    except BaseException as e:  # noqa: BLE001
        return e


class BatcherPool(Scheduler):
    """Several `StreamBatcher`s, one thread each, a session kept on one of them (its finish too): for runtimes whose
    batched call keeps only one core busy (ONNX Runtime on this small graph)."""

    def __init__(self, batchers: list[StreamBatcher]):
        if not batchers:
            raise ValueError("BatcherPool needs at least one StreamBatcher")
        self.batchers = list(batchers)
        self.stats = BatchStats()  # one for all: the sizes of every batcher's batches
        self._home: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # source (session) -> its batcher
        self._lock = threading.Lock()

    def _batcher(self, source: WindowSource) -> StreamBatcher:
        with self._lock:
            home = self._home.get(source)
            if home is None:
                load = [0] * len(self.batchers)
                for b in self._home.values():
                    load[self.batchers.index(b)] += 1
                home = self._home[source] = self.batchers[load.index(min(load))]
            return home

    def windows(self, window_ms: int, max_call_s: float = 1.0, max_buffer_s: float = 2.0) -> WindowPolicy:
        return self.batchers[0].windows(window_ms, max_call_s, max_buffer_s)

    def submit_push(self, source: WindowSource, samples: np.ndarray, rank: float = 0.0) -> Future:
        return self._batcher(source).submit_push(source, samples, rank)

    def submit_ranked(self, rank: float, fn: Callable, /, *args, **kwargs) -> Future:
        owner = getattr(fn, "__self__", None)  # a source's bound method (its finish): on that source's batcher
        with self._lock:
            home = self._home.get(owner) if owner is not None else None
        return (home or min(self.batchers, key=lambda b: b.queued_jobs())).submit_ranked(rank, fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        for b in self.batchers:
            b.shutdown(wait=False, cancel_futures=cancel_futures)
        if wait:
            for b in self.batchers:
                b.shutdown(wait=True)

    @property
    def workers(self) -> int:
        return sum(b.workers for b in self.batchers)

    def queued_jobs(self) -> int:
        return sum(b.queued_jobs() for b in self.batchers)

    @property
    def observer(self):
        return self.batchers[0].observer

    @observer.setter
    def observer(self, value) -> None:
        for b in self.batchers:
            b.observer = value

    @property
    def stats(self) -> BatchStats:
        """The batches' sizes (one `BatchStats` that every batcher adds to)."""
        return self.batchers[0].stats

    @stats.setter
    def stats(self, value) -> None:
        for b in self.batchers:
            b.stats = value

    @property
    def cost(self) -> CycleCost:
        return self.batchers[0].cost


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _shared_pool() -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(thread_name_prefix="session")
        return _POOL


class PoolScheduler(Scheduler):
    """Any `concurrent.futures.Executor` as a scheduler: each window a job of its own, ranks ignored.
    None: one thread pool shared by every such session (sessions built without a scheduler)."""

    def __init__(self, executor: Executor | None = None):
        self.executor = executor

    def _pool(self) -> Executor:
        return self.executor if self.executor is not None else _shared_pool()

    def submit_push(self, source: WindowSource, samples: np.ndarray, rank: float = 0.0) -> Future:
        return self._pool().submit(_infer, source, samples)

    def submit_ranked(self, rank: float, fn: Callable, /, *args, **kwargs) -> Future:
        return self._pool().submit(fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        if self.executor is not None:
            self.executor.shutdown(wait, cancel_futures=cancel_futures)


def as_scheduler(scheduler: Scheduler | Executor | None) -> Scheduler:
    """A session's `scheduler` argument (a `Scheduler`, any `concurrent.futures.Executor`, or None) as a Scheduler."""
    return scheduler if isinstance(scheduler, Scheduler) else PoolScheduler(scheduler)


def __getattr__(name: str):
    """`RankedExecutor`: the deprecated name of `RankedScheduler` (one name: scheduler), with a warning."""
    if name == "RankedExecutor":
        warnings.warn("streamer.scheduling.RankedExecutor is deprecated: use RankedScheduler", DeprecationWarning,
                      stacklevel=2)
        return RankedScheduler
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
