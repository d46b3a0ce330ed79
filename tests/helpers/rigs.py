"""Target rigs made from the training skeleton for the retargeting tests: renamed to another convention, other
bone lengths and units, an A-pose or a T-pose, rest rotations like a glTF skin's, fingers removed, bones added."""

from __future__ import annotations

import numpy as np

from dimgestor import rotations as R
from dimgestor.bvh import Skeleton
from dimgestor.retarget.names import CONVENTIONS, auto_map
from dimgestor.retarget.rig import Rig


def renamed(names: list[str], parents: list[int], convention: str = "unreal") -> list[str]:
    """Our joints under another convention's names (the humanoid bones), the rest prefixed `x_`."""
    _, ours = auto_map(names, parents)
    table = CONVENTIONS[convention]
    by_joint = {j: b for b, j in ours.items()}
    spine_names = {"unreal": ("spine_01", "spine_03", "spine_05"), "smplx": ("spine1", "spine2", "spine3"),
                   "mixamo": ("Spine", "Spine1", "Spine2"), "vroid": ("J_Bip_C_Spine", "J_Bip_C_Chest",
                                                                      "J_Bip_C_UpperChest"), "vrm": ("spine", "chest", "upperChest")}
    spine = dict(zip(("spine", "chest", "upperChest"), spine_names[convention]))
    out = []
    for n in names:
        bone = by_joint.get(n)
        out.append(spine[bone] if bone in spine else table[bone] if bone in table else f"x_{n}")
    return out


def world_positions(skeleton: Skeleton) -> np.ndarray:
    p = np.zeros((skeleton.num_joints, 3))
    for j, a in enumerate(skeleton.parents):
        p[j] = skeleton.offsets[j] + (p[a] if a >= 0 else 0)
    return p


def a_pose(skeleton: Skeleton, degrees: float = 45.0, lengths: dict[str, float] | None = None,
           units: float = 0.01, convention: str = "unreal") -> Skeleton:
    """A BVH skeleton: ours renamed, each arm lowered `degrees` at the upper arm, bone lengths scaled per body part
    (`lengths`: {'arm', 'leg', 'spine', 'hand'}: factor), in `units` (0.01: centimetres -> metres)."""
    lengths = {"arm": 0.9, "leg": 1.1, "spine": 1.05, "hand": 1.2} | (lengths or {})
    names = skeleton.names
    offsets = skeleton.offsets.copy()
    for j, n in enumerate(names):
        part = ("hand" if "Hand" in n and n not in ("LeftHand", "RightHand") else
                "arm" if any(k in n for k in ("Arm", "Hand")) else
                "leg" if any(k in n for k in ("Leg", "Foot", "Toe")) else "spine")
        offsets[j] *= lengths[part]
    world = world_positions(Skeleton(names, skeleton.parents, offsets, skeleton.channels))
    for side, sign in (("Left", -1.0), ("Right", 1.0)):
        top = names.index(f"{side}Arm")
        below = _subtree(skeleton.parents, top)
        rot = R.quat_from_axis_angle(2, np.radians(sign * degrees))  # about +Z (forward): the left arm goes down
        world[below] = world[top] + R.quat_rotate(rot, world[below] - world[top])
    offsets = np.array([world[j] - (world[p] if p >= 0 else 0) for j, p in enumerate(skeleton.parents)]) * units
    offsets[0] = world[0] * units
    return Skeleton(renamed(names, skeleton.parents, convention), list(skeleton.parents), offsets,
                    [list(c) for c in skeleton.channels])


def _subtree(parents: list[int], top: int) -> list[int]:
    out = [top]
    for j, p in enumerate(parents):
        if p in out:
            out.append(j)
    return out


def with_rest_rotations(rig: Rig, seed: int = 0) -> Rig:
    """The same rest pose with a random local frame per joint, as glTF skins have (Blender's bones point along Y)."""
    rng = np.random.default_rng(seed)
    wq, wp = rig.rest_world()
    new_world = R.quat_normalize(rng.normal(size=(rig.num_joints, 4)))
    local_q, local_t = np.empty_like(new_world), np.empty_like(wp)
    for j, p in enumerate(rig.parents):
        pq, pp = (rig.base_rotation, rig.base_position) if p < 0 else (new_world[p], wp[p])
        local_q[j] = R.quat_mul(R.quat_conj(pq), new_world[j])
        local_t[j] = R.quat_rotate(R.quat_conj(pq), wp[j] - pp)
    return Rig(list(rig.names), list(rig.parents), local_t, local_q, np.ones(rig.num_joints), path=rig.path,
               kind="gltf")


def subset(skeleton: Skeleton, drop=lambda name: False, extra: dict[str, tuple[str, tuple]] | None = None) -> Skeleton:
    """A skeleton without the joints `drop` names (and their children), plus `extra` bones {name: (parent name,
    offset)} inserted as leaves, in BVH order (depth first)."""
    keep = [j for j, n in enumerate(skeleton.names) if not drop(n)]
    keep = [j for j in keep if all(a in keep or a < 0 for a in _ancestors(skeleton.parents, j))]
    names = [skeleton.names[j] for j in keep]
    parents = [names.index(skeleton.names[skeleton.parents[j]]) if skeleton.parents[j] >= 0 else -1 for j in keep]
    offsets = [skeleton.offsets[j] for j in keep]
    channels = [list(skeleton.channels[j]) for j in keep]
    for name, (parent, offset) in (extra or {}).items():
        at = names.index(parent)
        insert = at + 1 + sum(1 for k in range(at + 1, len(names)) if _is_below(parents, k, at))
        names.insert(insert, name)
        parents = [p + (p >= insert) for p in parents]
        parents.insert(insert, at if at < insert else at + 1)
        offsets.insert(insert, np.asarray(offset, dtype=np.float64))
        channels.insert(insert, ["Zrotation", "Yrotation", "Xrotation"])
    return Skeleton(names, parents, np.array(offsets), channels)


def _ancestors(parents, j):
    out = []
    while parents[j] >= 0:
        j = parents[j]
        out.append(j)
    return out


def _is_below(parents, k, at):
    return at in _ancestors(parents, k)
