"""Does the recipe get better with more data, and stay smooth as K rises? (synthetic speech and gestures)

Real paired data here is one 69 s clip; the full datasets are out of reach. `dimgestor.training.synthetic`'s
speech-and-gesture generator makes paired audio and motion at any length with a known rule (arms up while
speaking, a beat stroke on each stressed syllable, rest in pauses, idle sway). The `realtime` preset is
trained with the default recipe on 1, 10 and 60 minutes of it (same steps, seed and settings) and scored
on 3 held-out minutes from other seeds, per K, with the output filter off: hand jerk / ground truth,
speech/silence contrast (the rule's), BeatAlign, FGD and diversity.

    python benchmarks/data_scale.py                        # 1, 10, 60 min; ~1 h on 2 CPU cores
    python benchmarks/data_scale.py --minutes 1,10 --steps 400 --work /tmp/ds   # quicker
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from common import (RESULTS, code_version, describe_device, load_average, reference_line, save_panels, utc_now,
                    write_json)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", default="1,10,60")
    p.add_argument("--valid-minutes", type=float, default=3.0)
    p.add_argument("--steps", type=int, default=800, help="training steps per data size")
    p.add_argument("--preset", default="realtime")
    p.add_argument("--recipe", default="streaming")
    p.add_argument("--ks", default="1,2,4,8")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--work", default="runs/data_scale", help="data and runs (reused when present)")
    p.add_argument("--out", default=str(RESULTS / "data_scale.json"))
    p.add_argument("--train-only", action="store_true",
                   help="make the data and train, no scoring (run one per size in parallel, then again to score)")
    args = p.parse_args()
    import torch

    torch.set_num_threads(1)
    from dimgestor.evaluation.eval import fgd_autoencoder, k_report, parse_ks, valid_clips
    from dimgestor.streaming.checkpoint import latest_checkpoint, load_checkpoint
    from dimgestor.training.dataset import GestureDataset
    from dimgestor.training.synthetic import make_gesture_corpus
    from dimgestor.training.train import TrainConfig, train

    work = Path(args.work)
    valid_dir = work / "valid"
    if not (valid_dir / "clip_000.wav").is_file():
        make_gesture_corpus(valid_dir, args.valid_minutes, seed=999)
    minutes = [float(m) for m in args.minutes.split(",")]
    results, ae, valid = {}, None, None
    for m in minutes:
        data, run = work / f"train_{m:g}min", work / f"run_{m:g}min"
        if not (data / "clip_000.wav").is_file():
            make_gesture_corpus(data, m, seed=1)
        if latest_checkpoint(run) is None:
            started = time.time()
            train(TrainConfig(data=str(data), out=str(run), preset=args.preset, recipe=args.recipe,
                              max_steps=args.steps, batch_size=8, window_s=5.0, valid_fraction=0.05,
                              ckpt_every=args.steps, valid_every=max(args.steps // 4, 1), keep=1, seed=0,
                              mirror=m < 30, speeds=(0.9, 1.1) if m < 30 else (), progress=False))
            print(f"{m:g} min: trained {args.steps} steps in {time.time() - started:.0f} s")
        if args.train_only:
            continue
        bundle = load_checkpoint(run)
        bundle.model.eval()
        if valid is None:
            common = dict(spec=bundle.feature_spec, window_s=4.0)
            valid = GestureDataset(valid_dir, split="train", valid_fraction=0.0, **common)
            # one FGD feature extractor for every size: trained on the largest training set there is
            largest = max(work.glob("train_*min"), key=lambda d: float(d.name[6:-3]))
            ae = fgd_autoencoder(GestureDataset(largest, split="train", valid_fraction=0.0, **common),
                                 work / "fgd_autoencoder", 1500)
        clips = valid_clips(valid)
        ks = parse_ks(args.ks, bundle.config.n_steps, bundle.config.sample_steps)
        print(f"== {m:g} min")
        results[f"{m:g}"] = k_report(bundle, clips, ks, args.seeds, 0, ae, smoothing=None)
    if args.train_only:
        return 0
    write_json(Path(args.out), {
        "benchmark": "data_scale", "created": utc_now(), "code_version": code_version(),
        "device": describe_device("cpu"), "load_average": load_average(),
        "command": " ".join(["python", "benchmarks/data_scale.py"] + sys.argv[1:]), "preset": args.preset,
        "recipe": args.recipe, "train_steps": args.steps, "valid_minutes": args.valid_minutes,
        "output_filter": "off", "results": results})
    plot(results, Path(args.out).with_suffix(".png"))
    return 0


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    minutes = [float(m) for m in results]
    ks = list(next(iter(results.values()))["per_k"])
    panels = [("jerk_ratio", "hand jerk / ground truth"), ("contrast", "speech / silence wrist speed"),
              ("beat_align", "BeatAlign"), ("fgd_feature", "FGD (lower is better)"), ("diversity", "diversity (cm)")]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.3))
    for ax, (m, title) in zip(axes, panels):
        for k in ks:
            ax.plot(minutes, [results[f"{x:g}"]["per_k"][k][m] for x in minutes], "o-", label=f"K={k}")
        reference_line(ax, m, next(iter(results.values()))["reference"])
        ax.set_xscale("log")
        ax.set_xlabel("minutes of training data")
        ax.set_title(title, fontsize=9)
    save_panels(fig, axes, "synthetic speech and gestures: quality against data (black: ground truth), filter off", path)


if __name__ == "__main__":
    sys.exit(main())
