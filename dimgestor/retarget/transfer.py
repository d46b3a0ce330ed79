"""Motion from one rig onto another whose rest pose, proportions and joint names differ.

Each humanoid bone's motion is carried as a world rotation relative to its rig's rest pose. The two rest poses
are first aligned bone by bone (`align`: the rotation that turns the target's rest bone onto the source's, its
direction exactly and its roll by the other children, e.g. the fingers about the hand), so an A-posed target
raises its arms to where a T-posed source holds them. Per frame, a bone's world rotation on the target is

    W_t = C * A * Rt        C: the source bone's rotation from its rest, Rs^-1 taken out (corrected so its
                            direction reaches the source's next mapped bone even across unmapped joints)
                            A: the rest alignment, Rt: the target bone's rest world rotation

and its local rotation is W_t over its parent's world rotation. Joints the map leaves out keep their rest local
rotation; the hips move as the source's, scaled by leg length. The two rigs may face opposite ways (VRM 0.x faces
-Z): the source's world is turned about the vertical (Y) onto the target's first (`facing`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dimgestor import rotations as R
from dimgestor.bvh import BvhMotion
from dimgestor.retarget.names import HUMAN_BONES, apply_map, auto_map, effective_parents, load_map
from dimgestor.retarget.rig import Rig, RigError, load_rig

__all__ = ["Retarget", "Target", "load_target", "swing", "resolve_map"]

_CENTRE = ("hips", "spine", "chest", "upperChest", "neck", "head")
_NOT_DIRECTIONS = {"jaw", "leftEye", "rightEye"}  # children that do not say where a bone points
_FINGER_ORDER = ("Middle", "Index", "Ring", "Little", "Thumb")
MIN_BONES = 6  # fewer recognised bones is not a humanoid the names were meant for


def swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (..., 4) turning directions a onto b (..., 3)."""
    a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    d = np.sum(a * b, axis=-1, keepdims=True)
    q = np.concatenate([1.0 + d, np.cross(a, b)], axis=-1)
    opposite = (1.0 + d[..., 0]) < 1e-9
    if np.any(opposite):  # half a turn about any axis perpendicular to a
        helper = np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        axis = np.cross(a, helper)
        q = np.where(opposite[..., None], np.concatenate([np.zeros_like(d), axis], axis=-1), q)
    return R.quat_normalize(q)


def _about(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def _roll_fit(q: np.ndarray, axis: np.ndarray, us: list[np.ndarray], vs: list[np.ndarray]) -> np.ndarray:
    """q turned about `axis` by the angle that best lays q us onto vs, seen across the axis (least squares)."""
    n = axis / np.linalg.norm(axis)
    sin_sum = cos_sum = 0.0
    for u, v in zip(us, vs):
        a = R.quat_rotate(q, u)
        a, v = a - np.dot(a, n) * n, v - np.dot(v, n) * n
        sin_sum += np.dot(np.cross(a, v), n)
        cos_sum += np.dot(a, v)
    if abs(sin_sum) + abs(cos_sum) < 1e-12:
        return q
    return R.quat_mul(_about(n, np.arctan2(sin_sum, cos_sum)), q)


@dataclass(frozen=True, eq=False)
class Target:
    """A user's rig read and mapped once (`load_target`, at the command line's edge), passed down to whatever
    retargets onto it or writes it: nothing below reads its file or its map again."""
    rig: Rig
    bones: dict[str, str]  # {VRM 1.0 bone: joint}, as `resolve_map` gave it

    @property
    def path(self) -> str:
        return self.rig.path


def load_target(path: str | Path, map_path=None) -> Target:
    """Read the rig at `path` (BVH, glTF/GLB, VRM) and its bone map (`map_path`: a JSON file, a dict or None)."""
    rig = load_rig(path)
    return Target(rig, resolve_map(rig, map_path))


def resolve_map(rig: Rig, map_path=None, what: str = "target") -> dict[str, str]:
    """{VRM 1.0 bone: joint} for a rig: its VRM humanoid, else recognised from its joint names; a map (a file, or
    a dict) over it."""
    mapping = dict(rig.humanoid)
    convention = rig.kind
    if not mapping:
        convention, mapping = auto_map(rig.names, rig.parents)
    if isinstance(map_path, dict):
        mapping = apply_map(map_path, rig.names, mapping, f"{rig.path}: map")
    elif map_path is not None:
        mapping = load_map(map_path, rig.names, mapping)
    if "hips" not in mapping or len(mapping) < MIN_BONES:
        raise RigError(f"{rig.path}: cannot tell which of its {rig.num_joints} joints are the humanoid bones "
                       f"(recognised {sorted(mapping) or 'none'}); pass a bone map file ({what}-map) that names "
                       f"them, e.g. {{\"hips\": \"pelvis\", \"leftUpperArm\": \"arm_L\", ...}}")
    return mapping


def _side_vector(world_pos: np.ndarray, index: dict[str, int]) -> np.ndarray | None:
    """From the right to the left of a rig at rest, on the ground plane."""
    for pair in (("rightUpperLeg", "leftUpperLeg"), ("rightUpperArm", "leftUpperArm"),
                 ("rightShoulder", "leftShoulder"), ("rightHand", "leftHand")):
        if all(b in index for b in pair):
            v = world_pos[index[pair[1]]] - world_pos[index[pair[0]]]
            v = np.array([v[0], 0.0, v[2]])
            if np.linalg.norm(v) > 1e-9:
                return v
    return None


def _size(world_pos: np.ndarray, index: dict[str, int]) -> float | None:
    """Leg length (hip to knee to ankle), else hips to head: what root motion scales by."""
    for chain in (("leftUpperLeg", "leftLowerLeg", "leftFoot"), ("rightUpperLeg", "rightLowerLeg", "rightFoot"),
                  ("hips", "head"), ("hips", "neck")):
        if all(b in index for b in chain):
            p = world_pos[[index[b] for b in chain]]
            return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=-1)))
    return None


class Retarget:
    """Source rig motion -> target rig local pose.

    The joints carried are the humanoid bones both maps name, and besides them the joints both rigs call by the
    same name under the same carried parent (twist and end joints of a rig and its copy): a rig onto itself is the
    identity. `labels` name them (a VRM 1.0 bone or the joint's name), source order, parents first. `move`:
    where the hips' travel goes, "hips" (its own translation, where the rig lets it) or "root" (the root joint's:
    streams carry one position per frame).
    """

    def __init__(self, source: Rig, target: Rig, source_map: dict[str, str], target_map: dict[str, str],
                 move: str = "hips"):
        self.source, self.target = source, target
        self.move = move  # where the hips' travel goes: "hips" (its own translation where it may have one) or "root"
        bones = [b for b in HUMAN_BONES if b in source_map and b in target_map]
        if "hips" not in bones:
            raise RigError(f"{target.path}: the two rigs share no hips bone; cannot place the motion")
        pairs = {source.index(source_map[b]): (b, target.index(target_map[b])) for b in bones}
        if len({t for _, t in pairs.values()}) != len(pairs):
            raise RigError(f"{target.path}: one joint is mapped to several bones")
        self._check_humanoid(pairs)
        taken_s, taken_t = set(pairs), {t for _, t in pairs.values()}
        extras = {j: (name, target.names.index(name)) for j, name in enumerate(source.names)
                  if j not in taken_s and name in target.names and target.names.index(name) not in taken_t}
        pairs = self._consistent(pairs, extras)
        order = sorted(pairs)
        self.labels = [pairs[s][0] for s in order]
        self.source_joints = np.array(order)
        self.target_joints = np.array([pairs[s][1] for s in order])
        self.parent = self._parents(source, self.source_joints)
        self.source_rest_q, self.source_rest_p = source.rest_world()
        self.target_rest_q, self.target_rest_p = target.rest_world()
        sp, tp = self.source_rest_p[self.source_joints], self.target_rest_p[self.target_joints]
        at = {label: k for k, label in enumerate(self.labels)}
        s_side, t_side = _side_vector(sp, at), _side_vector(tp, at)
        self.facing = R.quat_identity()  # a turn about Y (up) from the source's facing to the target's
        if s_side is not None and t_side is not None:
            self.facing = R.yaw_quat(np.arctan2(s_side[2], s_side[0]) - np.arctan2(t_side[2], t_side[0]))
        s_size, t_size = _size(sp, at), _size(tp, at)
        self.scale = t_size / s_size if s_size and t_size else 1.0
        humanoid_parent = effective_parents(bones)
        self.children = [self._direction_children(k, at, bones, humanoid_parent) for k in range(len(order))]
        self.align = self._align(sp, tp)
        self._tables()

    @property
    def bones(self) -> list[str]:
        """The humanoid bones carried."""
        return [label for label in self.labels if label in HUMAN_BONES]

    @staticmethod
    def _parents(rig: Rig, joints) -> list[int]:
        """Per carried joint, the index of its nearest carried ancestor in `rig` (-1: none)."""
        where = {int(j): k for k, j in enumerate(joints)}
        out = []
        for j in joints:
            a = rig.parents[int(j)]
            while a >= 0 and a not in where:
                a = rig.parents[a]
            out.append(where.get(a, -1))
        return out

    def _check_humanoid(self, pairs: dict[int, tuple[str, int]]) -> None:
        """Refuse maps whose bones nest differently in the two rigs (a hand mapped outside its arm)."""
        order = sorted(pairs)
        s_parent = self._parents(self.source, order)
        t_parent = self._parents(self.target, [pairs[s][1] for s in order])
        for k, s in enumerate(order):
            if s_parent[k] != t_parent[k]:
                bone, t = pairs[s]
                want = pairs[order[s_parent[k]]][0] if s_parent[k] >= 0 else "nothing"
                raise RigError(f"{self.target.path}: bone {bone!r} (joint {self.target.names[t]!r}) is not under "
                               f"{want!r} as in the source rig; check the bone map")

    def _consistent(self, pairs: dict, extras: dict) -> dict:
        """pairs plus the extras that nest the same way in both rigs."""
        pairs = dict(pairs)
        for s in sorted(extras):  # parents first: an extra is checked against those above it
            trial = pairs | {s: extras[s]}
            order = sorted(trial)
            s_parent = self._parents(self.source, order)
            t_parent = self._parents(self.target, [trial[x][1] for x in order])
            if s_parent == t_parent:
                pairs = trial
        return pairs

    def _direction_children(self, k: int, at: dict, bones: list[str], humanoid_parent: dict) -> list[int]:
        """The carried children that say where joint k points, the one the chain continues through first."""
        kids = [c for c in range(len(self.labels)) if self.parent[c] == k and self.labels[c] not in _NOT_DIRECTIONS]
        label = self.labels[k]
        if label not in HUMAN_BONES or not kids:
            return kids
        hkids = [b for b in bones if humanoid_parent[b] == label and b not in _NOT_DIRECTIONS]
        main = ([b for b in hkids if b in _CENTRE] if label in _CENTRE else
                [b for f in _FINGER_ORDER for b in hkids if f in b and b.endswith(("Proximal", "Metacarpal"))])
        main = main or hkids
        if main:  # the child on the way to the humanoid child (itself, or a carried joint above it)
            target = int(self.source_joints[at[main[0]]])
            for c in kids:
                j = target
                while j >= 0 and j != self.source_joints[c]:
                    j = self.source.parents[j]
                if j >= 0:
                    return [c] + [x for x in kids if x != c]
        return kids

    def _align(self, sp: np.ndarray, tp: np.ndarray) -> np.ndarray:
        """(B, 4): per carried joint, the world rotation from the target's rest bone to the source's (facing applied)."""
        align = np.empty((len(self.labels), 4))
        g = self.facing
        for k in range(len(self.labels)):
            kids = self.children[k]
            if not kids:  # an end bone (head, hand without fingers, last phalanx) turns with its parent
                align[k] = align[self.parent[k]] if self.parent[k] >= 0 else g
                continue
            us = [tp[c] - tp[k] for c in kids]
            vs = [R.quat_rotate(g, sp[c] - sp[k]) for c in kids]
            q = swing(us[0], vs[0])
            align[k] = _roll_fit(q, vs[0], us[1:], vs[1:]) if len(kids) > 1 else q
        return align

    def _tables(self) -> None:
        """The per-joint constants of `__call__`, as arrays over the carried joints."""
        g, n = self.facing, len(self.labels)
        self._has_child = np.array([bool(c) for c in self.children])
        self._child = np.array([self.source_joints[c[0]] if c else s for c, s in zip(self.children, self.source_joints)])
        self._rest_dir = R.quat_rotate(np.broadcast_to(g, (n, 4)), self.source_rest_p[self._child]
                                       - self.source_rest_p[self.source_joints])
        self._rest_inv = R.quat_conj(self.source_rest_q[self.source_joints])
        self._aligned_rest = R.quat_mul(self.align, self.target_rest_q[self.target_joints])
        self._slot = np.full(self.target.num_joints, -1)
        self._slot[self.target_joints] = np.arange(n)

    def __call__(self, rotations: np.ndarray, translations: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Source local rotations (T, Js, 4) (+ translations (T, Js, 3)) -> target local rotations (T, Jt, 4) and
        translations (T, Jt, 3). All carried joints at once, then the target one tree level at a time."""
        src, tgt, g = self.source, self.target, self.facing
        T = rotations.shape[0]
        wq, wp = src.world(rotations, translations)
        s = self.source_joints
        delta = R.quat_mul(wq[:, s], self._rest_inv)  # each joint's world rotation from its rest
        delta = R.quat_mul(R.quat_mul(g, delta), R.quat_conj(g))
        # carry the direction to the next carried joint exactly, past the joints in between
        now = R.quat_rotate(np.broadcast_to(g, wp[:, s].shape[:-1] + (4,)), wp[:, self._child] - wp[:, s])
        fix = swing(R.quat_rotate(delta, np.broadcast_to(self._rest_dir, now.shape)), now)
        delta = np.where(self._has_child[:, None], R.quat_mul(fix, delta), delta)
        bone_world = R.quat_mul(delta, self._aligned_rest)  # (T, B, 4)
        local_q = np.broadcast_to(tgt.rotations, (T, tgt.num_joints, 4)).copy()
        world_q = np.empty_like(local_q)
        parents = np.asarray(tgt.parents)
        for level in tgt.levels:
            pq = (np.broadcast_to(tgt.base_rotation, (T, len(level), 4)) if parents[level[0]] < 0
                  else world_q[:, parents[level]])
            slot = self._slot[level]
            carried = slot >= 0
            w = R.quat_mul(pq, local_q[:, level])  # joints not carried keep their rest local rotation
            w[:, carried] = bone_world[:, slot[carried]]
            world_q[:, level] = w
            local_q[:, level[carried]] = R.quat_mul(R.quat_conj(pq[:, carried]), w[:, carried])
        local_q = R.quat_continuity(local_q, axis=0)
        local_t = np.broadcast_to(tgt.translations, (T, tgt.num_joints, 3)).copy()
        self._place_hips(wp, world_q, local_t)
        return local_q, local_t

    def _place_hips(self, source_world_p: np.ndarray, world_q: np.ndarray, local_t: np.ndarray) -> None:
        """Move the target's hips as the source's moved from rest, scaled by leg length (in place)."""
        k = self.labels.index("hips")
        tgt, hips_s, hips_t = self.target, self.source_joints[k], self.target_joints[k]
        moved = source_world_p[:, hips_s] - self.source_rest_p[hips_s]
        want = self.target_rest_p[hips_t] + self.scale * R.quat_rotate(np.broadcast_to(self.facing, moved.shape[:1] + (4,)), moved)
        joint = hips_t if tgt.can_translate(hips_t) and self.move == "hips" else (0 if tgt.can_translate(0) else None)
        if joint is None:
            return  # a rig that cannot translate (a BVH without position channels) stays in place
        ws = tgt.world_scales()

        def frame(j: int):  # the rotation and scale a joint's translation is in: its parent's
            p = tgt.parents[j]
            return ((np.broadcast_to(tgt.base_rotation, world_q[:, 0].shape), tgt.base_scale) if p < 0
                    else (world_q[:, p], ws[p]))

        path = [hips_t]  # the hips' position: along its ancestors only
        while tgt.parents[path[-1]] >= 0:
            path.append(tgt.parents[path[-1]])
        pos = np.broadcast_to(tgt.base_position, want.shape).copy()
        for j in reversed(path):
            q, sc = frame(j)
            pos = pos + sc * R.quat_rotate(q, local_t[:, j])
        q, sc = frame(joint)
        local_t[:, joint] += R.quat_rotate(R.quat_conj(q), want - pos) / sc

    def motion(self, motion: BvhMotion) -> BvhMotion:
        """A BVH motion on the source skeleton -> the same motion on the target's BVH skeleton."""
        if self.target.skeleton is None:
            raise RigError(f"{self.target.path}: not a BVH rig; write it as glTF instead")
        q, t = self(motion.rotations(), motion.translations())
        sk = self.target.skeleton
        for k, j in enumerate(self.target_joints):
            if len(sk.rotation_order(int(j))) != 3:
                raise RigError(f"{self.target.path}: joint {sk.names[j]!r} ({self.labels[k]}) has no three rotation "
                               f"channels to carry its motion")
        return BvhMotion.from_pose(sk, motion.frame_time, q, t)
