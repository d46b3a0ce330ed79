"""A tiny animated skeleton written with pygltflib as a glTF binary: a skinned .glb (one triangle per joint) or, given
humanoid bone names, a VRM Animation (.vrma: nodes, one animation and `VRMC_vrm_animation`), with its forward
kinematics in numpy as the reference that the checks with real tools (glTF validator, Blender, three-vrm) compare
against. Quaternions are glTF's (x, y, z, w); lengths in metres; Y up."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pygltflib as G

from dimgestor import rotations as R

FLOAT, USHORT = 5126, 5123
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


@dataclass
class Rig:
    names: list[str]
    parents: list[int]  # -1 for the root; parents come before their children
    translations: np.ndarray  # (J, 3) rest local translations
    rotations: np.ndarray | None = None  # (J, 4) rest local rotations; None: identity

    def __post_init__(self):
        self.translations = np.asarray(self.translations, np.float64).reshape(-1, 3)
        J = len(self.names)
        self.rotations = (np.tile([0.0, 0, 0, 1], (J, 1)) if self.rotations is None
                          else np.asarray(self.rotations, np.float64).reshape(J, 4))


@dataclass
class Clip:
    times: np.ndarray  # (K,) seconds, one input accessor shared by every channel (LINEAR)
    rotations: dict[int, np.ndarray] = field(default_factory=dict)  # joint -> (K, 4)
    translations: dict[int, np.ndarray] = field(default_factory=dict)  # joint -> (K, 3)


def wxyz(q: np.ndarray) -> np.ndarray:
    return np.roll(q, 1, axis=-1)


def local_pose(rig: Rig, clip: Clip) -> tuple[np.ndarray, np.ndarray]:
    """Each joint's local rotation (K, J, 4) wxyz and translation (K, J, 3) at the clip's keys."""
    K = len(clip.times)
    q = np.broadcast_to(wxyz(rig.rotations), (K, len(rig.names), 4)).copy()
    t = np.broadcast_to(rig.translations, (K, len(rig.names), 3)).copy()
    for j, v in clip.rotations.items():
        q[:, j] = R.quat_normalize(wxyz(np.asarray(v, np.float64)))
    for j, v in clip.translations.items():
        t[:, j] = v
    return q, t


def world_positions(rig: Rig, clip: Clip) -> np.ndarray:
    """World positions of the joints (K, J, 3) at the clip's keys (the scene root is the identity)."""
    q, t = local_pose(rig, clip)
    world_q, world_p = np.empty_like(q), np.empty_like(t)
    for j, p in enumerate(rig.parents):
        if p < 0:
            world_q[:, j], world_p[:, j] = q[:, j], t[:, j]
        else:
            world_q[:, j] = R.quat_mul(world_q[:, p], q[:, j])
            world_p[:, j] = world_p[:, p] + R.quat_rotate(world_q[:, p], t[:, j])
    return world_p


def _rest_world_matrices(rig: Rig) -> np.ndarray:
    M = np.tile(np.eye(4), (len(rig.names), 1, 1))
    for j, p in enumerate(rig.parents):
        local = np.eye(4)
        local[:3, :3] = R.quat_to_matrix(wxyz(rig.rotations[j]))
        local[:3, 3] = rig.translations[j]
        M[j] = local if p < 0 else M[p] @ local
    return M


class _Buffer:
    """One binary buffer that accessors are appended to, each in a 4-byte aligned view of its own."""

    def __init__(self, gltf: G.GLTF2):
        self.gltf, self.data = gltf, bytearray()

    def add(self, array: np.ndarray, kind: str, component: int = FLOAT, target: int | None = None,
            bounds: bool = False) -> int:
        raw = np.ascontiguousarray(array, np.float32 if component == FLOAT else np.uint16).tobytes()
        self.gltf.bufferViews.append(G.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(raw),
                                                  target=target))
        self.data += raw + b"\0" * (-len(raw) % 4)
        rows = np.asarray(array, np.float64).reshape(len(array), -1)
        self.gltf.accessors.append(G.Accessor(
            bufferView=len(self.gltf.bufferViews) - 1, componentType=component, count=len(array), type=kind,
            min=rows.min(0).tolist() if bounds else None, max=rows.max(0).tolist() if bounds else None))
        return len(self.gltf.accessors) - 1


def write_glb(path: Path, rig: Rig, clip: Clip, *, humanoid: dict[str, int] | None = None) -> Path:
    """The rig and clip as a GLB at `path`: skinned (one small triangle per joint) unless `humanoid` (VRM bone name
    -> joint) is given, which makes it a VRMA instead (nodes and animation only, as the format has it)."""
    J = len(rig.names)
    nodes = [G.Node(name=n, translation=rig.translations[j].tolist(), rotation=rig.rotations[j].tolist())
             for j, n in enumerate(rig.names)]
    for j, p in enumerate(rig.parents):
        if p >= 0:
            nodes[p].children.append(j)
    gltf = G.GLTF2(asset=G.Asset(generator="dimgestor tests"), scene=0, nodes=nodes)
    buf = _Buffer(gltf)
    roots = [j for j, p in enumerate(rig.parents) if p < 0]

    if humanoid is None:
        world = _rest_world_matrices(rig)
        corners = np.array([[-0.01, 0, 0], [0.01, 0, 0], [0, 0.02, 0]])
        pos = (world[:, None, :3, 3] + corners).reshape(-1, 3)
        joints = np.zeros((3 * J, 4))
        joints[:, 0] = np.repeat(np.arange(J), 3)
        weights = np.zeros((3 * J, 4))
        weights[:, 0] = 1
        attributes = G.Attributes(POSITION=buf.add(pos, "VEC3", target=ARRAY_BUFFER, bounds=True),
                                  JOINTS_0=buf.add(joints, "VEC4", USHORT, target=ARRAY_BUFFER),
                                  WEIGHTS_0=buf.add(weights, "VEC4", target=ARRAY_BUFFER))
        indices = buf.add(np.arange(3 * J), "SCALAR", USHORT, target=ELEMENT_ARRAY_BUFFER)
        # column-major, as glTF stores matrices
        ibm = buf.add(np.linalg.inv(world).transpose(0, 2, 1).reshape(J, 16), "MAT4")
        gltf.meshes = [G.Mesh(name="body", primitives=[G.Primitive(attributes=attributes, indices=indices)])]
        gltf.skins = [G.Skin(joints=list(range(J)), inverseBindMatrices=ibm, skeleton=roots[0])]
        gltf.nodes.append(G.Node(name="body", mesh=0, skin=0))
        roots.append(J)
    else:
        gltf.extensionsUsed = ["VRMC_vrm_animation"]
        gltf.extensions = {"VRMC_vrm_animation": {
            "specVersion": "1.0", "humanoid": {"humanBones": {b: {"node": j} for b, j in humanoid.items()}}}}
    gltf.scenes = [G.Scene(nodes=roots)]

    times = buf.add(clip.times, "SCALAR", bounds=True)
    channels, samplers = [], []
    for path_, tracks, kind in (("rotation", clip.rotations, "VEC4"), ("translation", clip.translations, "VEC3")):
        for j, values in tracks.items():
            samplers.append(G.AnimationSampler(input=times, output=buf.add(values, kind), interpolation="LINEAR"))
            channels.append(G.AnimationChannel(sampler=len(samplers) - 1,
                                               target=G.AnimationChannelTarget(node=j, path=path_)))
    gltf.animations = [G.Animation(name="clip", channels=channels, samplers=samplers)]
    gltf.buffers = [G.Buffer(byteLength=len(buf.data))]
    gltf.set_binary_blob(bytes(buf.data))
    gltf.save_binary(str(path))
    return Path(path)
