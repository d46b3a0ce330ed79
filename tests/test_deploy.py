"""deploy/: `streamer serve` workers behind nginx, started by deploy/local-cluster (real nginx, real workers with the
embedded default model, real WebSocket clients through the balancer), and the shipped nginx template."""

import asyncio
import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import tomllib
import urllib.error
import urllib.request
import wave
from importlib.machinery import SourceFileLoader
from pathlib import Path

import numpy as np
import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from dimgestor.bvh import forward_kinematics, read_bvh
from streamer import protocol as P
from helpers import warm
from helpers.clients import SPEECH_WAV
from helpers.cluster import LOCAL_CLUSTER, NGINX, Cluster
from helpers.stalls import LoopStalls

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.timeout(120)
needs_nginx = pytest.mark.skipif(NGINX is None, reason="nginx not installed (Debian: apt-get install nginx; .ci/run "
                                                       "installs it): deploy/local-cluster runs a real nginx")
FPS, SECONDS = 20, 2.0
WORKER_ARGS = ["--max-sessions", "2", "--status-every", "0"]


def get(url: str) -> tuple[int, str]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def metric(base: str, name: str) -> float:
    status, text = get(base + "/metrics")
    assert status == 200
    return {s.name: s.value for f in text_string_to_metric_families(text) for s in f.samples}[name]


def speech_pcm16(seconds: float, offset_s: float = 0.0) -> bytes:
    with wave.open(str(SPEECH_WAV)) as w:
        assert (w.getframerate(), w.getnchannels(), w.getsampwidth()) == (16000, 1, 2)
        w.setpos(int(offset_s * 16000))
        return w.readframes(int(seconds * 16000))


async def talk(c, pcm: bytes, pace_s: float = 0.0) -> tuple[list[dict], dict | None]:
    """Send `pcm` (in 0.1 s chunks, `pace_s` apart) then `audio_end`; read binary frames until `end` or the close."""
    frames, end = [], None

    async def send():
        for i in range(0, len(pcm), 3200):
            await c.send(pcm[i : i + 3200])
            await asyncio.sleep(pace_s)
        await c.send(json.dumps({"type": "audio_end"}))

    sender = asyncio.create_task(send())
    async for m in c:
        if isinstance(m, bytes):
            frames.append(P.parse_frame_binary(m))
        elif json.loads(m)["type"] == "end":
            end = json.loads(m)
            break
    sender.cancel()
    return frames, end


async def hello(c) -> dict:
    h = json.loads(await asyncio.wait_for(c.recv(), 30))
    assert h["type"] == "hello"
    await c.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "binary"}))
    return h


@needs_nginx
def test_the_cluster_spreads_streams_over_its_workers_serves_them_through_nginx_and_stops_on_sigterm():
    cluster = Cluster("--no-state-store", "--", *WORKER_ARGS)  # (sessions end with their worker: `end`, no goaway)
    try:
        cluster.wait_for(r"^ready: ws://127\.0\.0\.1:\d+/ \(2 workers\)")
        workers = cluster.workers()
        assert sorted(workers) == [1, 2], cluster.output
        direct = {n: f"http://127.0.0.1:{port}" for n, (port, _) in workers.items()}

        # health and metrics through the balancer (one worker's answer)
        assert get(cluster.http + "/healthz") == (200, "ok\n")
        status, why = get(cluster.http + "/readyz")
        assert status == 200 and why.startswith("ready"), why
        assert metric(cluster.http, "dimgestor_streams") == 0

        # the viewer's pages come from nginx's origin: a browser there may connect; another site may not
        async def origins():
            async with connect(cluster.url, origin=cluster.http) as c:
                await hello(c)
            with pytest.raises(InvalidStatus) as e:
                async with connect(cluster.url, origin="http://elsewhere.example"):
                    pass
            return e.value.response.status_code

        assert asyncio.run(origins()) == 403

        pcm = speech_pcm16(SECONDS)

        async def four_talkers():
            clients, placed = [], []

            async def join():  # one at a time, each placed before the next arrives: nginx counts them all
                c = await connect(cluster.url)
                await hello(c)
                clients.append(c)
                while sum(metric(d, "dimgestor_clients") for d in direct.values()) < len(clients):
                    await asyncio.sleep(0.05)
                counts = {n: metric(d, "dimgestor_clients") for n, d in direct.items()}
                placed.append(next(n for n in counts if counts[n] > sum(p == n for p in placed)))

            await join()
            await join()
            # one leaves and another comes: it goes to the worker left with fewer connections (round robin
            # would send it to the first client's)
            left = placed.pop()
            await clients.pop().close()
            while sum(metric(d, "dimgestor_clients") for d in direct.values()) > len(clients):
                await asyncio.sleep(0.05)
            await join()
            assert placed[1] == left, placed
            await join()
            await join()
            results = await asyncio.gather(*(talk(c, pcm) for c in clients))
            for c in clients:
                await c.close()
            return placed, results

        placed, results = asyncio.run(four_talkers())
        # least connections: the second client goes to the worker the first did not take, and two each in all
        assert placed[0] != placed[1] and sorted(placed) == [1, 1, 2, 2], placed
        for frames, end in results:
            assert end is not None and end["frames"] == len(frames) == int(SECONDS * FPS)
            assert [f["index"] for f in frames] == list(range(len(frames)))
        for n, d in direct.items():
            assert metric(d, "dimgestor_sessions_started_total") == 2, n
        # interchangeable workers: the same speech gives the same motion whichever worker ran it
        rot = [np.stack([f["rotations"] for f in frames]) for frames, _ in results]
        assert np.abs(rot[0] - rot[1]).max() < 1e-3
        assert np.ptp(rot[0], axis=0).max() > 1e-2  # (and it moves)

        # SIGTERM mid-sentence: the worker drains, its client gets `end` through nginx, then everything exits 0
        async def talker_cut_off():
            async with connect(cluster.url) as c:
                await hello(c)
                task = asyncio.create_task(talk(c, speech_pcm16(10.0), pace_s=0.1))
                while sum(metric(d, "dimgestor_streams") for d in direct.values()) < 1 and not task.done():
                    await asyncio.sleep(0.05)
                await asyncio.sleep(0.5)
                code = await asyncio.to_thread(cluster.stop)
                return code, await asyncio.wait_for(task, 30)

        code, (frames, end) = asyncio.run(talker_cut_off())
        assert code == 0, cluster.output
        assert end is not None and 0 < end["frames"] == len(frames) < 10 * FPS, (end, len(frames))
        assert [f["index"] for f in frames] == list(range(len(frames)))
        for port, pid in workers.values():
            with pytest.raises(ProcessLookupError):
                os.kill(pid, 0)
        with pytest.raises(urllib.error.URLError):
            get(cluster.http + "/healthz")
    finally:
        if cluster.proc.poll() is None:
            cluster.proc.kill()


def example_client():
    """clients/python/client.py as a module (its own file, as users run it)."""
    loader = SourceFileLoader("dimgestor_example_client", str(REPO / "clients" / "python" / "client.py"))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(loader.name, loader))
    loader.exec_module(module)
    return module


needs_redis = pytest.mark.skipif(shutil.which("redis-server") is None or importlib.util.find_spec("redis") is None,
                                 reason="redis-server or the redis client is missing (Debian: apt-get install "
                                        "redis-server; pip install 'dimgestor[cluster]'): sessions move through it")


@needs_nginx
@needs_redis
@pytest.mark.alone  # its gaps are the cluster's: beside another cluster test, 2 cores are not enough for both
def test_sessions_of_a_stopped_worker_resume_on_the_other_exactly_and_the_rest_see_no_gap(tmp_path):
    """Issue 22's rolling-restart test: 2 workers + nginx + Redis (local-cluster), 8 clients (the example Python
    client, as users run it) send real-time speech; SIGTERM the worker serving half of them mid-sentence: those
    resume on the other worker within 1 s and their BVH equals `dimgestor generate` on the same audio, seed, K
    and root mode; the other clients' largest frame gap stays under 500 ms."""
    seconds, clients, sampling = 6.0, 8, ("--steps", "4", "--seed", "3")
    wav = tmp_path / "speech.wav"
    with wave.open(str(wav), "wb") as w:
        w.setnchannels(1), w.setsampwidth(2), w.setframerate(16000)
        w.writeframes(speech_pcm16(seconds))
    offline = tmp_path / "offline.bvh"
    # the reference first: beside the cluster it would compete with the surviving worker at the move
    generate = warm.run([sys.executable, "-m", "dimgestor_app.cli", "generate", "--audio", str(wav), "--out",
                         str(offline), "--root", "tether", *sampling], cwd=REPO,
                        env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.PIPE,
                        stderr=subprocess.STDOUT, text=True, timeout=120)
    assert generate.returncode == 0, generate.stdout
    client = example_client()
    arrivals: dict[str, list[float]] = {}  # --bvh path -> arrival time of each frame
    goaway_at: dict[str, float] = {}  # resume token -> when its goaway arrived
    moved: set[str] = set()  # --bvh paths of the clients that got a goaway
    resumed_in: list[float] = []  # goaway -> session_resumed, seconds

    class TimedPrinter(client.Printer):
        def handle(self, message):
            msg = super().handle(message)
            if msg.get("type") == "frame":
                arrivals.setdefault(self.args.bvh, []).append(time.monotonic())
            elif msg.get("type") == "goaway":
                goaway_at[msg["resume_token"]] = time.monotonic()
                moved.add(self.args.bvh)
            return msg

    resume_session = client.resume_session

    async def timed_resume(ws, goaway, *args, **kw):
        sample = await resume_session(ws, goaway, *args, **kw)
        resumed_in.append(time.monotonic() - goaway_at[goaway["resume_token"]])
        return sample

    client.Printer, client.resume_session = TimedPrinter, timed_resume
    cluster = Cluster("--", "--window-ms", "100", "--status-every", "0", *sampling)
    try:
        cluster.wait_for(r"^ready: .*handed over through the state store")
        workers = cluster.workers()
        bvh = [tmp_path / f"client{i}.bvh" for i in range(clients)]

        async def everyone():
            watch, runs = asyncio.create_task(stalls.watch()), []
            for path in bvh:  # one after another: least connections puts every other one on each worker
                args = client.parse_args(["--url", cluster.url, "--wav", str(wav), "--binary", "--quiet",
                                          "--bvh", str(path)])
                runs.append(asyncio.create_task(client.run(args)))
                await asyncio.sleep(0.2)
            deadline = time.monotonic() + 60  # (6 s of speech each: frames that stop are a failure to report)
            while min(len(arrivals.get(str(p), ())) for p in bvh) < 40:  # mid-sentence: 2 s of frames each
                assert time.monotonic() < deadline, (
                    f"frames per client {[len(arrivals.get(str(p), ())) for p in bvh]}, the last "
                    f"{time.monotonic() - max(max(a) for a in arrivals.values()):.1f} s ago; clients done "
                    f"{[r.done() for r in runs]}; local-cluster's output:\n{cluster.output[-6000:]}")
                await asyncio.sleep(0.05)
            killed_at.append(time.monotonic())
            os.kill(workers[1][1], signal.SIGTERM)
            try:
                return await asyncio.wait_for(asyncio.gather(*runs), 60)
            finally:
                watch.cancel()

        stalls = LoopStalls()  # this process's own stalls (CI shares its cores): not the cluster's doing
        killed_at: list[float] = []
        codes = asyncio.run(everyone())
        assert codes == [0] * clients
        cluster.wait_for(r"worker 1 exited while serving \(exit status 0\)")
    finally:
        cluster.stop()
    assert len(resumed_in) == len(moved) == clients // 2, (resumed_in, moved, cluster.output[-3000:])
    assert max(resumed_in) < 1.0, resumed_in
    want = read_bvh(offline)
    gaps = {}
    for path in bvh:
        got = read_bvh(path)
        assert got.num_frames == want.num_frames == int(seconds * FPS), path
        assert np.abs(forward_kinematics(got) - forward_kinematics(want)).max() < 1e-3, path  # cm
        gaps[str(path)] = np.diff(arrivals[str(path)]).max()
    # the moved clients' gap holds their goaway and resume; the others must not notice: their largest gap under
    # 0.5 s (0.25-0.35 s here), or under twice what they saw in the 2 s before the restart on a machine that
    # stretches gaps by itself (beside a busy loop 0.19-0.30 s before it; a fresh clone on a slow day 0.60 s after)
    stayed = [gap for path, gap in gaps.items() if path not in moved]
    kill = killed_at[0]
    before = max(float(np.diff(a[(a > kill - 2.0) & (a < kill)]).max())
                 for path, a in ((p, np.array(arrivals[p])) for p in gaps) if path not in moved)
    print(f"resumed in {max(resumed_in):.3f} s at most; largest frame gap "
          f"{max(gaps[p] for p in moved):.3f} s (moved), {max(stayed):.3f} s (stayed; {before:.3f} s in the 2 s "
          f"before); this process stalled {stalls.worst:.3f} s at most")
    assert max(stayed) < max(0.5, 2 * before) + stalls.worst, (gaps, before, stalls.worst)


@needs_nginx
def test_a_dead_worker_is_passed_over_its_clients_stream_again_within_2_s_and_the_cluster_reports_it(tmp_path):
    """Passive health checks: after SIGKILL of a worker its clients (the example Python client) reconnect through
    nginx and go on with a fresh stream within 2 s; the other worker's clients see nothing; every new connection
    reaches the live worker."""
    seconds, clients = 5.0, 4
    wav = tmp_path / "speech.wav"
    with wave.open(str(wav), "wb") as w:
        w.setnchannels(1), w.setsampwidth(2), w.setframerate(16000)
        w.writeframes(speech_pcm16(seconds))
    client = example_client()
    arrivals: dict[str, list[tuple[float, int]]] = {}  # --bvh path -> (arrival time, index) of each frame

    class TimedPrinter(client.Printer):
        def handle(self, message):
            msg = super().handle(message)
            if msg.get("type") == "frame":
                arrivals.setdefault(self.args.bvh, []).append((time.monotonic(), msg["index"]))
            return msg

    client.Printer = TimedPrinter
    cluster = Cluster("--no-state-store", "--", "--window-ms", "100", "--status-every", "0")
    try:
        cluster.wait_for(r"^ready:")
        port, pid = cluster.workers()[1]
        bvh = [str(tmp_path / f"client{i}.bvh") for i in range(clients)]

        async def everyone():
            watch, runs = asyncio.create_task(stalls.watch()), []
            for path in bvh:
                args = client.parse_args(["--url", cluster.url, "--wav", str(wav), "--binary", "--quiet", "--bvh", path])
                runs.append(asyncio.create_task(client.run(args)))
                await asyncio.sleep(0.2)
            deadline = time.monotonic() + 60
            while min(len(arrivals.get(p, ())) for p in bvh) < 30:
                assert time.monotonic() < deadline, (
                    f"frames per client {[len(arrivals.get(p, ())) for p in bvh]}; clients done "
                    f"{[r.done() for r in runs]}; local-cluster's output:\n{cluster.output[-6000:]}")
                await asyncio.sleep(0.05)
            os.kill(pid, signal.SIGKILL)
            killed = time.monotonic()
            try:
                return killed, await asyncio.wait_for(asyncio.gather(*runs), 60)
            finally:
                watch.cancel()

        stalls = LoopStalls()  # this process's own stalls (CI shares its cores): not the cluster's doing
        killed, codes = asyncio.run(everyone())
        assert codes == [0] * clients
        cluster.wait_for(r"worker 1 exited while serving")

        async def connections():
            servers = []
            for _ in range(4):
                async with connect(cluster.url) as c:
                    servers.append((await hello(c))["server"])
            return servers

        assert len(asyncio.run(connections())) == 4
        assert get(cluster.http + "/healthz") == (200, "ok\n")
        assert cluster.stop() == 1  # a worker died on its own: not a clean run
    finally:
        if cluster.proc.poll() is None:
            cluster.proc.kill()
    restarted = {p for p in bvh if any(i == 0 for _, i in arrivals[p][1:])}  # a fresh stream: index 0 again
    assert len(restarted) == clients // 2, {p: [i for _, i in a][:5] for p, a in arrivals.items()}
    for path in bvh:
        times = np.array([t for t, _ in arrivals[path]])
        if path in restarted:  # streaming again within 2 s of the kill
            assert times[times > killed].min() - killed < 2.0, path
        else:
            assert np.diff(times).max() < 0.5 + stalls.worst, (path, stalls.worst)
        assert read_bvh(path).num_frames == seconds * FPS  # the whole timeline, the fresh stream's after the rest


@needs_nginx
def test_a_worker_that_cannot_start_stops_the_cluster_and_says_why(tmp_path):
    cluster = Cluster("--", "--checkpoint", str(tmp_path / "missing"), workers=2)
    assert cluster.proc.wait(90) == 1
    cluster.reader.join(5)
    assert re.search(r"worker \d exited while starting \(exit status 2\); its last lines:\n.*cannot load", cluster.output), \
        cluster.output
    assert not re.search(r"^ready:", cluster.output, re.M)


def test_local_cluster_refuses_worker_flags_it_owns():
    r = subprocess.run([sys.executable, str(LOCAL_CLUSTER), "--port", "1", "--", "--ws", "0.0.0.0:9"],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 2 and "--ws" in r.stderr


@needs_nginx
@pytest.mark.skipif(shutil.which("envsubst") is None, reason="envsubst not installed (Debian: gettext-base)")
def test_the_compose_entrypoint_fills_the_template_as_local_cluster_does(tmp_path):
    """deploy/nginx-entrypoint.sh (envsubst, the compose nginx) and local-cluster fill deploy/nginx.conf alike,
    and nginx accepts the result."""
    cluster = _local_cluster_module()
    upstream = [f"127.0.0.1:{p}" for p in (9001, 9002)]
    ours = cluster.nginx_config((REPO / "deploy" / "nginx.conf").read_text(), str(tmp_path), "127.0.0.1:9000", upstream)
    servers = "\n        ".join(f"server {a} max_fails=1 fail_timeout={cluster.FAIL_TIMEOUT_S}s;" for a in upstream)
    env = {**os.environ, "DIMGESTOR_NGINX_DIR": str(tmp_path), "DIMGESTOR_LISTEN": "127.0.0.1:9000",
           "DIMGESTOR_UPSTREAM": servers, "PATH": f"{Path(NGINX).parent}:{os.environ['PATH']}"}
    r = subprocess.run(["sh", str(REPO / "deploy" / "nginx-entrypoint.sh"), "-t", "-q"], env=env,
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "nginx.conf").read_text() == ours
    assert "$http_upgrade" in ours and "least_conn;" in ours and "DIMGESTOR" not in ours.split("worker_processes")[1]


def test_a_worker_takes_its_inference_threads_from_omp_num_threads(monkeypatch):
    """N workers on one machine: each runs the threads it is given, not every core but one (N x the cores)."""
    from streamer.server import inference_threads, onnx_lanes

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert inference_threads() == onnx_lanes() == 3
    monkeypatch.delenv("OMP_NUM_THREADS")
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    # torch's batcher leaves a core to the event loop; ONNX Runtime's lanes (its calls free of Python's lock) take
    # every core
    assert (inference_threads(), onnx_lanes()) == (1, 2)
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert (inference_threads(), onnx_lanes()) == (1, 1)


def _local_cluster_module():
    loader = SourceFileLoader("local_cluster", str(LOCAL_CLUSTER))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(loader.name, loader))
    loader.exec_module(module)
    return module


# deploy/compose.yaml and deploy/Dockerfile: no Docker daemon or compose runs where the tests run, so they are checked
# here as data (PyYAML, the Dockerfile's instructions), against the code that will run them: the serve argument
# parser and options, the state store's URL reading, the health endpoints, the nginx template's placeholders.
DEPLOY = REPO / "deploy"


def compose_services() -> dict:
    return yaml.safe_load((DEPLOY / "compose.yaml").read_text())["services"]


# what an operator sets before `docker compose up` (docs/deploy.md, "The state store"): compose refuses without them
COMPOSE_SECRETS = {"DIMGESTOR_REDIS_PASSWORD": "redis-pw-0123", "DIMGESTOR_STATE_SECRET": "state-secret-4567"}


def interpolated(text: str, env: dict | None = None) -> str:
    """A compose value as compose fills it from `env` (default: only the secrets set): `${NAME:-default}` -> the
    value or default; `${NAME:?message}` -> the value, or compose's refusal (ValueError) when it is unset."""
    env = COMPOSE_SECRETS if env is None else env

    def fill(m):
        name, op, arg = m.group(1), m.group(2), m.group(3) or ""
        if op == ":?":
            if not env.get(name):
                raise ValueError(f"{name}: {arg}")
            return env[name]
        return env.get(name) or (arg if op else "")
    return re.sub(r"\$\{(\w+)(?:(:\?|:?-)([^}]*))?\}", fill, text)


def compose_values(value) -> list[str]:
    """Every string in a compose value (lists and mappings walked)."""
    if isinstance(value, dict):
        return [s for v in value.values() for s in compose_values(v)]
    if isinstance(value, list):
        return [s for v in value for s in compose_values(v)]
    return [value] if isinstance(value, str) else []


def dockerfile() -> list[tuple[str, str]]:
    """deploy/Dockerfile's final stage as (INSTRUCTION, arguments), continuation lines joined, comments dropped."""
    lines, joined = [], ""
    for line in (DEPLOY / "Dockerfile").read_text().splitlines():
        if line.lstrip().startswith("#") or not line.strip():
            continue
        joined += line.rstrip("\\").strip() + " "
        if not line.endswith("\\"):
            lines.append(joined.strip())
            joined = ""
    stages = [i for i, line in enumerate(lines) if line.startswith("FROM ")]
    return [tuple(line.split(" ", 1)) for line in lines[stages[-1]:]]


def instruction(name: str) -> list[str]:
    return [args for op, args in dockerfile() if op == name]


def serve_parser():
    """The argument parser `dimgestor serve` runs."""
    from dimgestor_app.cli import build_parser

    return build_parser()


def served(argv: list[str]):
    """argv (`dimgestor serve ...`) as the worker would take it: parsed, then validated -> its ServeOptions."""
    from streamer.options import ServeOptions

    assert argv[:2] == ["dimgestor", "serve"], argv
    args = serve_parser().parse_args(argv[1:])
    return ServeOptions.parse(**{k: v for k, v in vars(args).items() if k in ServeOptions.model_fields})


def worker_commands() -> dict[str, list[str]]:
    """Every worker command line: the compose worker's and the image's default (CMD)."""
    cmd = json.loads(instruction("CMD")[-1])
    return {"compose worker": [interpolated(a) for a in compose_services()["worker"]["command"]], "image CMD": cmd}


def test_every_worker_command_is_dimgestor_serve_as_its_parser_and_options_take_it():
    assert pytest.raises(SystemExit, serve_parser().parse_args, ["serve", "--no-such-flag"])  # (it does check)
    for where, argv in worker_commands().items():
        options = served(argv)
        assert options.source == "ws" and options.ws == ("0.0.0.0", 8765), (where, options)
    compose = served(worker_commands()["compose worker"])
    assert compose.allow_origin == ("http://localhost:8765",)  # DIMGESTOR_PUBLIC_ORIGIN's default


def test_the_compose_workers_hand_sessions_over_through_its_redis_service():
    """Sessions outlive their worker under compose: every worker is given the `redis` service as its state store,
    starts after it answers, and the image has the client (the `cluster` extra)."""
    from streamer.handover import open_store

    services = compose_services()
    worker = services["worker"]
    store = open_store(served(worker_commands()["compose worker"]).state_store)
    address = store.client.connection_pool.connection_kwargs
    assert address["host"] in services and services[address["host"]]["image"].startswith("redis:"), address
    redis = services[address["host"]]
    assert str(address["port"]) in redis["expose"]
    assert "--port" not in redis["command"] and redis["command"][0] == "redis-server"
    assert ["--save", ""] == redis["command"][1:3]  # no persistence: states live for tens of ms
    assert worker["depends_on"][address["host"]] == {"condition": "service_healthy"}
    assert redis["healthcheck"]["test"] == ["CMD", "redis-cli", "ping"]
    # the image: CPU torch first (the pin pyproject.toml holds), then the package with the `cluster` extra
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    pin = next(d for d in pyproject["dependencies"] if d.startswith("torch=="))
    assert any(d.startswith("redis") for d in pyproject["optional-dependencies"]["cluster"])
    runs = instruction("RUN")
    torch_at = next(i for i, r in enumerate(runs) if f"pip install --no-cache-dir {pin} " in r)
    assert "--index-url https://download.pytorch.org/whl/cpu" in runs[torch_at]
    package_at = next(i for i, r in enumerate(runs) if "pip install --no-cache-dir -e '.[cluster]'" in r)
    assert torch_at < package_at


def test_health_checks_poll_what_a_worker_answers_and_the_docs_they_point_to_exist():
    from urllib.parse import urlsplit

    from streamer.health import Readiness, answer

    services = compose_services()
    check = instruction("HEALTHCHECK")
    assert len(check) == 1
    argv = json.loads(check[0][check[0].index("CMD ") + 4:])
    assert argv[:2] == ["python", "-c"]
    compile(argv[2], "HEALTHCHECK", "exec")
    url = urlsplit(re.search(r"http://[^'\"]+", argv[2]).group(0))
    for where, cmd in worker_commands().items():  # the port each worker listens on
        assert (url.hostname, url.port) == ("127.0.0.1", served(cmd).ws[1]), where
    # liveness: 200 whatever the load (a busy or draining worker is not restarted), from the worker's own handler
    busy = Readiness()
    busy.draining = True
    live = answer("GET", url.path, busy)
    assert live is not None and live.status == 200, url.path
    assert answer("GET", "/readyz", busy).status == 503  # (readiness is the other endpoint)
    # every service another waits on to be healthy has a health check: its own, or the image's for the worker
    for name, service in services.items():
        for dependency, how in service.get("depends_on", {}).items():
            if how["condition"] == "service_healthy":
                has_check = "healthcheck" in services[dependency] or ("build" in services[dependency] and check)
                assert has_check, (name, dependency)
    # the sections the deploy files' comments point to are in docs/deploy.md
    headings = set(re.findall(r"^#+ (.+)$", (REPO / "docs" / "deploy.md").read_text(), re.M))
    for path in (DEPLOY / "Dockerfile", DEPLOY / "compose.yaml"):
        for section in re.findall(r'docs/deploy\.md, "([^"]+)"', path.read_text()):
            assert section in headings, (path.name, section)
    assert "Health checks" in headings


def test_compose_gives_redis_a_password_and_the_workers_a_state_secret_and_refuses_to_start_without_them(monkeypatch):
    """The README's advice for operators, in the compose file: Redis requires the password the workers' store URL
    carries (its health check authenticates with it too), every worker seals its saves with the same secret from
    the environment (not a flag: other users can read a command line), and an unset one stops compose."""
    from streamer.handover import open_store
    from streamer.server import STATE_SECRET_ENV, read_state_secret

    services = compose_services()
    redis, worker = services["redis"], services["worker"]
    password = COMPOSE_SECRETS["DIMGESTOR_REDIS_PASSWORD"]
    command = [interpolated(a) for a in redis["command"]]
    assert command[command.index("--requirepass") + 1] == password
    assert interpolated(redis["environment"]["REDISCLI_AUTH"]) == password  # redis-cli ping authenticates
    options = served(worker_commands()["compose worker"])
    assert open_store(options.state_store).client.connection_pool.connection_kwargs["password"] == password
    environment = dict(interpolated(e).split("=", 1) for e in worker["environment"] if "=" in e)
    assert environment[STATE_SECRET_ENV] == COMPOSE_SECRETS["DIMGESTOR_STATE_SECRET"]
    assert not any(STATE_SECRET_ENV in a or "--state-secret" in a for a in worker["command"])
    monkeypatch.setenv(STATE_SECRET_ENV, environment[STATE_SECRET_ENV])
    assert read_state_secret(options) == COMPOSE_SECRETS["DIMGESTOR_STATE_SECRET"].encode()
    for name in COMPOSE_SECRETS:  # either one unset: compose says which and where it is documented
        env = {k: v for k, v in COMPOSE_SECRETS.items() if k != name}
        with pytest.raises(ValueError, match=rf"{name}: set {name} \(docs/deploy\.md\)"):
            [interpolated(v, env) for v in compose_values(services)]
    assert (REPO / "deploy" / ".env").relative_to(REPO).as_posix() in {
        line.strip("/") for line in (REPO / ".gitignore").read_text().splitlines()}  # the secrets file stays local
    text = (REPO / "docs" / "deploy.md").read_text()
    assert all(name in text for name in COMPOSE_SECRETS)


def test_nginx_in_compose_fills_the_tested_template_with_the_worker_service():
    """The compose nginx: the local cluster's template and entrypoint, its upstream the `worker` service on the
    port the workers listen on, with the tested passive checks."""
    services = compose_services()
    nginx, worker = services["nginx"], services["worker"]
    upstream = nginx["environment"]["DIMGESTOR_UPSTREAM"]
    host, port = re.fullmatch(r"server (\S+):(\d+) max_fails=1 fail_timeout=(\d+)s;", upstream).group(1, 2)
    assert host == "worker" and host in services
    assert int(port) == served(worker_commands()["compose worker"]).ws[1] and port in worker["expose"]
    assert upstream.endswith(f"fail_timeout={_local_cluster_module().FAIL_TIMEOUT_S}s;")
    assert nginx["ports"] == [f"{nginx['environment']['DIMGESTOR_LISTEN']}:{nginx['environment']['DIMGESTOR_LISTEN']}"]
    assert {v.split(":")[0] for v in nginx["volumes"]} == {"./nginx.conf", "./nginx-entrypoint.sh"}
    assert all((DEPLOY / v.split(":")[0]).is_file() for v in nginx["volumes"])
    assert nginx["entrypoint"] == ["/bin/sh", "/deploy/nginx-entrypoint.sh"]
    assert set(re.findall(r"\$\{(DIMGESTOR_\w+)\}", (DEPLOY / "nginx.conf").read_text())) == {
        k for k in nginx["environment"] if k.startswith("DIMGESTOR_")}
    assert (DEPLOY / worker["build"]["context"] / worker["build"]["dockerfile"]).resolve() == DEPLOY / "Dockerfile"
    assert "OMP_NUM_THREADS=1" in worker["environment"]


def test_the_local_cluster_store_is_capped_and_evicts_the_saves_nearest_expiry_first():
    """Issue 40 item 6: local-cluster's redis-server runs with maxmemory (--store-maxmemory) and `volatile-ttl`,
    so abandoned saves cannot grow it until it dies (tests/test_streamer_handover.py fills one such store). Its
    workers seal their saves with a secret made for the cluster (--state-secret-file), never shown."""
    import redis

    cluster = Cluster("--workers", "1", "--store-maxmemory", "32mb", "--", *WORKER_ARGS)
    try:
        port = int(cluster.wait_for(r"state store: redis://127\.0\.0\.1:(\d+)/0").group(1))
        r = redis.Redis(port=port)
        assert r.config_get("maxmemory") == {"maxmemory": str(32 * 2**20)}
        assert r.config_get("maxmemory-policy") == {"maxmemory-policy": "volatile-ttl"}
        cluster.wait_for(r"saved sessions sealed with the workers' shared secret")
        cluster.wait_for(r"^ready: ws://")
        worker = Path(f"/proc/{cluster.workers()[1][1]}/cmdline").read_text().split("\0")  # (Linux)
        secret = Path(worker[worker.index("--state-secret-file") + 1])
        assert secret.stat().st_mode & 0o777 == 0o600 and len(secret.read_text()) == 64
        assert secret.read_text() not in cluster.output
    finally:
        assert cluster.stop() == 0, cluster.output
