"""SMPL-X motion as BEAT2 ships it: one `.npz` per take beside its `.wav`, read into and written from a `BvhMotion`
on a SMPL-X skeleton (the 55 joints of the body model, in its order).

A take holds `poses` (frames x 165: 55 joints x axis-angle, radians; joint 0's is the global orientation),
`trans` (frames x 3, metres), `betas` (the body's shape), `expressions` (FLAME), `model`, `gender` and
`mocap_frame_rate`. SMPL-X's rest pose is a T-pose whose every joint frame is the world's (Y up, facing +Z, the
body's left at +X), so a joint's local rotation is its axis-angle as it stands, and its offset is its rest
position less its parent's. The pelvis of a posed body is at its rest position plus `trans`.

The skeleton: with the user's own body-model file (`SMPLX_NEUTRAL_2020.npz`, licensed by its authors and never
shipped here), the exact joints of the take's betas (`body_model_joints`); without it, `GENERIC_REST`, a generic
adult of 1.70 m built here from published segment proportions. Rotations are the same either way (they are what
the model learns); joint positions differ by the body's proportions, and the pelvis of the generic skeleton rests
at the origin, so a take read without the body model sits where `trans` alone puts it.

The BVH side is in centimetres (as the ZEGGS and BEAT captures), each joint with Z, X, Y rotation channels and the
pelvis with positions too.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dimgestor import rotations as R
from dimgestor.bvh import BvhMotion, Skeleton

__all__ = ["JOINTS", "PARENTS", "BVH_ORDER", "GENERIC_REST", "SmplxError", "skeleton", "body_model_joints", "read_smplx",
           "write_smplx", "is_smplx", "CM"]

_FINGERS = ("index", "middle", "pinky", "ring", "thumb")
JOINTS = ["pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
          "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
          "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw",
          "left_eye", "right_eye"] + [f"{side}_{finger}{k}" for side in ("left", "right") for finger in _FINGERS
                                      for k in (1, 2, 3)]
PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15] + [
    p for wrist, first in ((20, 25), (21, 40)) for f in range(5) for p in (wrist, first + 3 * f, first + 3 * f + 1)]
CM = 100.0  # BVH units per metre


def _depth_first() -> list[int]:
    order, stack = [], [0]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed([k for k, p in enumerate(PARENTS) if p == j]))
    return order


# The skeleton's joints in BVH's order (each joint's subtree follows it): SMPL-X's indices, in that order
BVH_ORDER = _depth_first()


def _generic_rest() -> np.ndarray:
    """(55, 3) rest joint positions in metres of a 1.70 m adult in SMPL-X's T-pose, pelvis at the origin.

    Segment lengths as fractions of stature H from anthropometry's standard tables (Drillis and Contini's: thigh
    0.245 H, shank 0.246 H, upper arm 0.186 H, forearm 0.146 H, hand 0.108 H; shoulder width 0.259 H), the trunk's
    joints spaced as SMPL-X places them (three spine joints, neck, head), fingers from the hand's length.
    """
    H = 1.70
    thigh, shank, upper_arm, forearm = 0.245 * H, 0.246 * H, 0.186 * H, 0.146 * H
    p = {"pelvis": (0.0, 0.0, 0.0), "spine1": (0.0, 0.10, -0.01), "spine2": (0.0, 0.21, 0.0),
         "spine3": (0.0, 0.26, 0.01), "neck": (0.0, 0.45, -0.02), "head": (0.0, 0.53, 0.01),
         "jaw": (0.0, 0.52, 0.06), "left_eye": (0.032, 0.59, 0.08), "right_eye": (-0.032, 0.59, 0.08)}
    shoulder_x, shoulder_y = 0.259 * H / 2 - 0.06, 0.385
    for side, s in (("left", 1.0), ("right", -1.0)):
        hip = np.array([0.08 * s, -0.09, 0.0])
        knee = hip + (0.01 * s, -thigh, 0.0)
        ankle = knee + (0.0, -shank, -0.03)
        p[f"{side}_hip"], p[f"{side}_knee"], p[f"{side}_ankle"] = hip, knee, ankle
        p[f"{side}_foot"] = ankle + (0.01 * s, -0.055, 0.12)
        p[f"{side}_collar"] = (0.07 * s, 0.37, -0.01)
        shoulder = np.array([shoulder_x * s, shoulder_y, -0.01])
        elbow = shoulder + (upper_arm * s, 0.0, 0.0)
        wrist = elbow + (forearm * s, 0.0, 0.0)
        p[f"{side}_shoulder"], p[f"{side}_elbow"], p[f"{side}_wrist"] = shoulder, elbow, wrist
        # (first joint from the wrist, then the two phalanx lengths; fingers spread across z, palm down)
        fingers = {"index": ((0.090, -0.005, 0.025), 0.035, 0.022), "middle": ((0.095, -0.005, 0.005), 0.040, 0.025),
                   "ring": ((0.088, -0.007, -0.015), 0.037, 0.024), "pinky": ((0.078, -0.010, -0.034), 0.028, 0.018)}
        for finger, (base, a, b) in fingers.items():
            first = wrist + np.array(base) * (s, 1, 1)
            p[f"{side}_{finger}1"], p[f"{side}_{finger}2"] = first, first + (a * s, 0.0, 0.0)
            p[f"{side}_{finger}3"] = first + ((a + b) * s, 0.0, 0.0)
        thumb = wrist + np.array((0.025 * s, -0.015, 0.030))
        direction = np.array((0.7 * s, 0.0, 0.7))
        p[f"{side}_thumb1"], p[f"{side}_thumb2"] = thumb, thumb + 0.035 * direction
        p[f"{side}_thumb3"] = thumb + 0.065 * direction
    return np.array([p[name] for name in JOINTS], dtype=np.float64)


GENERIC_REST = _generic_rest()


class SmplxError(ValueError):
    """A file that is not a SMPL-X take (or body model) as this module reads it; the message names the file."""


def skeleton(rest: np.ndarray | None = None) -> Skeleton:
    """The SMPL-X skeleton in centimetres from rest joint positions (55, 3) in metres (default: `GENERIC_REST`)."""
    rest = GENERIC_REST if rest is None else np.asarray(rest, dtype=np.float64)
    at = {j: i for i, j in enumerate(BVH_ORDER)}  # SMPL-X index -> the skeleton's
    offsets = np.array([rest[j] - (rest[PARENTS[j]] if PARENTS[j] >= 0 else 0.0) for j in BVH_ORDER]) * CM
    rot = ["Zrotation", "Xrotation", "Yrotation"]
    channels = [["Xposition", "Yposition", "Zposition", *rot]] + [list(rot) for _ in JOINTS[1:]]
    # an End Site past each leaf, along its bone (the viewers draw the last segment from it)
    end_sites = {at[j]: offsets[at[j]] * 0.5 for j in range(len(JOINTS)) if j not in PARENTS}
    return Skeleton([JOINTS[j] for j in BVH_ORDER], [at[PARENTS[j]] if PARENTS[j] >= 0 else -1 for j in BVH_ORDER],
                    offsets, channels, end_sites)


def is_smplx(sk: Skeleton) -> bool:
    """Whether a skeleton is SMPL-X's: its 55 joints by name, each under its SMPL-X parent (in any file order)."""
    if sorted(sk.names) != sorted(JOINTS):
        return False
    return all((sk.names[p] if p >= 0 else None) == (JOINTS[PARENTS[JOINTS.index(n)]] if n != "pelvis" else None)
               for n, p in zip(sk.names, sk.parents))


def _smplx_index(sk: Skeleton) -> list[int]:
    """For each SMPL-X joint in its order, its index in `sk` (a SMPL-X skeleton in any file order)."""
    return [sk.index(name) for name in JOINTS]


def body_model_joints(path: str | Path, betas: np.ndarray | None = None) -> np.ndarray:
    """(55, 3) rest joint positions in metres of a SMPL-X body-model file (`v_template`, `shapedirs`,
    `J_regressor`) shaped by `betas` (as many as given, up to the file's shape components)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as f:
            template = np.asarray(f["v_template"], np.float64)
            regressor = np.asarray(f["J_regressor"], np.float64)
            shapedirs = np.asarray(f["shapedirs"], np.float64) if "shapedirs" in f.files else None
    except KeyError as e:
        raise SmplxError(f"{path}: not a SMPL-X body model (no {e.args[0]!r})") from None
    except (OSError, ValueError) as e:
        raise SmplxError(f"{path}: not a SMPL-X body model ({e})") from None
    if template.ndim != 2 or template.shape[1] != 3 or regressor.shape != (len(JOINTS), len(template)):
        raise SmplxError(f"{path}: a body model's v_template (V, 3) and J_regressor ({len(JOINTS)}, V); got "
                         f"{template.shape} and {regressor.shape}")
    vertices = template
    if betas is not None and shapedirs is not None:
        betas = np.asarray(betas, np.float64).reshape(-1)
        n = min(len(betas), shapedirs.shape[-1], 300)  # (after 300: the expression's components)
        vertices = template + shapedirs[..., :n] @ betas[:n]
    return regressor @ vertices


def _field(f, path: Path, key: str) -> np.ndarray:
    if key not in f.files:
        raise SmplxError(f"{path}: not a SMPL-X take: no {key!r} (it holds {', '.join(sorted(f.files))})")
    return np.asarray(f[key])


def read_smplx(path: str | Path, body_model: str | Path | None = None) -> tuple[BvhMotion, dict]:
    """(the take as a BvhMotion on the SMPL-X skeleton, its other fields: betas, expressions, gender, model).
    `body_model`: the user's SMPL-X body-model file for the exact skeleton of the take's betas."""
    path = Path(path)
    try:
        f = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise SmplxError(f"{path}: not a SMPL-X take ({e})") from None
    with f:
        poses, trans = _field(f, path, "poses"), _field(f, path, "trans")
        fps = _field(f, path, "mocap_frame_rate")
        extra = {k: np.asarray(f[k]) for k in ("betas", "expressions", "gender", "model") if k in f.files}
    if poses.ndim != 2 or poses.shape[1] != 3 * len(JOINTS):
        raise SmplxError(f"{path}: poses must be (frames, {3 * len(JOINTS)}) (55 joints x axis-angle), got "
                         f"{poses.shape}")
    if trans.shape != (len(poses), 3):
        raise SmplxError(f"{path}: trans must be ({len(poses)}, 3) (one position a frame), got {trans.shape}")
    if fps.size != 1 or not np.issubdtype(fps.dtype, np.number) or not np.isfinite(fps).all() or float(fps) <= 0:
        raise SmplxError(f"{path}: mocap_frame_rate must be one positive number, got {fps!r}")
    for name, a in (("poses", poses), ("trans", trans)):
        if not np.issubdtype(a.dtype, np.number):
            raise SmplxError(f"{path}: {name} must be numbers, got {a.dtype}")
        bad = ~np.isfinite(a.astype(np.float64)).all(axis=1)
        if bad.any():
            raise SmplxError(f"{path}: {name} is not finite at frame {int(np.argmax(bad))} ({int(bad.sum())} frames)")
    rest = body_model_joints(body_model, extra.get("betas")) if body_model is not None else GENERIC_REST
    sk = skeleton(rest)
    q = R.expmap_to_quat(poses.astype(np.float64).reshape(len(poses), len(JOINTS), 3))[:, BVH_ORDER]
    t = np.broadcast_to(sk.offsets, (len(poses), len(JOINTS), 3)).copy()
    t[:, 0] = (rest[0] + trans.astype(np.float64)) * CM  # (the pelvis: first in either order)
    return BvhMotion.from_pose(sk, 1.0 / float(fps), q, t), extra


def write_smplx(path: str | Path, motion: BvhMotion, betas: np.ndarray | None = None,
                expressions: np.ndarray | None = None, gender: str = "neutral") -> Path:
    """A BEAT2-format take of a motion on the SMPL-X skeleton: `trans` is the pelvis less its rest position (the
    skeleton's root offset). `betas`: the body the skeleton was made from (default: 300 zeros)."""
    sk = motion.skeleton
    if not is_smplx(sk):
        raise SmplxError(f"{path}: only a motion on the SMPL-X skeleton is written as SMPL-X (this one has "
                         f"{sk.num_joints} joints, {sk.names[0]!r} first); retarget it onto SMPL-X first")
    T = motion.num_frames
    index = _smplx_index(sk)
    rotations = motion.rotations()[:, index]
    poses = R.expmap_continuity(R.quat_to_expmap(rotations), axis=0).reshape(T, 3 * len(JOINTS))
    pelvis = index[0]
    trans = motion.translations()[:, pelvis] / CM - sk.offsets[pelvis] / CM  # (its OFFSET: its rest position)
    path = Path(path)
    with open(path, "wb") as out:  # (np.savez would add ".npz" to another name)
        np.savez(out, poses=poses, trans=trans,
                 betas=np.zeros(300, np.float32) if betas is None else np.asarray(betas, np.float32),
                 expressions=np.zeros((T, 100), np.float32) if expressions is None else np.asarray(expressions,
                                                                                                   np.float32),
                 model=np.array("smplx2020"), gender=np.array(gender), mocap_frame_rate=np.array(motion.fps))
    return path
