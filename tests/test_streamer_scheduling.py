"""The schedulers behind one interface: every kind gives a session its offline frames; the window rule; exit."""

import asyncio
import subprocess
import sys
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from dimgestor.streaming.stream import generate_offline
from dimgestor.training.synthetic import synthetic_speech
from streamer.scheduling import (BatcherPool, PoolScheduler, RankedScheduler, Scheduler, StreamBatcher, WindowPolicy,
                                 as_scheduler)
from streamer.sessions import Session
from streamer.sources import AudioChunk

pytestmark = pytest.mark.timeout(120)
REPO = Path(__file__).resolve().parents[1]


async def _chunks(audio, n=700):
    for a in range(0, len(audio), n):
        yield AudioChunk(audio[a:a + n], a / 16000, 0.0)


@pytest.mark.parametrize("kind", ["batcher", "batchers", "ranked", "pool", "none"])
def test_every_scheduler_gives_a_session_its_offline_frames(bundle, kind):
    audio = synthetic_speech(1.13, seed=2)
    scheduler = {"batcher": lambda: StreamBatcher(), "ranked": lambda: RankedScheduler(2),
                 "batchers": lambda: BatcherPool([StreamBatcher(), StreamBatcher()]),
                 "pool": lambda: ThreadPoolExecutor(1), "none": lambda: None}[kind]()
    session = Session.from_bundle(bundle, steps=2, seed=4, window_ms=130, scheduler=scheduler)
    assert isinstance(session.scheduler, Scheduler)
    frames = []
    try:
        n = asyncio.run(session.run(_chunks(audio), frames.extend))
    finally:
        session.scheduler.shutdown()
    want = bundle.denormalize(generate_offline(bundle.model, audio, steps=2, seed=4))
    assert n == len(frames) == len(want) and [f.index for f in frames] == list(range(n))
    assert np.abs(np.stack([f.features for f in frames]) - want).max() < 1e-4


def test_a_batcher_pool_keeps_each_session_on_one_batcher_and_shares_them_out(bundle):
    """Four sessions on two batchers: two each, every window of a session (and its finish) on the same batcher's
    thread, each session's frames its offline ones."""
    from dimgestor.streaming.batch import push_many

    threads: dict[int, set] = {}

    def recording(streams, chunks, return_exceptions=False):
        for s in streams:
            threads.setdefault(id(s), set()).add(threading.current_thread().name)
        return push_many(streams, chunks, return_exceptions)

    pool = BatcherPool([StreamBatcher(push_many=recording, thread_name=f"lane-{i}") for i in range(2)])
    audio = [synthetic_speech(0.9 + 0.1 * j, seed=j) for j in range(4)]
    sessions = [Session.from_bundle(bundle, steps=2, seed=j, window_ms=100, scheduler=pool) for j in range(4)]

    async def run_all():
        out = [[] for _ in sessions]
        await asyncio.gather(*(s.run(_chunks(a, 400), o.extend) for s, a, o in zip(sessions, audio, out)))
        return out

    try:
        outs = asyncio.run(run_all())
        homes = [pool._home[s] for s in sessions]
    finally:
        pool.shutdown()
    assert sorted(homes.count(b) for b in pool.batchers) == [2, 2]
    for s, home, a, frames in zip(sessions, homes, audio, outs):
        assert threads[id(s.stream)] == {home._threads[0].name}
        want = bundle.denormalize(generate_offline(bundle.model, a, steps=2, seed=sessions.index(s)))
        assert len(frames) == len(want) and np.abs(np.stack([f.features for f in frames]) - want).max() < 1e-4
    assert pool.workers == 2 and pool.stats.batches > 0 and pool.queued_jobs() == 0


def test_the_window_rule():
    p = WindowPolicy.of(130, max_call_s=0.5, max_buffer_s=2.0)
    assert (p.window, p.call, p.buffer, p.whole) == (2080, 8000, 32000, False)
    x = np.arange(17000)
    assert [len(c) for c in p.calls(x)] == [8000, 8000, 1000] and np.array_equal(np.concatenate(p.calls(x)), x)
    w = WindowPolicy.of(130, max_call_s=0.5, max_buffer_s=2.0, whole=True)  # a batching scheduler's
    assert (w.window, w.call, w.buffer, w.whole) == (2080, 6240, 32000, True)  # a call: the whole windows in 0.5 s
    assert [len(c) for c in w.calls(x)] == [6240, 6240, 4520]  # (the last window of a source that ended)
    pool, ranked = BatcherPool([StreamBatcher()]), RankedScheduler(1)
    try:
        assert pool.windows(130) == pool.batchers[0].windows(130) == WindowPolicy.of(130, whole=True)
        assert PoolScheduler().windows(130) == ranked.windows(130) == WindowPolicy.of(130)
    finally:
        pool.shutdown()
        ranked.shutdown()
    big = WindowPolicy.of(5000)  # a window longer than a call or the buffer: one call, room for one window
    assert big.call == big.buffer == big.window == 80000
    for bad in (9, 5001):
        with pytest.raises(ValueError, match="window_ms"):
            WindowPolicy.of(bad)
    assert RankedScheduler.windows is PoolScheduler.windows  # one rule; a batcher's differs only in `whole` (above)


def test_ranked_scheduler_runs_real_time_before_backlog():
    ex, gate, order = RankedScheduler(1), threading.Event(), []
    try:
        ex.submit(gate.wait, 30)
        futures = [ex.submit_ranked(r, order.append, r) for r in (2.0, 0.5, -1.0, 0.0, -1.0)]
        gate.set()
        [f.result(30) for f in futures]
        assert order == [-1.0, -1.0, 0.0, 0.5, 2.0]
    finally:
        gate.set()
        ex.shutdown()
    with pytest.raises(RuntimeError, match="shutdown"):
        ex.submit(print)


def test_shutdown_cancels_what_waits():
    for ex in (RankedScheduler(1), StreamBatcher()):
        gate, started = threading.Event(), threading.Event()
        running = ex.submit(lambda: (started.set(), gate.wait(30))[1])
        assert started.wait(30)
        waiting = ex.submit(lambda: 1)
        ex.shutdown(wait=False, cancel_futures=True)
        gate.set()
        ex.shutdown()
        assert running.result(5) is True and waiting.cancelled()


def test_a_plain_executor_is_adapted_and_a_scheduler_is_itself():
    b = StreamBatcher()
    try:
        assert as_scheduler(b) is b
        assert isinstance(as_scheduler(None), PoolScheduler) and as_scheduler(None).submit(lambda: 7).result(10) == 7
    finally:
        b.shutdown()


def test_the_old_name_executor_still_works_and_warns():
    """`executor` was the scheduler's old name: Session(executor=), Pipeline.executor and RankedExecutor still work,
    each with a DeprecationWarning; giving both names is an error (GestureProcessor's: test_pipecat)."""
    from types import SimpleNamespace

    import streamer.scheduling as scheduling
    from streamer.server import Pipeline

    pool = ThreadPoolExecutor(1)
    try:
        with pytest.warns(DeprecationWarning, match="use scheduler="):
            session = Session(SimpleNamespace(frames_out=0), None, None, 20, executor=pool)
        assert isinstance(session.scheduler, PoolScheduler) and session.scheduler.submit(lambda: 7).result(10) == 7
        with pytest.raises(TypeError, match="scheduler= only"):
            Session(SimpleNamespace(frames_out=0), None, None, 20, scheduler=pool, executor=pool)
    finally:
        pool.shutdown()
    with pytest.warns(DeprecationWarning, match="use RankedScheduler"):
        assert scheduling.RankedExecutor is RankedScheduler
    p = Pipeline(*[None] * 7, scheduler=pool, sinks=[])
    with pytest.warns(DeprecationWarning, match="Pipeline.scheduler"):
        assert p.executor is pool


def test_the_interpreter_exits_with_schedulers_left_running():
    """Never shut down, jobs inside torch calls: the exit hook lets them end and the process exits cleanly
    (without it the daemon workers die mid-call and the process aborts: "terminate called ...")."""
    code = """if True:
        import sys, time, torch
        from streamer.scheduling import RankedScheduler, StreamBatcher
        ex, b = RankedScheduler(1), StreamBatcher()
        def job(name):
            t0 = time.monotonic()
            while time.monotonic() - t0 < 0.5:
                torch.randn(200, 200).matmul(torch.randn(200, 200))
            sys.stdout.write(f"done {name}\\n")  # one write: print's pieces from two threads interleave
            sys.stdout.flush()
        ex.submit(job, "ranked"), b.submit(job, "batcher")
        time.sleep(0.2)
        print("leaving", flush=True)
    """
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "terminate" not in r.stderr, r.stderr[-2000:]
    assert r.stdout.split("\n")[0] == "leaving" and {"done ranked", "done batcher"} <= set(r.stdout.split("\n"))


def test_frames_protocol_and_vmc_do_not_import_the_threaded_engine():
    code = ("import sys, streamer.protocol, streamer.vmc, streamer.record; "
            "print(sorted(m for m in sys.modules if m in ('streamer.engine', 'streamer.sessions', "
            "'streamer.scheduling', 'dimgestor.streaming.batch')))")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", (r.stdout, r.stderr[-2000:])


class _Ranks(Scheduler):
    """Runs nothing: records each call's (rank, seconds of audio) and answers it at once with no frames; each
    call advances a fake clock by `compute_per_audio_s` times its audio (inference slower or faster than real time)."""

    def __init__(self, clock: list, compute_per_audio_s: float = 0.0):
        self.clock, self.compute_per_audio_s, self.calls = clock, compute_per_audio_s, []
        self.on_call = lambda rank, seconds: None

    def submit_push(self, session, samples, rank=0.0):
        self.calls.append((rank, len(samples) / 16000))
        self.clock[0] += self.compute_per_audio_s * len(samples) / 16000
        self.on_call(rank, len(samples) / 16000)
        return self._done([])

    def submit_ranked(self, rank, fn, /, *args, **kwargs):
        return self._done([])

    @staticmethod
    def _done(result):
        f = Future()
        f.set_result(result)
        return f


def _ranked_session(scheduler: _Ranks) -> Session:
    from types import SimpleNamespace

    from streamer.sessions import AudioClock

    session = Session(SimpleNamespace(frames_out=0), None, None, 20, window_ms=200, scheduler=scheduler)
    session.clock = AudioClock(now=lambda: scheduler.clock[0])
    return session


@pytest.mark.parametrize("stall_s", [0.0, 3.0])
def test_a_real_time_sender_ranks_as_real_time_however_its_packets_jitter(stall_s):
    """A talker's 100 ms packets, each up to 40 ms early or late (a fake clock; inference takes no time, but
    for one call that takes `stall_s`, meanwhile the talker's packets pile up): every call is real time
    (rank <= 0), so it never waits behind a backlog. (The clock used to start at the first call, which put
    a real-time sender at 0 +- its jitter: half its windows ranked as backlog; and a stall beyond the credit
    of 2 s used to leave it ranked ahead by the excess for good.)"""
    clock = [0.0]
    scheduler = _Ranks(clock)
    jitter = np.random.default_rng(0).uniform(-0.04, 0.04, 100)
    x = synthetic_speech(10.0, seed=1)
    taken = lambda: sum(s for _, s in scheduler.calls)  # noqa: E731

    def stall(rank, seconds):  # the 20th call takes stall_s
        if len(scheduler.calls) == 20:
            clock[0] += stall_s

    scheduler.on_call = stall

    async def talker():
        for k in range(100):
            arrival = 0.1 * (k + 1) + jitter[k]  # when this packet's last sample arrives
            if arrival > clock[0]:  # (not there yet: the session took its window meanwhile)
                while taken() < 0.1 * k - 0.1 - 1e-9:
                    await asyncio.sleep(0)
                clock[0] = max(clock[0], arrival)
            yield AudioChunk(x[1600 * k:1600 * (k + 1)], 0.1 * k, arrival)

    asyncio.run(_ranked_session(scheduler).run(talker(), lambda frames: None))
    assert taken() == pytest.approx(10.0)
    ranks = [r for r, _ in scheduler.calls]
    assert max(ranks) <= 0, f"real-time calls ranked as backlog: {np.round(ranks, 3)}"


@pytest.mark.parametrize("pieces", [1, 40])
def test_a_fast_sender_held_back_by_the_server_ranks_as_backlog_even_when_it_gets_less_than_real_time(pieces):
    """A 20 s message in a client's source (`PushSource`, as `streamer serve` holds a fast sender's audio),
    put at once or in 0.5 s pieces (as the server resamples it), inferred at half real time (fake clock): the
    client is ahead of real time by what waits, so its calls rank as backlog (> 0) as long as more than the
    credit of time without audio (2 s) waits behind them, though the audio inferred falls behind the time
    elapsed. (Ranked by audio inferred alone, it had looked real time after 2 s and shared every cycle with
    the real-time talkers; and counting only what was queued, its first calls, each on the first pieces of
    its first message, looked real time: 31 new flooders in one real-time cycle had held a talker 1.1 s.)"""
    from streamer.sources import PushSource

    clock = [0.0]
    scheduler = _Ranks(clock, compute_per_audio_s=2.0)

    async def main(pieces: int):
        source = PushSource(max_backlog_s=30.0)
        x = synthetic_speech(20.0, seed=1)

        async def client():  # one 20 s message, put in `pieces` as `streamer serve` resamples it
            for k, y in enumerate(np.array_split(x, pieces)):
                await source.put(y, more_s=20.0 * (pieces - 1 - k) / pieces)
                await asyncio.sleep(0)
            await source.close()

        await asyncio.gather(client(), _ranked_session(scheduler).run(source, lambda frames: None))

    asyncio.run(main(pieces))
    assert sum(s for _, s in scheduler.calls) == pytest.approx(20.0)
    left = 20.0 - np.cumsum([s for _, s in scheduler.calls])  # audio behind each call
    ranks = np.array([r for r, _ in scheduler.calls])
    assert clock[0] == pytest.approx(40.0) and np.all(ranks[left > 2.5] > 0), \
        f"backlog calls ranked as real time: {np.round(ranks, 2)} with {np.round(left, 1)} s behind"


def test_backlogs_rank_by_service_not_by_queue():
    """Two fast senders held back by the server: served alike, they rank alike whatever their queues (30 s, or
    62 s in the middle of a 32 s message); the one served more goes after. (Ranked by their queues, the one
    that had just read a new message waited until every other had worked through theirs: 19 of 31 flooders
    closed by the keepalive, measured.) A real-time call ranks before both."""
    from streamer.sessions import AudioClock

    t = [0.0]
    a, b = AudioClock(now=lambda: t[0]), AudioClock(now=lambda: t[0])
    for clock, queue in ((a, 30.0), (b, 62.0)):
        clock.rank(1.0, queue)
        clock.audio_s += 1.0
    t[0] = 1.5
    assert a.rank(1.0, 30.0) == b.rank(1.0, 62.0) > 0
    a.audio_s += 1.0
    t[0] = 2.0
    assert 0 < b.rank(1.0, 62.0) < a.rank(1.0, 30.0)
    assert AudioClock(now=lambda: t[0]).rank(0.2, 0.1) <= 0  # (a talker's window, its next packet behind it)


def test_fast_senders_far_ahead_take_turns_instead_of_waiting_for_the_others_to_catch_up():
    """One fast sender served alone at a flood's start (40 s ahead of real time) and one that joined later
    (1 s ahead): beyond the lead cap (2 s) they tie, so they take turns in arrival order; the early one no
    longer waits for every other to catch up 40 s (no frame for 40 s, closed by the keepalive: measured).
    Below the cap the one served less still goes first, and a real-time call before both."""
    from streamer.sessions import AudioClock

    t = [0.0]
    early, late = AudioClock(now=lambda: t[0]), AudioClock(now=lambda: t[0])
    early.rank(1.0, 30.0)
    early.audio_s = 41.0  # served 41 s of audio in its first second
    t[0] = 1.0
    late.rank(1.0, 30.0)
    late.audio_s = 1.0
    t[0] = 1.5
    assert late.rank(1.0, 30.0) < early.rank(1.0, 30.0)  # 0.5 s ahead: served less, first
    late.audio_s = 4.0
    t[0] = 2.0
    assert late.rank(1.0, 30.0) == early.rank(1.0, 30.0) > 0  # both beyond the cap: a tie
    assert AudioClock(now=lambda: t[0]).rank(0.2, 0.1) <= 0 < late.rank(1.0, 30.0)
    # (tied windows run in the order they were queued: test_streamer_batching)


def test_a_client_whose_next_session_waited_for_its_last_is_ahead_not_late():
    """A client that ends 0.5 s sessions and starts the next at once (its audio held while the last one finishes):
    the time its audio was held is not lateness, so its next session's windows and finish rank as backlog, after
    a talker. (Taken as the server's slowness, 30 such clients ranked as real time, 2 s late, and ran before a
    talker: its frames 0.35-0.68 s late against 0.06 s, measured.) A client silent between sessions stays real time."""
    from streamer.sessions import AudioClock

    t = [0.0]
    storm, pauser = AudioClock(now=lambda: t[0]), AudioClock(now=lambda: t[0])
    for clock in (storm, pauser):
        assert clock.rank(0.5) <= 0  # a first session: its audio took its length to arrive
        clock.audio_s += 0.5
    ranks = []
    for _ in range(5):  # each session: 0.2 s served, then 0.6 s waiting for the last one's finish
        t[0] += 0.8
        storm.held(0.6)
        ranks.append((storm.rank(0.5), storm.rank()))  # its window, and its finish
        storm.audio_s += 0.5
    # its first session's audio was credited its length (0.5 s): from its second session on, ahead of real time
    assert all(r > 0 for pair in ranks[1:] for r in pair), ranks
    assert pauser.rank(0.5) <= 0  # 4 s later, having sent nothing meanwhile: real time
    assert AudioClock(now=lambda: t[0]).rank(0.2, 0.1) <= 0 < storm.rank(0.5)
    storm.held(-1.0)  # (nothing held: no change)
    fresh = AudioClock(now=lambda: t[0])
    fresh.held(3.0)  # (before any call: nothing to shift)
    assert fresh.t0 is None
