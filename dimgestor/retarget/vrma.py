"""VRM Animation (`.vrma`): our motion on the VRM T-pose humanoid, with the face's expressions.

A VRM Animation carries a humanoid whose rest pose the player reads as the VRM T-pose (VRM 1.0's definition:
facing +Z, arms, hands and fingers along X, palms down, the thumbs 45 degrees between X and +Z, legs straight
down, feet along +Z). `vrm_t_pose` builds that humanoid with our bone lengths, identity rest rotations and metres;
our motion is retargeted onto it (so our own rest's small departures from a T-pose are aligned away), and each
preset expression is a node whose translation x is the expression's weight.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dimgestor import rotations as R
from dimgestor.retarget import gltf as io
from dimgestor.retarget.names import HUMAN_BONES, effective_parents
from dimgestor.retarget.rig import Rig
from dimgestor.retarget.transfer import Retarget

__all__ = ["vrm_t_pose", "write_vrma", "VRMA_EXPRESSIONS"]

VRMA_EXPRESSIONS = ("aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft", "blinkRight", "happy")
_X = np.array([1.0, 0.0, 0.0])


def _direction(parent: str, bone: str, offset: np.ndarray) -> np.ndarray:
    """The VRM T-pose direction from `parent` to `bone`, or `offset`'s own where the T-pose leaves it free."""
    sign = 1.0 if parent.startswith("left") else -1.0
    if parent in ("hips", "spine", "chest", "upperChest", "neck") and bone in ("spine", "chest", "upperChest",
                                                                               "neck", "head"):
        return np.array([0.0, 1.0, 0.0])  # standing straight
    if "Thumb" in parent:
        return np.array([sign, 0.0, 1.0]) / np.sqrt(2.0)
    if parent.endswith(("UpperArm", "LowerArm")) or any(f in parent for f in ("Index", "Middle", "Ring", "Little")):
        return sign * _X
    if parent.endswith(("UpperLeg", "LowerLeg")):
        return np.array([0.0, -1.0, 0.0])
    return offset / max(np.linalg.norm(offset), 1e-12)  # shoulders, hips to legs, hand to fingers, foot to toes


def vrm_t_pose(source: Rig, mapping: dict[str, str], units: float) -> tuple[Rig, dict[str, str]]:
    """The humanoid bones of `source` as a VRM T-pose rig in metres (`units`: metres per source unit)."""
    bones = [b for b in HUMAN_BONES if b in mapping]
    parent = effective_parents(bones)
    _, rest_p = source.rest_world()
    where = {b: rest_p[source.index(mapping[b])] * units for b in bones}
    pos: dict[str, np.ndarray] = {}
    for b in bones:
        p = parent[b]
        if p is None:
            pos[b] = where[b] * np.array([0.0, 1.0, 0.0])  # centred on the vertical axis
            continue
        offset = where[b] - where[p]
        pos[b] = pos[p] + _direction(p, b, offset) * np.linalg.norm(offset)
    names = bones
    parents = [bones.index(parent[b]) if parent[b] else -1 for b in bones]
    translations = np.array([pos[b] - (pos[parent[b]] if parent[b] else 0.0) for b in bones])
    rig = Rig(names, parents, translations, R.quat_identity((len(bones),)), np.ones(len(bones)), path="VRM T-pose",
              kind="vrma")
    return rig, {b: b for b in bones}


def write_vrma(path: str | Path, source: Rig, source_map: dict[str, str], rotations: np.ndarray,
               translations: np.ndarray, fps: float, units: float, face: dict[str, np.ndarray] | None = None) -> None:
    """Motion on `source` (local rotations (T, J, 4), translations (T, J, 3)) -> a VRM Animation file, with the
    preset expressions in `face` ({VRM 1.0 expression name: (T,) weight})."""
    rig, rig_map = vrm_t_pose(source, source_map, units)
    q, t = Retarget(source, rig, source_map, rig_map)(rotations, translations)
    gltf, nodes = io.skeleton_gltf(rig, mesh=False)
    hips = rig.names.index("hips")
    expression_nodes = {}
    for name in face or {}:
        gltf.nodes.append(io.G.Node(name=f"expression:{name}", translation=[0.0, 0.0, 0.0]))
        gltf.scenes[0].nodes.append(len(gltf.nodes) - 1)
        expression_nodes[name] = len(gltf.nodes) - 1
    io.add_animation(gltf, nodes, fps, q, t, rotate=list(range(rig.num_joints)), translate=[hips],
                     weights={expression_nodes[n]: np.clip(w, 0.0, 1.0) for n, w in (face or {}).items()})
    extension = {"specVersion": "1.0", "humanoid": {"humanBones": {b: {"node": nodes[k]} for k, b in enumerate(rig.names)}}}
    if expression_nodes:
        extension["expressions"] = {"preset": {n: {"node": i} for n, i in expression_nodes.items()}}
    gltf.extensionsUsed = ["VRMC_vrm_animation"]
    gltf.extensions = {"VRMC_vrm_animation": extension}
    io.save_glb(gltf, path)
