"""Issue 40 item 8: fast senders at a high rate beside a real-time talker, against `dimgestor serve --source ws`.

For each number of flooders (default 1, 3, 7): a fresh server, one talker sending 16 kHz PCM16 speech paced in real
time, quiet for Q seconds, then beside the flooders for F seconds (each sends 1 MiB messages of 192 kHz stereo
float32 as fast as the socket takes them, ignoring `slow_down`), then 2 s quiet and `audio_end`. Reports the talker's
frame latency p50/p95 quiet and flooded, the `slow_down` and `resume` each flooder was told, the messages each got
in, and whether the talker got every frame (tests/helpers/intake_load.py measures).

    python benchmarks/intake_fairness.py                         # the tiny random model, 1/3/7 flooders
    python benchmarks/intake_fairness.py --flooders 3 --flood-s 20 --checkpoint runs/x
    python benchmarks/intake_fairness.py --plot-only benchmarks/results/intake_fairness.json   # redraw the .png

Writes the JSON and a plot beside it (.png: the talker's p95 quiet and flooded per number of flooders, with
STEM_before.json's runs beside them when that file is there, or --before).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
from pathlib import Path

from common import (RESULTS, code_version, describe_device, load_average, read_before,  # noqa: E402
                    save_against_before, utc_now, write_json)

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def one(checkpoint: Path, flooders: int, quiet_s: float, flood_s: float) -> dict:
    from helpers.intake_load import talker_beside_flood
    from helpers.serve import serve

    s = serve(checkpoint, "--source", "ws")
    try:
        url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
        r = asyncio.run(talker_beside_flood(url, flooders, quiet_s=quiet_s, flood_s=flood_s))
    finally:
        s.proc.terminate()
        s.finish(10)
    talker, counts = r["talker"], r["counts"]
    per = lambda key: [counts.get(f"{k}:{key}", 0) for k in range(flooders)]  # noqa: E731
    out = {
        "flooders": flooders,
        "talker_p95_quiet_ms": round(1000 * r["quiet_p95_s"], 1),
        "talker_p95_flooded_ms": round(1000 * r["flooded_p95_s"], 1),
        "talker_p50_quiet_ms": round(1000 * talker.percentile(*r["quiet"], q=50), 1),
        "talker_p50_flooded_ms": round(1000 * talker.percentile(*r["flooded"], q=50), 1),
        "slow_down": per("slow_down"), "resume": per("resume"), "messages_in": per("sent"),
        "talker_frames": talker.frames, "talker_end_frames": (talker.end or {}).get("frames"),
        "talker_errors": [e["code"] for e in talker.errors],
        "traceback_in_log": "Traceback" in s.output,
    }
    print(out, flush=True)
    return out


def plot(result: dict, path: Path, before: dict | None = None) -> None:
    """The talker's p95 quiet and flooded per number of flooders as grouped bars (log y), `before`'s beside."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    flooders = sorted({r["flooders"] for res in (result, before) if res for r in res["runs"]})
    now = "" if before is None else ", this code"
    series = [(f"quiet{now}", "talker_p95_quiet_ms", result, "tab:green", ""),
              (f"flooded{now}", "talker_p95_flooded_ms", result, "tab:red", "")]
    if before is not None:
        series = [("quiet, code before", "talker_p95_quiet_ms", before, "tab:green", "//"),
                  ("flooded, code before", "talker_p95_flooded_ms", before, "tab:red", "//")] + series
    fig, ax = plt.subplots(figsize=(9, 5))
    width = 0.8 / len(series)
    x = np.arange(len(flooders))
    lowest = []
    for i, (what, key, res, color, hatch) in enumerate(series):
        by = {r["flooders"]: r[key] for r in res["runs"]}
        values = [by.get(n, np.nan) for n in flooders]
        lowest += [v for v in values if np.isfinite(v) and v > 0]
        bars = ax.bar(x + (i - (len(series) - 1) / 2) * width, values, width, color=color, hatch=hatch,
                      edgecolor="k" if hatch else color, alpha=0.55 if hatch else 0.9, label=what)
        ax.bar_label(bars, labels=[f"{v:.0f}" if np.isfinite(v) else "" for v in values], fontsize=7, padding=2)
    ax.set_yscale("log")
    ax.set_xticks(x, [str(n) for n in flooders])
    ax.set_xlabel("flooders (each sending 1 MiB messages of 192 kHz stereo float32 as fast as it can)")
    ax.set_ylabel("talker frame latency p95 (ms, log scale)")
    ax.grid(axis="y", alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_ylim(min(lowest, default=10) / 3, ax.get_ylim()[1] * 2)
    lines = [f"a real-time talker beside fast senders: quiet {result['quiet_s']:g} s, then flooded "
             f"{result['flood_s']:g} s; {result['checkpoint']}",
             f"this code {result['code_version']}; {result['device']}"]
    save_against_before(fig, ax, lines, before["code_version"] if before is not None else None, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flooders", type=int, nargs="+", default=[1, 3, 7])
    ap.add_argument("--quiet-s", type=float, default=6.0)
    ap.add_argument("--flood-s", type=float, default=10.0)
    ap.add_argument("--checkpoint", type=Path, default=None, help="default: a tiny random-init model (the tests')")
    ap.add_argument("--out", default=str(RESULTS / "intake_fairness.json"))
    ap.add_argument("--plot-only", type=Path, metavar="RESULTS.json",
                    help="redraw RESULTS.png from an existing results file; measures nothing")
    ap.add_argument("--before", type=Path, default=None,
                    help="the older code's results to plot beside (default: STEM_before.json beside the results)")
    args = ap.parse_args()
    if args.plot_only:
        plot(json.loads(args.plot_only.read_text()), args.plot_only.with_suffix(".png"),
             read_before(args.plot_only, args.before))
        return
    with tempfile.TemporaryDirectory() as tmp:
        checkpoint = args.checkpoint
        if checkpoint is None:
            from helpers.checkpoint import make_tiny_checkpoint

            checkpoint = make_tiny_checkpoint(Path(tmp))
        load_before = load_average()
        runs = [one(checkpoint, n, args.quiet_s, args.flood_s) for n in args.flooders]
    result = {
        "when": utc_now(), "code_version": code_version(), "device": describe_device("cpu"),
        "load_average_before": load_before, "load_average_after": load_average(),
        "checkpoint": str(args.checkpoint or "tiny random-init (tests/helpers/checkpoint.py)"),
        "flood": "1 MiB messages of 192 kHz stereo float32 (0.68 s each), as fast as the socket takes them",
        "talker": "16 kHz PCM16 speech in 50 ms messages paced in real time", "quiet_s": args.quiet_s,
        "flood_s": args.flood_s, "runs": runs}
    out = Path(args.out)
    write_json(out, result)
    plot(result, out.with_suffix(".png"), read_before(out, args.before))


if __name__ == "__main__":
    main()
