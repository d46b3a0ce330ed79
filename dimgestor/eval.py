"""`dimgestor eval`: how a model's motion compares with real capture, per number of sampling steps K.

Per K (`--ks`, whole held-out stretches or whole WAV files): hand jerk and area under jerk (beside the
real capture's: the ratio is the jitter), speech/silence motion contrast, BeatAlign beside a
shuffled-audio baseline, FGD, diversity across seeds, net turn and turning speed. With `--wavs DIR`
(speech without motion) only the reference-free metrics are reported.

Systems, each scored on the held-out (valid) windows of a data folder:
  ground_truth        the real motion of each window (FGD 0 by definition: it is the reference set)
  model               the model driven by the window's audio
  model_other_audio   the model driven by the audio of a training window (mismatched speech)
  other_real_motion   real motion of a training window, scored against this window's audio
  mean_pose           the training mean pose held still (no root travel or turning)
The windowed systems below are scored at the first K. A metric means something only against these: BeatAlign of real but unrelated motion is the chance
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
from .features import HEADING_COLUMN, VELOCITY_COLUMNS, decode_features, heading_track

SYSTEMS = ("ground_truth", "model", "model_other_audio", "other_real_motion", "mean_pose")
METRICS = ("fgd_raw", "fgd_feature", "beat_align", "jerk", "mean_speed")


def body_frame(features: np.ndarray, spec) -> np.ndarray:
    """Features with the root's ground velocity and heading zeroed: the pose in the body's own frame."""
    f = np.array(features, dtype=np.float64)
    f[:, list(VELOCITY_COLUMNS) + [HEADING_COLUMN]] = 0.0
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


KMETRICS = ("jerk_ratio", "auj_ratio", "hand_jerk", "contrast", "beat_align", "beat_align_shuffled", "fgd_feature",
            "diversity", "net_yaw_deg", "max_yaw_deg", "yaw_speed_deg_s")


def clip_stats(raw: np.ndarray, audio: np.ndarray, skeleton, spec, sr: int = 16000) -> dict:
    """Reference-free numbers of one clip's raw features (T, D) made for `audio`."""
    fps = float(spec.fps)
    pos = joint_positions(raw, skeleton, spec)
    upper, hands = metrics.upper_body_joints(skeleton.names), metrics.hand_joints(skeleton.names)
    onsets = metrics.audio_onsets(audio, sr)
    shifted = (onsets + len(audio) / sr / 2) % (len(audio) / sr)  # the same onsets, half a clip away
    beats = metrics.motion_beats(pos[:, upper], fps)
    heading = np.degrees(heading_track(raw, spec))
    hand_speed = metrics.joint_speed(pos[:, hands], fps).mean(axis=1)
    return {"hand_jerk": metrics.jerk(pos[:, hands], fps), "auj": metrics.area_under_jerk(pos[:, upper], fps),
            "hand_speed": hand_speed, "mask": metrics.speech_mask(audio, sr, fps, len(raw)),
            "beat_hits": (metrics.beat_align(onsets, beats) * len(onsets)) if len(onsets) else 0.0,
            "beat_hits_shuffled": (metrics.beat_align(shifted, beats) * len(onsets)) if len(onsets) else 0.0,
            "n_onsets": len(onsets), "net_yaw_deg": float(heading[-1]),
            "yaw_speed_deg_s": float(np.abs(np.diff(heading)).mean() * fps) if len(heading) > 1 else 0.0,
            "max_yaw_deg": float(np.abs(heading).max()), "upper": pos[:, upper],
            "seconds": len(raw) / fps}


def pool_stats(stats: list[dict]) -> dict:
    """One line of numbers from the per-clip stats (pooled over clips, weighted by length or onsets)."""
    w = np.array([s["seconds"] for s in stats])
    onsets = sum(s["n_onsets"] for s in stats)
    speed, mask = np.concatenate([s["hand_speed"] for s in stats]), np.concatenate([s["mask"] for s in stats])
    return {"hand_jerk": float(np.average([s["hand_jerk"] for s in stats], weights=w)),
            "auj": float(np.average([s["auj"] for s in stats], weights=w)),
            "contrast": metrics.speech_contrast(speed, mask),
            "beat_align": sum(s["beat_hits"] for s in stats) / onsets if onsets else float("nan"),
            "beat_align_shuffled": sum(s["beat_hits_shuffled"] for s in stats) / onsets if onsets else float("nan"),
            "net_yaw_deg": float(np.mean([abs(s["net_yaw_deg"]) for s in stats])),
            "max_yaw_deg": float(np.mean([s["max_yaw_deg"] for s in stats])),
            "yaw_speed_deg_s": float(np.average([s["yaw_speed_deg_s"] for s in stats], weights=w))}


def k_report(bundle, clips: list[tuple[np.ndarray, np.ndarray | None]], ks: list[int], seeds: int, seed: int,
             ae: metrics.MotionAutoencoder | None, log=print, smoothing=None) -> dict:
    """{"reference": real motion's numbers or None, "per_k": {K: numbers}} over whole clips (audio, raw or None)."""
    from .stream import generate_offline

    skeleton, spec = bundle.skeleton, bundle.feature_spec
    has_ref = all(raw is not None for _, raw in clips)
    ref = [clip_stats(raw, audio, skeleton, spec) for audio, raw in clips] if has_ref else None
    real_chunks = np.concatenate([metrics.motion_chunks(raw, ae.chunk, 8) for _, raw in clips]) if has_ref and ae else None
    out = {"reference": pool_stats(ref) if ref else None, "per_k": {}}
    started = time.time()
    for K in ks:
        per_seed = []
        for j in range(seeds):
            gens = [np.asarray(bundle.denormalize(generate_offline(bundle.model, audio, steps=K, seed=seed + j,
                                                                   smoothing=smoothing)), np.float32)
                    for audio, _ in clips]
            per_seed.append(gens)
        stats = [clip_stats(g, audio, skeleton, spec) for g, (audio, _) in zip(per_seed[0], clips)]
        row = pool_stats(stats)
        upper = metrics.upper_body_joints(skeleton.names)
        ups = [[joint_positions(g, skeleton, spec)[:, upper] for g in gens] for gens in per_seed]
        pairs = [(a, b) for a in range(seeds) for b in range(a + 1, seeds)]
        # diversity: mean distance (file units) between the upper body of two seeds at the same moment
        row["diversity"] = float(np.mean([np.linalg.norm(ups[a][i] - ups[b][i], axis=-1).mean()
                                          for a, b in pairs for i in range(len(clips))])) if pairs else float("nan")
        if ref:
            r = out["reference"]
            row["jerk_ratio"] = row["hand_jerk"] / max(r["hand_jerk"], 1e-12)
            row["auj_ratio"] = row["auj"] / max(r["auj"], 1e-12)
            if ae is not None:
                chunks = np.concatenate([metrics.motion_chunks(g, ae.chunk, 8) for g in per_seed[0]])
                row["fgd_feature"] = metrics.feature_fgd(ae, real_chunks, chunks)
        out["per_k"][str(K)] = {m: row.get(m, float("nan")) for m in KMETRICS}
        log(f"K={K}: " + ", ".join(f"{m} {row.get(m, float('nan')):.3g}" for m in KMETRICS)
            + f" ({time.time() - started:.0f} s)")
    return out


def valid_clips(valid) -> list[tuple[np.ndarray, np.ndarray]]:
    """A split's whole stretches (the valid split: its held-out tails) as (audio, raw features)."""
    return [(np.asarray(valid.clips[c].audio[a * valid.spf:b * valid.spf], np.float32),
             np.asarray(valid.clips[c].features[a:b], np.float32)) for c, a, b in valid.segments]


def wav_clips(folder: Path) -> tuple[list[tuple[np.ndarray, None]], list[str]]:
    """Every WAV under `folder` (16 kHz mono after loading) as a clip without reference motion."""
    from .audio import load_wav

    paths = sorted(Path(folder).rglob("*.wav"))
    if not paths:
        raise ValueError(f"{folder}: no .wav files found")
    return [(load_wav(p), None) for p in paths], [str(p.relative_to(folder)) for p in paths]


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
    """Per-K panels (jerk ratio, contrast, BeatAlign, FGD, diversity, net turn) and, with reference motion,
    the windowed systems' bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = [int(k) for k in result.get("per_k", {})]
    panels = [] if not ks else [("jerk_ratio", "hand jerk / real (1 = real)"), ("contrast", "speech / silence wrist speed"),
              ("beat_align", "BeatAlign (dashed: shuffled audio)"), ("fgd_feature", "FGD (feature space)"),
              ("diversity", "diversity across seeds"), ("net_yaw_deg", "|net turn| per clip (deg)")]
    has_systems = "systems" in result
    rows = [r for r in ((panels and "k"), (has_systems and "s")) if r]
    ncols = max(len(panels), len(METRICS) if has_systems else 0)
    fig, axes = plt.subplots(len(rows), ncols, figsize=(3.0 * ncols, 3.2 * len(rows)), squeeze=False)
    k_axes, s_axes = (axes[0] if panels else []), (axes[-1] if has_systems else [])
    ref = result.get("reference") or {}
    for ax in list(k_axes)[len(panels):]:
        ax.axis("off")
    for ax, (m, title) in zip(k_axes, panels):
        xs = range(len(ks))  # evenly spaced: K = 1, 2, 4, 8
        ax.plot(xs, [result["per_k"][str(k)][m] for k in ks], "o-", color="#1f77b4", label="model")
        if m == "beat_align":
            ax.plot(xs, [result["per_k"][str(k)]["beat_align_shuffled"] for k in ks], "o--", color="#9ecae1")
        ref_key = {"jerk_ratio": None, "fgd_feature": None, "diversity": None}.get(m, m)
        if m == "jerk_ratio":
            ax.axhline(1.0, color="#555555", lw=1, label="real")
        elif ref_key in ref:
            ax.axhline(ref[ref_key], color="#555555", lw=1, label="real")
        ax.set_xticks(list(xs), [str(k) for k in ks])
        ax.set_xlabel("DDIM steps K")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
    if has_systems:
        systems = list(result["systems"])
        colors = ["#555555", "#1f77b4", "#9ecae1", "#ff7f0e", "#bbbbbb"]
        for ax, m in zip(s_axes, METRICS):
            values = [result["systems"][s][m] for s in systems]
            ax.bar(range(len(systems)), values, color=colors[: len(systems)])
            ax.set_xticks(range(len(systems)), systems, rotation=60, ha="right", fontsize=8)
            ax.set_title(f"{m} (K={result['steps']})" + (" lower is better" if m.startswith("fgd") else ""), fontsize=9)
            ax.grid(axis="y", alpha=0.3)
        for ax in list(s_axes)[len(METRICS):]:
            ax.axis("off")
    src = result.get("data") or result.get("wavs")
    if "steps" not in result:
        result = {**result, "steps": "?"}
    fig.suptitle(f"{result.get('checkpoint')} on {src} (smoothing {result.get('smooth_hz') or 'off'}"
                 f"{' Hz' if result.get('smooth_hz') else ''}, {result.get('seeds')} seeds)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def parse_ks(text: str | None, n_steps: int, default: int) -> list[int]:
    """--ks "1,2,4,8" -> [1, 2, 4, 8] (values above the model's chain dropped); None -> [default]."""
    if text is None:
        return [default]
    try:
        ks = [int(k) for k in text.split(",") if k.strip()]
    except ValueError:
        raise ValueError(f"--ks expects comma-separated step counts such as 1,2,4,8, got {text!r}") from None
    if not ks or any(k < 1 for k in ks):
        raise ValueError(f"--ks needs step counts >= 1, got {text!r}")
    kept = [k for k in ks if k <= n_steps]
    if not kept:
        raise ValueError(f"--ks {text}: the model has only {n_steps} diffusion steps")
    return kept


def run(args: argparse.Namespace) -> dict:
    from .checkpoint import load_checkpoint
    from .dataset import GestureDataset
    from .stream import smoothing_from_flag

    smoothing = smoothing_from_flag(getattr(args, "smooth", None))  # before anything slow
    if (args.data is None) == (getattr(args, "wavs", None) is None):
        raise ValueError("give --data (BVH+WAV pairs: every metric) or --wavs (speech only: reference-free metrics)")
    bundle = load_checkpoint(args.checkpoint)
    bundle.model.eval()
    if getattr(args, "guidance", None) is not None:  # every generation below takes the config's scale
        from .diffusion import check_guidance
        bundle.config = bundle.model.config = bundle.config.model_copy(update={"guidance": check_guidance(args.guidance)})
    c = bundle.config
    if args.steps is None:
        args.steps = c.sample_steps
    ks = parse_ks(getattr(args, "ks", None), c.n_steps, args.steps)
    smooth_hz = c.smooth_hz if smoothing == "config" else smoothing
    seeds = getattr(args, "seeds", 3)
    if getattr(args, "wavs", None) is not None:
        clips, names = wav_clips(Path(args.wavs))
        print(f"{len(clips)} WAV files, {sum(len(a) for a, _ in clips) / 16000:.1f} s: reference-free metrics only")
        rep = k_report(bundle, clips, ks, seeds, args.seed, None, smoothing=smoothing)
        return {"checkpoint": str(args.checkpoint or "embedded default"), "wavs": str(args.wavs), "files": names,
                "ks": ks, "seeds": seeds, "seed": args.seed, "smooth_hz": smooth_hz, "guidance": c.guidance,
                **rep, "notes": NOTES}
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
    gen = generate_systems(bundle, valid, train, ks[0], args.seed, args.max_windows, smoothing=smoothing)
    rep = k_report(bundle, valid_clips(valid), ks, seeds, args.seed, ae, smoothing=smoothing)
    result = {
        "checkpoint": str(args.checkpoint or "embedded default"), "data": str(data), "split": "valid",
        "n_windows": len(gen["audio"]), "window_s": valid.window / valid.fps, "windows": gen["labels"],
        "steps": ks[0], "ks": ks, "seeds": seeds, "seed": args.seed, "smooth_hz": smooth_hz, "guidance": c.guidance,
        "fgd_autoencoder": str(ae_path),
        "systems": score(gen["windows"], gen["audio"], bundle.skeleton, valid.spec, ae),
        **rep, "notes": NOTES,
    }
    return result


NOTES = {"fgd_reference": "the valid split's real motion (so ground_truth has FGD 0)",
         "fgd_raw": "Fréchet distance of per-frame motion features",
         "fgd_feature": "Fréchet distance of 34-frame chunk embeddings (GENEA-style conv autoencoder)",
         "beat_align": "mean over audio onsets of exp(-d^2/(2*0.3^2)), d to the nearest upper-body speed minimum",
         "beat_align_shuffled": "the same against the clip's onsets moved by half its length: the chance level",
         "jerk": "mean |d^3p/dt^3| of upper-body joint positions, root-relative in the body frame (file units/s^3)",
         "hand_jerk": "the same for the two wrists; jerk_ratio = model / real capture (1 = as smooth as real)",
         "auj": "area under the peak-jerk curve per second (upper body); auj_ratio = model / real",
         "contrast": "mean wrist speed during speech / during silence (0.75 s away from speech)",
         "diversity": "mean distance of the upper body between seeds at the same moment (file units)",
         "net_yaw_deg": "mean |net turn| of a whole clip (degrees); max_yaw_deg: its largest |heading| from the start; "
                        "yaw_speed_deg_s: mean turning speed",
         "mean_speed": "mean speed of the same joints (file units/s)"}


def print_table(result: dict) -> None:
    if "systems" in result:
        print(f"\n{'system (K=' + str(result['steps']) + ')':20s}" + "".join(f"{m:>13s}" for m in METRICS))
        for name, vals in result["systems"].items():
            print(f"{name:20s}" + "".join(f"{vals[m]:13.4g}" for m in METRICS))
    rows = [("real", result["reference"])] if result.get("reference") else []
    rows += [(f"K={k}", v) for k, v in result["per_k"].items()]
    print(f"\n{'':8s}" + "".join(f"{m:>20s}" for m in KMETRICS))
    for name, vals in rows:
        print(f"{name:8s}" + "".join(f"{vals.get(m, float('nan')):20.4g}" for m in KMETRICS))


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
    p.add_argument("--data", default=None, help="folder of NAME.bvh + NAME.wav pairs (its valid split is scored)")
    p.add_argument("--wavs", default=None, help="instead of --data: a folder of speech WAVs without motion "
                                                   "(reference-free metrics only)")
    p.add_argument("--steps", type=int, default=None, help="DDIM steps K (default: the checkpoint's sample_steps)")
    p.add_argument("--ks", default=None, metavar="K,K,...",
                   help="report these step counts, e.g. 1,2,4,8 (default: --steps alone)")
    p.add_argument("--seeds", type=int, default=3, help="seeds per K (diversity is measured between them)")
    p.add_argument("--guidance", type=float, default=None, metavar="S",
                   help="classifier-free guidance scale of every generation (default: the checkpoint's; 1 = unguided)")
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
    p = subparsers.add_parser("eval", help="jerk, speech contrast, BeatAlign, FGD, diversity and turning per K",
                              description=__doc__.split("\n\n")[0])
    add_arguments(p)
    p.set_defaults(func=main_from_args)
    return p
