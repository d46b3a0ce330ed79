"""Synthetic BVH + WAV pairs for tests: gestures whose size follows the loudness of the speech.

The "speech" is bursts of harmonic tones (a voice-like source with syllable-rate amplitude
modulation) and a little noise, separated by silences. The arms swing, the forearms flex and the
head nods with an amplitude that follows the smoothed loudness, so a model can learn that loud
audio means large gestures and silence means rest. Everything is deterministic given the seed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dimgestor.bvh import BvhMotion, Skeleton

ROT = {o: [f"{a}rotation" for a in o] for o in ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")}
POS = ["Xposition", "Yposition", "Zposition"]

# name, parent, offset (cm, Y up, facing +Z, T-pose arms along +-X), rotation order
_JOINTS = [
    ("Hips", None, (0.0, 95.0, 0.0), "ZXY"),
    ("Spine", "Hips", (0.0, 10.0, 0.0), "ZXY"),
    ("Spine1", "Spine", (0.0, 15.0, -1.0), "ZXY"),
    ("Neck", "Spine1", (0.0, 20.0, 0.0), "ZXY"),
    ("Head", "Neck", (0.0, 10.0, 2.0), "ZXY"),
    ("LeftShoulder", "Spine1", (5.0, 17.0, 0.0), "XYZ"),
    ("LeftArm", "LeftShoulder", (12.0, 0.0, 0.0), "XYZ"),
    ("LeftForeArm", "LeftArm", (28.0, 0.0, 0.0), "ZYX"),
    ("LeftHand", "LeftForeArm", (25.0, 0.0, 0.0), "YXZ"),
    ("RightShoulder", "Spine1", (-5.0, 17.0, 0.0), "ZYX"),
    ("RightArm", "RightShoulder", (-12.0, 0.0, 0.0), "ZXY"),
    ("RightForeArm", "RightArm", (-28.0, 0.0, 0.0), "XYZ"),
    ("RightHand", "RightForeArm", (-25.0, 0.0, 0.0), "YZX"),
]
_END_SITES = {"Head": (0.0, 15.0, 0.0), "LeftHand": (10.0, 0.0, 0.0), "RightHand": (-10.0, 0.0, 0.0)}


def synthetic_skeleton() -> Skeleton:
    """13 joints: 6-channel hips, spine, neck, head and two arms with mixed rotation orders."""
    names = [j[0] for j in _JOINTS]
    return Skeleton(
        names=names,
        parents=[-1 if p is None else names.index(p) for _, p, _, _ in _JOINTS],
        offsets=np.array([o for _, _, o, _ in _JOINTS]),
        channels=[(POS if p is None else []) + ROT[order] for _, p, _, order in _JOINTS],
        end_sites={names.index(n): np.array(o) for n, o in _END_SITES.items()},
    )


def synthetic_speech(seconds: float, rate: int = 16000, seed: int = 0) -> np.ndarray:
    """Speech-like bursts (harmonic tones with syllable rhythm, some breath noise) and silences."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * rate))
    t = np.arange(n) / rate
    out = np.zeros(n)
    pos = int(rng.uniform(0.2, 0.6) * rate)  # start with a short silence
    while pos < n:
        length = min(int(rng.uniform(0.5, 1.6) * rate), n - pos)
        seg = slice(pos, pos + length)
        ts = t[seg] - t[pos]
        f0 = rng.uniform(110, 230) * (1 + 0.08 * np.sin(2 * np.pi * rng.uniform(0.5, 2) * ts))
        phase = 2 * np.pi * np.cumsum(f0) / rate
        voice = sum(np.sin(k * phase) / k for k in range(1, 9))
        syllables = np.sin(np.pi * rng.uniform(3.0, 5.0) * ts) ** 2  # ~4 syllables per second
        fade = np.minimum(1.0, np.minimum(ts, ts[-1] - ts) / 0.05)
        loud = rng.uniform(0.3, 1.0)
        out[seg] = loud * fade * syllables * (0.25 * voice + 0.05 * rng.standard_normal(length))
        pos += length + int(rng.uniform(0.25, 0.9) * rate)
    return (0.7 * out / max(np.abs(out).max(), 1e-9)).astype(np.float32)


def loudness_envelope(audio: np.ndarray, rate: int, fps: float, n_frames: int, smooth_s: float = 0.25) -> np.ndarray:
    """Per-frame RMS loudness, smoothed over `smooth_s` (centred) and scaled to [0, 1]."""
    t = (np.arange(n_frames) + 0.5) / fps
    hop = rate / fps
    cum = np.concatenate([[0.0], np.cumsum(audio.astype(np.float64) ** 2)])
    lo = np.clip(((t * rate) - hop).astype(int), 0, len(audio))
    hi = np.clip(((t * rate) + hop).astype(int), 0, len(audio))
    rms = np.sqrt((cum[hi] - cum[lo]) / np.maximum(hi - lo, 1))
    k = max(1, int(round(smooth_s * fps)))
    env = np.convolve(np.pad(rms, k, mode="edge"), np.ones(2 * k + 1) / (2 * k + 1), mode="same")[k:-k]
    return env / max(env.max(), 1e-9)


def synthetic_motion(seconds: float = 10.0, fps: float = 30.0, seed: int = 0, loudness: np.ndarray | None = None) -> BvhMotion:
    """Procedural motion at `fps`; gesture amplitude follows `loudness` (per frame, 0..1)."""
    rng = np.random.default_rng(seed + 1000)
    sk = synthetic_skeleton()
    n = int(round(seconds * fps))
    t = np.arange(n) / fps
    e = np.ones(n) * 0.5 if loudness is None else np.asarray(loudness, dtype=np.float64)[:n]
    ph = rng.uniform(0, 2 * np.pi, 8)
    sin = lambda f, p: np.sin(2 * np.pi * f * t + p)  # noqa: E731
    angles = {  # degrees, per joint in that joint's own channel order
        "Hips": (3 * sin(0.13, ph[0]), 2 * sin(0.21, ph[1]), 25 * sin(0.05, ph[2]) + 10 * t / max(seconds, 1e-9)),
        "Spine": (2 * sin(0.3, ph[3]), 6 * e, 3 * e * sin(0.7, ph[4])),
        "Spine1": (1.5 * sin(0.25, ph[5]), 3 * e, 2 * e * sin(0.5, ph[6])),
        "Neck": (0 * t, 4 * e * sin(1.1, ph[7]), 5 * sin(0.1, ph[0])),
        "Head": (2 * sin(0.4, ph[1]), 10 * e * sin(2.0, ph[2]), 8 * e * sin(0.9, ph[3])),
    }
    for side, sign, base in (("Left", 1.0, ph[4]), ("Right", -1.0, ph[5])):
        swing = e * sin(1.5, base)
        euler = {  # axis -> degrees; arms hang ~70 deg down from the T-pose and swing forward
            f"{side}Shoulder": {"X": 0 * t, "Y": -sign * 5 * e, "Z": sign * 8 * e},
            f"{side}Arm": {"X": 10 * swing, "Y": -sign * (15 + 35 * swing), "Z": -sign * (70 - 25 * e)},
            f"{side}ForeArm": {"X": 5 * swing, "Y": -sign * (15 + 60 * e), "Z": sign * 10 * e},
            f"{side}Hand": {"X": 20 * e * sin(2.2, base), "Y": 0 * t, "Z": 15 * e * sin(1.3, base)},
        }
        for name, by_axis in euler.items():
            order = sk.rotation_order(sk.index(name))
            angles[name] = tuple(by_axis[a] for a in order)
    root_pos = np.stack([6 * sin(0.07, ph[6]), 95 + 1.0 * sin(0.4, ph[7]) - 2 * e, 4 * sin(0.05, ph[0]) + 8 * t / max(seconds, 1e-9)], -1)
    cols = []
    for j, name in enumerate(sk.names):
        if j == 0:
            cols += [root_pos[:, 0], root_pos[:, 1], root_pos[:, 2]]
        cols += list(angles[name])
    return BvhMotion(sk, 1.0 / fps, np.stack(cols, -1))


def make_synthetic_pair(out_dir, name: str = "synth", seconds: float = 10.0, seed: int = 0,
                        fps: float = 30, rate: int = 16000) -> tuple[Path, Path]:
    """Write out_dir/NAME.bvh and out_dir/NAME.wav (PCM16 mono) of equal duration; returns their paths."""
    from dimgestor.audio import save_wav
    from dimgestor.bvh import write_bvh

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    audio = synthetic_speech(seconds, rate, seed)
    n = int(round(seconds * fps))
    motion = synthetic_motion(seconds, fps, seed, loudness_envelope(audio, rate, fps, n))
    bvh_path, wav_path = out_dir / f"{name}.bvh", out_dir / f"{name}.wav"
    write_bvh(bvh_path, motion)
    save_wav(wav_path, audio, rate)
    return bvh_path, wav_path
