"""numpy's BLAS threads in a served process with a face on every stream (issue 50): `dimgestor serve` keeps numpy's
BLAS on one thread (`streamer.server.one_blas_thread`); the other arm leaves it its own pool (a thread a core, what
numpy's OpenBLAS takes when nothing is set).

Each trial is `streams.serving_trial` in a child process of its own: the embedded default model (or
`--checkpoint`), K from the model, 100 ms windows, batched, staggered clients, the face on every session, the batcher
on the torch threads `serve` gives it here (`inference_threads`), `--seconds` of paced audio. The arms take turns at
each stream count. `--neighbour` runs each trial also beside a busy loop on one core (what a game, a voice agent's
speech recogniser or a second worker does to a served process on the same machine). With `--before ROOT` (a checkout
of older code, e.g. `git worktree add --detach /tmp/before 0578d34`), a third arm runs that code and its embedded
model as its `serve` ran them (numpy's BLAS pool), taking turns with the other two. Per trial: the lags (p95, ms),
whether it kept real time, and the process's CPU seconds. `--arms` picks the current arms: "face process" is
serve's one BLAS thread with the faces made in a child process beside the batcher (`serve --face-process`); its
CPU seconds are the served process's and the child's together.

    .venv/bin/python benchmarks/blas_threads.py --streams 32 40 48 --repeats 2 --neighbour
    .venv/bin/python benchmarks/blas_threads.py --streams 48 56 64 --arms "one thread" "face process"
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from common import RESULTS, code_version, commit_of, describe_device, load_average, utc_now, write_json

ARMS = ("one thread", "face process", "pool", "before")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--streams", type=int, nargs="+", default=[32, 40, 48], help="stream counts, each with a face")
    p.add_argument("--repeats", type=int, default=2, help="trials per arm, count and neighbour")
    p.add_argument("--seconds", type=float, default=12.0, help="audio per trial")
    p.add_argument("--window-ms", type=int, default=100)
    p.add_argument("--checkpoint", default=None,
                   help="the model of the two current arms (default: the embedded default model; --before's arm "
                        "runs its own)")
    p.add_argument("--arms", nargs="+", choices=ARMS[:3], default=["one thread", "pool"],
                   help="the current code's arms (default: one thread, pool); --before adds its own")
    p.add_argument("--neighbour", action="store_true", help="each trial also beside a busy loop on one core")
    p.add_argument("--before", type=Path, default=None, metavar="ROOT",
                   help="a third arm: the code (and embedded model) of this checkout, numpy's BLAS pool as it had")
    p.add_argument("--before-streams", type=int, nargs="+", default=None,
                   help="the stream counts of --before's arm (default: --streams)")
    p.add_argument("--out", type=Path, default=RESULTS / "blas_threads.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # internal: one trial, as JSON
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def child(job: dict) -> dict:
    """One trial in this process: the arm's BLAS threads, then `serving_trial`."""
    import torch
    from threadpoolctl import threadpool_info

    import dimgestor
    from dimgestor.face import FaceOptions
    from dimgestor.streaming.checkpoint import load_checkpoint
    from streamer.server import inference_threads
    from streams import serving_trial

    bundle = load_checkpoint(job["checkpoint"], "cpu")
    if job["arm"] in ("one thread", "face process"):
        from streamer.server import one_blas_thread

        one_blas_thread()
    process, kw = None, {}
    if job["arm"] == "face process":
        from streamer.face_process import FaceProcess

        started = time.perf_counter()
        process = FaceProcess()
        process.ready()
        kw = {"face_process": process, "start_s": time.perf_counter() - started}
    threads = inference_threads()
    torch.set_num_threads(threads)
    blas = sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})
    child_cpu = _children_cpu_s()
    try:
        r = serving_trial(bundle, job["streams"], bundle.config.sample_steps, job["window_ms"], job["seconds"], True,
                          threads, face=FaceOptions(), face_process=process)
    finally:
        if process is not None:
            process.close()
    r["process_cpu_s"] += _children_cpu_s() - child_cpu  # (the face process's, once it has ended)
    return {**job, "blas_threads": blas, "torch_threads": threads, "dimgestor": dimgestor.__file__,
            "model_steps": bundle.config.sample_steps, "guidance": bundle.config.guidance,
            **({"face_process_start_s": kw["start_s"]} if process is not None else {}), **{k: r[k] for k in (
        "lag_ms_p50", "lag_ms_p95", "end_lag_ms_max", "mean_batch", "wall_s", "process_cpu_s", "ok")}}


def _children_cpu_s() -> float:
    import resource

    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def busy_loop() -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def plan(args) -> list[tuple[bool, int, str]]:
    """The trials in order, (neighbour, streams, arm): by count, the arms taking turns at each repeat, each arm at
    its own counts (--before-streams for --before's)."""
    arms = [a for a in ARMS if a in args.arms or (a == "before" and args.before is not None)]
    counts = {arm: args.before_streams if arm == "before" and args.before_streams else args.streams for arm in arms}
    out = []
    for neighbour in ([False, True] if args.neighbour else [False]):
        for n in sorted({n for c in counts.values() for n in c}):
            for k in range(args.repeats):
                out += [(neighbour, n, arm) for arm in (arms if k % 2 == 0 else arms[::-1]) if n in counts[arm]]
    return out


def job_of(args, arm: str, n: int, neighbour: bool) -> dict:
    """One trial's settings: the before arm runs its own code's embedded model, whatever --checkpoint says."""
    return {"arm": arm, "streams": n, "neighbour": neighbour, "seconds": args.seconds, "window_ms": args.window_ms,
            "checkpoint": None if arm == "before" else args.checkpoint}


def trial(args, arm: str, n: int, neighbour: bool) -> dict:
    job = job_of(args, arm, n, neighbour)
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    env["MPLBACKEND"] = "Agg"
    if arm == "before":
        env["PYTHONPATH"] = os.pathsep.join([str(args.before), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    loop = busy_loop() if neighbour else None
    try:
        time.sleep(0.3 if neighbour else 0.0)
        proc = subprocess.run([sys.executable, __file__, "--child", json.dumps(job)], env=env, capture_output=True,
                              text=True)
    finally:
        if loop is not None:
            loop.kill()
            loop.wait()
    if proc.returncode != 0:
        raise RuntimeError(f"trial {job} failed:\n{proc.stderr[-3000:]}")
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    row["load_avg"] = load_average()
    print(f"{arm:10s} {n:3d} streams{' beside a busy core' if neighbour else ''}: p95 {row['lag_ms_p95']:.0f} ms, "
          f"{'real time' if row['ok'] else 'behind'}, process CPU {row['process_cpu_s']:.1f} s "
          f"(BLAS threads {row['blas_threads']})", flush=True)
    return row


def summary(rows: list[dict]) -> list[dict]:
    out = []
    for neighbour in sorted({r["neighbour"] for r in rows}):
        for n in sorted({r["streams"] for r in rows}):
            for arm in ARMS:
                rs = [r for r in rows if (r["neighbour"], r["streams"], r["arm"]) == (neighbour, n, arm)]
                if rs:
                    out.append({"neighbour": neighbour, "streams": n, "arm": arm, "trials": len(rs),
                                "real_time": sum(r["ok"] for r in rs),
                                "lag_ms_p95": [round(r["lag_ms_p95"]) for r in rs],
                                "process_cpu_s": [round(r["process_cpu_s"], 1) for r in rs]})
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted({s["neighbour"] for s in result["summary"]})
    fig, axes = plt.subplots(len(groups), 2, figsize=(12, 4.2 * len(groups)), squeeze=False)
    for g, neighbour in enumerate(groups):
        rows = [r for r in result["trials"] if r["neighbour"] == neighbour]
        where = "beside a busy core" if neighbour else "alone"
        for arm, colour in zip(ARMS, ("tab:blue", "tab:green", "tab:orange", "tab:grey")):
            mine = [r for r in rows if r["arm"] == arm]
            if not mine:
                continue
            label = (f"{result['before']['commit']} as it served (BLAS pool)" if arm == "before"
                     else "BLAS: one thread, faces in a child process" if arm == "face process" else f"BLAS: {arm}")
            axes[g][0].scatter([r["streams"] for r in mine], [min(r["lag_ms_p95"], 2000) for r in mine],
                                   color=colour, label=label)
            axes[g][1].scatter([r["streams"] for r in mine], [r["process_cpu_s"] for r in mine],
                                       color=colour, label=label)
        bar = result["window_ms"] + 150
        axes[g][0].axhline(bar, color="grey", ls="--", lw=1, label=f"real-time bar ({bar} ms)")
        axes[g][0].set(xlabel="streams with a face", ylabel="p95 lag, ms (2000 = off the chart)",
                           title=f"lag, {where}")
        axes[g][1].set(xlabel="streams with a face", ylabel=f"process CPU s per {result['seconds']:g} s trial",
                               title=f"process CPU, {where}")
        for ax in axes[g]:
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
    fig.suptitle(f"numpy's BLAS threads in a served process with a face on every stream ({result['code']}, "
                 f"{result['device']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return 0
    rows = [trial(args, arm, n, neighbour) for neighbour, n, arm in plan(args)]
    result = {"benchmark": "blas_threads", "created": utc_now(), "code": code_version(),
              "device": describe_device("cpu"), "command": "python benchmarks/blas_threads.py " + " ".join(args.argv),
              "note": args.note, "checkpoint": args.checkpoint or "the embedded default model",
              "seconds": args.seconds, "window_ms": args.window_ms, "trials": rows, "summary": summary(rows),
              "before": None if args.before is None else {"root": str(args.before), "commit": commit_of(args.before)}}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    for s in result["summary"]:
        print(s)
    return 0


if __name__ == "__main__":
    sys.exit(main())
