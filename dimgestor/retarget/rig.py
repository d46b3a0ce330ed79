"""A target rig: the joints of a BVH skeleton, a glTF/GLB skin or a VRM humanoid, with their rest (bind) pose.

A rig is the joint tree (parents first), each joint's rest local translation, rotation and scale, and the world
transform above its root (a glTF armature node's, identity for BVH). Rotations are wxyz quaternions, as in
`dimgestor.rotations`; space is the file's (BVH: Y up, file units; glTF: Y up, metres). Scales are taken as
uniform per joint (their mean), as rigs are built.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dimgestor import rotations as R
from dimgestor.bvh import BvhError, Skeleton, read_bvh
from dimgestor.retarget.names import canonical_bone

__all__ = ["Rig", "RigError", "load_rig", "GLTF_SUFFIXES"]

GLTF_SUFFIXES = (".glb", ".gltf", ".vrm")


class RigError(ValueError):
    """A target rig that cannot be read or used; the message names the file and what is wrong."""


@dataclass(eq=False)
class Rig:
    names: list[str]
    parents: list[int]              # -1 for the root (one root); parents before children
    translations: np.ndarray        # (J, 3) rest local translations
    rotations: np.ndarray           # (J, 4) rest local rotations, wxyz
    scales: np.ndarray              # (J,) rest local scale (uniform)
    path: str = "<rig>"
    kind: str = "bvh"               # bvh, gltf, vrm0, vrm1
    humanoid: dict[str, str] = field(default_factory=dict)  # {VRM 1.0 bone: joint}, from a VRM file's extension
    base_rotation: np.ndarray = field(default_factory=lambda: R.quat_identity())  # world transform above the root
    base_position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    base_scale: float = 1.0
    skeleton: Skeleton | None = None  # a BVH rig's skeleton (its channels say which joints may translate)
    nodes: list[int] | None = None    # a glTF rig's node index per joint
    document: object = field(default=None, repr=False)  # a glTF rig's file as read (a pygltflib GLTF2), for
    # writing the animation into a copy of it without reading the file again (`gltf.load_for_animation`)

    def __post_init__(self):
        J = len(self.names)
        self.translations = np.asarray(self.translations, dtype=np.float64).reshape(J, 3)
        self.rotations = R.quat_normalize(np.asarray(self.rotations, dtype=np.float64).reshape(J, 4))
        self.scales = np.asarray(self.scales, dtype=np.float64).reshape(J)
        if [p for p in self.parents if p < 0] != [-1] or self.parents[0] != -1:
            raise RigError(f"{self.path}: a rig needs exactly one root joint, first")
        if any(p >= j for j, p in enumerate(self.parents) if p >= 0):
            raise RigError(f"{self.path}: joints must come after their parents")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise RigError(f"{self.path}: no joint named {name!r}") from None

    def can_translate(self, j: int) -> bool:
        """Whether joint j's local translation may be animated (BVH: only joints with position channels)."""
        return self.skeleton is None or self.skeleton.has_position(j)

    @property
    def levels(self) -> list[np.ndarray]:
        """Joint indices by depth (the root's level first): forward kinematics one level at a time."""
        if getattr(self, "_levels", None) is None:
            depth = np.zeros(self.num_joints, dtype=int)
            for j, p in enumerate(self.parents):
                depth[j] = 0 if p < 0 else depth[p] + 1
            self._levels = [np.flatnonzero(depth == d) for d in range(depth.max() + 1)]
        return self._levels

    def world(self, rotations: np.ndarray, translations: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Local rotations (T, J, 4) (and translations (T, J, 3), default rest) -> world rotations and positions."""
        T = rotations.shape[0]
        if translations is None:
            translations = np.broadcast_to(self.translations, (T, self.num_joints, 3))
        wq = np.empty((T, self.num_joints, 4))
        wp = np.empty((T, self.num_joints, 3))
        ws = self.world_scales()
        parents = np.asarray(self.parents)
        root = self.levels[0]
        wq[:, root] = R.quat_mul(self.base_rotation, rotations[:, root])
        wp[:, root] = self.base_position + self.base_scale * R.quat_rotate(
            np.broadcast_to(self.base_rotation, (T, len(root), 4)), translations[:, root])
        for level in self.levels[1:]:
            p = parents[level]
            wq[:, level] = R.quat_mul(wq[:, p], rotations[:, level])
            wp[:, level] = wp[:, p] + ws[p][:, None] * R.quat_rotate(wq[:, p], translations[:, level])
        return wq, wp

    def rest_world(self) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (J, 4) and positions (J, 3) of the rest pose."""
        wq, wp = self.world(self.rotations[None])
        return wq[0], wp[0]

    def world_scales(self) -> np.ndarray:
        """(J,) accumulated scale of each joint's frame (the scale its children's translations are in)."""
        ws = np.empty(self.num_joints)
        for j, p in enumerate(self.parents):
            ws[j] = (self.base_scale if p < 0 else ws[p]) * self.scales[j]
        return ws

    @classmethod
    def from_skeleton(cls, skeleton: Skeleton, path: str = "<skeleton>") -> "Rig":
        """A BVH skeleton's rig: its rest pose is all channels zero (OFFSETs, no rotation)."""
        J = skeleton.num_joints
        return cls(list(skeleton.names), list(skeleton.parents), skeleton.offsets.copy(), R.quat_identity((J,)),
                   np.ones(J), path=path, kind="bvh", skeleton=skeleton)


def load_rig(path: str | Path) -> Rig:
    """Read a target rig from a BVH, glTF/GLB or VRM (0.x or 1.0) file."""
    path = Path(path)
    if not path.exists():
        raise RigError(f"{path}: no such file")
    if path.is_dir():
        raise RigError(f"{path}: is a folder, expected a .bvh, .glb, .gltf or .vrm file")
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        try:
            return Rig.from_skeleton(read_bvh(path).skeleton, str(path))
        except BvhError as e:
            raise RigError(str(e)) from None
    if suffix in GLTF_SUFFIXES:
        return _load_gltf(path)
    raise RigError(f"{path}: unknown rig format {suffix or '(no suffix)'!r}; expected .bvh, .glb, .gltf or .vrm")


# ---- glTF / VRM ----------------------------------------------------------------------------------


def _node_trs(node) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A glTF node's local (translation, wxyz rotation, scale (3,))."""
    if node.matrix is not None:
        m = np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF matrices are column-major
        scale = np.linalg.norm(m[:3, :3], axis=0)
        rot = R.matrix_to_quat(m[:3, :3] / np.where(scale > 0, scale, 1.0))
        return m[:3, 3].copy(), rot, scale
    t = np.asarray(node.translation if node.translation is not None else (0, 0, 0), dtype=np.float64)
    x, y, z, w = node.rotation if node.rotation is not None else (0, 0, 0, 1)  # glTF stores xyzw
    s = np.asarray(node.scale if node.scale is not None else (1, 1, 1), dtype=np.float64)
    return t, R.quat_normalize(np.array([w, x, y, z], dtype=np.float64)), s


def read_gltf(path: Path):
    """A pygltflib GLTF2 for a .gltf, .glb or .vrm file (a VRM is a GLB), or RigError naming the file."""
    from pygltflib import GLTF2

    try:
        data = path.read_bytes()  # (once: a GLB is parsed from these bytes; a .gltf's JSON is read by its loader)
        if data[:4] != b"glTF":
            return GLTF2().load_json(str(path))
        gltf = GLTF2.load_from_bytes(data)
        # a GLB whose buffer is a file beside it (rare) is read by the loader that knows where it lies
        return GLTF2().load_binary(str(path)) if any(b.uri for b in gltf.buffers or []) else gltf
    except Exception as e:  # pygltflib raises whatever its parser meets (KeyError, JSONDecodeError, struct.error)
        raise RigError(f"{path}: not a readable glTF/GLB file ({type(e).__name__}: {e})") from None


def _vrm_humanoid(gltf, path: Path) -> tuple[str, dict[str, int]]:
    ext = gltf.extensions or {}
    if "VRMC_vrm" in ext:
        bones = ext["VRMC_vrm"].get("humanoid", {}).get("humanBones", {})
        out = {}
        for name, entry in bones.items():
            bone = canonical_bone(name)
            if bone is None or not isinstance(entry, dict) or "node" not in entry:
                raise RigError(f"{path}: VRMC_vrm humanoid bone {name!r} is not a VRM 1.0 bone with a node")
            out[bone] = int(entry["node"])
        return "vrm1", out
    if "VRM" in ext:
        out = {}
        for entry in ext["VRM"].get("humanoid", {}).get("humanBones", []):
            bone = canonical_bone(str(entry.get("bone", "")), old_thumbs=True)
            if bone is None or entry.get("node", -1) is None or int(entry.get("node", -1)) < 0:
                continue  # VRM 0.x exporters list unused bones with node -1
            out[bone] = int(entry["node"])
        return "vrm0", out
    return "gltf", {}


def _load_gltf(path: Path) -> Rig:
    gltf = read_gltf(path)
    nodes = gltf.nodes or []
    kind, humanoid_nodes = _vrm_humanoid(gltf, path)
    selected = {int(j) for skin in (gltf.skins or []) for j in skin.joints} | set(humanoid_nodes.values())
    if not selected:
        raise RigError(f"{path}: no skin and no VRM humanoid: nothing to animate (export the armature with its mesh)")
    if max(selected) >= len(nodes):
        raise RigError(f"{path}: a skin or humanoid bone names node {max(selected)}, the file has {len(nodes)} nodes")
    parent = {}
    for i, n in enumerate(nodes):
        for c in n.children or []:
            parent[int(c)] = i

    def ancestors(i):  # i, its parent, ..., a scene root
        out = [i]
        while out[-1] in parent:
            out.append(parent[out[-1]])
            if len(out) > len(nodes):
                raise RigError(f"{path}: the node hierarchy has a cycle")
        return out

    paths = [ancestors(i)[::-1] for i in sorted(selected)]  # scene root first
    if len({p[0] for p in paths}) != 1:
        raise RigError(f"{path}: the skeleton's joints sit under several scene roots")
    top = 0  # the joints' deepest common ancestor is the rig's root
    while all(len(p) > top + 1 for p in paths) and len({p[top + 1] for p in paths}) == 1:
        top += 1
    root = paths[0][top]
    included = {n for p in paths for n in p[top:]}
    order: list[int] = []
    stack = [root]
    while stack:  # depth first, children in file order
        i = stack.pop()
        order.append(i)
        stack.extend(reversed([int(c) for c in nodes[i].children or [] if int(c) in included]))
    index = {n: k for k, n in enumerate(order)}
    trs = [_node_trs(nodes[i]) for i in order]
    names, seen = [], set()
    for i in order:
        name = nodes[i].name or f"node{i}"
        name = name if name not in seen else f"{name}#{i}"  # names must be unique to map bones by name
        seen.add(name)
        names.append(name)
    base_q, base_p, base_s = R.quat_identity(), np.zeros(3), 1.0
    for a in ancestors(root)[1:][::-1]:  # the world transform above the root, top down
        t, q, s = _node_trs(nodes[a])
        base_p = base_p + base_s * R.quat_rotate(base_q, t)
        base_q, base_s = R.quat_mul(base_q, q), base_s * float(np.mean(s))
    return Rig(names, [index[parent[i]] if i != root else -1 for i in order], np.array([t for t, _, _ in trs]),
               np.array([q for _, q, _ in trs]), np.array([float(np.mean(s)) for _, _, s in trs]), path=str(path),
               kind=kind, humanoid={b: names[index[n]] for b, n in humanoid_nodes.items()}, base_rotation=base_q,
               base_position=base_p, base_scale=base_s, nodes=order, document=gltf)
