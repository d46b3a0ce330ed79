"""Issue 22, item 6: a load simulation against `deploy/local-cluster` (workers + nginx + Redis on loopback).

Clients (the example Python client, clients/python/client.py, run in this process) join at random, keep about
`--clients` sessions going, each sending real speech paced like a talker for 3-10 s; a fifth of them leave
early (the connection drops mid-sentence). At `--restart-at` seconds the cluster gets SIGHUP: a rolling
restart, each worker in turn drains, hands its sessions over through Redis and is replaced. Reported:

  sessions   started, finished, left early, failed; for each finished one whether every frame came once and
             in order (`complete`), how often it was moved (goaway + resume) and its largest frame gap
  resume     goaway -> session_resumed, seconds (the moved sessions)
  gaps       the largest gap between two frames of a session: p50 / p95 / max, moved and not moved
  cost       CPU seconds of the workers, nginx and redis-server over the run (sampled from /proc each 0.5 s),
             redis-server's peak memory, the size of one saved session state

    python benchmarks/cluster_load.py                                # 3 workers, 12 clients, 60 s, restart at 20 s
    python benchmarks/cluster_load.py --workers 2 --clients 4 --seconds 15 --restart-at 5 --out /tmp/x.json
"""

from __future__ import annotations

import argparse
import asyncio
import contextvars
import importlib.util
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import wave
from importlib.machinery import SourceFileLoader
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers.cluster import Cluster  # noqa: E402  (deploy/local-cluster, as the tests run it)

REPO = Path(__file__).resolve().parents[1]
FPS = 20
CLIPS = [REPO / "dimgestor" / "assets" / name for name in ("demo_en.wav", "demo_zh.wav")]


def example_client():
    loader = SourceFileLoader("dimgestor_example_client", str(REPO / "clients" / "python" / "client.py"))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(loader.name, loader))
    loader.exec_module(module)
    return module


def cpu_seconds(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime
    except (OSError, IndexError, ValueError):
        return None


def nginx_pids(cluster_pid: int) -> list[int]:
    """nginx's master (local-cluster's child) and its worker (the master's child)."""
    def children(pid: int) -> list[int]:
        try:
            return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
        except OSError:
            return []

    masters = [c for c in children(cluster_pid) if _name(c) == "nginx"]
    return masters + [w for m in masters for w in children(m)]


def _name(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return ""


def clip_files(folder: Path, rng: random.Random, n: int) -> list[tuple[Path, float]]:
    """n WAVs of 3-10 s cut from the bundled speech clips (16 kHz PCM16)."""
    out = []
    for i in range(n):
        src = CLIPS[i % len(CLIPS)]
        with wave.open(str(src)) as w:
            total = w.getnframes() / w.getframerate()
            seconds = round(rng.uniform(3.0, min(10.0, total)), 2)
            w.setpos(int(rng.uniform(0, total - seconds) * w.getframerate()))
            pcm = w.readframes(int(seconds * w.getframerate()))
        path = folder / f"clip{i:02d}.wav"
        with wave.open(str(path), "wb") as o:
            o.setnchannels(1), o.setsampwidth(2), o.setframerate(16000)
            o.writeframes(pcm)
        out.append((path, len(pcm) // 2 / 16000))
    return out


def state_size_bytes(worker_args: list[str]) -> int:
    """The saved state of one session (dimgestor.streaming.savestate) after 2 s of speech, with the workers' model."""
    from dimgestor.audio import load_wav
    from dimgestor.streaming import savestate
    from dimgestor.streaming.checkpoint import load_checkpoint, resolve_checkpoint

    args = dict(zip(worker_args[::2], worker_args[1::2]))
    bundle = load_checkpoint(resolve_checkpoint(args.get("--checkpoint")))
    stream = bundle.stream(steps=int(args["--steps"]) if "--steps" in args else None)
    stream.push(load_wav(CLIPS[0])[: 2 * 16000])
    return len(savestate.dumps(stream, stream.state, {}))


async def simulate(args, cluster: Cluster, clips, rng: random.Random) -> tuple[list[dict], list[tuple[float, int]]]:
    client = example_client()
    t0 = time.monotonic()
    sessions: dict[str, dict] = {}  # session id -> what it saw (times in seconds since t0)
    tokens: dict[str, str] = {}  # resume token -> session id

    class TimedPrinter(client.Printer):
        def handle(self, message):
            msg = super().handle(message)
            s, kind = sessions[self.args.session_id], msg.get("type")
            if kind == "frame":
                s["times"].append(time.monotonic() - t0)
                s["indices"].append(msg["index"])
            elif kind == "goaway":
                s["goaways"].append(time.monotonic() - t0)
                s["notes"].append(f"goaway: samples {msg['samples']}, frames {msg['frames']}")
                tokens[msg["resume_token"]] = self.args.session_id
            return msg

    resume_session = client.resume_session

    async def timed_resume(ws, goaway, *a, **kw):
        sample = await resume_session(ws, goaway, *a, **kw)
        sessions[tokens[goaway["resume_token"]]]["resumed"].append(time.monotonic() - t0)
        return sample

    client.Printer, client.resume_session = TimedPrinter, timed_resume
    current = contextvars.ContextVar("session_id")  # each session's task runs in its own copy of the context

    def notes(*values, file=None, **_):  # the client's own lines on stderr, kept with the session that said them
        if file is sys.stderr:
            sessions[current.get()]["notes"].append(" ".join(map(str, values)))

    client.print = notes
    timeline: list[tuple[float, int]] = []
    running: set[asyncio.Task] = set()

    async def one(i: int):
        path, seconds = clips[rng.randrange(len(clips))]
        leave_after = rng.uniform(1.0, seconds) if rng.random() < args.leave_fraction else None
        s = sessions[f"s{i}"] = {"id": f"s{i}", "clip_s": seconds, "start": time.monotonic() - t0, "times": [],
                                 "indices": [], "goaways": [], "resumed": [], "notes": [],
                                 "left_early": leave_after is not None}
        current.set(s["id"])
        cargs = client.parse_args(["--url", cluster.url, "--wav", str(path), "--binary", "--quiet"])
        cargs.session_id = s["id"]
        try:
            s["code"] = await asyncio.wait_for(client.run(cargs), leave_after or seconds + 60)
        except asyncio.TimeoutError:  # a client that leaves mid-sentence: its connection drops
            s["code"] = "left" if leave_after is not None else "timed out"
        except Exception as e:  # noqa: BLE001 - the simulation reports every failure
            s["code"] = f"{type(e).__name__}: {e}"
        s["end"] = time.monotonic() - t0

    i, restarted = 0, False
    while time.monotonic() - t0 < args.seconds:
        if not restarted and args.restart_at is not None and time.monotonic() - t0 >= args.restart_at:
            cluster.proc.send_signal(signal.SIGHUP)
            restarted = True
        if len(running) < args.clients:
            task = asyncio.create_task(one(i))
            running.add(task)
            task.add_done_callback(running.discard)
            i += 1
            await asyncio.sleep(rng.expovariate(1 / args.join_every))  # arrivals at random
        else:
            await asyncio.sleep(0.05)
        timeline.append((round(time.monotonic() - t0, 2), len(running)))
    await asyncio.gather(*running)
    return list(sessions.values()), timeline


def runs(indices: list[int]) -> list[list[int]]:
    """Frame indices as [first, last] runs of consecutive ones: [[0, 177]] for a whole 178-frame session."""
    out: list[list[int]] = []
    for i in indices:
        if out and i == out[-1][1] + 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return out


def summarize(sessions: list[dict]) -> dict:
    finished = [s for s in sessions if not s["left_early"] and s.get("code") == 0]
    failed = [s for s in sessions if s.get("code") not in (0, "left")]
    moved = [s for s in finished if s["goaways"]]
    stayed = [s for s in finished if not s["goaways"]]

    def complete(s) -> bool:
        n = int(s["clip_s"] * 16000) // (16000 // FPS)  # frames of the clip's whole samples
        return s["indices"] == list(range(n))

    def gap(s) -> float:
        return float(np.diff(s["times"]).max()) if len(s["times"]) > 1 else float("nan")

    def dist(values):
        v = np.array([x for x in values if np.isfinite(x)])
        return {"n": int(v.size), "p50": round(float(np.percentile(v, 50)), 3) if v.size else None,
                "p95": round(float(np.percentile(v, 95)), 3) if v.size else None,
                "max": round(float(v.max()), 3) if v.size else None}

    resume_s = [r - g for s in moved for g, r in zip(s["goaways"], s["resumed"])]
    return {
        "sessions_started": len(sessions),
        "sessions_finished": len(finished),
        "sessions_left_early": sum(s["left_early"] for s in sessions),
        "sessions_failed": len(failed),
        "failures": [s["code"] for s in failed][:10],
        "finished_complete": sum(complete(s) for s in finished),
        "finished_moved": len(moved),
        "moved_complete": sum(complete(s) for s in moved),
        "resume_s": dist(resume_s),
        "largest_gap_s_moved": dist([gap(s) for s in moved]),
        "largest_gap_s_stayed": dist([gap(s) for s in stayed]),
        "frames_received": int(sum(len(s["indices"]) for s in sessions)),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workers", type=int, default=3)
    p.add_argument("--clients", type=int, default=12, help="sessions kept going at once (clients join at random)")
    p.add_argument("--seconds", type=float, default=60.0, help="how long new clients join")
    p.add_argument("--restart-at", type=float, default=20.0, help="SIGHUP (rolling restart) this many s in")
    p.add_argument("--join-every", type=float, default=0.5, help="mean seconds between two arrivals")
    p.add_argument("--leave-fraction", type=float, default=0.2, help="clients that leave mid-sentence")
    p.add_argument("--fail-timeout", type=int, default=10, help="local-cluster --fail-timeout (nginx's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--worker-args", default="--window-ms 100 --status-every 0",
                   help="arguments for every worker (after local-cluster's --)")
    p.add_argument("--out", default=str(RESULTS / "cluster_load.json"))
    args = p.parse_args()
    rng = random.Random(args.seed)
    worker_args = args.worker_args.split()
    import tempfile

    folder = Path(tempfile.mkdtemp(prefix="cluster-load-"))
    clips = clip_files(folder, rng, 12)
    cluster = Cluster("--fail-timeout", str(args.fail_timeout), "--", *worker_args, workers=args.workers, threads=None)
    cpu: dict[int, float] = {}
    stop = threading.Event()

    def sample():
        while not stop.wait(0.5):
            known = cluster.pids()
            for pid in [*known["workers"], *known["redis"], *nginx_pids(cluster.proc.pid)]:
                if (v := cpu_seconds(pid)) is not None:
                    cpu[pid] = v

    try:
        cluster.wait_for(r"^ready: ", 180)
        baseline = {pid: cpu_seconds(pid) or 0.0 for pid in
                    [*cluster.pids()["workers"], *cluster.pids()["redis"], *nginx_pids(cluster.proc.pid)]}
        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        t0 = time.monotonic()
        sessions, timeline = asyncio.run(simulate(args, cluster, clips, rng))
        wall = time.monotonic() - t0
        if args.restart_at is not None:
            cluster.wait_for(r"rolling restart done", 60)
        stop.set()
        sampler.join(2)
        known = cluster.pids()
        redis_peak = None
        try:
            import redis

            url = re.search(r"^state store: (\S+)", cluster.output, re.M).group(1)
            redis_peak = redis.Redis.from_url(url).info("memory")["used_memory_peak"]
        except Exception as e:  # noqa: BLE001
            print(f"redis INFO failed: {e}", file=sys.stderr)
        nginx = nginx_pids(cluster.proc.pid)
        used = {pid: cpu.get(pid, 0.0) - baseline.get(pid, 0.0) for pid in cpu}
    finally:
        stop.set()
        cluster.proc.send_signal(signal.SIGTERM)
        try:
            cluster.proc.wait(60)
        except subprocess.TimeoutExpired:
            cluster.proc.kill()
        shutil.rmtree(folder, ignore_errors=True)  # the clients' clips
    summary = summarize(sessions)
    workers_cpu = sum(used.get(pid, 0.0) for pid in known["workers"])
    cost = {"wall_s": round(wall, 1),
            "cpu_s_workers": round(workers_cpu, 1),
            "cpu_s_nginx": round(sum(used.get(pid, 0.0) for pid in nginx), 2),
            "cpu_s_redis": round(sum(used.get(pid, 0.0) for pid in known["redis"]), 2),
            "redis_peak_memory_bytes": redis_peak,
            "session_state_bytes": state_size_bytes(worker_args)}
    cost["nginx_per_worker_cpu"] = round(cost["cpu_s_nginx"] / workers_cpu, 4) if workers_cpu else None
    cost["redis_per_worker_cpu"] = round(cost["cpu_s_redis"] / workers_cpu, 4) if workers_cpu else None
    result = {"benchmark": "cluster_load", "created": utc_now(), "code_version": code_version(),
              "device": describe_device("cpu"), "load_average": load_average(),
              "command": "python " + " ".join(sys.argv), "workers": args.workers, "clients": args.clients,
              "seconds": args.seconds, "restart_at": args.restart_at, "worker_args": worker_args,
              "fail_timeout_s": args.fail_timeout,
              "summary": summary, "cost": cost, "timeline": timeline[:: max(1, len(timeline) // 400)],
              "sessions": [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in s.items()
                            if k not in ("times", "indices", "goaways", "resumed")}
                           | {"frames": len(s["indices"]), "moved": len(s["goaways"]), "index_runs": runs(s["indices"])}
                           for s in sessions]}
    write_json(Path(args.out), result)
    print(f"wrote {args.out}")
    for k, v in {**summary, **cost}.items():
        print(f"  {k}: {v}")
    plot(sessions, timeline, args, Path(args.out).with_suffix(".png"))
    return 0 if summary["sessions_failed"] == 0 else 1


def plot(sessions, timeline, args, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    t, n = zip(*timeline) if timeline else ((), ())
    a.plot(t, n, lw=1)
    a.set_ylabel("sessions going")
    for s in sessions:
        if len(s["times"]) > 1:
            times = np.array(s["times"])
            b.plot(times[1:], np.diff(times), lw=0.6, color="tab:red" if s["goaways"] else "0.5")
    for ax in (a, b):
        if args.restart_at is not None:
            ax.axvline(args.restart_at, color="k", ls="--", lw=1)
    b.set_ylabel("gap between frames (s)")
    b.set_xlabel("seconds (dashed: SIGHUP, rolling restart; red: sessions moved)")
    fig.suptitle(f"cluster load: {args.workers} workers, ~{args.clients} clients")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())
