"""Which diffusion training recipe makes smooth, speech-driven motion at every K? (issue: recipe x K table)

Each candidate is trained on the same data with the same budget (the `realtime` preset, one CPU thread,
fixed seed), then `dimgestor eval`'s per-K report scores it on the held-out stretch with the output
filter OFF: hand jerk / real (1 = as smooth as real capture), speech/silence contrast, BeatAlign beside
its shuffled-audio baseline, FGD, diversity across seeds, net turn. The embedded model of the previous
release can be scored beside them as "before" (`--before CHECKPOINT`). Short chains are sampled with
"linspace" DDIM spacing (every K ends on the finest level), as the default recipe does.

    python benchmarks/recipes.py --data ../shared/data/zeggs_sample --valid-seconds 15 --steps 800
    python benchmarks/recipes.py --data DIR --only streaming --runs-dir runs/recipes   # one candidate

Runs already trained in --runs-dir are reused (delete them to retrain).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from common import (RESULTS, code_version, describe_device, load_average, reference_line, save_panels, utc_now,
                    write_json)

# name -> TrainConfig fields (everything else as in train_candidate). "streaming" is the default recipe.
CANDIDATES = {
    "x0_vel1_acc1": dict(recipe="streaming", heading="velocity", vel_weight=1.0, acc_weight=1.0, root_weight=0.0),
    "x0_vel1_acc1_noise5": dict(recipe="streaming", heading="velocity", vel_weight=1.0, acc_weight=1.0,
                                root_weight=0.0, overrides={"noise_taps": 5}),
    "x0_vel4_acc4": dict(recipe="streaming", heading="velocity", vel_weight=4.0, acc_weight=4.0, root_weight=0.0),
    "x0_vel4_acc4_root1": dict(recipe="streaming", heading="velocity", vel_weight=4.0, acc_weight=4.0, root_weight=1.0),
    "streaming": dict(recipe="streaming"),  # x0, vel/acc 4, facing heading, root 0.1
    "paper": dict(recipe="paper"),
}


def train_candidate(name: str, args, out: Path) -> Path:
    """The candidate's checkpoint after args.steps steps (trained here unless the run folder has it)."""
    from dimgestor.training.train import TrainConfig, train

    ckpt = out / f"ckpt_{args.steps:07d}"
    if (ckpt / "config.json").is_file():
        print(f"{name}: reusing {ckpt}")
        return ckpt
    opts = TrainConfig(data=args.data, out=str(out), preset="realtime", max_steps=args.steps, batch_size=8,
                       window_s=5.0, valid_seconds=args.valid_seconds, ckpt_every=args.steps,
                       valid_every=max(args.steps // 4, 1), keep=1, seed=0, mirror=args.mirror,
                       speeds=tuple(args.speeds), progress=False, **CANDIDATES[name])
    started = time.time()
    train(opts)
    print(f"{name}: trained {args.steps} steps in {time.time() - started:.0f} s")
    return ckpt


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="BVH+WAV folder (its held-out tail is scored)")
    p.add_argument("--valid-seconds", type=float, default=15.0)
    p.add_argument("--steps", type=int, default=800, help="training steps per candidate")
    p.add_argument("--ks", default="1,2,4,8")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--only", default=None, help="comma-separated candidate names (default: all)")
    p.add_argument("--runs-dir", default="runs/recipes")
    p.add_argument("--before", default=None, metavar="CHECKPOINT",
                   help="also score this checkpoint as 'before' (e.g. a copy of the previous embedded model)")
    p.add_argument("--no-mirror", dest="mirror", action="store_false")
    p.add_argument("--speeds", default="0.9,1.1", help="speed perturbation factors ('' = none)")
    p.add_argument("--out", default=str(RESULTS / "recipes.json"))
    args = p.parse_args()
    args.speeds = [float(r) for r in args.speeds.split(",") if r.strip()]
    import torch

    torch.set_num_threads(1)
    from dimgestor.evaluation.eval import fgd_autoencoder, k_report, parse_ks, valid_clips
    from dimgestor.streaming.checkpoint import load_checkpoint
    from dimgestor.training.dataset import GestureDataset

    names = args.only.split(",") if args.only else list(CANDIDATES)
    unknown = [n for n in names if n not in CANDIDATES]
    if unknown:
        p.error(f"unknown candidates {unknown}; choose from {', '.join(CANDIDATES)}")
    results, aes = {}, {}  # one FGD feature extractor per feature layout (velocity or facing heading)
    systems = [("before", args.before)] if args.before else []
    systems += [(n, train_candidate(n, args, Path(args.runs_dir) / n)) for n in names]
    for name, ckpt in systems:
        bundle = load_checkpoint(ckpt)
        bundle.model.eval()
        common = dict(spec=bundle.feature_spec, window_s=4.0, valid_seconds=args.valid_seconds)
        valid = GestureDataset(args.data, split="valid", **common)
        heading = bundle.feature_spec.heading
        if heading not in aes:
            aes[heading] = fgd_autoencoder(GestureDataset(args.data, split="train", **common), None, 1500)
        ae = aes[heading]
        if bundle.config.n_steps <= 16:  # short chains end every K on their finest level (the default's spacing)
            bundle.model.config = bundle.model.config.model_copy(update={"ddim_spacing": "linspace"})
        c = bundle.config = bundle.model.config
        ks = parse_ks(args.ks, c.n_steps, c.sample_steps)
        print(f"== {name}: {c.n_steps} {c.schedule} steps, predicts {c.prediction}, noise over {c.noise_taps} frames")
        rep = k_report(bundle, valid_clips(valid), ks, args.seeds, 0, ae, smoothing=None)
        results[name] = {"config": {k: getattr(c, k) for k in ("n_steps", "schedule", "prediction", "noise_taps",
                                                               "ddim_spacing")},
                         "heading": bundle.feature_spec.heading,
                         "training": bundle.info.get("options", {}), **rep}
    write_json(Path(args.out), {
        "benchmark": "recipes", "created": utc_now(), "code_version": code_version(), "device": describe_device("cpu"),
        "load_average": load_average(), "command": " ".join(["python", "benchmarks/recipes.py"] + sys.argv[1:]),
        "data": args.data, "valid_seconds": args.valid_seconds, "train_steps": args.steps,
        "augmentation": {"mirror": args.mirror, "speeds": args.speeds}, "output_filter": "off",
        "fgd_note": "FGD compares only between candidates of the same heading layout (one feature extractor each)",
        "results": results})
    plot(results, Path(args.out).with_suffix(".png"))
    return 0


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("jerk_ratio", "hand jerk / real capture (1 = real)", True), ("contrast", "speech / silence wrist speed", False),
              ("beat_align", "BeatAlign", False), ("fgd_feature", "FGD (feature space)", True),
              ("diversity", "diversity across seeds (cm)", True), ("net_yaw_deg", "|net turn| over the clip (deg)", True)]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.4))
    for ax, (m, title, log) in zip(axes, panels):
        for name, r in results.items():
            ks = [int(k) for k in r["per_k"]]
            ax.plot(ks, [r["per_k"][str(k)][m] for k in ks], "o-", label=name)
        reference_line(ax, m, next(iter(results.values())).get("reference"))
        if log:
            ax.set_yscale("log")
        ax.set_xscale("log", base=2)
        ax.set_xlabel("DDIM steps K")
        ax.set_title(title, fontsize=9)
    save_panels(fig, axes, "recipe x K, output filter off (black: real capture)", path)


if __name__ == "__main__":
    sys.exit(main())
