"""A distilled student against its teacher (issue 50): quality on the training speaker's held-out stretch, and what a
window costs through `dimgestor serve`.

    .venv/bin/python benchmarks/distill.py --student runs/default_1step [--student runs/default_2step] [--seeds 3]

Models: the teacher (`--teacher`, the embedded default model unless given) at its own K and guidance; the same
teacher at each student's K without guidance (what fewer steps give without distilling); and each `--student` at
its own K (guidance 1). Quality: `dimgestor eval` on ../shared's ZEGGS clip's held-out 15 s (the split the default
model was trained with), output filter off, `--seeds` seeds: wrist jerk over the real capture's, FGD (feature; one
autoencoder for all, trained on the first run), diversity between seeds, loudness coupling, wrist speed in speech
over inserted silence, variety (nearest-window ratio). Cost: the user+sys CPU of `dimgestor serve --source FILE
--fast --window-ms 100 --no-ws` on `--speech-s` s of real speech (../shared's unseen BEAT speaker) less that on 2 s,
over the windows, with `--face arkit` and `--face none`, one thread. Writes results/distill.json and a plot beside it.

    .venv/bin/python benchmarks/distill.py --plot-only benchmarks/results/distill.json
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SHARED = REPO.parent / "shared" / "data"
ZEGGS = SHARED / "zeggs_sample"
SPEECH = SHARED / "unseen_speech" / "4_lawrence_0_19_19.wav"
QUALITY = ("jerk_ratio", "fgd_feature", "diversity", "coupling", "silence_ratio", "variety")


def cli(*args: str, threads: int = 1) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    return subprocess.run([sys.executable, "-m", "dimgestor_app.cli", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, check=True)


def quality(checkpoint: str, k: int, guidance: float | None, seeds: int, folder: Path) -> dict:
    out = folder / f"eval_{len(list(folder.glob('eval_*')))}.json"
    cli("eval", "--checkpoint", checkpoint, "--data", str(ZEGGS), "--valid-seconds", "15", "--steps", str(k),
        "--smooth", "0", "--seeds", str(seeds), "--out", str(out),
        *(["--guidance", str(guidance)] if guidance is not None else []), threads=2)
    row = json.loads(out.read_text())["per_k"][str(k)]
    return {m: round(float(row[m]), 4) for m in QUALITY}


def serve_cpu(checkpoint: str, wav: Path, face: str) -> float:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    cli("serve", "--checkpoint", checkpoint, "--source", str(wav), "--fast", "--window-ms", "100", "--no-ws",
        "--status-every", "0", "--face", face)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime


def cost(checkpoint: str, long_wav: Path, short_wav: Path, seconds: float, runs: int) -> dict:
    """CPU ms per 100 ms window: (the long file's - the short file's) over the windows between; median of runs."""
    out = {}
    for face in ("arkit", "none"):
        per = [(serve_cpu(checkpoint, long_wav, face) - serve_cpu(checkpoint, short_wav, face)) / ((seconds - 2) * 10)
               for _ in range(runs)]
        out[f"window_ms_face_{face}"] = round(1000 * float(np.median(per)), 2)
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["models"]
    names = [r["label"] for r in rows]
    metrics = [("jerk_ratio", "wrist jerk / real (<= 1.5)"), ("fgd_feature", "FGD (lower is better)"),
               ("coupling", "coupling, held-out"), ("silence_ratio", "speech / silence (>= 3)"),
               ("variety", "variety"), ("window_ms_face_arkit", "CPU ms a window, with the face")]
    fig, axes = plt.subplots(1, len(metrics), figsize=(3.2 * len(metrics), 4.2))
    for ax, (key, title) in zip(axes, metrics):
        values = [r.get(key, np.nan) for r in rows]
        bars = ax.bar(range(len(rows)), values, color=[f"C{i}" for i in range(len(rows))])
        ax.bar_label(bars, labels=[f"{v:.2f}" for v in values], fontsize=7)
        ax.set_title(title, fontsize=9)
        ax.set_xticks(range(len(rows)), names, rotation=60, ha="right", fontsize=7)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"distilled students against their teacher; {result['code']}; {result['machine']}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--teacher", default="default")
    ap.add_argument("--student", action="append", default=[], metavar="CHECKPOINT", help="repeatable")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--speech-s", type=float, default=60.0, help="speech for the cost (default 60)")
    ap.add_argument("--runs", type=int, default=3, help="cost runs per model and face, the median kept")
    ap.add_argument("--out", type=Path, default=RESULTS / "distill.json")
    ap.add_argument("--plot-only", type=Path, metavar="RESULTS.json", help="redraw RESULTS.png; measures nothing")
    args = ap.parse_args()
    if args.plot_only:
        plot(json.loads(args.plot_only.read_text()), args.plot_only.with_suffix(".png"))
        return 0
    if not ZEGGS.is_dir() or not SPEECH.is_file():
        raise SystemExit(f"needs ../shared/data (the ZEGGS clip and the unseen speech), not found at {SHARED}")
    from dimgestor.audio import SAMPLE_RATE, load_wav, save_wav
    from dimgestor.streaming.checkpoint import load_checkpoint

    folder = Path(tempfile.mkdtemp(prefix="distill-bench-"))
    audio = load_wav(SPEECH, SAMPLE_RATE)
    long_wav, short_wav = folder / "long.wav", folder / "short.wav"
    save_wav(long_wav, audio[: int(args.speech_s * SAMPLE_RATE)], SAMPLE_RATE)
    save_wav(short_wav, audio[: 2 * SAMPLE_RATE], SAMPLE_RATE)
    teacher = load_checkpoint(args.teacher).config
    plan = [(f"teacher, K={teacher.sample_steps}, guidance {teacher.guidance:g}", args.teacher, teacher.sample_steps,
             None)]
    students = [(s, load_checkpoint(s).config) for s in args.student]
    for k in sorted({c.sample_steps for _, c in students}):
        plan.append((f"teacher, K={k}, no guidance (not distilled)", args.teacher, k, 1.0))
    for s, c in students:
        plan.append((f"student {Path(s).name}, K={c.sample_steps}", s, c.sample_steps, None))
    rows = []
    for label, checkpoint, k, guidance in plan:
        row = {"label": label, "checkpoint": checkpoint, "steps": k, "guidance": guidance,
               **quality(checkpoint, k, guidance, args.seeds, folder)}
        if guidance is None:  # (a model as it serves: its own K and guidance)
            row.update(cost(checkpoint, long_wav, short_wav, args.speech_s, args.runs))
        rows.append(row)
        print(row, flush=True)
    result = {"what": "distilled students against their teacher: held-out quality and serving CPU per window",
              "when": utc_now(), "code": code_version(), "machine": describe_device("cpu"),
              "load_average": load_average(), "setup": {"seeds": args.seeds, "speech_s": args.speech_s,
                                                        "runs": args.runs, "window_ms": 100, "threads": 1},
              "models": rows}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
