"""A small VRM avatar written from scratch for the tests (never downloaded): a skinned glTF binary (GLB) with a
T-posed humanoid skeleton, one box per bone, and the VRM humanoid extension of VRM 1.0 (`VRMC_vrm`, facing +Z)
or VRM 0.x (`VRM`, facing -Z as UniVRM exports it); with `expressions`, the preset expressions a face drives
(EXPRESSIONS, VRM 1.0 names; VRM 0.x presets a, i, u, e, o, blink, blink_l, blink_r, joy), expression k bound to
morph target k of the mesh, which moves the head box's lower corners down."""

from __future__ import annotations

import json
import struct

import numpy as np

# (VRM humanoid bone, parent, local translation in metres), T-pose, facing +Z, the avatar's left at +X.
BONES = [
    ("hips", None, (0.0, 0.95, 0.0)), ("spine", "hips", (0.0, 0.10, 0.0)), ("chest", "spine", (0.0, 0.15, 0.0)),
    ("neck", "chest", (0.0, 0.22, 0.0)), ("head", "neck", (0.0, 0.10, 0.0)),
]
for _s, _x in (("left", 1.0), ("right", -1.0)):
    BONES += [
        (f"{_s}Shoulder", "chest", (0.04 * _x, 0.18, 0.0)), (f"{_s}UpperArm", f"{_s}Shoulder", (0.12 * _x, 0.0, 0.0)),
        (f"{_s}LowerArm", f"{_s}UpperArm", (0.27 * _x, 0.0, 0.0)), (f"{_s}Hand", f"{_s}LowerArm", (0.24 * _x, 0.0, 0.0)),
        (f"{_s}UpperLeg", "hips", (0.10 * _x, -0.05, 0.0)), (f"{_s}LowerLeg", f"{_s}UpperLeg", (0.0, -0.42, 0.0)),
        (f"{_s}Foot", f"{_s}LowerLeg", (0.0, -0.42, 0.0)),
    ]


# The preset expressions of a face (VRM 1.0 names) and their VRM 0.x preset names, in morph target order.
EXPRESSIONS = ("aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft", "blinkRight", "happy")
V0_PRESETS = ("a", "i", "u", "e", "o", "blink", "blink_l", "blink_r", "joy")


def make_vrm(version: str = "1.0", expressions: bool = False, arms_down: float = 0.0) -> bytes:
    """The avatar as .vrm bytes; version "1.0" or "0.0"; expressions: with EXPRESSIONS (one morph target each);
    arms_down: its rest pose with both arms lowered that many degrees at the shoulder joint (45: an A-pose, as
    many non-VRM rigs and some converted VRMs are)."""
    flip = np.array([-1.0, 1.0, -1.0]) if version == "0.0" else np.ones(3)  # VRM 0.x faces -Z
    names = [b for b, _, _ in BONES]
    local = np.array([t for _, _, t in BONES], dtype=np.float64)
    if arms_down:
        local = _lower_arms(names, local, np.radians(arms_down))
    local = local * flip
    world = np.zeros_like(local)
    for i, (_, parent, _) in enumerate(BONES):
        world[i] = local[i] + (world[names.index(parent)] if parent else 0.0)

    # One 4 cm box per bone, bound to that bone only.
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32) * 0.02
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([[q[0], q[1], q[2], q[0], q[2], q[3]] for q in quads]).reshape(-1)
    pos = np.concatenate([world[i] + corners for i in range(len(BONES))]).astype(np.float32)
    joints = np.repeat(np.arange(len(BONES)), 8)[:, None] * np.array([1, 0, 0, 0])
    weights = np.tile(np.array([1, 0, 0, 0], np.float32), (len(pos), 1))
    idx = np.concatenate([faces + 8 * i for i in range(len(BONES))]).astype(np.uint16)
    ibm = np.tile(np.eye(4, dtype=np.float32), (len(BONES), 1, 1))
    ibm[:, 3, :3] = -world  # column-major: the translation is the last column, stored as the 4th row here
    blobs = [pos.tobytes(), joints.astype(np.uint16).tobytes(), weights.tobytes(), idx.tobytes(), ibm.tobytes()]
    targets = []
    if expressions:  # target k: the head box's lower corners down (2 cm for an open A, 1 cm for the others)
        head = names.index("head")
        for k in range(len(EXPRESSIONS)):
            d = np.zeros_like(pos)
            d[8 * head: 8 * head + 8][corners[:, 1] < 0, 1] = -0.02 if k == 0 else -0.01
            targets.append(d)
            blobs.append(d.tobytes())
    views, offset = [], 0
    for b in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(b)})
        offset += (len(b) + 3) // 4 * 4
    binary = b"".join(b + b"\0" * ((-len(b)) % 4) for b in blobs)
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
         "min": pos.min(0).tolist(), "max": pos.max(0).tolist()},
        {"bufferView": 1, "componentType": 5123, "count": len(pos), "type": "VEC4"},
        {"bufferView": 2, "componentType": 5126, "count": len(pos), "type": "VEC4"},
        {"bufferView": 3, "componentType": 5123, "count": len(idx), "type": "SCALAR"},
        {"bufferView": 4, "componentType": 5126, "count": len(BONES), "type": "MAT4"},
    ] + [{"bufferView": 5 + k, "componentType": 5126, "count": len(pos), "type": "VEC3", "min": d.min(0).tolist(),
          "max": d.max(0).tolist()} for k, d in enumerate(targets)]
    nodes = [{"name": n, "translation": local[i].tolist()} for i, n in enumerate(names)]
    for i, (_, parent, _) in enumerate(BONES):
        if parent:
            nodes[names.index(parent)].setdefault("children", []).append(i)
    body, armature = len(nodes), len(nodes) + 1
    nodes += [{"name": "body", "mesh": 0, "skin": 0}, {"name": "Armature", "children": [0]}]
    gltf = {
        "asset": {"version": "2.0", "generator": "dimgestor tests"},
        "scene": 0, "scenes": [{"nodes": [armature, body]}], "nodes": nodes,
        "meshes": [{"name": "body", "primitives": [{"attributes": {"POSITION": 0, "JOINTS_0": 1, "WEIGHTS_0": 2},
                                                     "indices": 3, "material": 0,
                                                     **({"targets": [{"POSITION": 5 + k} for k in range(len(targets))]}
                                                        if targets else {})}]}],
        "materials": [{"name": "skin", "pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.6, 0.5, 1.0]}}],
        "skins": [{"joints": list(range(len(BONES))), "inverseBindMatrices": 4, "skeleton": 0}],
        "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(binary)}],
    }
    if version == "1.0":
        gltf["extensionsUsed"] = ["VRMC_vrm"]
        gltf["extensions"] = {"VRMC_vrm": {
            "specVersion": "1.0",
            "meta": {"name": "dimgestor test avatar 1.0", "version": "1", "authors": ["dimgestor tests"],
                     "licenseUrl": "https://vrm.dev/licenses/1.0/", "avatarPermission": "onlyAuthor",
                     "commercialUsage": "personalNonProfit", "creditNotation": "required", "allowRedistribution": False,
                     "modification": "prohibited"},
            "humanoid": {"humanBones": {n: {"node": i} for i, n in enumerate(names)}},
        }}
        if expressions:
            gltf["extensions"]["VRMC_vrm"]["expressions"] = {"preset": {
                n: {"morphTargetBinds": [{"node": body, "index": k, "weight": 1.0}]}
                for k, n in enumerate(EXPRESSIONS)}}
    else:
        gltf["extensionsUsed"] = ["VRM"]
        gltf["extensions"] = {"VRM": {
            "exporterVersion": "dimgestor tests", "specVersion": "0.0",
            "meta": {"title": "dimgestor test avatar 0.x", "version": "1", "author": "dimgestor tests",
                     "allowedUserName": "OnlyAuthor", "licenseName": "Other"},
            "humanoid": {"humanBones": [{"bone": n, "node": i, "useDefaultValues": True} for i, n in enumerate(names)]},
            "firstPerson": {"firstPersonBone": names.index("head"), "meshAnnotations": []},
            "blendShapeMaster": {"blendShapeGroups": [
                {"name": p.upper(), "presetName": p, "binds": [{"mesh": 0, "index": k, "weight": 100}]}
                for k, p in enumerate(V0_PRESETS if expressions else ())]},
            "secondaryAnimation": {"boneGroups": [], "colliderGroups": []},
            "materialProperties": [{"name": "skin", "shader": "VRM_USE_GLTFSHADER"}],
        }}
    text = json.dumps(gltf).encode()
    text += b" " * ((-len(text)) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def _lower_arms(names: list[str], local: np.ndarray, angle: float) -> np.ndarray:
    """Local translations with each arm below the upper arm turned down by `angle` (about +Z, the facing)."""
    parents = [names.index(p) if p else -1 for _, p, _ in BONES]
    world = np.zeros_like(local)
    for i, p in enumerate(parents):
        world[i] = local[i] + (world[p] if p >= 0 else 0.0)
    for side, sign in (("left", -1.0), ("right", 1.0)):
        top = names.index(f"{side}UpperArm")
        c, s_ = np.cos(sign * angle), np.sin(sign * angle)
        turn = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        below = [i for i in range(len(names)) if _under(parents, i, top)]
        world[below] = world[top] + (world[below] - world[top]) @ turn.T
    return np.array([world[i] - (world[p] if p >= 0 else 0.0) for i, p in enumerate(parents)])


def _under(parents: list[int], i: int, top: int) -> bool:
    while parents[i] >= 0:
        i = parents[i]
        if i == top:
            return True
    return False
