"""Skeleton pose -> Unity humanoid pose: the retarget map and the BVH -> Unity frame conversion.

BVH space is right-handed, Y up, file units (cm for ZEGGS). Unity is left-handed, Y up, metres.
Mirroring the X axis maps one to the other: a position (x, y, z) becomes (-x, y, z), and a rotation
(w, x, y, z) becomes (w, x, -y, -z): M R M with M = diag(-1, 1, 1) turns a rotation by angle a about
axis u into one by a about -M u (an axis is a pseudo-vector), i.e. (ux, -uy, -uz).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dimgestor.retarget.names import read_json
from dimgestor.rotations import quat_mul, quat_rotate
from streamer.frames import Frame

MAPS_DIR = Path(__file__).resolve().parent / "maps"
DEFAULT_MAP = MAPS_DIR / "zeggs.json"

# UnityEngine.HumanBodyBones, in enum order (LastBone excluded: it is a count, not a bone).
HUMAN_BODY_BONES: tuple[str, ...] = (
    "Hips", "LeftUpperLeg", "RightUpperLeg", "LeftLowerLeg", "RightLowerLeg", "LeftFoot", "RightFoot",
    "Spine", "Chest", "Neck", "Head", "LeftShoulder", "RightShoulder", "LeftUpperArm", "RightUpperArm",
    "LeftLowerArm", "RightLowerArm", "LeftHand", "RightHand", "LeftToes", "RightToes", "LeftEye",
    "RightEye", "Jaw",
    "LeftThumbProximal", "LeftThumbIntermediate", "LeftThumbDistal",
    "LeftIndexProximal", "LeftIndexIntermediate", "LeftIndexDistal",
    "LeftMiddleProximal", "LeftMiddleIntermediate", "LeftMiddleDistal",
    "LeftRingProximal", "LeftRingIntermediate", "LeftRingDistal",
    "LeftLittleProximal", "LeftLittleIntermediate", "LeftLittleDistal",
    "RightThumbProximal", "RightThumbIntermediate", "RightThumbDistal",
    "RightIndexProximal", "RightIndexIntermediate", "RightIndexDistal",
    "RightMiddleProximal", "RightMiddleIntermediate", "RightMiddleDistal",
    "RightRingProximal", "RightRingIntermediate", "RightRingDistal",
    "RightLittleProximal", "RightLittleIntermediate", "RightLittleDistal",
    "UpperChest",
)


class HumanoidMapError(ValueError):
    pass


def load_humanoid_map(path: str | Path | None = None) -> dict[str, str]:
    """Read a {HumanBodyBones name: joint name} JSON map (the shipped ZEGGS/BEAT map by default)."""
    path = Path(path) if path is not None else DEFAULT_MAP
    data = read_json(path, "humanoid map", HumanoidMapError)
    if not isinstance(data, dict):
        raise HumanoidMapError(f"{path}: expected a JSON object {{HumanBodyBones name: joint name}}")
    for bone, joint in data.items():
        if bone not in HUMAN_BODY_BONES:
            raise HumanoidMapError(f"{path}: {bone!r} is not a Unity HumanBodyBones name")
        if not isinstance(joint, str) or not joint:
            raise HumanoidMapError(f"{path}: {bone!r} must map to a joint name (string), got {joint!r}")
    joints = list(data.values())
    dupes = sorted({j for j in joints if joints.count(j) > 1})
    if dupes:
        raise HumanoidMapError(f"{path}: joints mapped to several bones: {dupes}")
    return dict(data)


# ---- BVH -> Unity ------------------------------------------------------------------------------


def to_unity_position(p: np.ndarray, scale: float = 0.01) -> np.ndarray:
    """(..., 3) right-handed BVH positions -> left-handed Unity positions, times scale (cm -> m)."""
    return p * np.array([-scale, scale, scale])


def to_unity_quat(q: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz BVH rotations -> wxyz Unity rotations (mirror of the X axis)."""
    return q * np.array([1.0, 1.0, -1.0, -1.0])


# ---- retargeting to humanoid bones ---------------------------------------------------------------


@dataclass(frozen=True)
class HumanoidRig:
    """The mapped bones of one skeleton, each with the joint path from its humanoid parent.

    Where training joints are left out of the map (ZEGGS Spine1, Neck1), a bone's local rotation is
    the product of the local rotations along that path, so the posed humanoid matches the skeleton.
    """

    bones: tuple[str, ...]          # HumanBodyBones names, parents before children
    joints: tuple[int, ...]         # skeleton joint index of each bone
    parents: tuple[int, ...]        # index into `bones` of the humanoid parent, -1 for the top bone
    paths: tuple[tuple[int, ...], ...]  # joints after the humanoid parent's joint, up to the bone's joint
    offsets: np.ndarray             # (J, 3) skeleton offsets, BVH space
    root_joint: int                 # skeleton root joint index
    skeleton_parents: tuple[int, ...] = ()  # parent of each skeleton joint (-1: root), for the rest pose
    rest_rotations: np.ndarray | None = None  # (J, 4) rest local rotations; None: identity (BVH skeletons)

    def __post_init__(self):
        # The padded path tables of `local_pose`: joint index (L, B) (J = identity), offset (L, B, 3), is-root (L, B).
        J, B = len(self.offsets), len(self.bones)
        L = max((len(p) for p in self.paths), default=0)
        idx, offs, is_root = np.full((L, B), J), np.zeros((L, B, 3)), np.zeros((L, B))
        for b, path in enumerate(self.paths):
            for d, k in enumerate(path):
                idx[d, b] = k
                if k == self.root_joint:
                    is_root[d, b] = 1.0
                else:
                    offs[d, b] = self.offsets[k]
        object.__setattr__(self, "_chains", (idx, offs, is_root))

    def rest_pose(self) -> np.ndarray:
        """(J, 4) the skeleton's rest local rotations."""
        if self.rest_rotations is None:
            return np.tile([1.0, 0.0, 0.0, 0.0], (len(self.offsets), 1))
        return np.asarray(self.rest_rotations, dtype=np.float64)

    @classmethod
    def build(cls, names, parents, offsets, humanoid: dict[str, str], rest_rotations=None) -> "HumanoidRig":
        index = {n: i for i, n in enumerate(names)}
        joint_to_bone = {index[j]: b for b, j in humanoid.items() if j in index}
        bones, joints, bparents, paths = [], [], [], []
        for j in range(len(names)):  # skeleton order puts parents first, so bones come out that way too
            if j not in joint_to_bone:
                continue
            path, a = [j], parents[j]
            while a != -1 and a not in joint_to_bone:
                path.append(a)
                a = parents[a]
            bones.append(joint_to_bone[j])
            joints.append(j)
            bparents.append(joints.index(a) if a != -1 else -1)
            paths.append(tuple(reversed(path)))
        return cls(tuple(bones), tuple(joints), tuple(bparents), tuple(paths),
                   np.asarray(offsets, dtype=np.float64), list(parents).index(-1), tuple(parents), rest_rotations)

    def mapping(self, names) -> dict[str, str]:
        """{HumanBodyBones name: joint name} for the bones this skeleton has (the hello's `humanoid`)."""
        return {b: names[j] for b, j in zip(self.bones, self.joints)}

    def local_pose(self, root_pos: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """root_pos (n, 3), rotations (n, J, 4) wxyz -> bone local positions (n, B, 3), rotations (n, B, 4), BVH space.

        All bones at once: step d of every bone's path is one batched rotate and one batched quaternion
        product over (n, B); paths are padded with the identity (`_chains`). `local_pose_reference` is
        the per-bone walk this must equal.
        """
        idx, offs, is_root = self._chains
        n = rotations.shape[0]
        rot = np.concatenate([rotations, np.broadcast_to([1.0, 0.0, 0.0, 0.0], (n, 1, 4))], axis=1)  # J = identity pad
        root = np.asarray(root_pos, dtype=np.float64)[:, None, :]
        q = np.broadcast_to(np.array([1.0, 0.0, 0.0, 0.0]), (n, len(self.bones), 4))
        p = np.zeros((n, len(self.bones), 3))
        for d in range(idx.shape[0]):  # p = o1 + R1 (o2 + R2 (... + o_k)), all bones in step
            o = offs[d] + is_root[d][:, None] * root
            p = p + quat_rotate(q, o)
            q = quat_mul(q, rot[:, idx[d]])
        return p, q

    def local_pose_reference(self, root_pos: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The per-bone, per-joint walk that `local_pose` vectorises (kept for the parity test and the benchmark)."""
        n = rotations.shape[0]
        pos = np.zeros((n, len(self.bones), 3))
        rot = np.zeros((n, len(self.bones), 4))
        for b, path in enumerate(self.paths):
            # Walk the path from the humanoid parent down: p = o1 + R1 (o2 + R2 (... + o_k)).
            q = np.broadcast_to(np.array([1.0, 0.0, 0.0, 0.0]), (n, 4))
            p = np.zeros((n, 3))
            for k in path:
                o = root_pos if k == self.root_joint else np.broadcast_to(self.offsets[k], (n, 3))
                p = p + quat_rotate(q, o)
                q = quat_mul(q, rotations[:, k])
            pos[:, b], rot[:, b] = p, q
        return pos, rot

    def rest_hips_height(self) -> float:
        """Standing height of the top bone (Hips) in the rest pose, file units: its rest height above the
        ground (y = 0), or above the lowest joint where the rest pose reaches below the ground."""
        world = np.zeros_like(self.offsets)
        turn = self.rest_pose().copy()  # each joint's rest world rotation
        for j, a in enumerate(self.skeleton_parents):  # parents come first in skeleton order
            if a >= 0:
                world[j] = world[a] + quat_rotate(turn[a], self.offsets[j])
                turn[j] = quat_mul(turn[a], turn[j])
            else:
                world[j] = self.offsets[j]
        return float(world[self.joints[0], 1] - min(0.0, world[:, 1].min()))


# ---- a user's rig (serve --target) ----------------------------------------------------------------


UNIT_TO_M = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # a skeleton's `units` (the hello's)


class TargetPose:
    """Frames on the model's skeleton -> frames on a target rig (`dimgestor.retarget`): its joints' local
    rotations (rest rotations included) and its root's position, for every sink that sends them (WebSocket
    clients get the rig in the hello, VMC receivers its humanoid bones' local pose)."""

    def __init__(self, skeleton, rig, bone_map=None, metres_per_unit: float | None = None, bones=None):
        from dimgestor.retarget import Retarget, Rig, resolve_map
        from dimgestor.retarget.export import metres_per_unit as guess_unit

        self.source = Rig.from_skeleton(skeleton, "the model's skeleton")
        self.rig = rig
        self.bones = bones if bones is not None else resolve_map(self.rig, bone_map)  # (bones: resolved already)
        self.file = None  # the `dimgestor.retarget.Target` read from --target (from_file), for the recorder
        self.retarget = Retarget(self.source, self.rig, resolve_map(self.source, what="source"), self.bones,
                                 move="root")
        self.metres_per_unit = guess_unit(self.rig) if metres_per_unit is None else metres_per_unit
        self.offsets = np.asarray(skeleton.offsets, dtype=np.float64)

    @classmethod
    def from_file(cls, skeleton, target: str, target_map: str | None = None) -> "TargetPose":
        """`serve --target RIG --target-map MAP`: the rig and its map read once, here."""
        from dimgestor.retarget import load_target

        file = load_target(target, target_map)
        pose = cls(skeleton, file.rig, bones=file.bones)
        pose.file = file
        return pose

    @classmethod
    def from_message(cls, skeleton, rig: dict) -> "TargetPose":
        """A client's `hello.rig` (checked by `protocol.parse_text`): its joints, rest pose, units and bone map."""
        from dimgestor import rotations as R
        from dimgestor.retarget import Rig

        J = len(rig["joints"])
        rest = np.asarray(rig["rest_rotations"], dtype=np.float64) if "rest_rotations" in rig else R.quat_identity((J,))
        target = Rig(list(rig["joints"]), list(rig["parents"]), np.asarray(rig["offsets"], dtype=np.float64), rest,
                     np.ones(J), path="hello.rig", kind="client")
        return cls(skeleton, target, rig.get("map"), UNIT_TO_M[rig.get("units", "m")])

    def skeleton_info(self):
        from streamer.protocol import SkeletonInfo

        units = {v: k for k, v in UNIT_TO_M.items()}[self.metres_per_unit]
        return SkeletonInfo(list(self.rig.names), list(self.rig.parents), self.rig.translations.copy(), units,
                            self.rig.rotations.copy())

    def humanoid(self) -> dict[str, str]:
        """{HumanBodyBones name: target joint}, the hello's `humanoid` and the VMC bones."""
        from dimgestor.retarget.names import unity_name

        return {unity_name(b): j for b, j in self.bones.items() if unity_name(b) in HUMAN_BODY_BONES}

    def humanoid_rig(self) -> HumanoidRig:
        return HumanoidRig.build(self.rig.names, self.rig.parents, self.rig.translations, self.humanoid(),
                                 self.rig.rotations)

    def __call__(self, frames: list[Frame]) -> list[Frame]:
        if not frames:
            return frames
        rotations = np.stack([f.rotations for f in frames])
        translations = np.broadcast_to(self.offsets, rotations.shape[:2] + (3,)).copy()
        translations[:, self.source.parents.index(-1)] = np.stack([f.root_pos for f in frames])
        q, t = self.retarget(rotations, translations)
        return [replace(f, rotations=q[k], root_pos=t[k, 0]) for k, f in enumerate(frames)]
