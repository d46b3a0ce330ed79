"""glTF 2.0 animation files (pygltflib): a skinned skeleton with one animation (`.glb`), the animation added to a
user's own GLB/VRM, and VRM Animation (`.vrma`, the VRMC_vrm_animation extension) on the VRM T-pose.

All binary data lives in the GLB's one buffer, each array in its own buffer view, 4-byte aligned. Animations
sample every frame with LINEAR interpolation (rotations are unit wxyz internally, xyzw in the file, signs kept
continuous so the slerp between frames takes the short way).
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pygltflib as G

from dimgestor import rotations as R
from dimgestor.retarget.rig import Rig, RigError, read_gltf

__all__ = ["skeleton_gltf", "add_animation", "save_glb", "load_for_animation"]

_FLOAT, _USHORT = 5126, 5123
_ARRAY, _ELEMENTS = 34962, 34963


class _Packer:
    """Appends arrays to a GLB's binary blob as buffer views + accessors."""

    def __init__(self, gltf: G.GLTF2):
        self.gltf = gltf
        self.blob = bytearray(gltf.binary_blob() or b"")
        if not gltf.buffers:
            gltf.buffers = [G.Buffer(byteLength=0)]

    def add(self, array: np.ndarray, kind: str, component: int = _FLOAT, target: int | None = None,
            bounds: bool = False) -> int:
        data = np.ascontiguousarray(array, dtype=np.uint16 if component == _USHORT else np.float32)
        self.blob.extend(b"\0" * (-len(self.blob) % 4))
        view = len(self.gltf.bufferViews)
        self.gltf.bufferViews.append(G.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=data.nbytes,
                                                  target=target))
        self.blob.extend(data.tobytes())
        flat = data.reshape(len(data), -1)
        accessor = G.Accessor(bufferView=view, componentType=component, count=len(data), type=kind)
        if bounds:
            accessor.min, accessor.max = flat.min(axis=0).tolist(), flat.max(axis=0).tolist()
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1

    def finish(self) -> None:
        self.blob.extend(b"\0" * (-len(self.blob) % 4))
        self.gltf.buffers[0].byteLength = len(self.blob)
        self.gltf.set_binary_blob(bytes(self.blob))


def _xyzw(q: np.ndarray) -> np.ndarray:
    return np.asarray(q)[..., [1, 2, 3, 0]]


def _matrix(q: np.ndarray, p: np.ndarray, s: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = R.quat_to_matrix(q) * s
    m[:3, 3] = p
    return m


def skeleton_gltf(rig: Rig, units: float = 1.0, mesh: bool = True) -> tuple[G.GLTF2, list[int]]:
    """A new glTF of `rig`'s joints at rest (translations times `units`, e.g. 0.01 for centimetres), skinned to a
    stick figure (one thin double pyramid per bone) so viewers show it; returns it and each joint's node index."""
    gltf = G.GLTF2(asset=G.Asset(generator="dimgestor", version="2.0"), scene=0, scenes=[G.Scene(nodes=[0])])
    for j, name in enumerate(rig.names):
        gltf.nodes.append(G.Node(name=name, translation=(rig.translations[j] * units).tolist(),
                                 rotation=_xyzw(rig.rotations[j]).tolist(),
                                 children=[k for k, p in enumerate(rig.parents) if p == j] or None))
    if np.abs(rig.scales - 1).max() > 1e-9:
        for j, s in enumerate(rig.scales):
            gltf.nodes[j].scale = [float(s)] * 3
    if mesh:
        _add_stick_figure(gltf, rig, units)
    return gltf, list(range(rig.num_joints))


def _add_stick_figure(gltf: G.GLTF2, rig: Rig, units: float) -> None:
    wq, wp = rig.rest_world()
    wp = wp * units
    ws = rig.world_scales()
    positions, joints, faces = [], [], []
    for c, j in enumerate(rig.parents):
        if j < 0:
            continue
        a, b = wp[j], wp[c]
        length = np.linalg.norm(b - a)
        if length < 1e-6:
            continue
        axis = (b - a) / length
        side = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        up = np.cross(axis, side)
        r = float(np.clip(0.12 * length, 0.004, 0.03))  # metres (wp is in metres already)
        mid = a + 0.2 * (b - a)
        ring = [mid + r * (np.cos(t) * side + np.sin(t) * up) for t in np.arange(4) * np.pi / 2]
        base = len(positions)
        positions += [a, b] + ring
        joints += [j] * 6
        for k in range(4):
            faces += [(base, base + 2 + k, base + 2 + (k + 1) % 4), (base + 1, base + 2 + (k + 1) % 4, base + 2 + k)]
    packer = _Packer(gltf)
    pos = packer.add(np.array(positions), "VEC3", target=_ARRAY, bounds=True)
    joint_ids = np.zeros((len(joints), 4))
    joint_ids[:, 0] = joints
    jnt = packer.add(joint_ids, "VEC4", component=_USHORT, target=_ARRAY)
    weights = np.zeros((len(joints), 4))
    weights[:, 0] = 1.0
    wgt = packer.add(weights, "VEC4", target=_ARRAY)
    idx = packer.add(np.array(faces).reshape(-1), "SCALAR", component=_USHORT, target=_ELEMENTS)
    inverse_bind = np.stack([np.linalg.inv(_matrix(wq[j], wp[j], ws[j])).T for j in range(rig.num_joints)])
    ibm = packer.add(inverse_bind.reshape(-1, 16), "MAT4")
    packer.finish()
    gltf.meshes.append(G.Mesh(name="bones", primitives=[G.Primitive(
        attributes=G.Attributes(POSITION=pos, JOINTS_0=jnt, WEIGHTS_0=wgt), indices=idx)]))
    gltf.skins.append(G.Skin(name="skeleton", joints=list(range(rig.num_joints)), inverseBindMatrices=ibm,
                             skeleton=0))
    gltf.nodes.append(G.Node(name="bones", mesh=0, skin=0))
    gltf.scenes[0].nodes.append(len(gltf.nodes) - 1)


def add_animation(gltf: G.GLTF2, nodes: list[int], fps: float, rotations: np.ndarray | None = None,
                  translations: np.ndarray | None = None, rotate: list[int] = (), translate: list[int] = (),
                  name: str = "dimgestor", weights: dict[int, np.ndarray] | None = None) -> None:
    """One animation: for joint j in `rotate` its rotation track rotations[:, j] (wxyz), in `translate` its
    translation track; `weights`: {node: (T,) values} as the node's translation x (VRM Animation expressions)."""
    T = next(len(a) for a in (rotations, translations, *(weights or {}).values()) if a is not None)
    packer = _Packer(gltf)
    times = packer.add(np.arange(T) / fps, "SCALAR", bounds=True)
    animation = G.Animation(name=name, samplers=[], channels=[])

    def track(node: int, path: str, values: np.ndarray, kind: str) -> None:
        out = packer.add(values, kind)
        animation.samplers.append(G.AnimationSampler(input=times, output=out, interpolation="LINEAR"))
        animation.channels.append(G.AnimationChannel(sampler=len(animation.samplers) - 1,
                                                     target=G.AnimationChannelTarget(node=node, path=path)))

    for j in rotate:
        track(nodes[j], "rotation", _xyzw(R.quat_continuity(R.quat_normalize(rotations[:, j]), axis=0)), "VEC4")
    for j in translate:
        track(nodes[j], "translation", translations[:, j], "VEC3")
    for node, w in (weights or {}).items():
        values = np.zeros((T, 3))
        values[:, 0] = w
        track(node, "translation", values, "VEC3")
    packer.finish()
    gltf.animations.append(animation)


def load_for_animation(source: Rig | str | Path) -> G.GLTF2:
    """A user's GLB/glTF/VRM with every buffer inside one binary blob, ready for `add_animation`: a copy of the
    file a glTF rig was read from (`Rig.document`: not read again), or the file at a path."""
    if isinstance(source, Rig) and source.document is not None:
        gltf, path = copy.deepcopy(source.document), source.path
    else:
        path = source.path if isinstance(source, Rig) else source
        gltf = read_gltf(Path(path))
    if len(gltf.buffers or []) > 1:
        raise RigError(f"{path}: {len(gltf.buffers)} buffers; save it as a single .glb first (Blender: Export glTF "
                       f"Binary)")
    if gltf.buffers and gltf.buffers[0].uri is not None:
        try:
            gltf.convert_buffers(G.BufferFormat.BINARYBLOB)
        except Exception as e:  # a missing .bin beside a .gltf
            raise RigError(f"{path}: cannot read its buffer {gltf.buffers[0].uri!r} ({e})") from None
    return gltf


def save_glb(gltf: G.GLTF2, path: str | Path) -> None:
    gltf.save_binary(str(path))
