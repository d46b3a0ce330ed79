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
import threading
import time
import urllib.error
import urllib.request
import wave
from importlib.machinery import SourceFileLoader
from pathlib import Path

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from streamer import protocol as P
from helpers.clients import SPEECH_WAV, free_port

REPO = Path(__file__).resolve().parents[1]
LOCAL_CLUSTER = REPO / "deploy" / "local-cluster"
NGINX = shutil.which("nginx") or next((p for p in ("/usr/sbin/nginx", "/usr/local/sbin/nginx") if os.access(p, os.X_OK)),
                                      None)
pytestmark = pytest.mark.timeout(120)
needs_nginx = pytest.mark.skipif(NGINX is None, reason="nginx not installed (Debian: apt-get install nginx; .ci/run "
                                                       "installs it): deploy/local-cluster runs a real nginx")
FPS, SECONDS = 20, 2.0
WORKER_ARGS = ["--max-sessions", "2", "--status-every", "0"]


class Cluster:
    """deploy/local-cluster as a user runs it, its output (stdout and stderr) read line by line in a thread."""

    def __init__(self, *args: str, workers: int = 2):
        self.port = free_port()
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen([sys.executable, str(LOCAL_CLUSTER), "--workers", str(workers), "--port",
                                      str(self.port), *args], cwd=REPO, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.reader = threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True)
        self.reader.start()
        self.url, self.http = f"ws://127.0.0.1:{self.port}/", f"http://127.0.0.1:{self.port}"

    @property
    def output(self) -> str:
        return "".join(self.lines)

    def wait_for(self, pattern: str, timeout: float = 90.0) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if m := re.search(pattern, self.output, re.M):
                return m
            if self.proc.poll() is not None and not self.reader.is_alive():
                break
            time.sleep(0.05)
        raise AssertionError(f"{pattern!r} never printed; local-cluster's output:\n{self.output}")

    def workers(self) -> dict[int, tuple[int, int]]:
        """worker number -> (its own port, its pid), from the lines local-cluster prints before `ready`."""
        return {int(n): (int(port), int(pid)) for n, port, pid in
                re.findall(r"^worker (\d+): http://127\.0\.0\.1:(\d+)/ \(pid (\d+)\)$", self.output, re.M)}

    def stop(self, timeout: float = 30.0) -> int:
        """SIGTERM, as a service manager or Ctrl-C would; -> its exit status (a bound, not a measured time)."""
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self.reader.join(5)


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
    cluster = Cluster("--", *WORKER_ARGS)
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


@needs_nginx
def test_a_dead_worker_is_passed_over_and_the_cluster_reports_it():
    """Passive health checks: after SIGKILL of a worker every new connection still reaches the other one."""
    cluster = Cluster("--", *WORKER_ARGS)
    try:
        cluster.wait_for(r"^ready:")
        port, pid = cluster.workers()[1]
        os.kill(pid, signal.SIGKILL)
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


@needs_nginx
def test_a_worker_that_cannot_start_stops_the_cluster_and_says_why(tmp_path):
    cluster = Cluster("--", "--checkpoint", str(tmp_path / "missing"), workers=2)
    assert cluster.proc.wait(90) == 1
    cluster.reader.join(5)
    assert re.search(r"worker \d exited while starting \(exit status 2\); its last lines:\n.*cannot load", cluster.output), \
        cluster.output
    assert "ready" not in cluster.output


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
    servers = "\n        ".join(f"server {a} {cluster.UPSTREAM_PARAMS};" for a in upstream)
    env = {**os.environ, "DIMGESTOR_NGINX_DIR": str(tmp_path), "DIMGESTOR_LISTEN": "127.0.0.1:9000",
           "DIMGESTOR_UPSTREAM": servers, "PATH": f"{Path(NGINX).parent}:{os.environ['PATH']}"}
    r = subprocess.run(["sh", str(REPO / "deploy" / "nginx-entrypoint.sh"), "-t", "-q"], env=env,
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "nginx.conf").read_text() == ours
    assert "$http_upgrade" in ours and "least_conn;" in ours and "DIMGESTOR" not in ours.split("worker_processes")[1]


def test_a_worker_takes_its_inference_threads_from_omp_num_threads(monkeypatch):
    """N workers on one machine: each runs the threads it is given, not every core but one (N x the cores)."""
    from streamer.server import inference_threads

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert inference_threads() == 3
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert inference_threads() == max(1, (os.cpu_count() or 1) - 1)


def _local_cluster_module():
    loader = SourceFileLoader("local_cluster", str(LOCAL_CLUSTER))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(loader.name, loader))
    loader.exec_module(module)
    return module


def test_the_compose_file_and_dockerfile_agree_with_what_is_tested_here():
    """Docker cannot run here: check that deploy/compose.yaml fills the tested template with the tested passive
    checks and mounts files that exist, and that the Dockerfile installs the torch pyproject.toml pins."""
    yaml = pytest.importorskip("yaml")
    deploy = REPO / "deploy"
    compose = yaml.safe_load((deploy / "compose.yaml").read_text())["services"]
    nginx, worker = compose["nginx"], compose["worker"]
    upstream = nginx["environment"]["DIMGESTOR_UPSTREAM"]
    assert upstream == f"server worker:8765 {_local_cluster_module().UPSTREAM_PARAMS};"
    assert {v.split(":")[0] for v in nginx["volumes"]} == {"./nginx.conf", "./nginx-entrypoint.sh"}
    assert all((deploy / v.split(":")[0]).is_file() for v in nginx["volumes"])
    assert (deploy / worker["build"]["context"] / worker["build"]["dockerfile"]).resolve() == deploy / "Dockerfile"
    assert "OMP_NUM_THREADS=1" in worker["environment"]
    pin = re.search(r'"(torch==[\d.]+)"', (REPO / "pyproject.toml").read_text()).group(1)
    assert f"pip install --no-cache-dir {pin} " in (deploy / "Dockerfile").read_text()
