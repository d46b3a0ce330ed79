"""Before/after streaming cost of two source trees, interleaved in one run so both see the same load.

Runs `streaming.py --sections sweep` against the `dimgestor` package of each tree in turn (rounds x
trees, alternating), and reports per configuration the median over rounds of the wall and thread-CPU
real-time factors, and after/before ratios. On a shared machine the ratios are what to read.

    python benchmarks/ab_streaming.py --before /work/main --rounds 5        # this tree is "after"
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json

HERE = Path(__file__).resolve().parent


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--before", type=Path, required=True, help="source tree whose dimgestor package is 'before'")
    p.add_argument("--after", type=Path, default=HERE.parent, help="source tree for 'after' (default: this one)")
    p.add_argument("--before-version", default=None, help="what 'before' is (default: git HEAD of --before)")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--preset", default="realtime")
    p.add_argument("--steps", type=int, nargs="+", default=[4, 8])
    p.add_argument("--windows-ms", type=int, nargs="+", default=[100])
    p.add_argument("--audio-s", type=float, default=8.0)
    p.add_argument("--out", type=Path, default=RESULTS / "streaming_ab.json")
    return p.parse_args(argv)


def run_sweep(tree: Path, args, out: Path) -> list[dict]:
    env = {**os.environ, "PYTHONPATH": str(tree.resolve())}
    cmd = [sys.executable, str(HERE / "streaming.py"), "--sections", "sweep", "--presets", args.preset,
           "--steps", *map(str, args.steps), "--windows-ms", *map(str, args.windows_ms),
           "--audio-s", str(args.audio_s), "--out", str(out)]
    subprocess.run(cmd, env=env, check=True, capture_output=True, text=True)
    return json.loads(out.read_text())["results"]


def main(argv=None) -> None:
    args = parse_args(argv)
    trees = {"before": args.before, "after": args.after}
    runs = {name: [] for name in trees}
    load_before, started = load_average(), time.time()
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for name, tree in trees.items():
                runs[name].append(run_sweep(tree, args, Path(tmp) / f"{name}_{r}.json"))
    rows = []
    for i, row in enumerate(runs["after"][0]):
        entry = {"steps": row["steps"], "window_ms": row["window_ms"]}
        for name in trees:
            for key in ("rtf", "rtf_cpu", "latency_ms_p50", "cpu_ms_p50"):
                vals = [run[i].get(key) for run in runs[name]]
                entry[f"{name}_{key}"] = float(np.median(vals)) if None not in vals else None
                entry[f"{name}_{key}_rounds"] = vals
        for key in ("rtf", "rtf_cpu", "latency_ms_p50", "cpu_ms_p50"):
            b, a = entry[f"before_{key}"], entry[f"after_{key}"]
            entry[f"ratio_{key}"] = a / b if a is not None and b else None
        rows.append(entry)
        print(f"K={entry['steps']} {entry['window_ms']} ms: rtf {entry['before_rtf']:.3f} -> {entry['after_rtf']:.3f} "
              f"(x{entry['ratio_rtf']:.2f}), thread-CPU rtf {entry['before_rtf_cpu']:.3f} -> {entry['after_rtf_cpu']:.3f} "
              f"(x{entry['ratio_rtf_cpu']:.2f})")
    tree_versions = {name: subprocess.run(["git", "-C", str(t), "rev-parse", "--short", "HEAD"], capture_output=True,
                                          text=True).stdout.strip() for name, t in trees.items()}
    tree_versions["after"] = code_version()
    if args.before_version:
        tree_versions["before"] = args.before_version
    write_json(args.out, {
        "device": describe_device("cpu"), "threads": 1, "preset": args.preset, "audio_s": args.audio_s,
        "rounds": args.rounds, "trees": {k: str(v) for k, v in trees.items()}, "tree_versions": tree_versions,
        "results": rows, "load_avg_before": load_before, "load_avg_after": load_average(),
        "measured_at": utc_now(), "wall_s": round(time.time() - started, 1), "code_version": code_version(),
        "definitions": {"rtf, rtf_cpu, latency_ms_p50, cpu_ms_p50": "as in streaming.json; medians over rounds",
                        "ratio_*": "after / before (< 1: after is cheaper)"},
        "note": "measured on a shared 2-core machine with other processes running; rounds alternate the trees",
    })
    plot(rows, args.out.with_suffix(".png"), tree_versions)


def plot(rows: list[dict], path: Path, versions: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    labels = [f"K={r['steps']}, {r['window_ms']} ms" for r in rows]
    xs = np.arange(len(rows))
    for off, name in ((-0.2, "before"), (0.2, "after")):
        ax.bar(xs + off, [r[f"{name}_rtf_cpu"] for r in rows], 0.4, label=f"{name} ({versions[name]})")
        for j, r in enumerate(rows):
            ax.plot([j + off] * len(r[f"{name}_rtf_cpu_rounds"]), r[f"{name}_rtf_cpu_rounds"], "k.", ms=3)
    ax.set_xticks(xs, labels)
    ax.set(ylabel="real-time factor (thread CPU time)", title="streaming cost, median of rounds (dots: rounds)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
