"""Health and metrics of a worker (issue 22): `/healthz`, `/readyz` (the real-time load rule, draining) and
`/metrics` in the Prometheus text format, counting what real sessions over loopback did; and a real
Prometheus server (Debian `prometheus`) scraping a `streamer serve` worker."""

import asyncio
import json
import re
import shutil
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.parse
import urllib.request

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from prometheus_client.parser import text_string_to_metric_families
from websockets.asyncio.client import connect

from dimgestor.audio import SAMPLE_RATE
from dimgestor.training.synthetic import synthetic_speech
from streamer import protocol as P
from streamer.health import Readiness, RealtimeLoad, answer
from streamer.metrics import ServerMetrics
from streamer.scheduling import StreamBatcher
from streamer.sessions import Session
from helpers.serve import serve
from helpers.ws import make_server, recv_json, running

pytestmark = pytest.mark.timeout(180)


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def get(port: int, path: str, method: str = "GET") -> tuple[int, str, str]:
    """(status, content type, body) of an HTTP request to the server on loopback."""
    request = urllib.request.Request(f"http://127.0.0.1:{port}{path}", method=method)
    try:
        with urllib.request.urlopen(request, timeout=10) as r:
            return r.status, r.headers["Content-Type"], r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.headers["Content-Type"], e.read().decode()


def samples(text: str) -> dict[tuple[str, tuple], float]:
    """A /metrics body parsed by prometheus_client's own parser -> {(sample name, sorted labels): value}."""
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


async def stream_speech(url: str, seconds: float, realtime: bool = False, seed: int = 1) -> int:
    """Send `seconds` of speech (16 kHz PCM16, 0.1 s messages; paced in real time if asked), then `audio_end`;
    -> the frames received before `end` (which must say as many)."""
    pcm = (np.clip(synthetic_speech(seconds, seed=seed), -1, 1) * 32767 * 0.8).astype("<i2").tobytes()
    step = 2 * SAMPLE_RATE // 10
    frames = 0
    async with connect(url) as c:
        assert (await recv_json(c))["type"] == "hello"
        await c.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "binary"}))

        async def send():
            for i in range(0, len(pcm), step):
                await c.send(pcm[i:i + step])
                if realtime:
                    await asyncio.sleep(0.1)
            await c.send(json.dumps({"type": "audio_end"}))

        sender = asyncio.create_task(send())
        while True:
            m = await asyncio.wait_for(c.recv(), 60)
            if isinstance(m, bytes):
                P.parse_frame_binary(m)
                frames += 1
            elif (msg := json.loads(m))["type"] == "end":
                assert msg["frames"] == frames
                break
        await sender
    return frames


# ---- the readiness rule (a fake clock) -----------------------------------------------------------

def test_the_realtime_load_is_busy_time_on_realtime_calls_over_the_window():
    clock = FakeClock()
    load = RealtimeLoad(window_s=10.0, now=clock)
    assert load.value() == 0.0  # the time before the start counts as idle
    load.began(realtime=True)
    clock.t += 3.0
    assert load.value() == pytest.approx(0.3)  # a call under way counts up to now
    assert load.ended() == (pytest.approx(3.0), True)
    load.began(realtime=False)  # a backlog cycle: busy, but not real-time work
    clock.t += 4.0
    load.ended()
    assert load.value() == pytest.approx(0.3)
    clock.t += 5.0  # the first call now lies 2 s before the window's start: 1 s of it is left inside
    assert load.value() == pytest.approx(0.1)
    clock.t += 10.0
    assert load.value() == 0.0 and not load._done  # forgotten
    two = RealtimeLoad(window_s=10.0, threads=2, now=clock)  # --no-batch: busy time per worker thread
    two.began(True)
    clock.t += 10.0
    two.ended()
    assert two.value() == pytest.approx(0.5)


def test_readyz_fails_over_the_load_limit_and_while_draining():
    clock = FakeClock()
    ready = Readiness(RealtimeLoad(window_s=10.0, now=clock), max_load=0.9)
    assert ready.check()[0]
    for busy, idle in [(0.19, 0.01)] * 50:  # 95% of every 0.2 s on real-time batches: it cannot keep up
        ready.load.began(True)
        clock.t += busy
        ready.load.ended()
        clock.t += idle
    ok, why = ready.check()
    assert not ok and "real-time load 0.95" in why and "limit 0.9" in why
    for _ in range(50):  # 80%: keeps real time again (once the busy seconds have left the window)
        ready.load.began(True)
        clock.t += 0.16
        ready.load.ended()
        clock.t += 0.04
    assert ready.check() == (True, "ready: real-time load 0.80")
    ready.draining = True
    assert ready.check() == (False, "not ready: draining (shutting down)")


def test_readyz_fails_while_a_real_time_clients_audio_piles_up_whatever_the_load():
    """Issue 52, item 4: a worker once said "ready: real-time load 0.85" while its talkers' audio waited 39 s (the
    faces' work, on their own thread, is not in the load). A client whose audio comes in real time and waits more
    than 1 s to be inferred is behind, and the worker not ready; a fast sender (a file sent at once) is ahead of
    real time, and its backlog its own."""
    clock = FakeClock()
    ready = Readiness(RealtimeLoad(window_s=10.0, now=clock))
    clock.t = 100.0

    def lag(received_s, waiting_s, since_s):  # (its first audio's time, audio received, not yet inferred)
        return clock.t - since_s, received_s, waiting_s
    talker, fast = lag(20.0, 0.2, 20.0), lag(60.0, 30.0, 5.0)  # in real time; a file, 55 s ahead
    ready.lags = lambda: [talker, fast, None]
    assert ready.check() == (True, "ready: real-time load 0.00")
    ready.lags = lambda: [talker, fast, lag(20.0, 3.5, 20.0), lag(20.5, 1.2, 20.0)]  # (0.5 s early: within slack)
    assert ready.check() == (False, "not ready: 2 real-time clients 3.5 s behind (limit 1 s): inference cannot "
                                    "keep real time")
    ready.lags = lambda: [talker, fast, lag(20.0, 1.0, 20.0)]  # at the limit: not over it
    assert ready.check()[0]


# ---- the three paths on a live server ------------------------------------------------------------

def test_health_paths_answer_without_the_token_get_and_head_only(bundle):
    with running(make_server(bundle, token="s3cret", files=None)) as ws:
        assert get(ws.port, "/healthz")[::2] == (200, "ok\n")
        assert get(ws.port, "/readyz")[::2] == (200, "ready: real-time load 0.00\n")
        status, ctype, body = get(ws.port, "/metrics")
        assert status == 200 and ctype.startswith("text/plain; version=") and "charset=utf-8" in ctype
        assert samples(body)[("dimgestor_clients", ())] == 0
        assert get(ws.port, "/metrics?token=wrong")[0] == 200  # (a token is neither needed nor checked)
        assert get(ws.port, "/readyz", "HEAD")[::2] == (200, "")
        assert get(ws.port, "/readyz", "POST")[0] == 405
        assert get(ws.port, "/healthz/")[0] == 401  # not one of the three: a handshake (no viewer), token first
        ws.metrics.readiness.draining = True
        assert get(ws.port, "/readyz")[::2] == (503, "not ready: draining (shutting down)\n")
        assert get(ws.port, "/healthz")[0] == 200  # alive all the same

        async def handshake(url):
            async with connect(url) as c:
                return (await recv_json(c))["type"]

        with pytest.raises(Exception, match="401"):  # the WebSocket still needs its token
            asyncio.run(handshake(ws.url))
        with pytest.raises(Exception, match="503"):  # and a draining worker takes no new one (a balancer retries)
            asyncio.run(handshake(ws.url + "?token=s3cret"))
        ws.metrics.readiness.draining = False
        assert asyncio.run(handshake(ws.url + "?token=s3cret")) == "hello"
    with running(make_server(bundle, serve_metrics=False)) as ws:  # --no-metrics
        assert get(ws.port, "/metrics")[0] == 404 and get(ws.port, "/readyz")[0] == 200


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["GET", "HEAD", "POST", "get", "", "OPTIONS"]),
       st.tuples(st.sampled_from(["/healthz", "/readyz", "/metrics", "//metrics", "/metrics/", "metrics", ""]),
                 st.text(max_size=12)).map("".join))
def test_the_three_paths_never_raise_and_answer_only_their_own_targets(method, target):
    ready = Readiness()
    a = answer(method, target, ready, ServerMetrics(ready))
    path = target.split("?", 1)[0]
    if a is None:  # (left to the viewer or the handshake, as any other target)
        assert path not in ("/healthz", "/readyz", "/metrics") or "#" in target or any(c in target for c in " \t\r\n\0")
    else:
        assert path in ("/healthz", "/readyz", "/metrics")
        assert a.status == (200 if method in ("GET", "HEAD") else 405)


def test_servers_in_one_process_keep_their_own_counts():
    a, b = ServerMetrics(), ServerMetrics()
    a.refused("busy")
    assert samples(a.exposition()[0].decode())[("dimgestor_sessions_refused_total", (("reason", "busy"),))] == 1
    assert ("dimgestor_sessions_refused_total", (("reason", "busy"),)) not in samples(b.exposition()[0].decode())


# ---- counts that follow real sessions ------------------------------------------------------------

def test_the_counters_equal_what_a_real_session_did(bundle):
    """A client streams 3 s of speech through the batched scheduler: frames sent = frames it received,
    one session, a latency per window, a compute time per batched call."""
    batcher = StreamBatcher()
    made: list[Session] = []

    def make_session(**kw):
        made.append(Session.from_bundle(bundle, steps=2, seed=3, window_ms=100, scheduler=batcher, **kw))
        return made[-1]

    ws = make_server(bundle)
    ws.make_session = make_session
    batcher.observer = ws.metrics
    try:
        with running(ws):
            received = asyncio.run(stream_speech(ws.url, 3.0))
            m = samples(get(ws.port, "/metrics")[2])
    finally:
        batcher.shutdown()
    assert received == int(3.0 * 20)
    assert m[("dimgestor_frames_sent_total", (("sink", "ws"),))] == received
    assert m[("dimgestor_frames_dropped_total", (("sink", "ws"),))] == 0
    assert m[("dimgestor_sessions_started_total", ())] == 1
    assert m[("dimgestor_latency_seconds_count", ())] == made[0].stats.windows > 0
    calls = m[("dimgestor_window_compute_seconds_count", ())]
    assert calls == m[("dimgestor_batch_windows_count", ())] >= 3  # at most 1 s of audio per call
    assert m[("dimgestor_batch_windows_sum", ())] == calls  # one stream: one window per batched call
    busy = sum(m.get(("dimgestor_inference_busy_seconds_total", (("work", w),)), 0) for w in ("realtime", "backlog"))
    assert busy >= m[("dimgestor_window_compute_seconds_sum", ())] > 0  # (finishes are busy time, not windows)
    assert m[("dimgestor_streams", ())] == 0 and m[("dimgestor_client_queue_messages", ())] == 0


def test_sessions_refused_are_counted_once_per_attempt(bundle):
    """--max-sessions 1: a second client's audio is refused `busy`, counted once per stream it tries, not per
    message; after `audio_end` its next audio is a new attempt."""
    pcm = np.zeros(1600, "<i2").tobytes()

    async def run(ws):
        async with connect(ws.url) as first, connect(ws.url) as second:
            await recv_json(first)
            await recv_json(second)
            await first.send(pcm)  # its session stays open: no audio_end
            while ws.live_sessions < 1:
                await asyncio.sleep(0.01)
            for _ in range(2):
                for _ in range(3):
                    await second.send(pcm)
                    assert (await recv_json(second))["code"] == "busy"
                await second.send(json.dumps({"type": "audio_end"}))
                assert (await recv_json(second))["type"] == "end"
            m = samples(get(ws.port, "/metrics")[2])  # (the server runs on its own thread)
            assert m[("dimgestor_streams", ())] == 1 and m[("dimgestor_clients", ())] == 2
            return m

    with running(make_server(bundle, max_sessions=1)) as ws:
        m = asyncio.run(run(ws))
    assert m[("dimgestor_sessions_refused_total", (("reason", "busy"),))] == 2
    assert m[("dimgestor_sessions_started_total", ())] == 1


def test_readyz_fails_while_slowed_inference_cannot_keep_real_time(bundle, monkeypatch):
    """Inference slowed to 0.4 s per call and 1.2 s per second of audio while a client streams in real time (0.1 s
    windows): the thread is busy on real-time work back to back, so /readyz turns 503, and once the client's audio
    waits more than 1 s it says so too; once the stream ends it turns 200 again."""
    import dimgestor.streaming.batch

    push_many = dimgestor.streaming.batch.push_many

    def slow(streams, chunks, *args, **kw):
        time.sleep(0.4 + 1.2 * max(len(c) for c in chunks) / 16000)
        return push_many(streams, chunks, *args, **kw)

    monkeypatch.setattr(dimgestor.streaming.batch, "push_many", slow)
    batcher = StreamBatcher()
    metrics = ServerMetrics(Readiness(RealtimeLoad(window_s=1.0)))
    batcher.observer = metrics
    ws = make_server(bundle, metrics=metrics)
    ws.make_session = lambda **kw: Session.from_bundle(bundle, steps=2, seed=3, window_ms=100, scheduler=batcher, **kw)
    seen: list[str] = []

    async def watch(stop: asyncio.Event):
        loop = asyncio.get_running_loop()
        while not stop.is_set():
            seen.append((await loop.run_in_executor(None, get, ws.port, "/readyz"))[2])
            await asyncio.sleep(0.1)

    async def run():
        stop = asyncio.Event()
        watcher = asyncio.create_task(watch(stop))
        await stream_speech(ws.url, 4.0, realtime=True)
        stop.set()
        await watcher

    try:
        with running(ws):
            asyncio.run(run())
            deadline = time.monotonic() + 30  # (a bound, not a timing: the load leaves its 1 s window)
            while (after := get(ws.port, "/readyz"))[0] != 200 and time.monotonic() < deadline:
                time.sleep(0.1)
    finally:
        batcher.shutdown()
    assert any(s.startswith("not ready: real-time load") for s in seen), seen
    assert any(re.search(r"; 1 real-time client \d+\.\d s behind \(limit 1 s\)", s) for s in seen), seen
    assert after[0] == 200, after


def test_sigterm_marks_the_worker_draining(tiny_checkpoint):
    """`run` sets draining on SIGTERM, before it closes anything (so /readyz says 503 from that moment)."""
    from streamer.options import ServeOptions
    from streamer.server import build, run

    p = build(ServeOptions(source="ws", checkpoint=str(tiny_checkpoint), ws=("127.0.0.1", 0), steps=2,
                           status_every=0))

    close, at_close = p.ws.close, []

    async def closing(*args, **kw):  # what a balancer's probe gets once the server starts closing its sinks
        at_close.append(await asyncio.get_running_loop().run_in_executor(None, get, p.ws.port, "/readyz"))
        return await close(*args, **kw)

    p.ws.close = closing

    async def main():
        loop = asyncio.get_running_loop()
        task = asyncio.create_task(run(p))
        while p.ws.port == 0:
            await asyncio.sleep(0.01)
        assert (await loop.run_in_executor(None, get, p.ws.port, "/readyz"))[0] == 200
        signal.raise_signal(signal.SIGTERM)
        await task

    try:
        asyncio.run(main())
    finally:
        p.scheduler.shutdown(wait=False, cancel_futures=True)
    assert [a[::2] for a in at_close] == [(503, "not ready: draining (shutting down)\n")]


# ---- a real Prometheus server --------------------------------------------------------------------

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def query(port: int, promql: str) -> list[dict]:
    url = f"http://127.0.0.1:{port}/api/v1/query?" + urllib.parse.urlencode({"query": promql})
    with urllib.request.urlopen(url, timeout=10) as r:
        answer = json.loads(r.read())
    assert answer["status"] == "success", answer
    return answer["data"]["result"]


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("prometheus") is None,
                    reason="the `prometheus` server binary is not installed (Debian: apt install prometheus)")
def test_a_real_prometheus_server_scrapes_a_worker(tiny_checkpoint, tmp_path):
    """`streamer serve` on loopback; a client streams 3 s of speech; Prometheus, scraping every second,
    stores the frames the worker sent (= the frames the client received) and its histograms."""
    s = serve(tiny_checkpoint, "--source", "ws", "--max-seconds", "120")
    prom = None
    try:
        port = int(s.wait_for(r"WebSocket\s+ws://127\.0\.0\.1:(\d+)/").group(1))
        received = asyncio.run(stream_speech(f"ws://127.0.0.1:{port}/", 3.0))
        prom_port = free_port()
        (tmp_path / "prometheus.yml").write_text(
            "global:\n  scrape_interval: 1s\n  scrape_timeout: 1s\n"
            "scrape_configs:\n  - job_name: dimgestor\n    static_configs:\n"
            f"      - targets: ['127.0.0.1:{port}']\n")
        prom = subprocess.Popen(["prometheus", f"--config.file={tmp_path / 'prometheus.yml'}",
                                 f"--storage.tsdb.path={tmp_path / 'data'}",
                                 f"--web.listen-address=127.0.0.1:{prom_port}"],
                                stdout=subprocess.DEVNULL, stderr=(tmp_path / "prometheus.log").open("w"))
        deadline, sent = time.monotonic() + 90, []  # a bound, not a timing: its start and first scrapes
        while not sent and time.monotonic() < deadline and prom.poll() is None:
            try:
                sent = query(prom_port, 'dimgestor_frames_sent_total{job="dimgestor",sink="ws"}')
            except (urllib.error.URLError, ConnectionError):
                pass
            time.sleep(0.5)
        assert sent, (tmp_path / "prometheus.log").read_text()[-3000:]
        assert float(sent[0]["value"][1]) == received == 60
        assert float(query(prom_port, 'up{job="dimgestor"}')[0]["value"][1]) == 1
        latency = query(prom_port, "dimgestor_latency_seconds_count")
        assert float(latency[0]["value"][1]) > 0
        p99 = query(prom_port, "histogram_quantile(0.99, dimgestor_window_compute_seconds_bucket)")
        assert 0 < float(p99[0]["value"][1]) < 10  # (a quantile Prometheus computed from our buckets)
        assert float(query(prom_port, "dimgestor_ready")[0]["value"][1]) == 1
    finally:
        if prom is not None:
            prom.terminate()
            try:
                prom.wait(30)
            except subprocess.TimeoutExpired:
                prom.kill()
        s.proc.send_signal(signal.SIGTERM)
        s.finish(30)
