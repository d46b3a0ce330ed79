"""Does classifier-free guidance make the motion follow the speech more? (synthetic speech and gestures)

`dimgestor.training.synthetic`'s generator makes paired audio and motion with a known rule (arms up while speaking,
a stroke on each stressed syllable, rest in pauses). The `realtime` preset is trained with the default recipe
on the same data, steps and seed with each condition-dropout probability, then scored on held-out minutes
(another seed) at each guidance scale and K, filter off: speech/silence wrist-speed contrast (the rule's own
beside it), BeatAlign against the same onsets shifted by half a clip (chance), hand jerk / ground truth.

    python benchmarks/guidance_quality.py                                   # ~40 min on 2 busy CPU cores
    python benchmarks/guidance_quality.py --drops 0,0.2 --train-only --only-drop 0.2   # one run, to parallelize
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from common import RESULTS, code_version, describe_device, load_average, save_panels, utc_now, write_json

SHOWN = ("contrast", "beat_align", "beat_align_shuffled", "jerk_ratio", "diversity")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=10.0, help="synthetic training data")
    p.add_argument("--valid-minutes", type=float, default=3.0)
    p.add_argument("--steps", type=int, default=400, help="training steps per run")
    p.add_argument("--drops", default="0,0.2", help="condition-dropout probabilities, one run each")
    p.add_argument("--scales", default="1,1.5,2,3", help="guidance scales scored")
    p.add_argument("--ks", default="4")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--preset", default="realtime")
    p.add_argument("--work", default="runs/guidance_quality", help="data and runs (reused when present)")
    p.add_argument("--out", default=str(RESULTS / "guidance_quality.json"))
    p.add_argument("--train-only", action="store_true")
    p.add_argument("--only-drop", type=float, default=None, help="train just this one of --drops")
    args = p.parse_args()
    import torch

    torch.set_num_threads(1)
    from dimgestor.evaluation.eval import k_report, parse_ks, valid_clips
    from dimgestor.streaming.checkpoint import latest_checkpoint, load_checkpoint
    from dimgestor.training.dataset import GestureDataset
    from dimgestor.training.synthetic import make_gesture_corpus
    from dimgestor.training.train import TrainConfig, train

    work = Path(args.work)
    data, valid_dir = work / f"train_{args.minutes:g}min", work / "valid"
    if not (valid_dir / "clip_000.wav").is_file():
        make_gesture_corpus(valid_dir, args.valid_minutes, seed=999)
    if not (data / "clip_000.wav").is_file():
        make_gesture_corpus(data, args.minutes, seed=1)
    drops = [float(x) for x in args.drops.split(",")]
    scales = [float(x) for x in args.scales.split(",")]
    results, train_s, valid = {}, {}, None
    for drop in drops:
        if args.only_drop is not None and drop != args.only_drop:
            continue
        run = work / f"run_drop{drop:g}"
        if latest_checkpoint(run) is None:
            started = time.time()
            train(TrainConfig(data=str(data), out=str(run), preset=args.preset, max_steps=args.steps, batch_size=8,
                              window_s=5.0, valid_fraction=0.05, ckpt_every=args.steps,
                              valid_every=max(args.steps // 4, 1), keep=1, seed=0, mirror=args.minutes < 30,
                              speeds=(0.9, 1.1) if args.minutes < 30 else (), progress=False, cond_drop=drop))
            train_s[f"{drop:g}"] = round(time.time() - started)
            print(f"cond_drop {drop:g}: trained {args.steps} steps in {train_s[f'{drop:g}']} s", flush=True)
        if args.train_only:
            continue
        bundle = load_checkpoint(run)
        bundle.model.eval()
        if valid is None:
            valid = GestureDataset(valid_dir, split="train", valid_fraction=0.0, spec=bundle.feature_spec, window_s=4.0)
        clips = valid_clips(valid)
        ks = parse_ks(args.ks, bundle.config.n_steps, bundle.config.sample_steps)
        per_scale = {}
        for s in scales if drop > 0 else [1.0]:  # a model never trained unconditionally has nothing to guide with
            bundle.model.config = bundle.config.model_copy(update={"guidance": s})
            print(f"== cond_drop {drop:g}, guidance {s:g}", flush=True)
            per_scale[f"{s:g}"] = k_report(bundle, clips, ks, args.seeds, 0, None, smoothing=None)
        results[f"{drop:g}"] = per_scale
    if args.train_only:
        return 0
    write_json(Path(args.out), {
        "benchmark": "guidance_quality", "created": utc_now(), "code_version": code_version(),
        "device": describe_device("cpu"), "load_average": load_average(),
        "command": " ".join(["python", "benchmarks/guidance_quality.py"] + sys.argv[1:]), "preset": args.preset,
        "recipe": "streaming", "train_minutes": args.minutes, "train_steps": args.steps, "train_wall_s": train_s,
        "valid_minutes": args.valid_minutes, "output_filter": "off", "results": results})
    plot(results, Path(args.out).with_suffix(".png"))
    return 0


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("contrast", "speech / silence wrist speed"), ("beat_align", "BeatAlign (dotted: shifted onsets)"),
              ("jerk_ratio", "hand jerk / ground truth"), ("diversity", "diversity (cm)")]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.3 * len(panels), 3.3))
    for ax, (m, title) in zip(axes, panels):
        for drop, per_scale in results.items():
            scales = [float(s) for s in per_scale]
            ks = list(next(iter(per_scale.values()))["per_k"])
            for k in ks:
                line, = ax.plot(scales, [per_scale[f"{s:g}"]["per_k"][k][m] for s in scales], "o-",
                                label=f"cond_drop {drop}, K={k}")
                if m == "beat_align":
                    ax.plot(scales, [per_scale[f"{s:g}"]["per_k"][k]["beat_align_shuffled"] for s in scales], ":",
                            color=line.get_color())
        ref = next(iter(next(iter(results.values())).values()))["reference"]
        if m == "jerk_ratio":
            ax.axhline(1.0, color="k", lw=1)
        elif ref and m in ref:
            ax.axhline(ref[m], color="k", lw=1)
        ax.set_xlabel("guidance scale")
        ax.set_title(title, fontsize=9)
    save_panels(fig, axes, "synthetic speech and gestures: guidance scale (black: the rule's ground truth), filter off",
                path)


if __name__ == "__main__":
    sys.exit(main())
