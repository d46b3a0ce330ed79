"""Motion features as in Alexanderson et al. (PyMO processing), used by DiM-Gestor, and their inverse.

One row per frame at `spec.fps` (20 by default), float32, columns in this order:

  root_dx, root_dz   ground-plane displacement of the root from the previous frame to this one,
                     in file units PER FRAME, expressed in the previous frame's heading frame
                     (rotated by -heading[t-1] about Y); 0 on the first frame
  root_dyaw          heading change from the previous frame, radians PER FRAME; 0 on the first frame
    or root_yaw      (spec.heading == "facing") heading relative to the clip's mean facing direction,
                     radians, unwrapped: bounded for a speaker who faces a camera, so a model that
                     outputs it cannot spin away by accumulating small errors in a turning velocity
  root_y             root height, file units
  root_tilt_x, _z    the root rotation with its heading removed (q_root = yaw(heading) * tilt),
                     as an exponential map; its Y component is 0 by construction, so it is dropped
  <joint>_rx/_ry/_rz for every kept non-root joint, its local rotation as an exponential map,
                     kept continuous over time (no sign flips, no 2 pi jumps)

Heading is the twist of the root rotation about +Y. Velocities are per frame (not per second), so
integrating is a cumulative sum and decoding in chunks equals decoding everything at once. "velocity"
heading is the paper's (PyMO's) choice; "facing" is this engine's default for co-speech gesture (speakers
face their audience; a generated heading velocity integrates to a spin).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from dimgestor import rotations as R
from dimgestor.bvh import BvhMotion, Skeleton

ROOT_COLUMNS = ("root_dx", "root_dz", "root_dyaw", "root_y", "root_tilt_x", "root_tilt_z")
HEADING_COLUMN = 2  # root_dyaw ("velocity" heading) or root_yaw ("facing" heading)
VELOCITY_COLUMNS = (0, 1)  # root_dx, root_dz: always per-frame velocities
AXIS_SUFFIXES = ("_rx", "_ry", "_rz")


class FeatureSpec(BaseModel):
    """What the feature rows contain; saved in checkpoints so generation decodes the same layout."""

    model_config = ConfigDict(frozen=True)

    fps: float = Field(20.0, gt=0, description="feature frame rate; the paper uses 20 fps")
    joints: tuple[str, ...] | None = Field(
        None, description="non-root joints whose rotations are features; None = every joint with rotation channels"
    )
    heading: Literal["velocity", "facing"] = Field(
        "velocity", description="root heading as a per-frame turn (PyMO, the paper) or relative to the clip's "
                                "mean facing direction (bounded: no spin from integrated errors)")

    @classmethod
    def for_skeleton(cls, skeleton: Skeleton, fps: float = 20.0, joints=None, exclude=()) -> "FeatureSpec":
        """A resolved spec: `joints` (default all) minus names in `exclude`, in skeleton order."""
        return cls(fps=fps, joints=joints).resolve(skeleton, exclude=exclude)

    def resolve(self, skeleton: Skeleton, exclude=()) -> "FeatureSpec":
        """This spec with `joints` listed explicitly (skeleton order), checked against the skeleton."""
        rotating = [n for j, n in enumerate(skeleton.names) if j > 0 and skeleton.rotation_order(j)]
        if self.joints is None:
            wanted = set(rotating)
        else:
            unknown = [n for n in self.joints if n not in skeleton.names]
            if unknown:
                raise ValueError(f"FeatureSpec joints not in the skeleton: {unknown}")
            static = [n for n in self.joints if n not in rotating]
            if static:
                raise ValueError(f"FeatureSpec joints without rotation channels (or the root): {static}")
            wanted = set(self.joints)
        wanted -= set(exclude)
        return self.model_copy(update={"joints": tuple(n for n in rotating if n in wanted)})

    def _resolved(self) -> tuple[str, ...]:
        if self.joints is None:
            raise ValueError("FeatureSpec.joints is unresolved; call spec.resolve(skeleton) first")
        return self.joints

    @property
    def root_columns(self) -> list[str]:
        cols = list(ROOT_COLUMNS)
        if self.heading == "facing":
            cols[HEADING_COLUMN] = "root_yaw"
        return cols

    @property
    def columns(self) -> list[str]:
        return self.root_columns + [n + s for n in self._resolved() for s in AXIS_SUFFIXES]

    @property
    def dim(self) -> int:
        return len(ROOT_COLUMNS) + 3 * len(self._resolved())

    def joint_indices(self, skeleton: Skeleton) -> list[int]:
        return [skeleton.index(n) for n in self._resolved()]

    def to_dict(self) -> dict:
        """JSON-safe; a resolved spec also lists its column names (for people reading config.json)."""
        d = self.model_dump(mode="json")
        if self.joints is not None:
            d["columns"] = self.columns
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "FeatureSpec":
        d = dict(d)
        columns = d.pop("columns", None)
        spec = cls.model_validate(d)
        if columns is not None and spec.joints is not None and list(columns) != spec.columns:
            raise ValueError("FeatureSpec dict: 'columns' do not match the listed joints")
        return spec


# ---- resampling ----------------------------------------------------------------------------------


def resample_pose(rotations: np.ndarray, positions: np.ndarray, frame_time: float, fps: float):
    """Resample local rotations (T, J, 4) by slerp and positions (T, ..., 3) linearly to `fps`.

    The output covers the same duration: floor(T * frame_time * fps) frames (at least 1), frame k
    at time k / fps. A source already at `fps` is returned unchanged.
    """
    T = rotations.shape[0]
    n_out = max(1, int(np.floor(T * frame_time * fps + 1e-6)))
    if abs(frame_time * fps - 1.0) < 1e-9:
        return rotations[:n_out].copy(), positions[:n_out].copy()
    u = np.arange(n_out) / (fps * frame_time)  # fractional source frame of each output frame
    i0 = np.minimum(np.floor(u + 1e-9).astype(int), T - 1)
    i1 = np.minimum(i0 + 1, T - 1)
    a = np.clip(u - i0, 0.0, 1.0)
    rot = R.quat_slerp(rotations[i0], rotations[i1], np.broadcast_to(a[:, None], (n_out, rotations.shape[1])))
    a_pos = a.reshape((-1,) + (1,) * (positions.ndim - 1))
    pos = (1.0 - a_pos) * positions[i0] + a_pos * positions[i1]
    return rot, pos


# ---- forward: motion -> features -----------------------------------------------------------------


def motion_to_features(motion: BvhMotion, spec: FeatureSpec | None = None) -> np.ndarray:
    """BVH motion at any frame rate -> features (T_fps, spec.dim) float32, the layout above."""
    skeleton = motion.skeleton
    spec = (spec or FeatureSpec()).resolve(skeleton)
    if skeleton.parents[0] != -1:
        raise ValueError("the root must be the first joint")
    kept = spec.joint_indices(skeleton)
    cols = [0] + kept
    rot, root_pos = resample_pose(motion.rotations()[:, cols], motion.translations()[:, 0], motion.frame_time, spec.fps)

    heading, tilt = R.split_heading(rot[:, 0])
    heading = np.unwrap(heading)
    h_prev = np.concatenate([heading[:1], heading[:-1]])
    step = np.diff(root_pos[:, [0, 2]], axis=0, prepend=root_pos[:1, [0, 2]])  # (T, 2) x, z
    c, s = np.cos(h_prev), np.sin(h_prev)
    dx = c * step[:, 0] - s * step[:, 1]  # rotate by -h_prev about Y
    dz = s * step[:, 0] + c * step[:, 1]
    tilt_v = R.expmap_continuity(R.quat_to_expmap(tilt))
    if spec.heading == "facing":
        yaw = heading - facing_direction(heading)
    else:
        yaw = np.diff(heading, prepend=heading[:1])
    root = np.stack([dx, dz, yaw, root_pos[:, 1], tilt_v[:, 0], tilt_v[:, 2]], -1)
    joints = R.expmap_continuity(R.quat_to_expmap(rot[:, 1:]), axis=0).reshape(len(rot), -1)
    return np.concatenate([root, joints], axis=1).astype(np.float32)


def facing_direction(heading: np.ndarray) -> float:
    """The clip's mean facing (circular mean of the unwrapped heading), on the branch nearest its median."""
    if len(heading) == 0:
        return 0.0
    mean = math.atan2(float(np.mean(np.sin(heading))), float(np.mean(np.cos(heading))))
    return mean + 2 * math.pi * round((float(np.median(heading)) - mean) / (2 * math.pi))


def heading_track(features: np.ndarray, spec: FeatureSpec) -> np.ndarray:
    """(n,) heading in radians relative to the first frame's, whichever way the features hold it."""
    h = np.asarray(features, dtype=np.float64)[:, HEADING_COLUMN]
    if len(h) == 0:
        return h
    return h - h[0] if spec.heading == "facing" else np.cumsum(h) - h[0]


# ---- inverse: features -> pose / motion ----------------------------------------------------------


@dataclass(frozen=True)
class RootState:
    """Root ground position and heading of the frame before the next one to decode."""

    x: float = 0.0
    z: float = 0.0
    heading: float = 0.0
    # "tether" only: the running mean of (dx, dz, dyaw) per frame (the model's steady drift) and how
    # many frames it has seen.
    drift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    frames: int = 0


@dataclass(frozen=True)
class Pose:
    root_pos: np.ndarray  # (n, 3) file units
    rotations: np.ndarray  # (n, J, 4) local quaternions wxyz for every skeleton joint


ROOT_MODES = ("free", "tether", "lock")


def leaky_cumsum(u: np.ndarray, prev: float, lam: float) -> np.ndarray:
    """y_n = lam * y_{n-1} + u_n from y_{-1} = prev (lam = 1: a plain running sum)."""
    if lam == 1.0:
        return prev + np.cumsum(u)
    # A loop, in the order scipy.signal.lfilter([1], [1, -lam], u, zi=[lam * prev]) adds (its output bit for bit,
    # tests/test_features.py): importing scipy.signal costs ~1 s of CPU, which a server's first frames paid.
    out, y, lam = np.empty(len(u)), float(prev), float(lam)
    for n, x in enumerate(np.asarray(u, dtype=np.float64).tolist()):
        y = lam * y + x
        out[n] = y
    return out


def _remove_drift(u: np.ndarray, drift, frames: int, n_avg: float) -> tuple[np.ndarray, np.ndarray, int]:
    """u (n, 3) per-frame (dx, dz, dyaw) minus their running mean (an average of all frames so far
    for the first n_avg frames, then exponential over n_avg): any steady walk or spin is removed
    whatever its rate, while a turn or step shorter than n_avg frames passes."""
    out, m = np.empty_like(u), np.array(drift, dtype=np.float64)
    for t in range(len(u)):
        frames += 1
        m += (u[t] - m) / min(frames, n_avg)
        out[t] = u[t] - m
    return out, m, frames


def decode_features(features: np.ndarray, skeleton: Skeleton, spec: FeatureSpec,
                    state: RootState = RootState(), root: str = "free", tether_s: float = 5.0,
                    anchor: RootState = RootState()) -> tuple[Pose, RootState]:
    """Features (n, D) -> poses, integrating the root from `state`; returns the state after frame n-1.

    root: how the ground-plane position and heading evolve. "free" integrates the velocities as the
    model made them (a BVH of the motion). "tether" (the live default) first removes the velocities'
    running mean over `tether_s` (a model that keeps spinning or walking one way then stays put), then
    integrates the rest with a leak of time constant `tether_s` towards `anchor`: a live avatar
    turns and shifts its weight as generated but faces and stands at its start on average, whatever
    the model's drift. "lock" keeps position and heading at `anchor`. Height and tilt always come from
    the features.
    """
    _check_root(root, tether_s)
    spec = spec.resolve(skeleton)
    return _decode(features, spec, spec.joint_indices(skeleton), skeleton.num_joints, state, root, tether_s, anchor)


def _check_root(root: str, tether_s: float) -> None:
    if root not in ROOT_MODES:
        raise ValueError(f"root must be one of {ROOT_MODES}, got {root!r}")
    if root == "tether" and not tether_s > 0:
        raise ValueError(f"tether_s must be > 0, got {tether_s}")


def _decode(features: np.ndarray, spec: FeatureSpec, kept: list[int], num_joints: int, state: RootState, root: str,
            tether_s: float, anchor: RootState) -> tuple[Pose, RootState]:
    """`decode_features` with the spec resolved and its joints' indices given (a `PoseDecoder` keeps them: resolving
    the spec was half of decoding a window)."""
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or f.shape[1] != spec.dim:
        raise ValueError(f"features must be (n, {spec.dim}) for this spec, got {f.shape}")
    n = f.shape[0]
    drift, frames = state.drift, state.frames
    if root == "lock":
        heading, x, z = (np.full(n, v) for v in (anchor.heading, anchor.x, anchor.z))
    else:
        lam = 1.0 if root == "free" else math.exp(-1.0 / (spec.fps * tether_s))
        a = anchor if root == "tether" else RootState()
        u = f[:, :3].copy()
        facing = spec.heading == "facing"
        if facing:  # the heading itself, relative to the start: nothing to integrate, nothing to drift
            u[:, HEADING_COLUMN] = 0.0
        if root == "tether":
            u, drift, frames = _remove_drift(u, drift, frames, spec.fps * tether_s)
            drift = tuple(float(v) for v in drift)
        if facing:
            heading = anchor.heading + f[:, HEADING_COLUMN]
        else:
            heading = a.heading + leaky_cumsum(u[:, 2], state.heading - a.heading, lam)
        h_prev = np.concatenate([[state.heading], heading[:-1]])
        c, s = np.cos(h_prev), np.sin(h_prev)
        x = a.x + leaky_cumsum(c * u[:, 0] + s * u[:, 1], state.x - a.x, lam)  # rotate by +h_prev about Y
        z = a.z + leaky_cumsum(-s * u[:, 0] + c * u[:, 1], state.z - a.z, lam)
    tilt = np.stack([f[:, 4], np.zeros(n), f[:, 5]], -1)
    rot = R.quat_identity((n, num_joints))
    rot[:, 0] = R.quat_mul(R.yaw_quat(heading), R.expmap_to_quat(tilt))
    rot[:, kept] = R.expmap_to_quat(f[:, len(ROOT_COLUMNS):].reshape(n, len(kept), 3))
    pose = Pose(root_pos=np.stack([x, f[:, 3], z], -1), rotations=rot)
    if n == 0:
        return pose, state
    return pose, RootState(float(x[-1]), float(z[-1]), float(heading[-1]), drift, frames)


class PoseDecoder:
    """Streaming inverse: decode feature chunks in order, carrying the root integration (see decode_features
    for `root`; the start position and heading are the anchor of "tether" and "lock")."""

    def __init__(self, skeleton: Skeleton, spec: FeatureSpec, start_pos=(0.0, 0.0, 0.0), start_heading: float = 0.0,
                 root: str = "free", tether_s: float = 5.0):
        _check_root(root, tether_s)
        self.skeleton = skeleton
        self.spec = spec.resolve(skeleton)
        self._kept = self.spec.joint_indices(skeleton)
        self.anchor = self.state = RootState(float(start_pos[0]), float(start_pos[2]), float(start_heading))
        self.root, self.tether_s = root, float(tether_s)

    def decode(self, features: np.ndarray) -> Pose:
        pose, self.state = _decode(features, self.spec, self._kept, self.skeleton.num_joints, self.state, self.root,
                                   self.tether_s, self.anchor)
        return pose


def features_to_motion(features: np.ndarray, skeleton: Skeleton, spec: FeatureSpec,
                       start_pos=(0.0, 0.0, 0.0), start_heading: float = 0.0, root: str = "free",
                       tether_s: float = 5.0) -> BvhMotion:
    """Features -> BvhMotion at spec.fps on `skeleton`; joints not kept get their rest rotation.

    start_pos is (x, ignored, z): the height comes from the features. Non-root position channels
    are written as the joint's OFFSET. root/tether_s: see decode_features.
    """
    start = RootState(float(start_pos[0]), float(start_pos[2]), float(start_heading))
    pose, _ = decode_features(features, skeleton, spec, start, root, tether_s, start)
    n = pose.rotations.shape[0]
    translations = np.broadcast_to(skeleton.offsets, (n, skeleton.num_joints, 3)).copy()
    translations[:, 0] = pose.root_pos
    return BvhMotion.from_pose(skeleton, 1.0 / spec.fps, pose.rotations, translations)


# ---- left/right mirroring ------------------------------------------------------------------------

def mirror_name(name: str) -> str:
    """The name of the joint on the other side (Left<->Right, L/R prefixes and suffixes), or the name."""
    swaps = {"Left": "Right", "Right": "Left", "left": "right", "right": "left", "LEFT": "RIGHT", "RIGHT": "LEFT"}
    out = re.sub(r"Left|Right|left|right|LEFT|RIGHT", lambda m: swaps[m.group()], name)
    if out != name:
        return out
    out = re.sub(r"(?:^|(?<=[:_.]))([LR])(?=[A-Z_.0-9])", lambda m: "R" if m.group(1) == "L" else "L", name)
    if out != name:
        return out
    return re.sub(r"(?<=[_.])([LlRr])$", lambda m: {"L": "R", "R": "L", "l": "r", "r": "l"}[m.group(1)], name)


def mirror_pairs(names: list[str]) -> list[int]:
    """For each name, the index of its mirror partner in `names` (itself when unpaired)."""
    index = {n: i for i, n in enumerate(names)}
    return [index.get(mirror_name(n), i) for i, n in enumerate(names)]


def mirror_features(features: np.ndarray, spec: FeatureSpec) -> np.ndarray:
    """Reflect features across the YZ plane (x -> -x) and swap left/right joints.

    A reflection maps a rotation vector (x, y, z) to (x, -y, -z). Exact for skeletons whose rest
    pose is left/right symmetric about x = 0 (the usual mocap T-pose facing +Z).
    """
    joints = list(spec._resolved())
    partner = mirror_pairs(joints)
    for i, p in enumerate(partner):
        if p == i and mirror_name(joints[i]) != joints[i]:
            raise ValueError(f"cannot mirror: {joints[i]!r} is kept but {mirror_name(joints[i])!r} is not")
    f = np.asarray(features)
    root = f[:, : len(ROOT_COLUMNS)] * np.array([-1, 1, -1, 1, 1, -1], dtype=f.dtype)
    j = f[:, len(ROOT_COLUMNS):].reshape(len(f), len(joints), 3)[:, partner] * np.array([1, -1, -1], dtype=f.dtype)
    return np.concatenate([root, j.reshape(len(f), -1)], axis=1)


def _is_left(name: str) -> bool:
    """Whether a joint with a mirror partner is on the left (the names mirror_name swaps)."""
    if re.search(r"Left|left|LEFT|Right|right|RIGHT", name):
        return re.search(r"Left|left|LEFT", name) is not None
    return re.search(r"(?:^|(?<=[:_.]))L(?=[A-Z_.0-9])|(?<=[_.])[Ll]$", name) is not None


def arm_columns(spec: FeatureSpec, skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Feature columns of the left and the right arm (every kept joint of a side whose nearest joint without a
    side is not the root: shoulders, arms, hands, fingers; legs hang from the root), in matching order."""
    joints = list(spec._resolved())
    partner = mirror_pairs(joints)
    names = skeleton.names

    def is_arm(name: str) -> bool:
        j = skeleton.index(name)
        while j >= 0 and mirror_name(names[j]) != names[j]:
            j = skeleton.parents[j]
        return j > 0  # a spine or neck joint, not the root

    def columns(idx: list[int]) -> np.ndarray:
        return np.array([len(ROOT_COLUMNS) + 3 * i + k for i in idx for k in range(3)], dtype=np.int64)

    left = [i for i, n in enumerate(joints) if partner[i] != i and is_arm(n) and _is_left(n)]
    return columns(left), columns([partner[i] for i in left])


def mix_arms(features: np.ndarray, spec: FeatureSpec, skeleton: Skeleton, side: str) -> np.ndarray:
    """The same motion with both arms doing what one arm did: `side` ("left" or "right") keeps that arm and
    puts its mirror image on the other (the rest of the body as it was). Body-part mixing for variety: a
    one-handed gesture becomes a two-handed one (or both arms rest), on the same timing as the speech."""
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    left, right = arm_columns(spec, skeleton)
    if not len(left):
        raise ValueError("cannot mix arms: no left/right arm joints among the kept joints")
    f = np.array(features, copy=True)
    m = mirror_features(f, spec)
    if side == "left":
        f[:, right] = m[:, right]
    else:
        f[:, left] = m[:, left]
    return f


def mirror_motion(motion: BvhMotion) -> BvhMotion:
    """The same motion reflected across x = 0 with left/right joints swapped, on the same skeleton."""
    sk = motion.skeleton
    partner = mirror_pairs(sk.names)
    rot = motion.rotations()[:, partner] * np.array([1, 1, -1, -1])
    trans = motion.translations()[:, partner] * np.array([-1, 1, 1])
    # Joints without position channels keep their own OFFSET (from_pose ignores their translations).
    return BvhMotion.from_pose(sk, motion.frame_time, rot, trans)
