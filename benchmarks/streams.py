"""Concurrent real-time streams through the serving path: how many one process keeps in real time.

Each trial runs n `streamer.sessions.Session`s in one asyncio loop, each fed by its own `PacedSource`
(20 ms chunks released when their last sample would have been spoken, as a microphone or a paced
file does), all on ONE `StreamBatcher` (batched: the due windows of all sessions as one forward per
sampler step) or ONE `RankedScheduler` (unbatched: each session's window alone, as `--no-batch`).
Sessions start at staggered phases (session j's audio clock begins j/n of a window later), as clients
that connect at random times do, so a cycle batches whichever windows are due.

Lag of a window = the time its frames came out - the time its last audio sample arrived. A count n
keeps real time when, over the second half of the trial, the 95th-percentile lag stays under one
window + `slack_ms` and no stream ends more than `end_ms` behind (the lag does not grow).
"""

from __future__ import annotations

import asyncio
import os
import threading
import time

import numpy as np

from common import percentile_ms, test_audio
from dimgestor.audio import SAMPLE_RATE


class PacedSource:
    """`audio` as 16 kHz chunks released in real time from `t0` (time.monotonic), stamped with their due time."""

    def __init__(self, audio: np.ndarray, t0: float, chunk_ms: int = 20):
        self.audio, self.t0, self.chunk = audio, t0, SAMPLE_RATE * chunk_ms // 1000

    async def __aiter__(self):
        from streamer.sources import AudioChunk

        for a in range(0, len(self.audio), self.chunk):
            x = self.audio[a: a + self.chunk]
            due = self.t0 + (a + len(x)) / SAMPLE_RATE
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            yield AudioChunk(x, a / SAMPLE_RATE, due)  # arrival = due: a late consumer shows as lag, like a live input


def random_bundle(preset: str, seed: int = 0):
    """A `Bundle` of `preset` with random weights and the embedded model's skeleton and normalization;
    preset "default": the embedded default model itself (its front end, lookahead and guidance).

    Speed does not depend on the weights; the skeleton makes each window's pose decoding (done on the
    inference thread, as in `dimgestor serve`) the real one.
    """
    import torch

    from dimgestor.config import get_preset
    from dimgestor.model.network import DiMGestor
    from dimgestor.streaming.checkpoint import Bundle, load_checkpoint

    base = load_checkpoint(None)
    if preset == "default":
        return base
    torch.manual_seed(seed)
    model = DiMGestor(get_preset(preset, motion_dim=base.feature_spec.dim)).eval()
    with torch.no_grad():  # adaLN-Zero init makes blocks the identity; random weights cost the same as trained ones
        for p in model.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return Bundle(model, model.config, base.feature_spec, base.skeleton, base.mean, base.std, {"random_init": True})


def _set_threads(scheduler, workers: int, threads: int) -> list[int]:
    """Set torch's intra-op thread count in each inference thread (it is per calling thread) -> what each has."""
    import torch

    barrier = threading.Barrier(workers)

    def job():
        torch.set_num_threads(threads)
        barrier.wait(timeout=30)  # every worker takes one job
        return torch.get_num_threads()

    return [f.result(timeout=60) for f in [scheduler.submit(job) for _ in range(workers)]]


class _CountingStats:
    """Wraps a batcher's BatchStats to also keep the exact mean batch size of a trial."""

    def __init__(self, inner):
        self.inner, self.count, self.total = inner, 0, 0

    def add(self, size: int) -> None:
        self.inner.add(size)
        self.count += 1
        self.total += size

    def __getattr__(self, name):
        return getattr(self.inner, name)


def make_scheduler(batched: bool, threads: int, batch_runner=None):
    """(scheduler, description): one StreamBatcher thread on `threads` torch threads, or a RankedScheduler as
    `dimgestor serve --no-batch` builds it (min(4, cores) workers) with one torch thread per worker.
    batch_runner: a `dimgestor.export.onnx_batch.BatchRunner`, or a list of them: a `BatcherPool` of one StreamBatcher a
    runner pushes its windows on them, as `dimgestor serve --backend onnxruntime` does (a runner's session threads
    are its own)."""
    from streamer.scheduling import RankedScheduler, StreamBatcher

    if batched and batch_runner is not None:
        import functools

        from dimgestor.export.onnx_batch import push_many
        from streamer.scheduling import BatcherPool

        runners = batch_runner if isinstance(batch_runner, (list, tuple)) else [batch_runner]
        ex = BatcherPool([StreamBatcher(push_many=functools.partial(push_many, r), thread_name=f"bench-batch-{i}")
                          for i, r in enumerate(runners)])  # as `dimgestor serve --backend onnxruntime` (one lane a runner)
        ex.stats = _CountingStats(ex.stats)
        return ex, {"executor": "BatcherPool", "inference_threads": len(runners),
                    "onnxruntime_threads": runners[0].threads, "graph_batches": runners[0].sizes}
    if batched:
        ex = StreamBatcher()
        ex.stats = _CountingStats(ex.stats)
        got = _set_threads(ex, 1, threads)
        return ex, {"executor": "StreamBatcher", "inference_threads": 1, "torch_threads_per_thread": got}
    workers = min(4, os.cpu_count() or 1)
    ex = RankedScheduler(max_workers=workers, thread_name_prefix="bench-infer")
    got = _set_threads(ex, workers, 1)
    return ex, {"executor": "RankedExecutor", "inference_threads": workers, "torch_threads_per_thread": got}


def serving_trial(bundle, n: int, steps: int, window_ms: int, seconds: float, batched: bool, threads: int,
                  aligned: bool = False, slack_ms: float = 150.0, end_ms: float = 500.0, grace_s: float = 10.0,
                  onnx=None, batch_runner=None, face=None, face_process=None) -> dict:
    """n paced sessions on one scheduler for `seconds` of audio each -> lags, batch sizes, frames, verdict.

    aligned: every session's audio clock starts at the same instant (all windows due together: the best
    case for batching) instead of staggered over one window. onnx: a `dimgestor.export.onnx_stream.OnnxModel`: the
    sessions run on it, as `dimgestor serve --backend onnxruntime` builds them (batched: on `batch_runner`, the
    export's batched graphs; unbatched: each window alone, as with --no-batch). face: a
    `dimgestor.face.FaceOptions`: every session makes a face too, as a client that asks for one. face_process: a
    `streamer.face_process.FaceProcess` the faces are made in (`serve --face-process`)."""
    from streamer.sessions import Session

    if onnx is not None and batched and batch_runner is None:
        raise ValueError("batched ONNX Runtime sessions need the export's BatchRunner (batch_runner=)")
    audio = test_audio(seconds, SAMPLE_RATE)
    scheduler, how = make_scheduler(batched, threads, batch_runner if onnx is not None else None)
    lags: list[list[tuple[float, float]]] = [[] for _ in range(n)]  # per session: (audio time, lag s)
    frames = [0] * n
    window_s = window_ms / 1000

    faces = {"face": face} if face_process is None else {"face": face, "face_process": face_process}  # (older code)

    async def one(j: int, t0: float) -> None:
        if onnx is None:
            session = Session.from_bundle(bundle, steps=steps, seed=j, window_ms=window_ms, scheduler=scheduler,
                                          name=f"bench{j}", **faces)
        else:
            from dimgestor.features import PoseDecoder

            session = Session(onnx.stream(seed=j, lookahead_s=bundle.model.lookahead_s),
                              PoseDecoder(bundle.skeleton, bundle.feature_spec), bundle.denormalize,
                              bundle.feature_spec.fps, window_ms=window_ms, scheduler=scheduler, name=f"bench{j}",
                              **faces)

        def emit(fs) -> None:
            frames[j] += len(fs)
            done = session.clock.audio_s  # audio handed to inference so far: this window's end
            if not lags[j] or done > lags[j][-1][0]:  # the finish() call after the source ends is not a window
                lags[j].append((done, time.monotonic() - (t0 + done)))

        await session.run(PacedSource(audio, t0), emit)

    async def main() -> float:
        start = time.monotonic() + 0.2
        tasks = [asyncio.ensure_future(one(j, start + (0.0 if aligned else window_s * j / n))) for j in range(n)]
        done, pending = await asyncio.wait(tasks, timeout=seconds + window_s + grace_s)
        for t in pending:
            t.cancel()
        await asyncio.gather(*pending, return_exceptions=True)
        for t in done:
            t.result()  # a failing session is a failing benchmark, not a slow one
        return time.monotonic() - start

    cpu0 = time.process_time()
    try:
        wall = asyncio.run(main())
    finally:
        scheduler.shutdown(wait=True, cancel_futures=True)
    cpu = time.process_time() - cpu0
    late = [lag for per in lags for a, lag in per if a >= seconds / 2]
    ends = [per[-1][1] if per and per[-1][0] >= seconds - window_s else float("inf") for per in lags]
    p95 = percentile_ms(late, 95) if late else float("inf")
    end_worst = max(ends) * 1000
    stats = getattr(scheduler, "stats", None)
    return {
        "streams": n, "batched": batched, "face": face is not None, "backend": "torch" if onnx is None else "onnxruntime", "phases": "aligned" if aligned else "staggered", **how,
        "lag_ms_p50": percentile_ms(late, 50) if late else float("inf"), "lag_ms_p95": p95,
        "end_lag_ms_max": end_worst, "windows": sum(len(x) for x in lags), "frames": sum(frames),
        "mean_batch": stats.total / stats.count if stats is not None and stats.count else 1.0,
        "batches": stats.count if stats is not None else None,
        "wall_s": wall, "process_cpu_s": cpu,
        "ok": bool(p95 < window_ms + slack_ms and end_worst < end_ms),
    }


def max_streams(bundle, steps: int, window_ms: int, seconds: float, batched: bool, threads: int, cap: int,
                aligned: bool = False, log=print, onnx=None, batch_runner=None, face=None) -> dict:
    """Double n until a trial falls behind (or n passes `cap`), then bisect between the last pass and the fail
    until they are within 10 % (the answer is the largest count that passed)."""
    trials, good, bad, n = [], 0, None, 1

    def trial(k: int) -> bool:
        r = serving_trial(bundle, k, steps, window_ms, seconds, batched, threads, aligned, onnx=onnx,
                          batch_runner=batch_runner, face=face)
        trials.append(r)
        log(f"  {'' if onnx is None else 'onnxruntime '}{'batched' if batched else 'unbatched':9s}{' aligned' if aligned else ''} K={steps} {k:3d} streams: lag p50/p95 "
            f"{r['lag_ms_p50']:.0f}/{r['lag_ms_p95']:.0f} ms, worst end {r['end_lag_ms_max']:.0f} ms, "
            f"batch {r['mean_batch']:.1f} -> {'ok' if r['ok'] else 'falls behind'}")
        return r["ok"]

    while n <= cap:
        if not trial(n):
            bad = n
            break
        good, n = n, min(n * 2, cap) if n < cap else cap + 1
    while bad is not None and bad - good > max(1, good // 10):  # to 10 %: trial-to-trial noise is larger
        mid = (good + bad) // 2
        good, bad = (mid, bad) if trial(mid) else (good, mid)
    return {"max_realtime_streams": good, "capped": bad is None, "batched": batched, "face": face is not None,
            "backend": "torch" if onnx is None else "onnxruntime",
            "phases": "aligned" if aligned else "staggered", "steps": steps,
            "window_ms": window_ms, "trial_s": seconds, "trials": sorted(trials, key=lambda r: r["streams"])}
