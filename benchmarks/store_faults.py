"""A worker's live avatars while its state store is quiet, paused (SIGSTOP) or killed (SIGKILL, then restarted).

    .venv/bin/python benchmarks/store_faults.py [--talkers 4] [--seconds 16] [--fault-at 3] [--fault-s 8]

One `dimgestor serve --source ws` worker (the embedded default model unless --worker-args says otherwise) with a
redis-server of its own as `--state-store`, `--save-state-every 2`; `--talkers` clients send synthetic speech
paced in real time (tests/helpers/talkers.py) for `--seconds`, three times: quiet; with Redis SIGSTOPped
`--fault-at` s into the run for `--fault-s` s; with Redis SIGKILLed at the same moment and started again on its
port `--fault-s` s later. For each run and talker: the largest gap between two frames' arrivals and the p95
latency (a frame's arrival after its audio was sent), the `/readyz` answers seen while the fault lasted, and the
periodic saves before, during and after it. Writes results/store_faults.json and a plot beside it (.png: the
worst talker's largest gap and p95 latency per run, with results/store_faults_before.json's runs beside them when
that file is there).

    .venv/bin/python benchmarks/store_faults.py --plot-only benchmarks/results/store_faults.json [--before B.json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import (RESULTS, code_version, describe_device, load_average, read_before,  # noqa: E402
                    save_against_before, utc_now, write_json)

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from helpers.serve import Serve  # noqa: E402
from helpers.talkers import Talker, readyz, talk_together  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_redis(port: int, folder: str) -> subprocess.Popen:
    import redis

    proc = subprocess.Popen([shutil.which("redis-server") or "/usr/bin/redis-server", "--port", str(port), "--bind",
                             "127.0.0.1", "--save", "", "--appendonly", "no", "--dir", folder],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(200):
        try:
            redis.Redis(port=port).ping()
            return proc
        except redis.ConnectionError:
            time.sleep(0.05)
    raise RuntimeError("redis-server did not answer")


def run(fault: str | None, url: str, http: str, args, store: list[subprocess.Popen], port: int, folder: str) -> dict:
    """One run of the talkers, with `fault` (None, "pause" or "kill") done to the store meanwhile."""
    talkers = [Talker(url, args.seconds, seed) for seed in range(args.talkers)]
    marks: dict[str, float] = {}

    async def do_fault():
        if fault is None:
            return []
        await asyncio.sleep(args.fault_at)
        marks["fault"] = time.monotonic()
        if fault == "pause":
            store[0].send_signal(signal.SIGSTOP)
        else:
            store[0].kill()
            store[0].wait()
        said = []
        while time.monotonic() < marks["fault"] + args.fault_s:
            said.append(await asyncio.to_thread(readyz, http))
            await asyncio.sleep(0.25)
        if fault == "pause":
            store[0].send_signal(signal.SIGCONT)
        else:
            store[0] = await asyncio.to_thread(start_redis, port, folder)
        marks["back"] = time.monotonic()
        return said

    said = asyncio.run(talk_together(talkers, do_fault))
    per = [t.stats() for t in talkers]
    out = {"largest_gap_s": [round(g, 3) for g, _ in per], "p95_latency_s": [round(p, 3) for _, p in per],
           "frames": [len(t.arrivals) for t in talkers], "frames_expected": int(args.seconds * 20)}
    if fault is not None:
        saves = [at for t in talkers for at, _ in t.of("session_saved")]
        out.update(readyz_during={"answers": len(said), "status_200": sum(c == 200 for c, _ in said),
                                  "degraded": sum(w.startswith("degraded") for _, w in said),
                                  "first": said[len(said) // 2][1].strip() if said else None},
                   saves={"before": sum(a < marks["fault"] for a in saves),
                          "during": sum(marks["fault"] <= a < marks["back"] for a in saves),
                          "after": sum(a >= marks["back"] for a in saves)})
    return out


def plot(result: dict, path: Path, before: dict | None = None) -> None:
    """The worst talker's largest frame gap and p95 latency per run as grouped bars (log y), `before`'s runs beside."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["runs"])
    label = {"quiet": "quiet", "paused": "Redis paused\n(SIGSTOP)", "killed": "Redis killed\n(SIGKILL, restarted)"}
    now = "" if before is None else ", this code"
    series = [("largest frame gap" + now, "largest_gap_s", result, "tab:blue", ""),
              ("p95 latency" + now, "p95_latency_s", result, "tab:orange", "")]
    if before is not None:
        series += [("largest frame gap, code before", "largest_gap_s", before, "tab:blue", "//"),
                   ("p95 latency, code before", "p95_latency_s", before, "tab:orange", "//")]
    fig, ax = plt.subplots(figsize=(9, 5))
    width = 0.8 / len(series)
    x = np.arange(len(names))
    lowest = []
    for i, (what, key, res, color, hatch) in enumerate(series):
        values = [max(res["runs"][n][key]) if n in res["runs"] else np.nan for n in names]
        lowest += [v for v in values if np.isfinite(v) and v > 0]
        bars = ax.bar(x + (i - (len(series) - 1) / 2) * width, values, width, color=color, hatch=hatch,
                      edgecolor="k" if hatch else color, alpha=0.55 if hatch else 0.9, label=what)
        ax.bar_label(bars, labels=[f"{v:.2f}" if np.isfinite(v) else "" for v in values], fontsize=7, padding=2)
    ax.set_yscale("log")
    ax.set_xticks(x, [label.get(n, n) for n in names])
    ax.set_ylabel("seconds, worst talker (log scale)")
    ax.set_xlabel("run (the store's fault while the talkers send)")
    ax.grid(axis="y", alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_ylim(min(lowest, default=0.1) / 3, ax.get_ylim()[1] * 2)
    setup = result["setup"]
    lines = [f"store faults: {setup['talkers']} talkers x {setup['seconds']:g} s, fault from "
             f"{setup['fault_at_s']:g} s to {setup['fault_at_s'] + setup['fault_s']:g} s into each run "
             f"({setup['fault_s']:g} s); saves every {setup['save_state_every_s']} s",
             f"this code {result['code']}; {result['machine']}"]
    save_against_before(fig, ax, lines, before["code"] if before is not None else None, path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--talkers", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=16.0, help="audio per talker and run (default 16)")
    ap.add_argument("--fault-at", type=float, default=3.0, help="seconds into a run the store is paused or killed")
    ap.add_argument("--fault-s", type=float, default=8.0, help="how long it stays paused or dead (default 8)")
    ap.add_argument("--worker-args", default="", help="more `dimgestor serve` arguments, e.g. '--checkpoint X'")
    ap.add_argument("--out", type=Path, default=RESULTS / "store_faults.json")
    ap.add_argument("--plot-only", type=Path, metavar="RESULTS.json",
                    help="redraw RESULTS.png from an existing results file; measures nothing")
    ap.add_argument("--before", type=Path, default=None,
                    help="the older code's results to plot beside (default: STEM_before.json beside the results)")
    args = ap.parse_args()
    if args.plot_only:
        plot(json.loads(args.plot_only.read_text()), args.plot_only.with_suffix(".png"),
             read_before(args.plot_only, args.before))
        return 0
    folder = tempfile.mkdtemp(prefix="store-faults-")
    port = free_port()
    store = [start_redis(port, folder)]
    worker = Serve("--source", "ws", "--ws", "127.0.0.1:0", "--state-store", f"redis://127.0.0.1:{port}/0",
                   "--save-state-every", "2", "--window-ms", "100", "--status-every", "0",
                   *shlex.split(args.worker_args))
    try:
        ws_port = int(worker.wait_for(r"ws://127\.0\.0\.1:(\d+)/", 180).group(1))
        url, http = f"ws://127.0.0.1:{ws_port}/", f"http://127.0.0.1:{ws_port}/"
        runs = {name: run(fault, url, http, args, store, port, folder)
                for name, fault in (("quiet", None), ("paused", "pause"), ("killed", "kill"))}
    finally:
        worker.proc.send_signal(signal.SIGTERM)
        worker.finish(30)
        store[0].send_signal(signal.SIGCONT)
        store[0].terminate()
        store[0].wait(10)
        shutil.rmtree(folder, ignore_errors=True)
    for name, r in runs.items():
        print(f"{name:7s} largest gap {max(r['largest_gap_s']):.3f} s, p95 latency {max(r['p95_latency_s']):.3f} s "
              f"(worst talker)" + (f"; readyz degraded {r['readyz_during']['degraded']}/{r['readyz_during']['answers']}"
                                   f", saves before/during/after {r['saves']}" if "saves" in r else ""))
    result = {
        "what": "a worker's talkers while its state store is quiet, paused (SIGSTOP) or killed and restarted",
        "when": utc_now(), "code": code_version(), "machine": describe_device("cpu"), "load_average": load_average(),
        "setup": {"talkers": args.talkers, "seconds": args.seconds, "fault_at_s": args.fault_at,
                  "fault_s": args.fault_s, "save_state_every_s": 2, "window_ms": 100,
                  "worker_args": args.worker_args or "(the embedded default model)"},
        "runs": runs,
        "summary": {name: {"largest_gap_s": float(np.max(r["largest_gap_s"])),
                           "p95_latency_s": float(np.max(r["p95_latency_s"]))} for name, r in runs.items()},
    }
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"), read_before(args.out, args.before))
    return 0


if __name__ == "__main__":
    sys.exit(main())
