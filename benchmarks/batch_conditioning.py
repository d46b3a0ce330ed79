"""Conditioning many streams as one call a group (the front end and the feature extractor, `dimgestor.conditioning`)
against another version of the code, in one run: where one cycle's time goes, and real-time streams per process.

Every measurement runs in a child process that imports `dimgestor` and `streamer` from one code root: this
checkout or `--before` (a checkout of the code to compare with, e.g. `git worktree add --detach /tmp/before
main`); the benchmark scripts themselves are this checkout's. The two roots take turns (A B, then B A), so
a neighbour's load falls on both alike.

  profile  B streams pushed together (`push_many`, 100 ms windows, one torch thread, smoothing off), rounds
           after a warm-up; per round: the front end's calls, the extractor's calls, the denoiser batch
           (`_denoise_rounds`), the output step (`end_step`) and the rest (`push_many`'s own work, timers)
  streams  the most real-time streams one process keeps through the serving path (`benchmarks/streams.py`:
           paced sessions on one `StreamBatcher`, staggered phases), at each K

    .venv/bin/python benchmarks/batch_conditioning.py --before /tmp/before
    .venv/bin/python benchmarks/batch_conditioning.py --before /tmp/before --sections profile --batch 32
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, describe_device, load_average, test_audio, utc_now, write_json

HERE = Path(__file__).resolve().parents[1]
PARTS = ("frontend", "extractor", "denoise", "end_step", "rest")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--before", type=Path, required=True, help="a checkout of the code to compare with (its root)")
    p.add_argument("--sections", nargs="+", choices=("profile", "streams"), default=["profile", "streams"])
    p.add_argument("--models", nargs="+", default=["realtime", "default"],
                   help="presets (random weights) or \"default\" (the embedded default model)")
    p.add_argument("--steps", type=int, nargs="+", default=[8, 4], help="DDIM steps K")
    p.add_argument("--batch", type=int, default=32, help="streams pushed together in the profile")
    p.add_argument("--rounds", type=int, default=20, help="timed rounds per profile (after 8 warm-up rounds)")
    p.add_argument("--repeats", type=int, default=2, help="profiles per code root, taking turns")
    p.add_argument("--window-ms", type=int, default=100)
    p.add_argument("--streams-s", type=float, default=6.0, help="seconds of paced audio per streams trial")
    p.add_argument("--streams-max", type=int, default=128, help="stop the streams search at this many")
    p.add_argument("--out", type=Path, default=RESULTS / "batch_conditioning.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # internal: one measurement, as JSON
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def commit_of(root: Path) -> str:
    """The short commit of a code root, '+dirty' when its dimgestor/ or streamer/ has uncommitted changes."""
    git = lambda *a: subprocess.run(["git", *a], cwd=root, capture_output=True, text=True, check=True).stdout.strip()  # noqa: E731
    try:
        return git("rev-parse", "--short", "HEAD") + ("+dirty" if git("status", "--porcelain", "--", "dimgestor", "streamer") else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"


def in_child(root: Path, job: dict) -> dict:
    """Run one measurement in a child process importing the code under `root`."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
           "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    proc = subprocess.run([sys.executable, __file__, "--before", str(root), "--child", json.dumps(job)], env=env,
                          capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"child {job} under {root} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _timer(totals: dict, part: str, fn):
    def timed(*a, **kw):
        t0 = time.perf_counter()
        try:
            return fn(*a, **kw)
        finally:
            totals[part] += time.perf_counter() - t0
    return timed


def profile(job: dict) -> dict:
    """B streams pushed together round by round -> each part's mean time per round (ms)."""
    import torch

    import dimgestor
    import dimgestor.batch as batch
    from dimgestor.stream import GestureStream
    from streams import random_bundle

    torch.set_num_threads(1)
    model = random_bundle(job["model"]).model.eval()
    B, window, warm, rounds = job["batch"], 16 * job["window_ms"], 8, job["rounds"]
    audios = [test_audio((warm + rounds) * window / 16000, 16000, seed=j) for j in range(B)]
    streams = [GestureStream(model, steps=job["steps"], seed=j, smoothing=None) for j in range(B)]
    totals = dict.fromkeys(PARTS, 0.0)
    fe, ex = type(model.frontend), type(model.extractor)
    fe.forward, ex.forward = _timer(totals, "frontend", fe.forward), _timer(totals, "extractor", ex.forward)
    batch._denoise_rounds = _timer(totals, "denoise", batch._denoise_rounds)
    GestureStream.end_step = _timer(totals, "end_step", GestureStream.end_step)
    walls = []
    for k in range(warm + rounds):
        if k == warm:  # the lookahead has filled, every stream past warm-up
            totals.update(dict.fromkeys(PARTS, 0.0))
        t0 = time.perf_counter()
        batch.push_many(streams, [a[k * window:(k + 1) * window] for a in audios])
        if k >= warm:
            walls.append(time.perf_counter() - t0)
    ms = {part: 1000 * t / rounds for part, t in totals.items()}
    ms["total"] = 1000 * float(np.mean(walls))
    ms["rest"] = ms["total"] - sum(ms[p] for p in PARTS if p != "rest")
    return {"ms_per_round": ms, "total_ms_p50": 1000 * float(np.median(walls)), "dimgestor": dimgestor.__file__,
            "frontend": model.config.frontend, "guidance": streams[0].guidance}


def streams_search(job: dict) -> dict:
    import dimgestor
    from streams import max_streams, random_bundle

    r = max_streams(random_bundle(job["model"]), job["steps"], job["window_ms"], job["seconds"], True, 1, job["cap"],
                    log=lambda line: print(line, file=sys.stderr, flush=True))
    return {**r, "dimgestor": dimgestor.__file__}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    ax = axes[0]
    labels, bottoms = [], None
    rows = result.get("profile", [])
    for i, r in enumerate(rows):
        labels.append(f"{r['model']} K={r['steps']}\n{r['code']}")
        bottom = 0.0
        for j, part in enumerate(PARTS):
            v = r["ms_per_round"][part]
            ax.bar(i, v, bottom=bottom, color=f"C{j}", label=part if i == 0 else None)
            bottom += v
    ax.set_xticks(range(len(rows)), labels, fontsize=6)
    ax.set_ylabel(f"ms per round of {result['batch']} streams (mean)")
    ax.set_title(f"one push_many round, {result['batch']} streams, {result['window_ms']} ms windows", fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[1]
    runs = result.get("streams", [])
    keys = sorted({(r["model"], r["steps"]) for r in runs})
    for c, code in enumerate(("before", "after")):
        vals = [max((r["max_realtime_streams"] for r in runs if (r["model"], r["steps"]) == k and r["code"] == code), default=0)
                for k in keys]
        ax.bar(np.arange(len(keys)) + 0.38 * c, vals, 0.38, label=f"{code} ({result['codes'][code]})")
    ax.set_xticks(np.arange(len(keys)) + 0.19, [f"{m} K={k}" for m, k in keys], fontsize=7)
    ax.set_ylabel("real-time streams (batched, staggered)")
    ax.set_title("streams one process keeps in real time", fontsize=9)
    ax.legend(fontsize=7)
    for a in axes:
        a.grid(alpha=0.3, axis="y")
    fig.suptitle(f"batched conditioning vs before; load {result['load_avg_before']} -> {result.get('load_avg_after')}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.child is not None:
        job = json.loads(args.child)
        print(json.dumps(profile(job) if job["section"] == "profile" else streams_search(job)), flush=True)
        return
    import torch

    roots = {"before": args.before.resolve(), "after": HERE}
    result = {"benchmark": "batch_conditioning", "created": utc_now(), "device": describe_device("cpu"),
              "torch": torch.__version__, "codes": {c: commit_of(r) for c, r in roots.items()},
              "command": " ".join(["python", "benchmarks/batch_conditioning.py"] + args.argv),
              "load_avg_before": load_average(), "batch": args.batch, "window_ms": args.window_ms, "note": args.note}
    turn = 0

    def both(job: dict) -> list[dict]:
        nonlocal turn
        order = ("before", "after") if turn % 2 == 0 else ("after", "before")
        turn += 1
        out = []
        for code in order:
            load = load_average()
            r = in_child(roots[code], job)
            out.append({**job, **r, "code": code, "commit": result["codes"][code], "load_avg": load})
        return out

    if "profile" in args.sections:
        result["profile"] = []
        for model in args.models:
            for steps in args.steps:
                for _ in range(args.repeats):
                    for r in both({"section": "profile", "model": model, "steps": steps, "batch": args.batch,
                                   "rounds": args.rounds, "window_ms": args.window_ms}):
                        ms = r["ms_per_round"]
                        print(f"profile {model} K={steps} B={args.batch} {r['code']:6s}: {ms['total']:.1f} ms a round "
                              f"(front end {ms['frontend']:.1f}, extractor {ms['extractor']:.1f}, denoise "
                              f"{ms['denoise']:.1f}, end_step {ms['end_step']:.1f}, rest {ms['rest']:.1f}); load "
                              f"{r['load_avg'][0]:.1f}", flush=True)
                        result["profile"].append(r)
    if "streams" in args.sections:
        result["streams"] = []
        for model in args.models:
            for steps in args.steps:
                for r in both({"section": "streams", "model": model, "steps": steps, "window_ms": args.window_ms,
                               "seconds": args.streams_s, "cap": args.streams_max}):
                    print(f"streams {model} K={steps} {r['code']:6s}: {r['max_realtime_streams']} real-time streams "
                          f"(load {r['load_avg'][0]:.1f})", flush=True)
                    result["streams"].append(r)
    result["load_avg_after"] = load_average()
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))


if __name__ == "__main__":
    main()
