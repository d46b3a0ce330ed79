"""Synthetic BVH + WAV pairs for tests: gestures whose size follows the loudness of the speech.

The "speech" is bursts of harmonic tones (a voice-like source with syllable-rate amplitude
modulation) and a little noise, separated by silences. The arms swing, the forearms flex and the
head nods with an amplitude that follows the smoothed loudness, so a model can learn that loud
audio means large gestures and silence means rest. Everything is deterministic given the seed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dimgestor.audio import SAMPLE_RATE
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


def synthetic_speech(seconds: float, rate: int = SAMPLE_RATE, seed: int = 0) -> np.ndarray:
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
                        fps: float = 30, rate: int = SAMPLE_RATE) -> tuple[Path, Path]:
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


# ---------------- speech and gestures with a known rule, at any length ----------------
#
# The rule a model must learn (and that tests and benchmarks can check):
#   * speech comes in phrases of syllables; some syllables are stressed (louder, higher, a consonant burst);
#   * while a phrase is spoken the arms come up into gesture space, and in pauses they return to rest;
#   * every stressed syllable launches a beat stroke of one or both hands: a minimum-jerk pulse that peaks
#     ~0.2 s after the syllable's onset, its size following the syllable's loudness;
#   * the spine, neck and head sway slowly all the time (idle motion), and the head nods on strokes.
# Every trajectory is a sum of smooth pulses and critically damped transitions, so speed and jerk are of the
# order of real capture's, not of a sine generator's.


def _min_jerk_pulse(u: np.ndarray) -> np.ndarray:
    """0 -> 1 -> 0 over u in [0, 1] with zero velocity and acceleration at both ends (64 u^3 (1-u)^3)."""
    v = np.clip(u, 0.0, 1.0)
    return 64.0 * v ** 3 * (1.0 - v) ** 3


def _critically_damped(target: np.ndarray, fps: float, tau: float) -> np.ndarray:
    """A critically damped second-order follower of `target` (time constant tau s): smooth, no overshoot."""
    from scipy.signal import lfilter

    a = np.exp(-1.0 / (fps * tau))  # two cascaded one-pole low-passes = a critically damped system
    y = lfilter([1 - a], [1, -a], target, zi=[a * target[0]])[0]
    return lfilter([1 - a], [1, -a], y, zi=[a * y[0]])[0]


def buzz_speech(seconds: float, rng: np.random.Generator, rate: int = SAMPLE_RATE) -> tuple[np.ndarray, dict]:
    """Buzz-syllable speech and its events: (audio, {"phrases": [(start, end)], "stresses": [(t, size)]})."""
    n_audio = int(round(seconds * rate))
    audio = np.zeros(n_audio)
    f0_speaker = rng.uniform(100, 220)
    phrases, stresses = [], []
    pos = rng.uniform(0.3, 1.2)
    while pos < seconds - 0.5:
        start, t = pos, pos
        for k in range(int(rng.integers(3, 12))):
            dur = rng.uniform(0.12, 0.26)
            if t + dur > seconds:
                break
            stressed = rng.random() < 0.35 or k == 0
            loud = rng.uniform(0.7, 1.0) if stressed else rng.uniform(0.25, 0.45)
            i0, i1 = int(t * rate), int((t + dur) * rate)
            ts = np.arange(i1 - i0) / rate
            f0 = f0_speaker * (1.15 if stressed else 1.0) * (1 - 0.1 * (t - start) / 3.0) * (1 + 0.05 * np.sin(9 * ts))
            phase = 2 * np.pi * np.cumsum(f0) / rate
            voice = sum(np.sin(h * phase) * np.exp(-((h * f0 - 700) / 900) ** 2) for h in range(1, 14))
            env = np.minimum(1.0, ts / 0.015) * np.minimum(1.0, (ts[-1] - ts) / 0.04) * np.exp(-ts / (dur * 1.5))
            seg = loud * env * voice / 3.0
            if stressed:  # a consonant burst makes the onset sharp
                burst = min(len(ts), int(0.025 * rate))
                seg[:burst] += loud * 0.6 * rng.standard_normal(burst) * np.linspace(1, 0, burst)
                stresses.append((t, loud))
            audio[i0:i1] += seg
            t += dur + rng.uniform(0.02, 0.09)
        phrases.append((start, t))
        pos = t + rng.uniform(0.4, 3.0)
    audio += 0.002 * rng.standard_normal(n_audio)  # room noise
    audio = (0.6 * audio / max(np.abs(audio).max(), 1e-9)).astype(np.float32)
    return audio, {"phrases": phrases, "stresses": stresses}


def gesture_motion(events: dict, n_frames: int, fps: float, rng: np.random.Generator,
                   engage_tau: float = 0.12) -> BvhMotion:
    """The rule's body motion for `events` (phrases [(start, end)] and stresses [(t, size)], seconds).

    Arms engage over each phrase (from 0.15 s before it to 0.1 s after), a minimum-jerk stroke of one or both
    hands starts 0.05 s before each stress (its length and hand drawn from rng), the head nods with it, and
    the trunk and head sway slowly with random phases (also from rng). engage_tau: the time constant (s) of
    the arms' rise into gesture space and return to rest.
    """
    n = n_frames
    time = np.arange(n) / fps
    speaking = np.zeros(n)
    for a, b in events["phrases"]:
        speaking[(time >= a - 0.15) & (time < b + 0.1)] = 1.0
    engage = _critically_damped(speaking, fps, engage_tau)  # arms up into gesture space while speaking
    stroke = {"Left": np.zeros(n), "Right": np.zeros(n)}
    nod = np.zeros(n)
    for t, loud in events["stresses"]:
        pulse = loud * _min_jerk_pulse((time - t + 0.05) / rng.uniform(0.4, 0.6))
        which = rng.choice(["Left", "Right", "both"], p=[0.35, 0.35, 0.3])
        for side in ("Left", "Right"):
            if which in (side, "both"):
                stroke[side] += pulse
        nod += 0.5 * pulse
    sk = synthetic_skeleton()
    ph = rng.uniform(0, 2 * np.pi, 12)
    sway = lambda f, p: np.sin(2 * np.pi * f * time + p)  # noqa: E731
    zero = 0 * time
    angles = {  # degrees, per joint in that joint's own channel order
        "Hips": (2 * sway(0.11, ph[0]), 1.5 * sway(0.17, ph[1]), 4 * sway(0.05, ph[2])),
        "Spine": (1.5 * sway(0.23, ph[3]) + 2 * engage, 2 * sway(0.13, ph[4]), 1.0 * sway(0.19, ph[5])),
        "Spine1": (1.0 * sway(0.29, ph[6]) + 1.5 * engage, 1.5 * sway(0.21, ph[7]), zero),
        "Neck": (zero, 3 * sway(0.15, ph[8]), 2 * sway(0.09, ph[9])),
        "Head": (1.5 * sway(0.31, ph[10]), 4 * nod + 2 * sway(0.27, ph[11]), 3 * sway(0.12, ph[0]) + 2 * engage),
    }
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        s, e = stroke[side], engage
        euler = {  # axis -> degrees: at rest the arms hang ~75 deg down; in gesture space the forearms come up
            f"{side}Shoulder": {"X": zero, "Y": -sign * 3 * e, "Z": sign * (4 * e + 3 * s)},
            f"{side}Arm": {"X": 6 * s, "Y": -sign * (8 + 22 * e + 18 * s), "Z": -sign * (75 - 20 * e - 12 * s)},
            f"{side}ForeArm": {"X": 4 * s, "Y": -sign * (10 + 55 * e + 30 * s), "Z": sign * 5 * e},
            f"{side}Hand": {"X": 12 * s, "Y": -sign * 6 * e, "Z": 8 * s},
        }
        for name, by_axis in euler.items():
            order = sk.rotation_order(sk.index(name))
            angles[name] = tuple(by_axis[a] for a in order)
    root_pos = np.stack([1.5 * sway(0.07, ph[1]), 95 + 0.5 * sway(0.2, ph[2]), 1.0 * sway(0.05, ph[3])], -1)
    cols = []
    for j, name in enumerate(sk.names):
        if j == 0:
            cols += [root_pos[:, 0], root_pos[:, 1], root_pos[:, 2]]
        cols += list(angles[name])
    return BvhMotion(sk, 1.0 / fps, np.stack(cols, -1))


def speech_and_gestures(seconds: float, seed: int = 0, rate: int = SAMPLE_RATE, fps: float = 30.0
                        ) -> tuple[np.ndarray, BvhMotion, dict]:
    """(audio, motion, events) following the rule above; events: phrases [(start, end)], stresses [(t, size)]."""
    rng = np.random.default_rng(seed)  # one stream: the speech's draws, then the motion's
    audio, events = buzz_speech(seconds, rng, rate)
    return audio, gesture_motion(events, int(round(seconds * fps)), fps, rng), events


def make_gesture_corpus(out_dir, minutes: float, clip_s: float = 60.0, seed: int = 0, fps: float = 30.0,
                        rate: int = SAMPLE_RATE) -> list[tuple[Path, Path]]:
    """Write `minutes` of speech_and_gestures as clip_NNN.bvh/.wav pairs of `clip_s` seconds (the last shorter)."""
    from dimgestor.audio import save_wav
    from dimgestor.bvh import write_bvh

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    total, paths, i = minutes * 60.0, [], 0
    while total > 1e-6:
        length = min(clip_s, total)
        audio, motion, _ = speech_and_gestures(length, seed=seed * 100003 + i, rate=rate, fps=fps)
        bvh, wav = out_dir / f"clip_{i:03d}.bvh", out_dir / f"clip_{i:03d}.wav"
        write_bvh(bvh, motion)
        save_wav(wav, audio, rate)
        paths.append((bvh, wav))
        total -= length
        i += 1
    return paths
