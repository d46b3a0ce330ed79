"""`dimgestor eval`: how a model's motion compares with real capture, per number of sampling steps K.

Per K (`--steps K,K,...`, whole held-out stretches or whole WAV files): hand jerk and area under jerk (beside the
real capture's: the ratio is the jitter), speech/silence motion contrast, BeatAlign beside a
shuffled-audio baseline, FGD, diversity across seeds, net turn and turning speed; and how much the hands
follow the speech, each beside its chance level: loudness coupling (beside circularly shifted audio),
onset alignment (beside onsets shuffled inside speech), wrist speed in speech over wrist speed in a 6 s
silence inserted into each clip; per K also one row per clip (the per-voice table). With `--wavs DIR`
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

from ..audio import SAMPLE_RATE
from ..bvh import forward_kinematics
from ..features import HEADING_COLUMN, VELOCITY_COLUMNS, decode_features, heading_track
from . import metrics

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
    from ..streaming.stream import generate_offline

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


def score(windows: dict, audio: list, skeleton, spec, ae: metrics.MotionAutoencoder, sr: int = SAMPLE_RATE,
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
            "diversity", "net_yaw_deg", "max_yaw_deg", "yaw_speed_deg_s") + (
            "coupling", "coupling_shifted", "coupling_shifted_sd", "coupling_above", "onset_align", "onset_shuffled",
            "silence_ratio", "nearest", "variety")
# the per-voice table (one row per clip, averaged over seeds): speech-drivenness, rest, smoothness
VOICE_METRICS = ("coupling", "coupling_seed_sd", "coupling_shifted", "coupling_shifted_sd", "coupling_above",
                 "onset_align", "onset_shuffled", "n_onsets", "onset_align_all", "onset_shuffled_all", "n_onsets_all",
                 "contrast", "speed_speech", "speed_silence", "silence_ratio", "hand_jerk", "nearest", "seconds")
SILENCE_S = 6.0  # the silence inserted into each clip (issue 20's target: hands >= 3x calmer in it than in speech)


def drive_stats(hand_speed: np.ndarray, audio: np.ndarray, onsets: np.ndarray, mask: np.ndarray, fps: float,
                sr: int = SAMPLE_RATE, seed: int = 0) -> dict:
    """Speech-drivenness of one clip's hand speed (T,): loudness coupling beside shifted audio; hits of the
    stressed onsets (metrics.stressed_onsets) and of all `onsets` beside as many onsets shuffled inside speech
    (counts, so that clips pool by their onsets)."""
    mean, sd = metrics.shifted_coupling(hand_speed, audio, sr, fps)
    out = {"coupling": metrics.speech_coupling(hand_speed, audio, sr, fps), "coupling_shifted": mean,
           "coupling_shifted_sd": sd}
    for tag, times in (("", metrics.stressed_onsets(audio, sr)), ("_all", onsets)):
        shuffled = metrics.shuffled_onset_alignment(len(times), hand_speed, fps, mask == 1, seed=seed)
        out[f"n_onsets{tag or '_stressed'}"] = len(times)
        out[f"onset_hits{tag}"] = int(metrics.onset_hits(times, hand_speed, fps).sum())
        out[f"onset_hits{tag}_shuffled"] = shuffled * len(times) if len(times) else 0.0
    return out


def silence_probe(audio: np.ndarray, sr: int = SAMPLE_RATE, seconds: float = SILENCE_S) -> tuple[np.ndarray, float]:
    """The clip with `seconds` of digital silence inserted at its quietest frame in the middle third (a pause
    made longer, no word cut), and where (s)."""
    n = len(audio) / sr
    at = metrics.quietest_point(audio, sr, n / 3, 2 * n / 3)
    return metrics.insert_silence(audio, sr, at, seconds), at


def silence_stats(raw: np.ndarray, gapped: np.ndarray, at_s: float, skeleton, spec, sr: int = SAMPLE_RATE,
                  seconds: float = SILENCE_S) -> dict:
    """Mean wrist speed (file units/s) in speech and inside the inserted silence, of motion made for `gapped`."""
    fps = float(spec.fps)
    speed = metrics.hand_speed(joint_positions(raw, skeleton, spec), metrics.hand_joints(skeleton.names), fps)
    speaking, silent = metrics.inserted_silence_speeds(speed, gapped, sr, fps, at_s, seconds)
    return {"speed_speech": speaking, "speed_silence": silent}


def clip_stats(raw: np.ndarray, audio: np.ndarray, skeleton, spec, sr: int = SAMPLE_RATE, seed: int = 0) -> dict:
    """Reference-free numbers of one clip's raw features (T, D) made for `audio`."""
    fps = float(spec.fps)
    pos = joint_positions(raw, skeleton, spec)
    upper, hands = metrics.upper_body_joints(skeleton.names), metrics.hand_joints(skeleton.names)
    onsets = metrics.audio_onsets(audio, sr)
    shifted = (onsets + len(audio) / sr / 2) % (len(audio) / sr)  # the same onsets, half a clip away
    beats = metrics.motion_beats(pos[:, upper], fps)
    heading = np.degrees(heading_track(raw, spec))
    hand_speed = metrics.hand_speed(pos, hands, fps)
    mask = metrics.speech_mask(audio, sr, fps, len(raw))
    return {"hand_jerk": metrics.jerk(pos[:, hands], fps), "auj": metrics.area_under_jerk(pos[:, upper], fps),
            **drive_stats(hand_speed, audio, onsets, mask, fps, sr, seed), "hand_speed": hand_speed, "mask": mask,
            "beat_hits": (metrics.beat_align(onsets, beats) * len(onsets)) if len(onsets) else 0.0,
            "beat_hits_shuffled": (metrics.beat_align(shifted, beats) * len(onsets)) if len(onsets) else 0.0,
            "n_onsets": len(onsets), "net_yaw_deg": float(heading[-1]),
            "yaw_speed_deg_s": float(np.abs(np.diff(heading)).mean() * fps) if len(heading) > 1 else 0.0,
            "max_yaw_deg": float(np.abs(heading).max()), "upper": pos[:, upper],
            "seconds": len(raw) / fps}


def pool_stats(stats: list[dict]) -> dict:
    """One line of numbers from the per-clip stats (pooled over clips and seeds, weighted by length or onsets)."""
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


def _nanmean(values, weights=None) -> float:
    v = np.asarray(values, dtype=np.float64)
    w = np.ones_like(v) if weights is None else np.asarray(weights, dtype=np.float64)
    keep = np.isfinite(v)
    return float(np.average(v[keep], weights=w[keep])) if keep.any() else float("nan")


def voice_row(seed_stats: list[dict]) -> dict:
    """One clip's per-voice numbers from its clip_stats (+ silence_stats) under several seeds: means over seeds;
    coupling_above says whether the mean coupling clears the shifted-audio mean + 2 sd."""
    s = seed_stats
    onsets, every = s[0]["n_onsets_stressed"], s[0]["n_onsets_all"]
    row = {"coupling": _nanmean([x["coupling"] for x in s]),
           "coupling_seed_sd": float(np.std([x["coupling"] for x in s], ddof=1)) if len(s) > 1 else float("nan"),
           "coupling_shifted": _nanmean([x["coupling_shifted"] for x in s]),
           "coupling_shifted_sd": _nanmean([x["coupling_shifted_sd"] for x in s]),
           "onset_align": sum(x["onset_hits"] for x in s) / (onsets * len(s)) if onsets else float("nan"),
           "onset_shuffled": sum(x["onset_hits_shuffled"] for x in s) / (onsets * len(s)) if onsets else float("nan"),
           "onset_align_all": sum(x["onset_hits_all"] for x in s) / (every * len(s)) if every else float("nan"),
           "onset_shuffled_all": (sum(x["onset_hits_all_shuffled"] for x in s) / (every * len(s)) if every
                                  else float("nan")),
           "n_onsets": onsets, "n_onsets_all": every,
           "contrast": _nanmean([metrics.speech_contrast(x["hand_speed"], x["mask"]) for x in s]),
           "speed_speech": _nanmean([x.get("speed_speech", np.nan) for x in s]),
           "speed_silence": _nanmean([x.get("speed_silence", np.nan) for x in s]),
           "hand_jerk": _nanmean([x["hand_jerk"] for x in s]), "seconds": s[0]["seconds"],
           "nearest": _nanmean([x.get("nearest", np.nan) for x in s])}
    row["coupling_above"] = bool(row["coupling"] > row["coupling_shifted"] + 2 * row["coupling_shifted_sd"])
    row["silence_ratio"] = row["speed_speech"] / row["speed_silence"] if row["speed_silence"] > 0 else float("nan")
    return row


def pool_drive(rows: list[dict]) -> dict:
    """The per-K speech-drivenness numbers from the clips' voice_rows: coupling and its baseline weighted by
    length, onset alignment by onsets, coupling_above the fraction of clips above chance, silence ratio of the
    mean speeds."""
    w = [r["seconds"] for r in rows]
    onsets = [r["n_onsets"] for r in rows]
    speech, silence = _nanmean([r["speed_speech"] for r in rows], w), _nanmean([r["speed_silence"] for r in rows], w)
    return {"coupling": _nanmean([r["coupling"] for r in rows], w),
            "coupling_shifted": _nanmean([r["coupling_shifted"] for r in rows], w),
            "coupling_shifted_sd": _nanmean([r["coupling_shifted_sd"] for r in rows], w),
            "coupling_above": float(np.mean([r["coupling_above"] for r in rows])),
            "onset_align": _nanmean([r["onset_align"] for r in rows], onsets) if sum(onsets) else float("nan"),
            "onset_shuffled": _nanmean([r["onset_shuffled"] for r in rows], onsets) if sum(onsets) else float("nan"),
            "silence_ratio": speech / silence if silence > 0 else float("nan"),
            "nearest": _nanmean([r.get("nearest", np.nan) for r in rows], w)}


def generate_raw(bundle, audio: np.ndarray, steps: int, seed: int, smoothing=None, eta: float = 0.0) -> np.ndarray:
    """Raw (denormalized) features (T, D) the model makes for a whole clip (DDIM; eta > 0: stochastic)."""
    from ..streaming.stream import generate_offline

    gen = generate_offline(bundle.model, audio, steps=steps, seed=seed, smoothing=smoothing, eta=eta)
    return np.asarray(bundle.denormalize(gen), np.float32)


def seed_stats(bundle, audio: np.ndarray, steps: int, seed: int, smoothing=None, sr: int = SAMPLE_RATE,
               silence_s: float = SILENCE_S, reference_upper: np.ndarray | None = None,
               eta: float = 0.0) -> tuple[np.ndarray, dict]:
    """The model's motion for `audio` under one seed, and its clip_stats with the inserted-silence speeds (the
    model run again, same seed, on the clip with silence_s of silence inserted); with `reference_upper` (the
    training stretch's upper body, `upper_positions`) also `nearest`: the median distance of its 1 s windows to
    the nearest window of that stretch (`variety_distance`)."""
    raw = generate_raw(bundle, audio, steps, seed, smoothing, eta)
    stats = clip_stats(raw, audio, bundle.skeleton, bundle.feature_spec, sr, seed)
    if reference_upper is not None:
        stats["nearest"] = variety_distance(stats["upper"], reference_upper, float(bundle.feature_spec.fps))
    gapped, at = silence_probe(audio, sr, silence_s)
    stats.update(silence_stats(generate_raw(bundle, gapped, steps, seed, smoothing, eta), gapped, at, bundle.skeleton,
                               bundle.feature_spec, sr, silence_s), silence_at_s=at)
    return raw, stats


def voice_report(bundle, audio: np.ndarray, steps: int, seeds: int, seed: int = 0, smoothing=None,
                 reference_upper: np.ndarray | None = None, eta: float = 0.0) -> dict:
    """The per-voice row of one clip: voice_row over seeds seed .. seed + seeds - 1 (with `reference_upper`, the
    training stretch's upper body: its variety too)."""
    return voice_row([seed_stats(bundle, audio, steps, seed + j, smoothing, reference_upper=reference_upper, eta=eta)[1]
                      for j in range(seeds)])


def upper_positions(raw: np.ndarray, skeleton, spec) -> np.ndarray:
    """The upper body's joint positions (T, J, 3) of raw features, root-relative in the body frame (file units)."""
    return joint_positions(raw, skeleton, spec)[:, metrics.upper_body_joints(skeleton.names)]


def variety_distance(upper: np.ndarray, reference_upper: np.ndarray, fps: float) -> float:
    """Median over the 1 s windows of `upper` (every 0.25 s) of the distance to the nearest 1 s window of
    `reference_upper` (metrics.nearest_window_distances; file units). Over the real actor's own figure (her
    held-out motion against her training stretch) it is the `variety`: 1 = as far from the training motion as
    the actor herself strays when she goes on talking, below 1 = replaying what the model saw."""
    return float(np.median(metrics.nearest_window_distances(upper, reference_upper, fps)))


def k_report(bundle, clips: list[tuple[np.ndarray, np.ndarray | None]], ks: list[int], seeds: int, seed: int,
             ae: metrics.MotionAutoencoder | None, log=print, smoothing=None, names: list[str] | None = None,
             train_upper: list[np.ndarray] | None = None) -> dict:
    """{"reference": real motion's numbers or None, "per_k": {K: numbers}, "per_file": {K: {name: voice_row}}}
    over whole clips (audio, raw or None). With `train_upper` (the training stretches' upper body): `nearest`,
    the median distance of 1 s windows to the nearest training window, and `variety`, that over the real
    motion's own (`variety_distance`)."""
    names = names or [f"clip_{i}" for i in range(len(clips))]
    skeleton, spec = bundle.skeleton, bundle.feature_spec
    fps = float(spec.fps)
    has_ref = all(raw is not None for _, raw in clips)
    ref = [clip_stats(raw, audio, skeleton, spec) for audio, raw in clips] if has_ref else None
    if ref and train_upper:
        for r in ref:
            r["nearest"] = variety_distance(r["upper"], train_upper, fps)
    real_chunks = np.concatenate([metrics.motion_chunks(raw, ae.chunk, 8) for _, raw in clips]) if has_ref and ae else None
    out = {"reference": {**pool_stats(ref), **pool_drive([voice_row([r]) for r in ref])} if ref else None,
           "per_k": {}, "per_file": {}}
    real_nearest = out["reference"].get("nearest", float("nan")) if ref else float("nan")
    started = time.time()
    for K in ks:
        per_seed, clip_seed_stats = [], [[] for _ in clips]
        for j in range(seeds):
            gens = []
            for i, (audio, _) in enumerate(clips):
                raw, st = seed_stats(bundle, audio, K, seed + j, smoothing, reference_upper=train_upper)
                gens.append(raw)
                clip_seed_stats[i].append(st)
            per_seed.append(gens)
        stats = [s for per_clip in clip_seed_stats for s in per_clip]  # every seed's clips, pooled
        voices = [voice_row(s) for s in clip_seed_stats]
        out["per_file"][str(K)] = dict(zip(names, voices))
        row = {**pool_stats(stats), **pool_drive(voices)}
        row["variety"] = row["nearest"] / real_nearest if real_nearest > 0 else float("nan")
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
                row["fgd_feature"] = float(np.mean([metrics.feature_fgd(ae, real_chunks, np.concatenate(
                    [metrics.motion_chunks(g, ae.chunk, 8) for g in gens])) for gens in per_seed]))
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
    from ..audio import load_wav

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
    from ..training.dataset import default_cache_dir

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


def parse_ks(text: str | None, n_steps: int, default: int, flag: str = "--ks") -> list[int]:
    """`flag` "1,2,4,8" -> [1, 2, 4, 8] (values above the model's chain dropped); None -> [default]."""
    if text is None:
        return [default]
    try:
        ks = [int(k) for k in text.split(",") if k.strip()]
    except ValueError:
        raise ValueError(f"{flag} expects comma-separated step counts such as 1,2,4,8, got {text!r}") from None
    if not ks or any(k < 1 for k in ks):
        raise ValueError(f"{flag} needs step counts >= 1, got {text!r}")
    kept = [k for k in ks if k <= n_steps]
    if not kept:
        raise ValueError(f"{flag} {text}: the model has only {n_steps} diffusion steps")
    return kept


def run(args: argparse.Namespace) -> dict:
    from ..cli_help import smoothing_from_flag
    from ..streaming.checkpoint import load_checkpoint
    from ..training.dataset import GestureDataset

    smoothing = smoothing_from_flag(getattr(args, "smooth", None))  # before anything slow
    if (args.data is None) == (getattr(args, "wavs", None) is None):
        raise ValueError("give --data (BVH+WAV pairs: every metric) or --wavs (speech only: reference-free metrics)")
    bundle = load_checkpoint(args.checkpoint)
    bundle.model.eval()
    if getattr(args, "guidance", None) is not None:  # every generation below takes the config's scale
        from ..model.diffusion import check_guidance
        bundle.config = bundle.model.config = bundle.config.model_copy(update={"guidance": check_guidance(args.guidance)})
    c = bundle.config
    if args.steps is None:
        args.steps = c.sample_steps
    ks = parse_ks(getattr(args, "ks", None), c.n_steps, args.steps, flag="--steps")
    smooth_hz = c.smooth_hz if smoothing == "config" else smoothing
    seeds = getattr(args, "seeds", 3)
    if getattr(args, "wavs", None) is not None:
        clips, names = wav_clips(Path(args.wavs))
        print(f"{len(clips)} WAV files, {sum(len(a) for a, _ in clips) / SAMPLE_RATE:.1f} s: reference-free metrics only")
        rep = k_report(bundle, clips, ks, seeds, args.seed, None, smoothing=smoothing, names=names)
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
    clips = valid_clips(valid)
    names = [f"{valid.clips[c].name}@{a / valid.fps:.1f}s" for c, a, _ in valid.segments]
    train_upper = [upper_positions(raw, bundle.skeleton, valid.spec) for _, raw in valid_clips(train)]
    rep = k_report(bundle, clips, ks, seeds, args.seed, ae, smoothing=smoothing, names=names, train_upper=train_upper)
    result = {
        "checkpoint": str(args.checkpoint or "embedded default"), "data": str(data), "split": "valid",
        "n_windows": len(gen["audio"]), "window_s": valid.window / valid.fps, "windows": gen["labels"],
        "steps": ks[0], "ks": ks, "seeds": seeds, "seed": args.seed, "smooth_hz": smooth_hz, "guidance": c.guidance,
        "fgd_autoencoder": str(ae_path),
        "systems": score(gen["windows"], gen["audio"], bundle.skeleton, valid.spec, ae),
        **rep, "notes": NOTES,
    }
    return result


NOTES = {"seeds": "per K, every seed's clips are pooled (jerk, AUJ, contrast, BeatAlign, turns, the per-voice "
                  "measures); FGD is the mean of each seed's",
         "fgd_reference": "the valid split's real motion (so ground_truth has FGD 0)",
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
         "mean_speed": "mean speed of the same joints (file units/s)",
         "coupling": "Pearson r between wrist speed (relative to the hips) and loudness in dB per 50 ms frame, both "
                     "averaged over 0.5 s, best lag within +-0.2 s (metrics.speech_coupling); mean over seeds and clips",
         "coupling_shifted": "the same against the clip's audio circularly shifted by 20 offsets from 10% to 90% of "
                             "its length: the chance level (coupling_shifted_sd: their sd)",
         "coupling_above": "fraction of clips whose coupling > coupling_shifted + 2 coupling_shifted_sd",
         "onset_align": "fraction of stressed onsets (the strongest 40% of BeatAlign's speech onsets, "
                        "metrics.stressed_onsets) with a wrist-speed peak (local maximum above the clip mean) from "
                        "0.1 s before to 0.3 s after them (metrics.onset_alignment); onset_align_all: of all onsets",
         "onset_shuffled": "the same for as many onsets placed at random inside speech (10 seeded draws): chance",
         "silence_ratio": f"mean wrist speed in speech / inside {SILENCE_S:g} s of digital silence inserted at the "
                          "quietest frame of each clip's middle third (0.75 s at both ends of it left out)",
         "nearest": "median over 1 s windows of the upper body (every 0.25 s) of the distance to the nearest 1 s "
                    "window of the training split's real motion: mean joint distance, root-relative in the body "
                    "frame (file units; metrics.nearest_window_distances); the reference row's is the real held-out "
                    "motion's own",
         "variety": "nearest over the real held-out motion's nearest: 1 = as far from the training motion as the "
                    "actor's own unseen motion, below 1 = replaying what the model saw",
         "per_file": "per K, one row per clip (mean over seeds): coupling (coupling_seed_sd: its sd over seeds), "
                     "its baseline, onset alignment, contrast in natural pauses, wrist speed in speech and in the "
                     "inserted silence, wrist jerk"}


def print_table(result: dict) -> None:
    if "systems" in result:
        print(f"\n{'system (K=' + str(result['steps']) + ')':20s}" + "".join(f"{m:>13s}" for m in METRICS))
        for name, vals in result["systems"].items():
            print(f"{name:20s}" + "".join(f"{vals[m]:13.4g}" for m in METRICS))
    rows = [("real", result["reference"])] if result.get("reference") else []
    rows += [(f"K={k}", v) for k, v in result["per_k"].items()]
    print_rows(rows, KMETRICS, 8)
    for k, files in result.get("per_file", {}).items():
        print(f"\nper file, K={k} (mean over {result.get('seeds')} seeds)")
        print_rows(list(files.items()), VOICE_METRICS, max([len(n) for n in files] + [8]))


def print_rows(rows: list[tuple[str, dict]], columns, first: int) -> None:
    """A plain table: one line per (name, values), a column per metric as wide as its name."""
    width = {m: max(len(m) + 2, 9) for m in columns}
    print(f"{'':{first}s}" + "".join(f"{m:>{width[m]}s}" for m in columns))
    for name, vals in rows:
        cells = []
        for m in columns:
            v = vals.get(m, float("nan"))
            cells.append(f"{str(v):>{width[m]}s}" if isinstance(v, bool) else f"{v:{width[m]}.3g}")
        print(f"{name:{first}s}" + "".join(cells))


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
    from ..cli_help import deprecated_alias

    g = p.add_argument_group("what to score")
    g.add_argument("--checkpoint", default=None, help="checkpoint or run folder (default: the embedded model)")
    g.add_argument("--data", default=None, metavar="DIR",
                   help="folder of NAME.bvh + NAME.wav pairs (its valid split is scored)")
    g.add_argument("--wavs", default=None, metavar="DIR", help="instead of --data: a folder of speech WAVs without "
                                                                "motion (reference-free metrics only)")
    g.add_argument("--window-s", type=float, default=4.0, metavar="S", help="length of the scored windows, in seconds")
    g.add_argument("--valid-fraction", type=float, default=0.15, metavar="F",
                   help="held-out tail of each clip when the folder has no split file")
    g.add_argument("--valid-seconds", type=float, default=None, metavar="S",
                   help="held-out tail of each clip in seconds (overrides --valid-fraction)")
    g.add_argument("--max-windows", type=int, default=None, metavar="N",
                   help="score at most this many valid windows (default: all)")
    g = p.add_argument_group("sampling")
    steps = g.add_argument("--steps", dest="ks", default=None, metavar="K[,K,...]",
                           help="DDIM steps K, or several to report each, e.g. 1,2,4,8 (default: the checkpoint's "
                                "sample_steps)")
    deprecated_alias(p, "--ks", steps, note=" (it takes the same K,K,...)")
    p.set_defaults(steps=None)  # (the first of --steps; run() fills in the checkpoint's)
    g.add_argument("--seeds", type=int, default=3, metavar="N", help="seeds per K (diversity is measured between them)")
    g.add_argument("--seed", type=int, default=0, help="first noise seed (the others follow it)")
    g.add_argument("--guidance", type=float, default=None, metavar="S",
                   help="classifier-free guidance scale of every generation (default: the checkpoint's; 1 = unguided)")
    g.add_argument("--smooth", type=float, default=None, metavar="HZ",
                   help="output filter cutoff in Hz, 0 = off (default: the checkpoint's setting)")
    g = p.add_argument_group("FGD feature extractor")
    g.add_argument("--fgd-model", default=None, metavar="DIR",
                   help="folder of the FGD autoencoder: loaded if present, else trained on the train split and saved "
                        "(default: a cache folder keyed by the data folder and feature layout)")
    g.add_argument("--fgd-steps", type=int, default=1500, metavar="N", help="training steps of the FGD autoencoder")
    g = p.add_argument_group("outputs")
    g.add_argument("--out", default="results.json", metavar="FILE.json", help="JSON output")
    g.add_argument("--plot", default=None, metavar="FILE.png", help="PNG bar chart of the metrics per system")


def register(subparsers) -> argparse.ArgumentParser:
    """Add the `eval` subcommand to the `dimgestor` CLI."""
    from ..cli_help import examples

    p = subparsers.add_parser("eval", help="jerk, speech contrast, BeatAlign, FGD, diversity and turning per K",
                              description=__doc__.split("\n\n")[0],
                              epilog=examples("dimgestor eval --data my_data --out results.json",
                                              "dimgestor eval --data my_data --steps 1,2,4,8 --plot results.png",
                                              "dimgestor eval --wavs other_voices --checkpoint live --steps 4",
                                              deprecated="--ks K,K,... (now --steps K,K,...)"))
    add_arguments(p)
    p.set_defaults(func=main_from_args)
    return p
