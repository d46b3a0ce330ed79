"""Session: one audio source -> gesture frames, window by window, inference off the event loop.

A session owns one `GestureStream` (the model's streaming state) and one `PoseDecoder` (the root
integration). Audio is gathered until a window (`window_ms`) is full; if inference fell behind, the
next window takes everything that queued up meanwhile, so latency recovers instead of growing. A large
take is inferred in pieces of at most `max_call_s` of audio: sessions share the inference workers, and
each one has at most one call queued, so short calls keep every other session's turn short. Each
frame is stamped with pts = index / fps on the audio clock.

Sessions share one `StreamBatcher` by default (`streamer serve`): the windows of all sessions that are
due run as one batched forward per sampler step, so the model's weights are read once per step for
all of them (`dimgestor.batch`). `RankedExecutor` (`--no-batch`) runs each session's window alone.
"""

from __future__ import annotations

import asyncio
import heapq
import inspect
import itertools
import threading
import time
from collections import deque
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import AsyncIterable, Callable

import numpy as np

from streamer.sources import RATE, AudioChunk


@dataclass(frozen=True)
class Frame:
    index: int
    pts: float              # seconds on the audio clock
    root_pos: np.ndarray    # (3,) BVH space, file units
    rotations: np.ndarray   # (J, 4) local, wxyz
    features: np.ndarray    # (D,) denormalized motion features (what --record writes)


@dataclass
class Stats:
    """Running measurements of one session; averages are exponential over recent windows."""

    windows: int = 0
    frames: int = 0
    audio_s: float = 0.0
    infer_s: float = 0.0
    latency_ms: float = 0.0  # last sample of a window in -> its frames out
    rtf: float = 0.0         # inference time / audio time
    ended: bool = False

    def update(self, audio_s: float, infer_s: float, latency_s: float, frames: int, alpha: float = 0.2) -> None:
        a = 1.0 if self.windows == 0 else alpha
        self.windows += 1
        self.frames += frames
        self.audio_s += audio_s
        self.infer_s += infer_s
        self.latency_ms += a * (1000 * latency_s - self.latency_ms)
        if audio_s > 0:
            self.rtf += a * (infer_s / audio_s - self.rtf)


class _Window:
    """Bounded audio buffer between the source reader and the inference loop (back pressure when full)."""

    def __init__(self, max_samples: int):
        self.chunks: deque[AudioChunk] = deque()
        self.samples = 0
        self.max_samples = max_samples
        self.closed = False
        self.error: BaseException | None = None
        self.changed = asyncio.Event()

    async def put(self, chunk: AudioChunk) -> None:
        while self.samples >= self.max_samples:
            self.changed.clear()
            await self.changed.wait()
        self.chunks.append(chunk)
        self.samples += len(chunk.samples)
        self.changed.set()

    def close(self, error: BaseException | None = None) -> None:
        self.closed, self.error = True, error
        self.changed.set()

    async def take(self, min_samples: int) -> list[AudioChunk]:
        """Everything buffered once at least min_samples are there (or the source ended)."""
        while self.samples < min_samples and not self.closed:
            self.changed.clear()
            await self.changed.wait()
        if self.error is not None:
            raise self.error
        chunks, self.chunks, self.samples = list(self.chunks), deque(), 0
        self.changed.set()
        return chunks


class AudioClock:
    """How far a stream's audio is ahead of real time: audio handed to inference minus time elapsed.

    Shared by the successive sessions of one client (so restarting sessions earns no priority); time
    without audio earns at most `max_credit_s` of catching up.
    """

    def __init__(self, max_credit_s: float = 2.0):
        self.t0: float | None = None
        self.audio_s = 0.0
        self.max_credit_s = max_credit_s

    def ahead_s(self) -> float:
        now = time.monotonic()
        if self.t0 is None:
            self.t0 = now
        behind = (now - self.t0) - self.audio_s
        if behind > self.max_credit_s:
            self.t0 += behind - self.max_credit_s
        return -min(behind, self.max_credit_s)


class RankedExecutor(Executor):
    """Worker threads that run the waiting job of lowest rank first (first come, first served among equals).

    Sessions rank their jobs by how far their audio is ahead of real time (rank > 0: working through a
    backlog). A job ahead of real time starts only while no real-time job (rank <= 0) runs, so a session
    fed in real time (a talker, a microphone, a paced file) neither waits behind a backlog nor shares the
    CPU and the GIL with one; backlogs get whatever real time leaves.
    """

    def __init__(self, max_workers: int, thread_name_prefix: str = "infer"):
        self._jobs: list = []
        self._seq = itertools.count()
        self._cv = threading.Condition()
        self._shutdown = False
        self._running_realtime = 0
        # Not daemon threads: a worker inside a torch call when the interpreter exits aborts the process
        # ("terminate called without an active exception"); they stop at shutdown() or, as in
        # concurrent.futures, when the interpreter exits.
        self._threads = [threading.Thread(target=self._work, name=f"{thread_name_prefix}_{i}")
                         for i in range(max_workers)]
        for t in self._threads:
            t.start()
        register = getattr(threading, "_register_atexit", None)
        if register is not None:
            register(lambda: self.shutdown(wait=True, cancel_futures=True))

    def submit(self, fn, /, *args, **kwargs) -> Future:
        return self.submit_ranked(0.0, fn, *args, **kwargs)

    def submit_ranked(self, rank: float, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        with self._cv:
            if self._shutdown:
                raise RuntimeError("cannot schedule new jobs after shutdown")
            heapq.heappush(self._jobs, (rank, next(self._seq), future, fn, args, kwargs))
            self._cv.notify()
        return future

    def _work(self) -> None:
        while True:
            with self._cv:
                while not (self._jobs and (self._jobs[0][0] <= 0 or not self._running_realtime)):
                    if self._shutdown and not self._jobs:
                        return
                    self._cv.wait()
                rank, _, future, fn, args, kwargs = heapq.heappop(self._jobs)
                realtime = rank <= 0
                self._running_realtime += realtime
            try:
                if future.set_running_or_notify_cancel():
                    try:
                        future.set_result(fn(*args, **kwargs))
                    except BaseException as e:
                        future.set_exception(e)
            finally:
                with self._cv:
                    self._running_realtime -= realtime
                    self._cv.notify_all()

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        with self._cv:
            self._shutdown = True
            if cancel_futures:
                for job in self._jobs:
                    job[2].cancel()
                self._jobs.clear()
            self._cv.notify_all()
        if wait:
            for t in self._threads:
                t.join()


@dataclass
class _PushJob:
    session: "Session"
    samples: np.ndarray
    rank: float
    future: Future


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


class StreamBatcher(Executor):
    """One inference thread that runs the due windows of all sessions as batched forwards.

    Sessions hand it their windows (`submit_push`); each cycle it takes every window waiting, runs
    each stream's front end and extractor, denoises the windows of equal length as one batch per
    sampler step (`dimgestor.batch.push_many`: one stream per batch row) and decodes the poses. A
    stream that has nothing due is not waited for, so a stalled client never delays the others;
    streams join and leave by submitting or not. Rank as in `RankedExecutor`: while a real-time window
    (rank <= 0) waits, windows ahead of real time (a backlog) wait for the next cycle. Other jobs
    (`submit`: a stream's finish) run alone between batches.

    A cycle of backlog alone takes windows (least ahead of real time first) only until they hold
    `backlog_s` of audio: a real-time window that arrives meanwhile then waits for a short cycle, not for
    every fast sender's next second at once (31 clients sending faster than real time had pushed a
    bystander's p95 latency from 0.15 to 4.5 s).
    """

    def __init__(self, max_batch: int = 256, thread_name: str = "infer-batch", backlog_s: float = 4.0):
        self.max_batch = max_batch
        self.backlog_samples = int(backlog_s * RATE)
        self.stats = BatchStats()
        self._pushes: list[_PushJob] = []
        self._jobs: deque = deque()
        self._cv = threading.Condition()
        self._shutdown = False
        self._thread = threading.Thread(target=self._work, name=thread_name)  # not daemon: see RankedExecutor
        self._thread.start()
        register = getattr(threading, "_register_atexit", None)
        if register is not None:
            register(lambda: self.shutdown(wait=True, cancel_futures=True))

    def submit_push(self, session: "Session", samples: np.ndarray, rank: float = 0.0) -> Future:
        """Queue one window of `session` -> a Future of its frames (list[Frame])."""
        future: Future = Future()
        with self._cv:
            if self._shutdown:
                raise RuntimeError("cannot schedule new jobs after shutdown")
            self._pushes.append(_PushJob(session, samples, rank, future))
            self._cv.notify()
        return future

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        with self._cv:
            if self._shutdown:
                raise RuntimeError("cannot schedule new jobs after shutdown")
            self._jobs.append((future, fn, args, kwargs))
            self._cv.notify()
        return future

    def submit_ranked(self, rank: float, fn, /, *args, **kwargs) -> Future:
        return self.submit(fn, *args, **kwargs)

    def _take(self) -> tuple[list[_PushJob], list]:
        """The next cycle's windows (real-time ones first, one per session) and solo jobs; None at shutdown."""
        with self._cv:
            while not (self._pushes or self._jobs):
                if self._shutdown:
                    return None
                self._cv.wait()
            pushes = sorted(self._pushes, key=lambda j: j.rank)
            realtime = bool(pushes) and pushes[0].rank <= 0
            if realtime:  # real time first: a backlog waits for a cycle without any
                pushes = [j for j in pushes if j.rank <= 0]
            taken, seen, backlog = [], set(), 0
            for j in pushes:
                if not realtime and taken and backlog + len(j.samples) > self.backlog_samples:
                    break  # a short backlog cycle, so that the next real-time window is not kept waiting
                if len(taken) < self.max_batch and id(j.session) not in seen:
                    taken.append(j)
                    seen.add(id(j.session))
                    backlog += len(j.samples)
            ids = {id(j) for j in taken}
            self._pushes = [j for j in self._pushes if id(j) not in ids]
            jobs, self._jobs = list(self._jobs), deque()
            return taken, jobs

    def _work(self) -> None:
        from dimgestor.batch import push_many

        while (cycle := self._take()) is not None:
            pushes, jobs = cycle
            pushes = [j for j in pushes if j.future.set_running_or_notify_cancel()]
            if pushes:
                self.stats.add(len(pushes))
                try:
                    results = push_many([j.session.stream for j in pushes], [j.samples for j in pushes],
                                        return_exceptions=True)
                except BaseException as e:  # noqa: BLE001 - handed to every waiting session
                    results = [e] * len(pushes)
                for j, r in zip(pushes, results):
                    if isinstance(r, BaseException):
                        j.future.set_exception(r)
                        continue
                    try:
                        j.future.set_result(j.session._frames(r))
                    except BaseException as e:  # noqa: BLE001
                        j.future.set_exception(e)
            for future, fn, args, kwargs in jobs:
                if future.set_running_or_notify_cancel():
                    try:
                        future.set_result(fn(*args, **kwargs))
                    except BaseException as e:  # noqa: BLE001
                        future.set_exception(e)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        with self._cv:
            self._shutdown = True
            if cancel_futures:
                for j in self._pushes:
                    j.future.cancel()
                for job in self._jobs:
                    job[0].cancel()
                self._pushes, self._jobs = [], deque()
            self._cv.notify_all()
        if wait and threading.current_thread() is not self._thread:
            self._thread.join()


class Session:
    """One audio stream -> frames. Build with `from_bundle`; drive with `run(source, emit)`."""

    def __init__(self, stream, decoder, denormalize: Callable[[np.ndarray], np.ndarray], fps: int,
                 window_ms: int = 200, executor: Executor | None = None, name: str = "session"):
        if not 10 <= window_ms <= 5000:
            raise ValueError(f"window_ms must be in 10..5000, got {window_ms}")
        self.stream, self.decoder, self.denormalize = stream, decoder, denormalize
        self.fps, self.window = fps, RATE * window_ms // 1000
        self.executor, self.name = executor, name
        self.stats = Stats()
        self.clock = AudioClock()  # ranks this session's jobs in a RankedExecutor (a client may share one)

    @classmethod
    def from_bundle(cls, bundle, steps: int | None = None, seed: int = 0, smoothing="config", root: str = "free",
                    tether_s: float = 5.0, guidance: float | None = None, **kw) -> "Session":
        from dimgestor.features import PoseDecoder

        decoder = PoseDecoder(bundle.skeleton, bundle.feature_spec, root=root, tether_s=tether_s)
        return cls(bundle.stream(steps=steps, seed=seed, smoothing=smoothing, guidance=guidance), decoder,
                   bundle.denormalize, bundle.feature_spec.fps, **kw)

    @property
    def lookahead_s(self) -> float:
        return float(self.stream.lookahead_s)

    def _frames(self, normalized: np.ndarray) -> list[Frame]:
        """Normalized features (n, D) of the next n frames -> Frames (the stream counted them already)."""
        n = len(normalized)
        if n == 0:
            return []
        first = self.stream.frames_out - n
        feats = np.asarray(self.denormalize(normalized), dtype=np.float64)
        pose = self.decoder.decode(feats)
        return [Frame(first + i, (first + i) / self.fps, np.asarray(pose.root_pos[i]),
                      np.asarray(pose.rotations[i]), feats[i]) for i in range(n)]

    def _job(self, fn, *args) -> asyncio.Future:
        """Run fn in the executor; a RankedExecutor gets how far this session is ahead of real time."""
        submit = getattr(self.executor, "submit_ranked", None)
        if submit is None:
            return asyncio.get_running_loop().run_in_executor(self.executor, fn, *args)
        return asyncio.wrap_future(submit(self.clock.ahead_s(), fn, *args))

    def _push_job(self, samples: np.ndarray) -> asyncio.Future:
        """This window's frames: batched with the other sessions' (a StreamBatcher) or a job of its own."""
        submit = getattr(self.executor, "submit_push", None)
        if submit is None:
            return self._job(self._push, samples)
        return asyncio.wrap_future(submit(self, samples, self.clock.ahead_s()))

    def _push(self, samples: np.ndarray) -> list[Frame]:  # worker thread
        return self._frames(self.stream.push(samples))

    def _finish(self) -> list[Frame]:  # worker thread
        return self._frames(self.stream.finish())

    async def run(self, source: AsyncIterable[AudioChunk], emit: Callable[[list[Frame]], object],
                  max_buffer_s: float = 2.0, max_call_s: float = 1.0) -> int:
        """Stream `source` to the end, calling emit(frames) per window; returns the frame count.

        emit may return an awaitable (a sink applying back pressure): the session waits for it.
        """
        window = _Window(max(self.window, int(max_buffer_s * RATE)))
        piece = max(self.window, int(max_call_s * RATE))

        async def out(frames: list[Frame]) -> None:
            if inspect.isawaitable(r := emit(frames)):
                await r

        async def read() -> None:
            try:
                async for chunk in source:
                    await window.put(chunk)
                window.close()
            except BaseException as e:  # surfaces in the inference loop, cancellation included
                window.close(e if not isinstance(e, asyncio.CancelledError) else None)
                raise

        reader = asyncio.create_task(read(), name=f"{self.name}-reader")
        try:
            while True:
                chunks = await window.take(self.window)
                if not chunks:
                    break
                samples = np.concatenate([c.samples for c in chunks])
                infer_s, n = 0.0, 0
                for a in range(0, len(samples), piece):
                    t0 = time.perf_counter()
                    frames = await self._push_job(samples[a : a + piece])
                    self.clock.audio_s += min(piece, len(samples) - a) / RATE
                    infer_s += time.perf_counter() - t0
                    n += len(frames)
                    await out(frames)
                self.stats.update(len(samples) / RATE, infer_s, time.monotonic() - chunks[-1].arrival, n)
            frames = await self._job(self._finish)
            await out(frames)
            self.stats.frames += len(frames)
            self.stats.ended = True
            return self.stream.frames_out
        finally:
            if not reader.done():
                reader.cancel()
            await asyncio.gather(reader, return_exceptions=True)
