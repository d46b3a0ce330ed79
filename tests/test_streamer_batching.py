"""Sessions sharing a StreamBatcher: batched windows, each session's frames as if alone, no waiting on a stalled one."""

import asyncio
import itertools
import threading
import time
from concurrent.futures import Future

import numpy as np
import pytest

from dimgestor.audio import save_wav
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.streaming.stream import generate_offline
from dimgestor.training.synthetic import synthetic_speech
from streamer.scheduling import StreamBatcher
from streamer.sessions import Session
from streamer.sources import WavSource
from helpers.checkpoint import make_tiny_checkpoint

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return load_checkpoint(make_tiny_checkpoint(tmp_path_factory.mktemp("ckpt"), jitter=0.05))


def test_sessions_share_batches_and_each_gets_its_own_frames(bundle, tmp_path):
    """Six real-time sessions (different seeds, audio, start times, one ending early) on one batcher:
    each session's frames equal its offline run, and a client whose sink stalls for 2 s neither delays
    the others nor loses a frame."""
    batcher = StreamBatcher()
    specs = [(seed, 1.6 if seed != 2 else 0.8, 0.15 * seed) for seed in range(6)]  # (seed, seconds, start delay)
    wavs = []
    for seed, seconds, _ in specs:
        wav = tmp_path / f"{seed}.wav"
        save_wav(wav, synthetic_speech(seconds, seed=seed), 16000)
        wavs.append(wav)
    stall_s = 2.0
    results = {}

    async def one(seed, wav, delay):
        await asyncio.sleep(delay)
        src = WavSource(wav, realtime=True, chunk_ms=20)
        session = Session.from_bundle(bundle, steps=3, seed=seed, window_ms=100, scheduler=batcher, name=f"s{seed}")
        frames, t0 = [], time.monotonic()

        async def emit(fs):
            if seed == 4 and not frames:  # a stalled client: its sink blocks
                await asyncio.sleep(stall_s)
            frames.extend(fs)

        await session.run(src, emit)
        results[seed] = (src.audio, frames, time.monotonic() - t0, delay)

    async def main():
        await asyncio.gather(*(one(seed, wav, delay) for (seed, _, delay), wav in zip(specs, wavs)))

    try:
        asyncio.run(main())
    finally:
        batcher.shutdown()
    assert batcher.stats.batches > 0
    for seed, (audio, frames, took, _) in results.items():
        want = bundle.denormalize(generate_offline(bundle.model, audio, steps=3, seed=seed))
        got = np.stack([f.features for f in frames])
        assert got.shape == want.shape
        assert np.abs(got - want).max() < 1e-3 * max(1.0, np.abs(want).max()), seed
        assert [f.index for f in frames] == list(range(len(frames)))
    audio_s = {seed: len(r[0]) / 16000 for seed, r in results.items()}
    assert results[4][2] >= stall_s  # the stalled one really waited (then caught up from its buffer)
    for seed in (0, 1, 3, 5):  # the others kept pace with their audio meanwhile
        assert results[seed][2] < audio_s[seed] + 1.5, (seed, results[seed][2])


def test_windows_waiting_together_run_as_one_batch(bundle):
    """Windows that are due while the batcher is busy run in one batch next cycle, real time before backlog."""
    batcher = StreamBatcher()
    gate = threading.Event()
    try:
        batcher.submit(gate.wait, 30)  # the batcher is busy until the windows below are all queued
        sessions = [Session.from_bundle(bundle, steps=2, seed=i, scheduler=batcher) for i in range(5)]
        audio = synthetic_speech(0.3, seed=3)
        futures = [batcher.submit_push(s, audio, rank=0.0 if i < 4 else 1.0) for i, s in enumerate(sessions)]
        gate.set()
        frames = [f.result(30) for f in futures]
        assert batcher.stats.batches == 2 and batcher.stats.peak == 4  # 4 real-time windows, then the backlog one
        for i, fs in enumerate(frames):
            want = bundle.denormalize(generate_offline(bundle.model, audio, steps=2, seed=i))[:len(fs)]
            assert len(fs) == len(want) > 0
            assert np.abs(np.stack([f.features for f in fs]) - want).max() < 1e-3 * max(1.0, np.abs(want).max())
        assert "batch" in batcher.stats.describe()
    finally:
        gate.set()
        batcher.shutdown()


@pytest.mark.parametrize("cycle_s, batches, peak", [(0.1, 7, 1), (0.25, 5, 2)])
def test_a_backlog_cycle_is_short_so_real_time_windows_do_not_wait_behind_it(bundle, cycle_s, batches, peak):
    """Six sessions with 0.6 s of backlog each; a fake clock on which every cycle takes 0.1 s: the first backlog
    cycle takes 1 s of audio (`backlog_s`, nothing measured yet), then as much as `cycle_s` of compute at the
    measured cost (0.1 s per 0.6 s window: one window in 0.1 s, two in 0.25 s), least ahead of real time first;
    a real-time window queued meanwhile runs in the next cycle, before the rest of the backlog."""
    ticks = itertools.count()
    batcher = StreamBatcher(backlog_s=1.0, cycle_s=cycle_s, clock=lambda: 0.1 * ((next(ticks) + 1) // 2))
    gate, order = threading.Event(), []
    try:
        batcher.submit(gate.wait, 30)
        sessions = [Session.from_bundle(bundle, steps=2, seed=i, scheduler=batcher) for i in range(7)]
        audio = synthetic_speech(0.6, seed=3)
        backlog = [batcher.submit_push(s, audio, rank=1.0 + i) for i, s in enumerate(sessions[:6])]
        for i, f in enumerate(backlog):
            f.add_done_callback(lambda _, i=i: order.append(i))
        speech, live = synthetic_speech(0.1, seed=4), Future()

        def queue_live(_):
            """The real-time window is queued as the first backlog window comes out, from the inference thread
            itself (where the done callback runs), so it is queued before the next cycle is taken on any machine
            (queued from the test's thread after `result()`, a loaded machine let 3 more cycles run first)."""
            f = batcher.submit_push(sessions[6], speech, rank=0.0)
            f.add_done_callback(lambda _: order.append("live"))
            f.add_done_callback(lambda f: live.set_exception(e) if (e := f.exception()) else live.set_result(f.result()))

        backlog[0].add_done_callback(queue_live)
        gate.set()
        for f in backlog + [live]:
            f.result(60)
        assert (batcher.stats.batches, batcher.stats.peak) == (batches, peak)  # (the live window's cycle is one)
        assert order.index("live") <= 2 * peak, order  # the live window overtakes the backlog (before: after all six)
        assert sorted(i for i in order if i != "live") == list(range(6)) and order.index(5) > order.index(0)
    finally:
        gate.set()
        batcher.shutdown()


def test_tied_backlog_windows_take_turns_in_the_order_they_were_queued(bundle):
    """Six fast senders all beyond the lead cap (one backlog rank), one window per cycle: they run in the
    order they were queued, not by session, so one that has just been served waits for the others' turn only."""
    ticks = itertools.count()
    batcher = StreamBatcher(backlog_s=0.6, cycle_s=0.1, clock=lambda: 0.1 * ((next(ticks) + 1) // 2))
    gate, order = threading.Event(), []
    try:
        batcher.submit(gate.wait, 30)
        sessions = [Session.from_bundle(bundle, steps=2, seed=i, scheduler=batcher) for i in range(6)]
        audio = synthetic_speech(0.6, seed=3)
        queued = [3, 0, 5, 1, 4, 2]
        futures = [batcher.submit_push(sessions[i], audio, rank=5.0) for i in queued]
        for i, f in zip(queued, futures):
            f.add_done_callback(lambda _, i=i: order.append(i))
        gate.set()
        for f in futures:
            f.result(60)
        assert batcher.stats.peak == 1 and order == queued, (order, batcher.stats.peak)
    finally:
        gate.set()
        batcher.shutdown()


def test_a_crowd_of_backlog_finishes_takes_one_turn_a_cycle_so_a_talkers_window_does_not_wait_behind_them(bundle):
    """Five sessions far ahead of real time end (their finishes queued at backlog ranks) while a talker's window
    is queued as the first finish runs: the talker's window runs next, not after the other four finishes (every
    queued finish used to run in one cycle, whatever its rank); a real-time finish still runs in its cycle."""
    batcher = StreamBatcher()
    gate, order = threading.Event(), []
    try:
        batcher.submit(gate.wait, 30)
        talker = Session.from_bundle(bundle, steps=2, seed=0, scheduler=batcher)
        live = Future()

        def finish(i):
            order.append(i)
            if i == 0:  # queued from the inference thread as the first finish runs: before the next cycle is taken
                f = batcher.submit_push(talker, synthetic_speech(0.1, seed=4), rank=-0.05)
                f.add_done_callback(lambda f: (order.append("live"), live.set_result(len(f.result()))))

        finishes = [batcher.submit_ranked(1.0 + i, finish, i) for i in range(5)]
        realtime_finish = batcher.submit_ranked(0.0, order.append, "realtime finish")
        gate.set()
        for f in [*finishes, realtime_finish, live]:
            f.result(60)
        assert order == ["realtime finish", 0, "live", 1, 2, 3, 4], order
    finally:
        gate.set()
        batcher.shutdown()


def test_a_crowd_of_late_finishes_takes_a_cycles_worth_a_cycle_so_a_talkers_window_does_not_wait_behind_them(bundle):
    """Six sessions late on real time end (a machine too slow for a crowd that restarts sessions over and over
    makes them late) while a talker's window is queued as the first finish runs: a real-time cycle runs only
    `cycle_s` of finishes (each measured: 50 ms on a fake clock, so two of 100 ms), the latest first, and the
    talker's window goes in the next cycle, not after all six (every real-time finish used to run in one cycle)."""
    now = [0.0]
    batcher = StreamBatcher(cycle_s=0.1, clock=lambda: now[0])
    gate, order = threading.Event(), []
    try:
        running = threading.Event()

        def first():  # measured at 50 ms: what sizes the next cycles' finishes
            running.set()
            gate.wait(30)
            now[0] += 0.05

        batcher.submit(first)
        assert running.wait(30)  # taken alone, before the finishes are queued (else the first cycle takes one of them)
        talker = Session.from_bundle(bundle, steps=2, seed=0, scheduler=batcher)
        live = Future()

        def finish(i):
            order.append(i)
            now[0] += 0.05
            if i == 0:  # queued from the inference thread as the first finish runs: before the next cycle is taken
                f = batcher.submit_push(talker, synthetic_speech(0.1, seed=4), rank=-0.05)
                f.add_done_callback(lambda f: (order.append("live"), live.set_result(len(f.result()))))

        finishes = [batcher.submit_ranked(-2.0 + 0.01 * i, finish, i) for i in range(6)]
        gate.set()
        for f in [*finishes, live]:
            f.result(60)
        assert order == [0, 1, "live", 2, 3, 4, 5], order
    finally:
        gate.set()
        batcher.shutdown()


def test_batcher_isolates_a_failing_stream(bundle):
    """A window that fails (a finished stream) fails its own future only; the batch's others get frames."""
    batcher = StreamBatcher()
    gate = threading.Event()
    try:
        good = Session.from_bundle(bundle, steps=2, seed=1, scheduler=batcher)
        bad = Session.from_bundle(bundle, steps=2, seed=2, scheduler=batcher)
        bad.stream.finish()
        audio = synthetic_speech(0.5, seed=1)
        batcher.submit(gate.wait, 30)
        f_good, f_bad = batcher.submit_push(good, audio), batcher.submit_push(bad, audio)
        gate.set()
        assert len(f_good.result(30)) > 0
        assert batcher.stats.last == 2  # they were in one batch
        with pytest.raises(RuntimeError, match="after finish"):
            f_bad.result(30)
        assert batcher.submit(lambda: 42).result(30) == 42
    finally:
        batcher.shutdown()
    with pytest.raises(RuntimeError, match="shutdown"):
        batcher.submit_push(good, audio)
