"""`dimgestor eval`: FGD (raw and feature space), BeatAlign and jerk of a model beside reference systems.

Systems, each scored on the held-out (valid) windows of a data folder:
  ground_truth        the real motion of each window (FGD 0 by definition: it is the reference set)
  model               the model driven by the window's audio
  model_other_audio   the model driven by the audio of a training window (mismatched speech)
  other_real_motion   real motion of a training window, scored against this window's audio
  mean_pose           the training mean pose held still (no root travel or turning)
A metric means something only against these: BeatAlign of real but unrelated motion is the chance
level, FGD of another real set is the natural gap between two samples of real motion.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np

from . import metrics
from .bvh import forward_kinematics
from .features import decode_features

SYSTEMS = ("ground_truth", "model", "model_other_audio", "other_real_motion", "mean_pose")
METRICS = ("fgd_raw", "fgd_feature", "beat_align", "jerk", "mean_speed")


def body_frame(features: np.ndarray, spec) -> np.ndarray:
    """Features with the root's ground velocity and turning zeroed: the pose in the body's own frame."""
    f = np.array(features, dtype=np.float64)
    f[:, [spec.columns.index(c) for c in ("root_dx", "root_dz", "root_dyaw")]] = 0.0
    return f


def joint_positions(features: np.ndarray, skeleton, spec) -> np.ndarray:
    """Raw motion features (T, D) -> joint positions (T, J, 3) relative to the root in the body frame, file units.

    Gestures, not travel: walking or turning would otherwise dominate the speeds BeatAlign and jerk see.
    """
    pose, _ = decode_features(body_frame(features, spec), skeleton, spec)
    n = pose.rotations.shape[0]
    translations = np.broadcast_to(skeleton.offsets, (n, skeleton.num_joints, 3)).copy()
    translations[:, 0] = pose.root_pos
    positions = forward_kinematics(skeleton, pose.rotations, translations)
    return positions - positions[:, :1]


def paired_train_windows(valid, train, n: int) -> list[int]:
    """n training-window indices of full length, evenly spread (deterministic)."""
    full = [k for k in range(len(train)) if train.windows[k][2] == valid.window]
    if not full:
        raise ValueError(f"the train split has no full {valid.window / valid.fps:g} s window for the "
                         "mismatched-audio and other-motion baselines; lower --window-s")
    return [full[int(i * len(full) / n)] for i in range(n)]


def generate_systems(bundle, valid, train, steps: int, seed: int, max_windows: int | None = None,
                     log=print, smoothing="config") -> dict:
    """{system: list of raw feature windows (W, D)} and the valid audio per window."""
    from .stream import generate_offline

    items = [valid[i] for i in range(len(valid)) if valid.windows[i][2] == valid.window]
    if not items:
        raise ValueError(f"no full {valid.window / valid.fps:g} s window in the valid split; lower --window-s")
    items = items[:max_windows] if max_windows else items
    partners = [train[k] for k in paired_train_windows(valid, train, len(items))]
    mean_pose = body_frame(np.asarray(bundle.mean)[None], valid.spec)[0].astype(np.float32)  # held still
    out = {name: [] for name in SYSTEMS}
    started = time.time()
    for i, (item, other) in enumerate(zip(items, partners)):
        W = len(item["motion"])
        out["ground_truth"].append(item["motion"])
        gen = generate_offline(bundle.model, item["audio"], steps=steps, seed=seed + i, smoothing=smoothing)
        out["model"].append(np.asarray(bundle.denormalize(gen), dtype=np.float32)[:W])
        gen = generate_offline(bundle.model, other["audio"], steps=steps, seed=seed + i, smoothing=smoothing)
        out["model_other_audio"].append(np.asarray(bundle.denormalize(gen), dtype=np.float32)[:W])
        out["other_real_motion"].append(other["motion"][:W])
        out["mean_pose"].append(np.broadcast_to(mean_pose, (W, mean_pose.size)).copy())
        log(f"window {i + 1}/{len(items)} ({item['name']} @ {item['start_frame'] / valid.fps:.1f} s) "
            f"generated, {time.time() - started:.0f} s")
    return {"windows": out, "audio": [it["audio"] for it in items],
            "labels": [f"{it['name']}@{it['start_frame']}" for it in items]}


def score(windows: dict, audio: list, skeleton, spec, ae: metrics.MotionAutoencoder, sr: int = 16000,
          chunk_stride: int = 8) -> dict:
    """Metric values per system; the valid ground truth is the FGD reference set."""
    fps = float(spec.fps)
    joints = metrics.upper_body_joints(skeleton.names)
    onsets = [metrics.audio_onsets(a, sr) for a in audio]
    real = windows["ground_truth"]
    real_frames = np.concatenate(real)
    real_chunks = np.concatenate([metrics.motion_chunks(w, ae.chunk, chunk_stride) for w in real])
    results = {}
    for name, wins in windows.items():
        pos = [joint_positions(w, skeleton, spec)[:, joints] for w in wins]
        # BeatAlign pooled over every onset of every window (a window's score weighs by its onsets)
        hits = [metrics.beat_align(o, metrics.motion_beats(p, fps)) * len(o) for o, p in zip(onsets, pos) if len(o)]
        n_onsets = sum(len(o) for o in onsets)
        chunks = np.concatenate([metrics.motion_chunks(w, ae.chunk, chunk_stride) for w in wins])
        results[name] = {
            "fgd_raw": metrics.fgd(real_frames, np.concatenate(wins)),
            "fgd_feature": metrics.feature_fgd(ae, real_chunks, chunks),
            "beat_align": float(sum(hits) / n_onsets) if n_onsets else float("nan"),
            "jerk": float(np.mean([metrics.jerk(p, fps) for p in pos])),
            "mean_speed": float(np.mean([metrics.joint_speed(p, fps).mean() for p in pos])),
        }
    return results


def fgd_autoencoder(train, path: Path | None, steps: int, log=print) -> metrics.MotionAutoencoder:
    """Load the FGD feature extractor from `path`, or train it on the train split's chunks and save it there."""
    if path is not None and (path / "fgd_autoencoder.json").is_file():
        ae = metrics.MotionAutoencoder.load(path)
        if ae.dim != train.motion_dim:
            raise ValueError(f"{path}: FGD autoencoder is for {ae.dim} features, the data has {train.motion_dim}")
        log(f"FGD autoencoder loaded from {path}")
        return ae
    chunks = np.concatenate([metrics.motion_chunks(np.asarray(train.clips[c].features[a:b]), 34, 4)
                             for c, a, b in train.segments])
    log(f"training the FGD autoencoder on {len(chunks)} chunks of 34 frames ({steps} steps)")
    ae = metrics.train_motion_autoencoder(chunks, steps=steps, log_every=max(steps // 5, 1))
    if path is not None:
        ae.save(path)
        log(f"FGD autoencoder saved to {path}")
    return ae


def default_ae_path(data_dir: Path, spec) -> Path:
    from .dataset import default_cache_dir

    key = hashlib.sha256(json.dumps([str(data_dir.resolve()), spec.to_dict()], sort_keys=True).encode()).hexdigest()
    return default_cache_dir().parent / "fgd" / key[:16]


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    systems = list(result["systems"])
    fig, axes = plt.subplots(1, len(METRICS), figsize=(3.2 * len(METRICS), 3.6))
    colors = ["#555555", "#1f77b4", "#9ecae1", "#ff7f0e", "#bbbbbb"]
    for ax, m in zip(axes, METRICS):
        values = [result["systems"][s][m] for s in systems]
        ax.bar(range(len(systems)), values, color=colors[: len(systems)])
        ax.set_xticks(range(len(systems)), systems, rotation=60, ha="right", fontsize=8)
        ax.set_title(m + (" (lower is better)" if m.startswith("fgd") else ""), fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"{result['checkpoint']} on {result['data']} ({result['split']}, {result['n_windows']} windows, "
                 f"K={result['steps']}, smoothing {result.get('smooth_hz') or 'off'}"
                 f"{' Hz' if result.get('smooth_hz') else ''})", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def run(args: argparse.Namespace) -> dict:
    from .checkpoint import load_checkpoint
    from .dataset import GestureDataset
    from .stream import smoothing_from_flag

    smoothing = smoothing_from_flag(getattr(args, "smooth", None))  # before anything slow
    bundle = load_checkpoint(args.checkpoint)
    bundle.model.eval()
    if args.steps is None:
        args.steps = bundle.config.sample_steps
    data = Path(args.data)
    common = dict(spec=bundle.feature_spec, window_s=args.window_s, valid_fraction=args.valid_fraction,
                  valid_seconds=getattr(args, "valid_seconds", None))
    valid = GestureDataset(data, split="valid", **common)
    train = GestureDataset(data, split="train", **common)
    if valid.spec.dim != bundle.model.config.motion_dim:
        raise ValueError(f"{data}: the data has {valid.spec.dim} feature columns, the checkpoint's model "
                         f"{bundle.model.config.motion_dim}; evaluate on data with the checkpoint's skeleton")
    if valid.window < 34:
        raise ValueError(f"--window-s {args.window_s} gives {valid.window} frames; feature-space FGD needs "
                         f"windows of at least 34 frames ({34 / valid.fps:g} s)")
    print(valid.summary())
    ae_path = Path(args.fgd_model) if args.fgd_model else default_ae_path(data, valid.spec)
    ae = fgd_autoencoder(train, ae_path, args.fgd_steps)
    gen = generate_systems(bundle, valid, train, args.steps, args.seed, args.max_windows, smoothing=smoothing)
    result = {
        "checkpoint": str(args.checkpoint or "embedded default"), "data": str(data), "split": "valid",
        "n_windows": len(gen["audio"]), "window_s": valid.window / valid.fps, "windows": gen["labels"],
        "steps": args.steps, "seed": args.seed, "smooth_hz": bundle.config.smooth_hz if smoothing == "config" else smoothing, "fgd_autoencoder": str(ae_path),
        "systems": score(gen["windows"], gen["audio"], bundle.skeleton, valid.spec, ae),
        "notes": {"fgd_reference": "the valid split's real motion (so ground_truth has FGD 0)",
                  "fgd_raw": "Fréchet distance of per-frame motion features",
                  "fgd_feature": "Fréchet distance of 34-frame chunk embeddings (GENEA-style conv autoencoder)",
                  "beat_align": "mean over audio onsets of exp(-d^2/(2*0.3^2)), d to the nearest upper-body speed minimum",
                  "jerk": "mean |d^3p/dt^3| of upper-body joint positions, root-relative in the body frame (file units/s^3)",
                  "mean_speed": "mean speed of the same joints (file units/s)"},
    }
    return result


def print_table(result: dict) -> None:
    print(f"\n{'system':20s}" + "".join(f"{m:>13s}" for m in METRICS))
    for name, vals in result["systems"].items():
        print(f"{name:20s}" + "".join(f"{vals[m]:13.4g}" for m in METRICS))


def main_from_args(args: argparse.Namespace) -> int:
    result = run(args)
    print_table(result)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    if args.plot:
        plot(result, Path(args.plot))
        print(f"wrote {args.plot}")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", default=None, help="checkpoint or run folder (default: the embedded model)")
    p.add_argument("--data", required=True, help="folder of NAME.bvh + NAME.wav pairs (its valid split is scored)")
    p.add_argument("--steps", type=int, default=None, help="DDIM steps K (default: the checkpoint's sample_steps)")
    p.add_argument("--smooth", type=float, default=None, metavar="HZ",
                   help="output filter cutoff in Hz, 0 = off (default: the checkpoint's setting)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--window-s", type=float, default=4.0, help="length of the scored windows (s)")
    p.add_argument("--valid-fraction", type=float, default=0.15,
                   help="held-out tail of each clip when the folder has no split file")
    p.add_argument("--valid-seconds", type=float, default=None,
                   help="held-out tail of each clip in seconds (overrides --valid-fraction)")
    p.add_argument("--max-windows", type=int, default=None, help="score at most this many valid windows")
    p.add_argument("--fgd-model", default=None,
                   help="folder of the FGD autoencoder: loaded if present, else trained on the train split and saved "
                        "(default: a cache folder keyed by the data folder and feature layout)")
    p.add_argument("--fgd-steps", type=int, default=1500, help="training steps of the FGD autoencoder")
    p.add_argument("--out", default="results.json", help="JSON output")
    p.add_argument("--plot", default=None, help="PNG bar chart of the metrics per system")


def register(subparsers) -> argparse.ArgumentParser:
    """Add the `eval` subcommand to the `dimgestor` CLI."""
    p = subparsers.add_parser("eval", help="FGD, BeatAlign and jerk of a checkpoint beside baselines",
                              description=__doc__.split("\n\n")[0])
    add_arguments(p)
    p.set_defaults(func=main_from_args)
    return p
