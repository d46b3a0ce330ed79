"""Conditioning many streams as one call a group (the front end and the feature extractor, `dimgestor.model.conditioning`)
against another version of the code, in one run: where one cycle's time goes, and real-time streams per process.

Every measurement runs in a child process that imports `dimgestor` and `streamer` from one code root: this
checkout or `--before` (a checkout of the code to compare with, e.g. `git worktree add --detach /tmp/before
main`); the benchmark scripts themselves are this checkout's. The two roots take turns (A B, then B A), so
a neighbour's load falls on both alike.

  profile  B streams pushed together (`push_many`, 100 ms windows, one torch thread, smoothing off), rounds
           after a warm-up; per round: the front end's calls, the extractor's calls, the denoiser batch
           (`denoise`'s calls), the output step (`end_step`) and the rest (`push_many`'s own work, timers),
           and the process's minor page faults (memory touched for the first time; Unix only)
  streams  the most real-time streams one process keeps through the serving path (`benchmarks/streams.py`:
           paced sessions on one `StreamBatcher`, staggered phases), at each K
  trials   serving trials at fixed stream counts (`--trial-streams`), `--repeats` per tree, taking turns: the
           lags at a count, less at the mercy of one slow trial than the search (which stops at its first fail)

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

from common import RESULTS, commit_of, describe_device, load_average, test_audio, utc_now, write_json

HERE = Path(__file__).resolve().parents[1]
PARTS = ("frontend", "extractor", "denoise", "end_step", "rest")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--before", type=Path, required=True, help="a checkout of the code to compare with (its root)")
    p.add_argument("--sections", nargs="+", choices=("profile", "streams", "trials"), default=["profile", "streams"])
    p.add_argument("--models", nargs="+", default=["realtime", "default"],
                   help="presets (random weights) or \"default\" (the embedded default model)")
    p.add_argument("--steps", type=int, nargs="+", default=[8, 4],
                   help="DDIM steps K (0: each model's own, which may differ between the two code roots' models)")
    p.add_argument("--batch", type=int, default=32, help="streams pushed together in the profile")
    p.add_argument("--groups", type=int, default=0,
                   help="profile: push a random 1..G of the B streams each round, as staggered clients make the "
                        "batches (0: all B every round); its times are then per window, not per round")
    p.add_argument("--rounds", type=int, default=20, help="timed rounds per profile (after 8 warm-up rounds)")
    p.add_argument("--repeats", type=int, default=2, help="profiles per code root, taking turns")
    p.add_argument("--window-ms", type=int, default=100)
    p.add_argument("--streams-s", type=float, default=6.0, help="seconds of paced audio per streams trial")
    p.add_argument("--streams-max", type=int, default=128, help="stop the streams search at this many")
    p.add_argument("--trial-streams", type=int, nargs="+", default=[16, 24], help="stream counts of the trials section")
    p.add_argument("--out", type=Path, default=RESULTS / "batch_conditioning.json")
    p.add_argument("--face", action="store_true",
                   help="streams and trials: the face (`FaceOptions()`) on every session, as `serve` makes it")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # internal: one measurement, as JSON
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


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


def minor_faults() -> int | None:
    """The process's minor page faults so far (None where `resource` is missing: Windows)."""
    try:
        import resource
    except ImportError:
        return None
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def profile(job: dict) -> dict:
    """B streams pushed together round by round (or random groups of 1..G of them) -> each part's mean time
    per round (or per window pushed, with groups), ms."""
    import torch

    import dimgestor
    import dimgestor.streaming.batch as batch
    from dimgestor.streaming.stream import GestureStream
    from streams import random_bundle

    torch.set_num_threads(1)
    model = random_bundle(job["model"]).model.eval()
    B, window, warm, rounds = job["batch"], 16 * job["window_ms"], 8, job["rounds"]
    G = job.get("groups", 0)
    windows = warm + rounds if not G else (warm + rounds) * (G + 1)  # with groups: twice what a stream takes on average
    audios = [test_audio(windows * window / 16000, 16000, seed=j) for j in range(B)]
    streams = [GestureStream(model, steps=job["steps"] or None, seed=j, smoothing=None) for j in range(B)]
    totals = dict.fromkeys(PARTS, 0.0)
    fe, ex = type(model.frontend), type(model.extractor)
    fe.forward, ex.forward = _timer(totals, "frontend", fe.forward), _timer(totals, "extractor", ex.forward)
    batch.denoise = _timer(totals, "denoise", batch.denoise)  # each batched sampler run `push_many` makes
    GestureStream.end_step = _timer(totals, "end_step", GestureStream.end_step)
    walls, pos, pushed, faults = [], [0] * B, 0, 0
    rng = np.random.default_rng(0)
    warm, rounds = (warm, rounds) if not G else (warm * B, rounds * B // 2)  # every stream past warm-up
    for k in range(warm + rounds):
        if k == warm:  # the lookahead has filled, every stream past warm-up
            totals.update(dict.fromkeys(PARTS, 0.0))
        due = range(B) if not G else sorted(rng.choice(B, size=int(rng.integers(1, G + 1)), replace=False))
        f0, t0 = minor_faults(), time.perf_counter()
        batch.push_many([streams[i] for i in due], [audios[i][pos[i]:pos[i] + window] for i in due])
        if k >= warm:
            walls.append(time.perf_counter() - t0)
            faults += (minor_faults() or 0) - (f0 or 0)
            pushed += len(due)
        for i in due:
            pos[i] += window
    per = rounds if not G else pushed  # per round, or per window with groups
    ms = {part: 1000 * t / per for part, t in totals.items()}
    ms["total"] = 1000 * sum(walls) / per
    ms["rest"] = ms["total"] - sum(ms[p] for p in PARTS if p != "rest")
    return {"ms_per_window" if G else "ms_per_round": ms, "dimgestor": dimgestor.__file__,
            "page_faults_per_window" if G else "page_faults_per_round": None if f0 is None else faults / per,
            "frontend": model.config.frontend, "guidance": streams[0].guidance,
            "model_steps": len(streams[0].pairs)}


def _face(job: dict):
    """The sessions' face: `FaceOptions()` with --face, else none."""
    if not job.get("face"):
        return None
    from dimgestor.face import FaceOptions

    return FaceOptions()


def streams_search(job: dict) -> dict:
    import dimgestor
    from streams import max_streams, random_bundle

    bundle = random_bundle(job["model"])
    r = max_streams(bundle, job["steps"] or bundle.config.sample_steps, job["window_ms"], job["seconds"], True, 1,
                    job["cap"],
                    face=_face(job),
                    log=lambda line: print(line, file=sys.stderr, flush=True))
    return {**r, "dimgestor": dimgestor.__file__, "model_steps": bundle.config.sample_steps}


def serving(job: dict) -> dict:
    import dimgestor
    from streams import random_bundle, serving_trial

    bundle = random_bundle(job["model"])
    r = serving_trial(bundle, job["streams"], job["steps"] or bundle.config.sample_steps, job["window_ms"],
                      job["seconds"], True, 1, face=_face(job))
    return {**r, "dimgestor": dimgestor.__file__, "model_steps": bundle.config.sample_steps}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [name for name in ("profile", "streams", "trials") if result.get(name)]
    trial_counts = len({(r["model"], r["steps"], r["streams"]) for r in result.get("trials") or []})
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels) + 0.9 * max(0, trial_counts - 4), 4.2),
                             squeeze=False)
    for ax, name in zip(axes[0], panels):
        {"profile": _plot_profile, "streams": _plot_streams, "trials": _plot_trials}[name](ax, result)
        ax.grid(alpha=0.3, axis="y")
    codes = result["codes"]
    fig.suptitle(f"{codes['after']} against {codes['before']}; load {result['load_avg_before']} -> "
                 f"{result.get('load_avg_after')}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _plot_profile(ax, result: dict) -> None:
    rows = result["profile"]
    configs = sorted({(r["model"], r["steps"]) for r in rows}, key=lambda c: (c[0], -c[1]))
    for i, (model, steps) in enumerate(configs):
        for c, code in enumerate(("before", "after")):
            runs = [r.get("ms_per_round") or r["ms_per_window"] for r in rows if (r["model"], r["steps"], r["code"]) == (model, steps, code)]
            bottom = 0.0
            for j, part in enumerate(PARTS):  # the median of the profiles of each part
                v = float(np.median([m[part] for m in runs]))
                ax.bar(i + 0.4 * c, v, 0.38, bottom=bottom, color=f"C{j}", hatch="//" if c == 0 else None,
                       label=part if i == 0 and c == 1 else None)
                bottom += v
    ax.set_xticks([i + 0.2 for i in range(len(configs))], [f"{m} K={k}\nbefore | after" for m, k in configs],
                  fontsize=7)
    ax.set_ylabel(f"ms per round of {result['batch']} streams (median)" if not result.get("groups") else
                  f"ms per window, {result['batch']} streams in groups of 1-{result['groups']} (median)")
    ax.set_title(f"one push_many round, {result['batch']} streams, {result['window_ms']} ms windows "
                 "(hatched: before)", fontsize=9)
    ax.legend(fontsize=7)


def _plot_streams(ax, result: dict) -> None:
    runs = result["streams"]
    keys = sorted({(r["model"], r["steps"]) for r in runs})
    for c, code in enumerate(("before", "after")):
        vals = [max((r["max_realtime_streams"] for r in runs if (r["model"], r["steps"]) == k and r["code"] == code), default=0)
                for k in keys]
        ax.bar(np.arange(len(keys)) + 0.38 * c, vals, 0.38, label=f"{code} ({result['codes'][code]})")
    ax.set_xticks(np.arange(len(keys)) + 0.19, [f"{m} K={k}" for m, k in keys], fontsize=7)
    ax.set_ylabel("real-time streams (batched, staggered)")
    ax.set_title("streams one process keeps in real time", fontsize=9)
    ax.legend(fontsize=7)


def _plot_trials(ax, result: dict) -> None:
    runs = result["trials"]
    keys = sorted({(r["model"], r["steps"], r["streams"]) for r in runs})
    for c, code in enumerate(("before", "after")):
        vals = [float(np.median([r["lag_ms_p95"] for r in runs if (r["model"], r["steps"], r["streams"]) == k
                                 and r["code"] == code])) for k in keys]
        ax.bar(np.arange(len(keys)) + 0.38 * c, vals, 0.38, label=f"{code} ({result['codes'][code]})")
    ax.axhline(result["window_ms"] + 150, color="grey", lw=0.8, label="pass: window + 150 ms")
    ax.set_xticks(np.arange(len(keys)) + 0.19, [f"{m} K={k}\n{n} streams" for m, k, n in keys], fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("lag p95, second half of the trial (ms, median of trials)")
    face = ", a face on each" if any(r.get("face") for r in runs) else ""
    ax.set_title(f"serving trials at fixed stream counts{face}", fontsize=9)
    ax.legend(fontsize=7)


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.child is not None:
        job = json.loads(args.child)
        run = {"profile": profile, "streams": streams_search, "trials": serving}[job["section"]]
        print(json.dumps(run(job)), flush=True)
        return
    import torch

    roots = {"before": args.before.resolve(), "after": HERE}
    result = {"benchmark": "batch_conditioning", "created": utc_now(), "device": describe_device("cpu"),
              "torch": torch.__version__, "codes": {c: commit_of(r) for c, r in roots.items()},
              "command": " ".join(["python", "benchmarks/batch_conditioning.py"] + args.argv),
              "load_avg_before": load_average(), "batch": args.batch, "groups": args.groups, "window_ms": args.window_ms, "note": args.note}
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
                                   "rounds": args.rounds, "window_ms": args.window_ms, "groups": args.groups}):
                        ms = r.get("ms_per_round") or r["ms_per_window"]
                        print(f"profile {model} K={steps} B={args.batch} {r['code']:6s}: {ms['total']:.1f} ms a {'window' if args.groups else 'round'} "
                              f"(front end {ms['frontend']:.1f}, extractor {ms['extractor']:.1f}, denoise "
                              f"{ms['denoise']:.1f}, end_step {ms['end_step']:.1f}, rest {ms['rest']:.1f}; page faults "
                              f"{r.get('page_faults_per_round', r.get('page_faults_per_window'))}); load "
                              f"{r['load_avg'][0]:.1f}", flush=True)
                        result["profile"].append(r)
    if "streams" in args.sections:
        result["streams"] = []
        for model in args.models:
            for steps in args.steps:
                for r in both({"section": "streams", "model": model, "steps": steps, "window_ms": args.window_ms,
                               "seconds": args.streams_s, "cap": args.streams_max, "face": args.face}):
                    print(f"streams {model} K={steps} {r['code']:6s}: {r['max_realtime_streams']} real-time streams "
                          f"(load {r['load_avg'][0]:.1f})", flush=True)
                    result["streams"].append(r)
    if "trials" in args.sections:
        result["trials"] = []
        for model in args.models:
            for steps in args.steps:
                for n in args.trial_streams:
                    for _ in range(args.repeats):
                        for r in both({"section": "trials", "model": model, "steps": steps, "streams": n,
                                       "window_ms": args.window_ms, "seconds": args.streams_s, "face": args.face}):
                            print(f"trial {model} K={steps} {n} streams{' with a face' if args.face else ''} {r['code']:6s}: lag p50/p95 {r['lag_ms_p50']:.0f}/"
                                  f"{r['lag_ms_p95']:.0f} ms, worst end {r['end_lag_ms_max']:.0f} ms, batch "
                                  f"{r['mean_batch']:.1f} -> {'ok' if r['ok'] else 'falls behind'} (load "
                                  f"{r['load_avg'][0]:.1f})", flush=True)
                            result["trials"].append(r)
    result["load_avg_after"] = load_average()
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))


if __name__ == "__main__":
    main()
