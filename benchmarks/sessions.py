"""Issue 25 at full size against `dimgestor serve` on loopback: throttled sessions and the keepalive,
a flood of malformed requests, and shutdown after both.

keepalive: N clients (default 31, beside one real-time talker: 32 = the default session limit) send
1 MiB audio messages as fast as the server takes them for T seconds (default 60), ignoring `slow_down`
and never pinging, while reading every frame; then `audio_end` and read to `end`. Reports how many
the server closed (should be 0), whether each got all its frames, and the talker's frame latency
(p50/p95) in a quiet phase and during the flood.

fuzz: R malformed requests (default 10,000) to the server's one port, half WebSocket handshakes and half
requests for the viewer's pages: the status codes seen (no 5xx), tracebacks in the log (none) and how much
the log grew.

    python benchmarks/sessions.py                              # the embedded default model, both parts
    python benchmarks/sessions.py --flooders 4 --seconds 20 --requests 2000 --checkpoint runs/x
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json
from dimgestor.audio import SAMPLE_RATE

REPO = Path(__file__).resolve().parents[1]
MIB = 1 << 20


class Server:
    def __init__(self, *args: str):
        self.proc = subprocess.Popen([sys.executable, "-m", "dimgestor_app.cli", "serve", *args], cwd=REPO,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True).start()

    def wait_for(self, pattern: str, timeout: float = 120.0) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in list(self.lines):
                if m := re.search(pattern, line):
                    return m
            time.sleep(0.05)
        raise RuntimeError(f"{pattern!r} never printed:\n{''.join(self.lines)[-3000:]}")

    def rss_mb(self) -> float:
        with open(f"/proc/{self.proc.pid}/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024

    def stop(self) -> float:
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(30)
        return time.monotonic() - t0

    @property
    def output(self) -> str:
        return "".join(self.lines)


def speech(seconds: float, seed: int) -> bytes:
    from dimgestor.training.synthetic import synthetic_speech

    return (synthetic_speech(seconds, seed=seed) * 20000).astype("<i2").tobytes()


async def flooder(url: str, seconds: float, chunk: bytes, out: dict) -> None:
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed

    from streamer import protocol as P

    out.update(frames=0, in_order=True, closed=None, end=None, sent=0)
    async with connect(url, ping_interval=None, max_size=None) as c:
        await c.recv()
        await c.send(json.dumps({"type": "hello", "encoding": "binary"}))

        async def read():
            try:
                async for m in c:
                    if isinstance(m, bytes):
                        out["in_order"] &= P.parse_frame_binary(m)["index"] == out["frames"]
                        out["frames"] += 1
                    elif (d := json.loads(m))["type"] == "end":
                        out["end"] = d["frames"]
                        return
            except ConnectionClosed as e:
                out["closed"] = f"{e.rcvd.code if e.rcvd else None} {e.rcvd.reason if e.rcvd else ''}"

        reader = asyncio.create_task(read())
        t0 = time.monotonic()
        try:
            while time.monotonic() - t0 < seconds and out["closed"] is None:
                await c.send(chunk)
                out["sent"] += len(chunk) // 2
            await c.send(json.dumps({"type": "audio_end"}))
        except ConnectionClosed:
            pass
        await asyncio.wait_for(reader, 900)


async def talker(url: str, stop: asyncio.Event, latency: list) -> None:
    """Real-time speech in 50 ms chunks; (arrival, latency) of each frame: arrival - when its audio was complete."""
    from websockets.asyncio.client import connect

    audio = speech(600.0, seed=5)
    sent: list[tuple[float, float]] = []
    async with connect(url) as c:
        hello = json.loads(await c.recv())

        async def read():
            async for m in c:
                d = json.loads(m)
                if d["type"] == "frame":
                    need = (d["index"] + 1) / hello["fps"] + hello["lookahead_s"]
                    done = next((t for a, t in sent if a >= need - 1e-6), None)
                    if done is not None:
                        latency.append((time.monotonic(), time.monotonic() - done))

        reader = asyncio.create_task(read())
        step, t0 = 1600, time.monotonic()
        for k, i in enumerate(range(0, len(audio) // 2, step)):
            if stop.is_set():
                break
            await c.send(audio[2 * i : 2 * (i + step)])
            sent.append(((i + step) / SAMPLE_RATE, time.monotonic()))
            await asyncio.sleep(max(0.0, t0 + (k + 1) * 0.1 - time.monotonic()))
        reader.cancel()


def worst_by_second(latency: list, t0: float, t1: float) -> list:
    """The talker's largest frame latency (ms) in each second from t0 to t1: where a p95 comes from (a stall)."""
    return [round(max((v for t, v in latency if t0 + k <= t < t0 + k + 1), default=0.0) * 1000)
            for k in range(int(t1 - t0))]


def percentiles(latency: list, t0: float, t1: float) -> dict:
    x = np.array([v for t, v in latency if t0 <= t <= t1]) * 1000
    return {"n": int(len(x)), "p50_ms": round(float(np.median(x)), 1) if len(x) else None,
            "p95_ms": round(float(np.percentile(x, 95)), 1) if len(x) else None}


async def flood(url: str, flooders: int, seconds: float) -> list[dict]:
    """`flooders` fast senders at once (in the flood child process, see keepalive_part)."""
    outs = [{} for _ in range(flooders)]
    chunk = speech(32.768, seed=3)[:MIB]
    print(f"flood starts {time.monotonic()}", flush=True)
    await asyncio.gather(*(flooder(url, seconds, chunk, o) for o in outs))
    return outs


async def keepalive_part(url: str, flooders: int, seconds: float, quiet_s: float) -> dict:
    """The talker here, the flooders in a child process of their own: sharing one event loop, 31 clients'
    handshakes, 1 MiB sends and frame reads delayed the talker's own sends and reads (its loop stalled for
    up to 1.5 s at the flood's start), which this measure would have charged to the server."""
    stop, latency = asyncio.Event(), []
    talk = asyncio.create_task(talker(url, stop, latency))
    while not latency:  # (the first frames: the model's first calls)
        await asyncio.sleep(0.1)
    t_quiet = time.monotonic()
    await asyncio.sleep(quiet_s)
    quiet = percentiles(latency, t_quiet + 1, time.monotonic())
    child = await asyncio.create_subprocess_exec(sys.executable, __file__, "--flood-child", url, str(flooders),
                                                 str(seconds), stdout=asyncio.subprocess.PIPE)
    t0 = float((await child.stdout.readline()).split()[-1])  # the system-wide monotonic clock, as here
    outs = json.loads(await child.stdout.read())
    await child.wait()
    flood = percentiles(latency, t0 + 2, t0 + seconds)
    flood["worst_ms_by_second"] = worst_by_second(latency, t0, t0 + seconds)
    stop.set()
    await asyncio.gather(talk, return_exceptions=True)
    return {"flooders": flooders, "seconds": seconds, "closed": sum(o["closed"] is not None for o in outs),
            "closes": [o["closed"] for o in outs if o["closed"]],
            "all_frames": sum(o["end"] == o["frames"] == int(o["sent"] / SAMPLE_RATE * 20) and o["in_order"] for o in outs),
            "audio_s_each": [round(o["sent"] / SAMPLE_RATE) for o in outs], "talker_quiet": quiet, "talker_flood": flood,
            "wall_s": round(time.monotonic() - t0, 1),
            # the flooders' throughput: all their audio over the time from the flood's start to their last `end`
            "flood_audio_s_per_s": round(sum(o["sent"] for o in outs) / SAMPLE_RATE / (time.monotonic() - t0), 1)}


def fuzz_requests(n: int, seed: int, websocket: bool) -> list[bytes]:
    rng = random.Random(seed)
    nasty = ["[::1", "//", "/..", "%", "%00", "%ff", "\\", ":", "@", "?", "a" * 300, "é", "*", "http://",
             "https://app.example.com//"]
    pick = lambda: rng.choice(nasty) + rng.choice(["", "x", "/", rng.choice(nasty)])  # noqa: E731
    base = [("Upgrade", "websocket"), ("Connection", "Upgrade"), ("Sec-WebSocket-Key", "dGhlIHNhbXBsZSBub25jZQ=="),
            ("Sec-WebSocket-Version", "13")] if websocket else []
    out = []
    for _ in range(n):
        hdrs = [("Host", rng.choice(["127.0.0.1", "[::1", pick()]))] + base
        for _ in range(rng.randrange(3)):
            hdrs.append((rng.choice(["Origin", "Host", "X-" + pick()]), rng.choice(["null", "https://e.example//", pick()])))
        rng.shuffle(hdrs)
        target = rng.choice(["/", "/config.json", "/" + pick(), pick(), "/" + "d" * rng.choice([256, 1000, 2100])])
        method = rng.choice(["GET", "GET", "HEAD", "POST", pick()])
        lines = [f"{method} {target} {rng.choice(['HTTP/1.1', 'HTTP/1.0', pick()])}", *(f"{k}: {v}" for k, v in hdrs)]
        out.append(("\r\n".join(lines) + "\r\n\r\n").encode("utf-8", "surrogatepass"))
    return out


def send(port: int, request: bytes) -> int | None:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            s.sendall(request)
            out = b""
            while b"\r\n\r\n" not in out and (chunk := s.recv(65536)):
                out += chunk
    except OSError:
        return None
    parts = out.split(b"\r\n", 1)[0].split(b" ")
    return int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else None


def fuzz_part(server: Server, port: int, requests: int) -> dict:
    log0 = len(server.output.encode())
    t0 = time.monotonic()
    statuses: dict[str, int] = {}
    for seed, websocket in ((port, True), (port + 1, False)):  # handshakes, then pages of the viewer
        for r in fuzz_requests(requests // 2, seed=seed, websocket=websocket):
            key = f"{'ws' if websocket else 'http'} {send(port, r)}"
            statuses[key] = statuses.get(key, 0) + 1
    time.sleep(0.5)
    grown = server.output.encode()[log0:]
    return {"requests": requests, "wall_s": round(time.monotonic() - t0, 1), "statuses": dict(sorted(statuses.items())),
            "5xx": sum(v for k, v in statuses.items() if k.split()[1].startswith("5")),
            "tracebacks": grown.count(b"Traceback"), "log_growth_bytes": len(grown),
            "log_lines": [line for line in grown.decode(errors="replace").splitlines() if "[streamer" not in line][:10]}


def main() -> None:
    if sys.argv[1:2] == ["--flood-child"]:  # (keepalive_part's child: URL FLOODERS SECONDS; JSON out)
        url, n, seconds = sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
        print(json.dumps(asyncio.run(flood(url, n, seconds))), flush=True)
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--flooders", type=int, default=31)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--quiet-s", type=float, default=10.0)
    ap.add_argument("--requests", type=int, default=10000)
    ap.add_argument("--out", default=str(RESULTS / "sessions.json"))
    args = ap.parse_args()
    extra = [*(["--checkpoint", args.checkpoint] if args.checkpoint else []),
             *(["--steps", str(args.steps)] if args.steps else [])]
    server = Server("--source", "ws", "--ws", "127.0.0.1:0", "--max-sessions", str(args.flooders + 1),
                    "--status-every", "10", *extra)
    ws_url = server.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    time.sleep(1.0)
    rss0 = server.rss_mb()
    result = {"when": utc_now(), "code_version": code_version(), "device": describe_device("cpu"),
              "load_before": load_average()}
    result["keepalive"] = asyncio.run(keepalive_part(ws_url, args.flooders, args.seconds, args.quiet_s))
    print(json.dumps(result["keepalive"]), flush=True)
    result["fuzz"] = fuzz_part(server, int(ws_url.rsplit(":", 1)[1].strip("/")), args.requests)
    print(json.dumps(result["fuzz"]), flush=True)
    result["rss_mb"] = {"before": round(rss0), "after": round(server.rss_mb())}
    result["sigterm_to_exit_s"] = round(server.stop(), 2)
    result["load_after"] = load_average()
    result["server_tracebacks"] = server.output.count("Traceback")
    # what the server said of its clients (keepalive closes, departures): the first 20 such lines
    result["server_client_lines"] = [line.strip() for line in server.output.splitlines()
                                     if "client " in line and "[streamer" not in line][:20]
    write_json(Path(args.out), result)


if __name__ == "__main__":
    main()
