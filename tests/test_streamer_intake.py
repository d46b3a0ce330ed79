"""Fair shares in compute (streamer/intake.py): the worker thread's fair order and each client's share of it in CPU
time; and fast senders at a high rate (192 kHz stereo float32, as fast as the socket takes it) beside a real-time
talker, against a live `dimgestor serve --source ws` (tests/helpers/intake_load.py).

A 192 kHz stereo float32 second costs ~100x a 16 kHz PCM16 one to take in (decode, channel mix, resample): the
flooders' intake is charged to them, so they are read more slowly and told `slow_down`, and the talker's small jobs
do not queue behind their big ones.
"""

import asyncio
import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from helpers.intake_load import talker_beside_flood
from helpers.serve import serve
from helpers.ws import make_server, recv_json
from streamer import protocol as P
from streamer.intake import (INTAKE_BURST_AUDIO_S, INTAKE_BURST_S, INTAKE_SHARE, MAX_SHARE, REAL_TIME_HEADROOM, Account,
                            ComputeBudget, FairWorker, submit_for)

pytestmark = pytest.mark.timeout(150)


def test_fast_192k_stereo_senders_are_throttled_and_a_talker_keeps_its_latency(tiny_checkpoint):
    """Issue 40's row: 3 clients send 192 kHz stereo float32 as fast as the socket takes it, beside a talker paced
    in real time (and a 192 kHz stereo sender paced in real time): the talker's p95 stays within 1.5x its quiet p95
    (a floor of 0.6 s), it loses nothing, the paced 192 kHz sender is never told slow_down."""
    s = serve(tiny_checkpoint, "--source", "ws")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)

    def within(r):  # a shared 2-core machine's scheduler alone moves a ~0.2 s p95 by ~0.1 s: the floor
        return r["flooded_p95_s"] <= max(1.5 * r["quiet_p95_s"], 0.6)

    try:
        trials = [asyncio.run(talker_beside_flood(url, clients=3, paced_high_rate=True))]
        if not within(trials[0]):
            # other work on a shared machine (a busy loop beside it: 0.78 s against 0.12 s once in 3 runs, 0.13-0.16 s
            # otherwise) can stretch one flood: measure once more, after a quiet phase of its own. A server that
            # lets flooders starve the talker (5-9 s here before) fails both times.
            trials.append(asyncio.run(talker_beside_flood(url, clients=3, paced_high_rate=True)))
    finally:
        s.proc.terminate()
        s.finish(10)
    report = [(round(r["quiet_p95_s"], 3), round(r["flooded_p95_s"], 3), r["counts"]) for r in trials]
    print("quiet p95 s, flooded p95 s, the flooders' counts:", report, "server output:\n" + s.output[-3000:])
    assert any(within(r) for r in trials), report
    for r in trials:
        talker, paced, counts = r["talker"], r["paced"], r["counts"]
        assert talker.end is not None and talker.frames == talker.end["frames"], (talker.frames, talker.end)
        assert talker.end["frames"] >= int(talker.sent_s * talker.fps) - 1  # all its audio became frames
        assert not talker.errors, talker.errors[:3]
        assert not paced.errors and paced.frames > 0, paced.errors  # 192 kHz stereo in real time: within its share
        # Each flooder is told once at most, and `resume` only after `slow_down`. Told at all when the machine let it
        # take more than its share in: here ~40 messages in 10 s, each told (a busy loop beside it held them to
        # ~25-30, ~0.07 of the thread: none was told); test_a_client_over_its_share_... tells one on any machine.
        assert all(counts.get(f"{k}:resume", 0) <= counts.get(f"{k}:slow_down", 0) <= 1 for k in range(3)), counts


def burn(seconds: float) -> None:
    """CPU work of about `seconds` (thread time, whatever else the machine runs)."""
    t = time.thread_time()
    while time.thread_time() - t < seconds:
        pass


def test_the_account_that_used_the_worker_least_goes_first():
    worker, order = FairWorker("test-fair"), []
    gate, flooder, talker = threading.Event(), Account(), Account()
    try:
        worker.submit(gate.wait)  # (the thread is held while the queue is built)
        for k in range(5):
            submit_for(worker, flooder, lambda k=k: (burn(0.02), order.append(f"f{k}")))
        jobs = [submit_for(worker, talker, lambda k=k: order.append(f"t{k}")) for k in range(3)]
        gate.set()
        for j in jobs:
            j.result(10)
        worker.submit(lambda: None).result(10)
    finally:
        worker.shutdown()
    # one flooder job may come first (it was queued first, at the same virtual time); then the talker's small jobs
    # go before the flooder's next, each of which moves the flooder back by what it took
    assert order[:4] in (["t0", "t1", "t2", "f0"], ["f0", "t0", "t1", "t2"]), order
    assert flooder.spent_s >= 5 * 0.02 and talker.spent_s < flooder.spent_s / 10


def test_a_fair_worker_is_an_executor_that_hands_back_errors_and_cancels_at_shutdown():
    worker = FairWorker("test-fair")
    assert worker.submit(sum, [1, 2]).result(10) == 3
    with pytest.raises(ZeroDivisionError):
        worker.submit(lambda: 1 / 0).result(10)
    gate = threading.Event()
    held, queued = worker.submit(gate.wait), worker.submit(lambda: "never")
    time.sleep(0.05)
    worker.shutdown(wait=False, cancel_futures=True)
    gate.set()
    assert held.result(10) is True and queued.cancelled()
    with pytest.raises(RuntimeError):
        worker.submit(sum, [])


def test_the_cost_is_measured_on_any_executor():
    account = Account()
    with ThreadPoolExecutor(1) as pool:
        assert submit_for(pool, account, lambda: (burn(0.03), "done")[1]).result(10) == "done"
    assert 0.03 <= account.spent_s < 1.0


def test_a_client_over_its_share_waits_in_proportion_and_is_within_it_again_once_refilled(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(time, "monotonic", lambda: now[0])
    account = Account()
    budget = ComputeBudget(account, share=0.1, burst_s=0.5)
    account.spent_s += 0.4  # within its burst
    assert budget.wait_s(now[0]) == 0.0 and not budget.over
    account.spent_s += 0.2  # 0.1 s of CPU into debt: 1 s at a tenth of the thread
    assert budget.wait_s(now[0]) == pytest.approx(1.0) and budget.over
    assert budget.refilled_in(now[0]) == pytest.approx(3.5)  # from -0.1 to half the burst, 0.25
    now[0] += 2.0
    assert budget.wait_s(now[0]) == 0.0 and budget.over  # out of debt, not yet back to half
    now[0] += 1.6
    assert budget.refilled_in(now[0]) == 0.0 and not budget.over
    now[0] += 100.0
    assert budget.wait_s(now[0]) == 0.0 and budget.tokens == 0.5  # (no credit saved beyond the burst)


def stream(budget: ComputeBudget, now: list[float], seconds: float, chunk_s: float, cost_per_audio_s,
           speed: float = 1.0, stall_every_s: float = 0.0, stall_s: float = 0.0) -> dict:
    """A client sending `chunk_s` messages at `speed` x real time on a fake clock (`now`), each costing
    cost_per_audio_s(t) CPU seconds per audio second, its socket read as the connection does (after `wait_s`);
    every `stall_every_s` the network holds its messages for `stall_s`, then they come at once. Returns how often
    it was `over`, the audio taken in and the time it took."""
    t0, account, over, sent = now[0], budget.account, 0, 0.0
    while sent < seconds:
        u = sent / speed  # when the client sent this message
        if stall_every_s and u % stall_every_s >= stall_every_s - stall_s:
            u = (u // stall_every_s + 1) * stall_every_s  # held, then all at once
        now[0] = max(now[0], t0 + u)
        account.spent_s += chunk_s * cost_per_audio_s(now[0] - t0)
        account.audio_s += chunk_s
        sent += chunk_s
        now[0] += budget.wait_s(now[0])
        over += budget.over
    return {"over": over, "audio_s": sent, "took_s": now[0] - t0}


def test_a_client_in_real_time_is_within_its_share_whatever_its_audio_costs_on_this_machine():
    """Issue 47: 192 kHz stereo float32 in real time takes 0.03-0.06 of the thread on one machine and more than
    the fixed 0.1 once was on a slower or busier one. Its share follows what its own audio costs here: sent in
    real time (with the network holding it 1 s in 3), it is never over, at 0.05 or 0.3 of the thread, or when the
    machine grows twice as slow under it; a fixed share (no headroom) would have slowed the slow machine's."""
    for cost in (lambda t: 0.05, lambda t: 0.3, lambda t: 0.1 if t < 20 else 0.2):
        now = [0.0]
        r = stream(ComputeBudget(Account(), now=now[0]), now, 60.0, 0.05, cost, stall_every_s=3.0, stall_s=1.0)
        assert r["over"] == 0 and r["took_s"] == pytest.approx(60.0, abs=1.0), r
    now = [0.0]
    fixed = ComputeBudget(Account(), headroom=0.0, burst_audio_s=0.0, now=now[0])
    assert stream(fixed, now, 60.0, 0.05, lambda t: 0.3)["over"] > 0  # what a slower machine's client was told


def test_a_client_faster_than_real_time_is_read_at_its_share_whatever_its_audio_costs():
    """Sent as fast as it is read (10x real time), a client that is dear to take in is read at REAL_TIME_HEADROOM x
    real time once its burst is spent, on a fast machine or a slow one; one that is cheap (16 kHz PCM16) at
    INTAKE_SHARE over its cost, far faster, as before."""
    for cost in (0.1, 0.3):
        now = [0.0]
        budget = ComputeBudget(Account(), now=now[0])
        r = stream(budget, now, 300.0, 0.5, lambda t: cost, speed=10.0)
        burst_audio_s = max(INTAKE_BURST_S / cost, INTAKE_BURST_AUDIO_S)
        assert r["over"] > 0 and budget.over
        assert (r["audio_s"] - burst_audio_s) / r["took_s"] == pytest.approx(REAL_TIME_HEADROOM, rel=0.05), r
    now = [0.0]
    r = stream(ComputeBudget(Account(), now=now[0]), now, 300.0, 0.5, lambda t: 0.001, speed=10.0)
    assert r["over"] == 0 and r["took_s"] == pytest.approx(30.0, abs=0.5), r


def test_a_client_whose_audio_costs_most_of_the_thread_is_held_to_half_of_it():
    """However dear a client makes its audio look (a new resampler with every message), its share stops at
    MAX_SHARE: in real time at 0.8 of the thread per second of audio it is over and read at MAX_SHARE / 0.8 of
    real time once its burst is spent; the others keep the rest of the thread."""
    now = [0.0]
    budget = ComputeBudget(Account(), now=now[0])
    r = stream(budget, now, 120.0, 0.5, lambda t: 0.8)
    assert budget.rate() == MAX_SHARE and r["over"] > 0
    burst_audio_s = max(INTAKE_BURST_S, INTAKE_BURST_AUDIO_S * 0.8) / 0.8
    assert (r["audio_s"] - burst_audio_s) / r["took_s"] == pytest.approx(MAX_SHARE / 0.8, rel=0.05), r


class CostlyWorker(FairWorker):
    """Decoding a client's audio costs `cost_s` of CPU per message more (on any machine: CPU time, not a sleep)."""

    def __init__(self, cost_s: float):
        super().__init__("test-costly")
        self.cost_s = cost_s

    def submit_for(self, account, fn, /, *args):
        if fn is P.decode_audio:
            return super().submit_for(account, lambda: (burn(self.cost_s), fn(*args))[1])
        return super().submit_for(account, fn, *args)


def test_a_client_over_its_share_is_read_more_slowly_told_slow_down_and_then_resume(bundle):
    """Each message (1 s of audio) costs 40 ms of the worker's CPU more, sent as fast as it is read: after its burst
    the client is over its share (the larger of INTAKE_SHARE and REAL_TIME_HEADROOM x what its audio costs: 0.1 of
    the thread), told `slow_down` once, read at ~2.5 messages a second, and told `resume` once its budget has
    refilled after it stopped; every frame of its audio still comes, then `end`."""
    from websockets.asyncio.client import connect

    n, cost_s = 16, 0.04

    async def scenario():
        server = make_server(bundle)
        server.prep = CostlyWorker(cost_s)
        await server.open()
        try:
            async with connect(f"ws://127.0.0.1:{server.port}/") as ws:
                assert (await recv_json(ws))["type"] == "hello"
                await ws.send(json.dumps({"type": "hello", "audio": {"rate": 16000, "format": "float32"}}))
                t0 = time.monotonic()
                speech = (0.1 * np.sin(np.arange(16000) * 0.05)).astype("<f4").tobytes()  # 1 s
                for _ in range(n):
                    await ws.send(speech)
                await ws.send(json.dumps({"type": "audio_end"}))
                told, frames, end = [], 0, None
                while end is None or "resume" not in [m["type"] for m in told]:
                    m = await recv_json(ws, timeout=30)
                    frames += m["type"] == "frame"
                    if m["type"] == "end":
                        end, t_end = m, time.monotonic()
                    elif m["type"] in ("error", "resume"):
                        told.append(m)
                return told, frames, end, t_end - t0
        finally:
            await server.close(within_s=0.5)

    told, frames, end, took_s = asyncio.run(scenario())
    assert [m.get("code", m["type"]) for m in told] == ["slow_down", "resume"], told
    assert "16000 Hz" in told[0]["message"]
    assert frames == end["frames"] > 0
    # its messages were read at its share: (n x 40 ms - its burst) / its share of the thread, at least
    share = max(INTAKE_SHARE, REAL_TIME_HEADROOM * cost_s)
    burst = max(INTAKE_BURST_S, INTAKE_BURST_AUDIO_S * cost_s)
    assert took_s >= 0.8 * (n * cost_s - burst) / share, took_s


def test_a_server_serving_a_client_at_another_rate_never_imports_scipy_signal(tiny_checkpoint):
    """scipy.signal costs ~1 s of CPU to import: paid by the first client whose audio needs resampling, it read as
    a dear client and was told `slow_down`; paid at start, it was a third of every server's start. The resampler's
    filter and the smoothing are numpy (`dimgestor.audio.kaiser_lowpass`), so neither pays it: a real server, run
    with `-X importtime`, serves a 44.1 kHz client's speech to its end and never imports scipy.signal."""
    from dimgestor.training.synthetic import synthetic_speech
    from helpers.serve import Serve
    from websockets.sync.client import connect

    s = Serve("-X", "importtime", "-m", "dimgestor_app.cli", "serve", "--checkpoint", str(tiny_checkpoint), "--ws",
              "127.0.0.1:0", "--steps", "2", "--status-every", "0", command=())
    try:
        url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
        audio = (synthetic_speech(2.0, seed=1, rate=44100) * 20000).astype("<i2")
        with connect(url) as c:
            c.send(json.dumps({"type": "hello", "audio": {"rate": 44100, "format": "pcm16"}}))
            for i in range(0, len(audio), 4410):
                c.send(audio[i:i + 4410].tobytes())
            c.send(json.dumps({"type": "audio_end"}))
            kinds = []
            while not kinds or kinds[-1] != "end":
                kinds.append(json.loads(c.recv(60))["type"])
        assert kinds.count("frame") >= 30 and "error" not in kinds, kinds
    finally:
        s.proc.terminate()
        s.finish(30)
    imported = [line.rsplit("|", 1)[-1].strip() for line in s.lines if line.startswith("import time:")]
    assert "dimgestor.audio" in imported and "websockets" in imported, s.output[-2000:]  # (importtime worked)
    assert not [m for m in imported if m.startswith("scipy.signal")], [m for m in imported if m.startswith("scipy")]