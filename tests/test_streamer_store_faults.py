"""When the state store is paused, dead or unreachable (issue 40, items 1-3), against a real redis-server and
real WebSocket clients paced in real time: a live avatar never freezes (its largest frame gap and p95 latency
stay within bounds from a quiet run of the same test), `/readyz` says "degraded" (200), a drain ends within
its bound and tells every client why, and the sessions go on (and are saved again) once the store is back."""
import asyncio
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from contextlib import ExitStack

import numpy as np
import pytest

from streamer.ws import HANDOVER_S

from helpers.clients import CLIENT, REPO, free_port, live_server
from helpers.cluster import NGINX, Cluster
from helpers.talkers import FPS, Talker, readyz, speech, talk_together

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]  # (each runs 20-35 s)
SERVE = ("--window-ms", "100")


@pytest.fixture
def redis(tmp_path):
    """A redis-server of its own -> (its URL, its process: SIGSTOP / SIGCONT / SIGKILL it)."""
    pytest.importorskip("redis", reason="the redis client is not installed (pip install 'dimgestor[cluster]')")
    exe = shutil.which("redis-server")
    if exe is None:
        pytest.skip("redis-server is not installed (Debian: apt-get install redis-server)")
    port = free_port()
    proc = subprocess.Popen([exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                             "--dir", str(tmp_path)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    import redis as client

    for _ in range(100):
        try:
            client.Redis(port=port).ping()
            break
        except client.ConnectionError:
            time.sleep(0.05)
    yield f"redis://127.0.0.1:{port}/0", proc
    proc.send_signal(signal.SIGCONT)
    proc.terminate()
    proc.wait(10)


def test_a_paused_store_never_freezes_a_live_avatar_readiness_says_degraded_and_saves_resume(tmp_path, checkpoint,
                                                                                            redis):
    url, store = redis
    n, quiet_s, paused_s, pause_at_s, pause_s = 3, 6.0, 16.0, 2.0, 8.0
    with live_server(tmp_path, "ws", checkpoint, http=True,
                     extra=("--state-store", url, "--save-state-every", "2", *SERVE)) as server:
        quiet = [Talker(server.ws_url, quiet_s, seed) for seed in range(n)]
        asyncio.run(talk_together(quiet))

        async def pause():
            await asyncio.sleep(pause_at_s)
            store.send_signal(signal.SIGSTOP)
            stopped, said = time.monotonic(), []
            while time.monotonic() < stopped + pause_s:
                said.append(await asyncio.to_thread(readyz, server.http_url))
                await asyncio.sleep(0.25)
            store.send_signal(signal.SIGCONT)
            resumed, back = time.monotonic(), None
            while back is None and time.monotonic() < resumed + 5:
                if (await asyncio.to_thread(readyz, server.http_url))[1].startswith("ready"):
                    back = time.monotonic() - resumed
                await asyncio.sleep(0.1)
            return stopped, resumed, said, back

        paused = [Talker(server.ws_url, paused_s, 10 + seed) for seed in range(n)]
        stopped, resumed, said, back = asyncio.run(talk_together(paused, pause))
    q = np.array([t.stats() for t in quiet])
    p = np.array([t.stats() for t in paused])
    print(f"quiet (largest gap, p95 latency) per talker: {q.round(3).tolist()}; paused: {p.round(3).tolist()}; "
          f"readiness back {back} s after SIGCONT")
    quiet_gap, quiet_p95 = q[:, 0].max(), q[:, 1].max()
    assert (p[:, 0] <= max(0.6, 2 * quiet_gap)).all(), (p, q)
    assert (p[:, 1] <= max(0.5, 1.5 * quiet_p95)).all(), (p, q)  # (the floor: a tiny model's p95 is ~20 ms)
    for t in paused:  # every frame, on time, and the session ended as usual
        assert sorted(t.arrivals) == list(range(int(paused_s * FPS))) and t.of("end")[-1][1]["frames"] == paused_s * FPS
    assert all(code == 200 for code, _ in said) and any(why.startswith("degraded: state store") for _, why in said), said
    assert back is not None, "readiness never said ready again after SIGCONT"
    for t in paused:  # saved before the pause, none while it lasted (a second's grace), saved again after
        times = [at for at, _ in t.of("session_saved")]
        assert any(at < stopped for at in times) and any(at > resumed for at in times), (stopped, resumed, times)
        assert not any(stopped + 1.0 < at < resumed for at in times), (stopped, resumed, times)


def _stop(server, talkers: list[Talker], after_frames: int = 20) -> float:
    """Once every talker has `after_frames` frames, SIGTERM to `server` -> seconds until it exited."""
    deadline = time.monotonic() + 30
    while min(len(t.arrivals) for t in talkers) < after_frames and time.monotonic() < deadline:
        time.sleep(0.02)
    t0 = time.monotonic()
    server.proc.send_signal(signal.SIGTERM)
    assert server.proc.wait(30) == 0, server.log_tail()
    return time.monotonic() - t0


def test_a_drain_with_the_store_paused_ends_within_its_bound_and_tells_every_client_why(tmp_path, checkpoint, redis):
    """SIGTERM to a worker with 2 talking clients, healthy then with Redis SIGSTOPped: the second drain costs at
    most the hand-over's bound more than the first, and each client gets a `goaway` without a token and why;
    the reference client then starts a fresh stream on another worker and gets every frame after its last."""
    import threading
    import wave

    url, store = redis
    extra = ("--state-store", url, *SERVE)
    wav = tmp_path / "speech.wav"
    with wave.open(str(wav), "wb") as w:
        w.setnchannels(1), w.setsampwidth(2), w.setframerate(16000)
        w.writeframes(speech(8.0, seed=7))
    with ExitStack() as stack:
        a = stack.enter_context(live_server(tmp_path, "ws", checkpoint, extra=extra))
        healthy = [Talker(a.ws_url, 10.0, seed) for seed in range(2)]
        runs = threading.Thread(target=asyncio.run, args=(talk_together(healthy),))
        runs.start()
        healthy_s = _stop(a, healthy)
        runs.join(30)

        b = stack.enter_context(live_server(tmp_path, "ws", checkpoint, extra=extra))
        c = stack.enter_context(live_server(tmp_path, "ws", checkpoint, extra=extra))
        talker, saved = Talker(b.ws_url, 10.0, 3), tmp_path / "saved"
        client = subprocess.Popen([sys.executable, str(CLIENT), "--url", b.ws_url, "--url", c.ws_url, "--wav", str(wav),
                                   "--binary", "--save", str(saved), "--quiet"], cwd=REPO, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        runs = threading.Thread(target=asyncio.run, args=(talk_together([talker]),))
        runs.start()
        deadline = time.monotonic() + 30
        while not (saved.is_dir() and sum(1 for _ in saved.iterdir()) > 20) and time.monotonic() < deadline:
            time.sleep(0.02)
        store.send_signal(signal.SIGSTOP)
        paused_s = _stop(b, [talker])
        runs.join(30)
        _, err = client.communicate(timeout=60)
    print(f"drain: {healthy_s:.2f} s with the store healthy, {paused_s:.2f} s with it paused")
    for t in healthy:
        assert t.of("goaway")[-1][1]["resume_token"], t.messages[-3:]
    assert paused_s <= healthy_s + HANDOVER_S, (healthy_s, paused_s)
    goaway = talker.of("goaway")[-1][1]
    assert goaway["resume_token"] is None and "state store is unreachable" in goaway["message"], goaway
    assert goaway["frames"] == len(talker.arrivals) > 0
    assert client.returncode == 0 and "goaway without a token" in err and "a fresh stream from sample" in err, err
    messages = [json.loads(p.read_text()) for p in sorted(saved.iterdir()) if p.suffix == ".json"]
    unsaved = next(m for m in messages if m["type"] == "goaway")
    assert unsaved["resume_token"] is None and messages[-1]["type"] == "end", messages[-3:]
    # the fresh stream covers the audio from the first frame the goaway did not bring to the end of the file
    assert unsaved["frames"] + messages[-1]["frames"] == 8 * FPS, (unsaved, messages[-1])


def test_a_killed_store_leaves_every_session_going_new_ones_accepted_and_saves_go_on_once_it_is_back(
        tmp_path, checkpoint, redis):
    url, store = redis
    argv = store.args
    with live_server(tmp_path, "ws", checkpoint, http=True,
                     extra=("--state-store", url, "--save-state-every", "2", *SERVE)) as server:
        talkers, late = [Talker(server.ws_url, 14.0, seed) for seed in range(2)], Talker(server.ws_url, 4.0, 5)
        restarted = []

        async def kill():
            await asyncio.sleep(2.0)
            store.kill()
            store.wait()
            killed, said = time.monotonic(), (0, "")
            while not said[1].startswith("degraded") and time.monotonic() < killed + 5:
                said = await asyncio.to_thread(readyz, server.http_url)
                await asyncio.sleep(0.1)
            await late.run()  # a new session while the store is dead
            await asyncio.sleep(max(0.0, killed + 6.0 - time.monotonic()))
            restarted.append(subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            back_at, back = time.monotonic(), None
            while back is None and time.monotonic() < back_at + 5:
                if (await asyncio.to_thread(readyz, server.http_url))[1].startswith("ready"):
                    back = time.monotonic()
                await asyncio.sleep(0.1)
            return said, back_at, back

        try:
            said, back_at, back = asyncio.run(talk_together(talkers, kill))
            _, text = readyz(server.http_url)
        finally:
            for p in restarted:
                p.terminate()
                p.wait(10)
    assert said[0] == 200 and said[1].startswith("degraded: state store unreachable"), said
    assert back is not None and text.startswith("ready"), text
    assert sorted(late.arrivals) == list(range(4 * 20)) and late.of("end")[-1][1]["frames"] == 4 * 20
    for t in talkers:  # every frame, its `end`, and saved again once the store was back
        assert sorted(t.arrivals) == list(range(14 * 20)) and t.of("end")[-1][1]["frames"] == 14 * 20
        assert any(at > back_at for at, _ in t.of("session_saved")), (back_at, t.of("session_saved"))


@pytest.mark.skipif(NGINX is None, reason="nginx is not installed (Debian: apt-get install nginx)")
def test_local_cluster_starts_a_killed_store_again_and_serves_throughout(checkpoint):
    """Redis SIGKILLed under 3 talkers in deploy/local-cluster: it is started again on its port, every session
    goes on to its `end`, a new one is served meanwhile, the workers are saving again after, and the cluster
    stops cleanly."""
    import re

    cluster = Cluster("--", "--checkpoint", str(checkpoint), "--steps", "2", "--status-every", "0",
                      "--save-state-every", "2", *SERVE)
    try:
        cluster.wait_for(r"^ready: .*handed over through the state store")
        pid = int(cluster.wait_for(r"^state store: redis://\S+ \(pid (\d+)\)").group(1))
        workers = cluster.workers()
        talkers, late = [Talker(cluster.url, 12.0, seed) for seed in range(3)], Talker(cluster.url, 3.0, 5)

        def saved() -> float:
            return sum(metric(f"http://127.0.0.1:{port}/", "dimgestor_sessions_saved_total")
                       for port, _ in workers.values())

        async def kill():
            await asyncio.sleep(2.0)
            os.kill(pid, signal.SIGKILL)
            new_session = asyncio.create_task(late.run())  # a new session while the store is dead
            restarted = await asyncio.to_thread(cluster.wait_for, r"^state store restarted: .* \(pid \d+\)", 20)
            then = await asyncio.to_thread(saved)
            await new_session
            return restarted, then

        restarted, saved_then = asyncio.run(talk_together(talkers, kill))
        ready = {n: readyz(f"http://127.0.0.1:{port}/") for n, (port, _) in workers.items()}
        deadline = time.monotonic() + 10
        while any(not why.startswith("ready") for _, why in ready.values()) and time.monotonic() < deadline:
            time.sleep(0.2)
            ready = {n: readyz(f"http://127.0.0.1:{port}/") for n, (port, _) in workers.items()}
        saved_after = saved()
    finally:
        code = cluster.stop()
    assert restarted and "exited" in cluster.output and "restarting the state store" in cluster.output
    assert all(status == 200 and why.startswith("ready") for status, why in ready.values()), ready
    assert sorted(late.arrivals) == list(range(3 * 20)) and late.of("end")[-1][1]["frames"] == 3 * 20
    for t in talkers:  # every frame of every session, its `end`, saved again once the store was back
        assert sorted(t.arrivals) == list(range(12 * 20)) and t.of("end")[-1][1]["frames"] == 12 * 20
    assert saved_after > saved_then, (saved_then, saved_after)  # saving again after the restart
    assert code == 0, cluster.output[-3000:]
    assert not re.search(r"every worker has exited|exited while serving", cluster.output)


def metric(base: str, name: str) -> float:
    from prometheus_client.parser import text_string_to_metric_families

    with urllib.request.urlopen(base + "metrics", timeout=5) as r:
        text = r.read().decode()
    return {s.name: s.value for f in text_string_to_metric_families(text) for s in f.samples}[name]


@pytest.mark.alone  # its bound compares two phases of one run: a test beside it that loads the cores in one phase and
# not the other is what it measures (a fresh clone's run, another test beside it: p95 41-49 ms against 9-11 ms
# quiet, twice; alone beside a busy loop, 17-22 ms)
def test_states_written_bad_into_the_store_are_refused_or_resume_finite_and_a_paced_bystander_never_notices(
        tmp_path, checkpoint, redis):
    """Issue 52, item 3, over a real store without a state secret (anyone who can write to it can seal a state):
    a client writes one mutation after another of a real saved state into redis-server (floats of any size or NaN
    in its arrays, every float 1e30, bits flipped, counters past the wire formats, a root flung away), each sealed
    anew, and resumes each on a new connection. Each is refused with `resume_failed` and a reason, or resumes; either
    way the client's own audio is streamed to its `end`, no frame holds a NaN or infinity, no error is `internal`,
    and the log holds no traceback. A talker paced in real time beside it keeps its p95 latency within 1.5x (+25 ms)
    of the quiet phase before (the bound of the rig abusers, test_streamer_abuse.py)."""
    import multiprocessing

    from streamer.handover import open_store
    from helpers.state_fuzz import run as fuzz

    url, _ = redis
    quiet_s, fuzz_s = 4.0, 8.0
    spawn = multiprocessing.get_context("spawn")

    async def saved_state(ws_url) -> bytes:
        """A session saved every second, its connection then lost -> its stored state's bytes."""
        from websockets.asyncio.client import connect

        async with connect(ws_url) as ws:
            assert json.loads(await ws.recv())["type"] == "hello"
            await ws.send(speech(3.0, 7))
            while (msg := json.loads(await asyncio.wait_for(ws.recv(), 30)))["type"] != "session_saved":
                pass
        store = open_store(url)
        for _ in range(50):  # (the lease of the session that was live goes with its connection)
            await asyncio.sleep(0.1)
            if (data := store.take(msg["resume_token"])) is not None:
                return data
        raise AssertionError("the saved state never became free to take")

    async def phases(ws_url, data, trial):
        talker = Talker(ws_url, 1.0 + quiet_s + fuzz_s + 3.0, seed=3 + trial, chunk_s=0.05, finish=False)
        task = asyncio.create_task(talker.run())
        await asyncio.sleep(1.0 + quiet_s)
        quiet = (talker.t0 + 1.0, time.monotonic())
        started, out = spawn.Event(), tmp_path / f"fuzz{trial}.json"
        fuzzer = spawn.Process(target=fuzz, args=(ws_url, url, data, fuzz_s, trial, started, str(out)), daemon=True)
        fuzzer.start()
        while not started.is_set() and fuzzer.is_alive():  # (its first attempt made: imported and fuzzing)
            await asyncio.sleep(0.05)
        t = time.monotonic()
        while fuzzer.is_alive():
            await asyncio.sleep(0.1)
        span = (t, time.monotonic() - 0.5)
        talker.stop.set()
        await task
        assert fuzzer.exitcode == 0, fuzzer.exitcode
        return talker, quiet, span, json.loads(out.read_text())

    with live_server(tmp_path, "ws", checkpoint, extra=("--state-store", url, "--save-state-every", "1", *SERVE)) as server:
        data = asyncio.run(saved_state(server.ws_url))
        trials = [asyncio.run(phases(server.ws_url, data, 0))]
        talker, quiet, span, _ = trials[0]
        if talker.percentile(*span) > 1.5 * talker.percentile(*quiet) + 0.025:
            # (a shared machine can stretch one phase by itself: measured once more; a fuzz that does hurt the
            # bystander fails both times, as the abusers of test_streamer_abuse.py)
            trials.append(asyncio.run(phases(server.ws_url, data, 1)))
        log = server.log.read_text(errors="replace")
    report = [(round(t.percentile(*q), 3), round(t.percentile(*s), 3), len(r)) for t, q, s, r in trials]
    results = [r for *_, rs in trials for r in rs]
    refused = [r for r in results if r["reply"] == "resume_failed"]
    print(f"bystander p95 quiet, with the fuzz, attempts per trial: {report}; {len(results)} states, "
          f"{len(refused)} refused; e.g. {[(r['what'], r['reason']) for r in refused[:3]]}")
    assert any(t.percentile(*s) <= 1.5 * t.percentile(*q) + 0.025 for t, q, s, _ in trials), report
    assert len(results) >= 10 and refused, results
    for r in results:
        assert r["reply"] in ("session_resumed", "resume_failed"), r
        assert r["reply"] == "session_resumed" or (r["reason"] and "\n" not in r["reason"]), r
        assert r["non_finite"] == 0 and not r["errors"] and r["end"] and r["frames"] > 0, r
    assert "Traceback" not in log and "internal" not in log, log[-3000:]
