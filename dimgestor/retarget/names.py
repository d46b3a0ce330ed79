"""Which joint of a rig is which humanoid bone: the VRM 1.0 humanoid bone names, recognised automatically from the
naming conventions rigs come with, or from a map file that overrides them.

The humanoid bones are VRM 1.0's (`hips`, `leftUpperArm`, `leftThumbMetacarpal`, ...): VRM Animation files use them
and every other convention maps onto them. Conventions recognised by name (after dropping a namespace such as
`mixamorig:` and ignoring case):

- "mixamo": Mixamo, Ready Player Me, ZEGGS, BEAT, most BVH (Hips, Spine1, LeftArm, LeftForeArm, LeftHandIndex1);
- "unreal": the Unreal Mannequin (UE4, UE5) and MetaHuman bodies (pelvis, spine_01, clavicle_l, upperarm_l);
- "smplx": SMPL, SMPL-H and SMPL-X (pelvis, left_collar, left_shoulder = the upper arm, left_elbow);
- "vroid": VRoid Studio exports without their VRM extension (J_Bip_C_Hips, J_Bip_L_UpperArm);
- "vrm": VRM 1.0 names used as joint names, or Unity's HumanBodyBones (LeftUpperArm, LeftThumbIntermediate).

The spine is found by the chain between the hips and the neck, whatever its joints are called: one joint is the
spine, two are spine and chest, more are the spine (first), chest (second last) and upper chest (last).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

__all__ = ["HUMAN_BONES", "HUMAN_PARENT", "CONVENTIONS", "MapError", "canonical_bone", "unity_name", "auto_map",
           "load_map", "apply_map", "read_json", "effective_parents"]

_SIDES = ("left", "right")
_FINGERS = ("Thumb", "Index", "Middle", "Ring", "Little")
_THUMB = ("Metacarpal", "Proximal", "Distal")
_PHALANGES = ("Proximal", "Intermediate", "Distal")


def _build_bones() -> dict[str, str | None]:
    """{bone: its parent in the humanoid tree} in VRM 1.0's names, parents first."""
    tree: dict[str, str | None] = {"hips": None, "spine": "hips", "chest": "spine", "upperChest": "chest",
                                   "neck": "upperChest", "head": "neck", "jaw": "head"}
    for s in _SIDES:
        tree |= {f"{s}Eye": "head", f"{s}Shoulder": "upperChest", f"{s}UpperArm": f"{s}Shoulder",
                 f"{s}LowerArm": f"{s}UpperArm", f"{s}Hand": f"{s}LowerArm"}
        for f in _FINGERS:
            parent = f"{s}Hand"
            for part in (_THUMB if f == "Thumb" else _PHALANGES):
                tree[f"{s}{f}{part}"] = parent
                parent = f"{s}{f}{part}"
    for s in _SIDES:
        tree |= {f"{s}UpperLeg": "hips", f"{s}LowerLeg": f"{s}UpperLeg", f"{s}Foot": f"{s}LowerLeg",
                 f"{s}Toes": f"{s}Foot"}
    return tree


HUMAN_PARENT = _build_bones()
HUMAN_BONES: tuple[str, ...] = tuple(HUMAN_PARENT)
_SPINE = ("spine", "chest", "upperChest")

# VRM 0.x and Unity name the thumb's three bones Proximal, Intermediate, Distal; VRM 1.0 Metacarpal, Proximal, Distal.
_OLD_THUMB = {f"{s}Thumb{old}": f"{s}Thumb{new}" for s in _SIDES
              for old, new in zip(_PHALANGES, _THUMB)}


class MapError(ValueError):
    """A bone map that cannot be used; the message names the file, bone or joint."""


def canonical_bone(name: str, old_thumbs: bool = False) -> str | None:
    """A VRM 1.0 bone name for a VRM 0.x / VRM 1.0 / Unity HumanBodyBones name (any case), or None.
    `old_thumbs`: read ThumbProximal/Intermediate/Distal the VRM 0.x / Unity way."""
    key = name[:1].lower() + name[1:]
    if old_thumbs and key in _OLD_THUMB:
        return _OLD_THUMB[key]
    if key in HUMAN_PARENT:
        return key
    lowered = {b.lower(): b for b in HUMAN_PARENT}
    return lowered.get(name.lower())


def unity_name(bone: str) -> str:
    """A VRM 1.0 bone's name in Unity's HumanBodyBones (the names VMC and our WebSocket hello use)."""
    for old, new in _OLD_THUMB.items():
        if bone == new:
            bone = old
            break
    return bone[:1].upper() + bone[1:]


def _fingers(fmt: str, names: dict[str, str], digits=("1", "2", "3")) -> dict[str, str]:
    out = {}
    for s in _SIDES:
        for f in _FINGERS:
            parts = _THUMB if f == "Thumb" else _PHALANGES
            for part, d in zip(parts, digits):
                out[f"{s}{f}{part}"] = fmt.format(side=names[s], finger=names[f], n=d)
    return out


def _sided(table: dict[str, str], sides: dict[str, str]) -> dict[str, str]:
    return {f"{s}{bone}": pattern.format(side=sides[s]) for s in _SIDES for bone, pattern in table.items()}


def _mixamo() -> dict[str, str]:
    sides = {"left": "Left", "right": "Right"}
    names = sides | {f: f for f in _FINGERS} | {"Little": "Pinky"}
    return ({"hips": "Hips", "neck": "Neck", "head": "Head"}
            | _sided({"Shoulder": "{side}Shoulder", "UpperArm": "{side}Arm", "LowerArm": "{side}ForeArm",
                      "Hand": "{side}Hand", "UpperLeg": "{side}UpLeg", "LowerLeg": "{side}Leg",
                      "Foot": "{side}Foot", "Toes": "{side}ToeBase", "Eye": "{side}Eye"}, sides)
            | _fingers("{side}Hand{finger}{n}", names))


def _unreal() -> dict[str, str]:
    sides = {"left": "l", "right": "r"}
    names = sides | {f: f.lower() for f in _FINGERS} | {"Little": "pinky"}
    return ({"hips": "pelvis", "neck": "neck_01", "head": "head"}
            | _sided({"Shoulder": "clavicle_{side}", "UpperArm": "upperarm_{side}", "LowerArm": "lowerarm_{side}",
                      "Hand": "hand_{side}", "UpperLeg": "thigh_{side}", "LowerLeg": "calf_{side}",
                      "Foot": "foot_{side}", "Toes": "ball_{side}", "Eye": "FACIAL_{side}_Eye"}, sides)
            | _fingers("{finger}_0{n}_{side}", names))


def _smplx() -> dict[str, str]:
    sides = {"left": "left", "right": "right"}
    names = sides | {f: f.lower() for f in _FINGERS} | {"Little": "pinky"}
    return ({"hips": "pelvis", "neck": "neck", "head": "head", "jaw": "jaw"}
            | _sided({"Shoulder": "{side}_collar", "UpperArm": "{side}_shoulder", "LowerArm": "{side}_elbow",
                      "Hand": "{side}_wrist", "UpperLeg": "{side}_hip", "LowerLeg": "{side}_knee",
                      "Foot": "{side}_ankle", "Toes": "{side}_foot", "Eye": "{side}_eye_smplhf"}, sides)
            | _fingers("{side}_{finger}{n}", names))


def _vroid() -> dict[str, str]:
    sides = {"left": "L", "right": "R"}
    names = sides | {f: f for f in _FINGERS}
    return ({"hips": "J_Bip_C_Hips", "spine": "J_Bip_C_Spine", "chest": "J_Bip_C_Chest",
             "upperChest": "J_Bip_C_UpperChest", "neck": "J_Bip_C_Neck", "head": "J_Bip_C_Head"}
            | _sided({"Shoulder": "J_Bip_{side}_Shoulder", "UpperArm": "J_Bip_{side}_UpperArm",
                      "LowerArm": "J_Bip_{side}_LowerArm", "Hand": "J_Bip_{side}_Hand",
                      "UpperLeg": "J_Bip_{side}_UpperLeg", "LowerLeg": "J_Bip_{side}_LowerLeg",
                      "Foot": "J_Bip_{side}_Foot", "Toes": "J_Bip_{side}_ToeBase"}, sides)
            | _fingers("J_Bip_{side}_{finger}{n}", names))


def _vrm() -> dict[str, str]:
    return {b: b for b in HUMAN_BONES}


CONVENTIONS: dict[str, dict[str, str]] = {"mixamo": _mixamo(), "unreal": _unreal(), "smplx": _smplx(),
                                          "vroid": _vroid(), "vrm": _vrm()}


def _key(joint: str) -> str:
    """A joint name without its namespace (`mixamorig:`, `Armature|`), lower case."""
    return re.split(r"[:|]", joint)[-1].lower()


def _match(convention: str, names: list[str]) -> dict[str, str]:
    keys: dict[str, str] = {}
    for n in names:
        keys.setdefault(_key(n), n)  # the first joint of a name wins (rigs rarely repeat one)
    found = {b: keys[pattern.lower()] for b, pattern in CONVENTIONS[convention].items() if pattern.lower() in keys}
    if convention == "vrm":
        unity_thumbs = any(_key(n) in ("leftthumbintermediate", "rightthumbintermediate") for n in names)
        if unity_thumbs:  # Unity's HumanBodyBones: Proximal/Intermediate/Distal thumbs are VRM 1.0's three
            found = {b: j for b, j in found.items() if "Thumb" not in b}
            for old, new in _OLD_THUMB.items():
                if old.lower() in keys:
                    found[new] = keys[old.lower()]
    return found


def _spine_chain(names: list[str], parents: list[int], found: dict[str, str]) -> dict[str, str]:
    """spine / chest / upperChest from the joints between the hips and the neck (or the head)."""
    top_bone = next((b for b in ("neck", "head") if b in found), None)
    if "hips" not in found or top_bone is None:
        return {}
    hips, j = names.index(found["hips"]), parents[names.index(found[top_bone])]
    chain = []
    while j not in (-1, hips):
        chain.append(j)
        j = parents[j]
    if j != hips or not chain:
        return {}
    chain.reverse()
    picked = {1: chain[:1], 2: chain[:2]}.get(len(chain), [chain[0], chain[-2], chain[-1]])
    return {b: names[j] for b, j in zip(_SPINE, picked)}


def auto_map(names: list[str], parents: list[int]) -> tuple[str | None, dict[str, str]]:
    """(convention, {bone: joint name}) for a rig's joints: the convention that names the most bones."""
    best, best_map = None, {}
    for convention in CONVENTIONS:
        found = _match(convention, names)
        if len(found) > len(best_map):
            best, best_map = convention, found
    if best is None or "hips" not in best_map:
        return None, {}
    for bone, joint in _spine_chain(names, parents, best_map).items():
        best_map.setdefault(bone, joint)
    return best, {b: best_map[b] for b in HUMAN_BONES if b in best_map}


def read_json(path: str | Path, what: str, error: type[ValueError] = MapError):
    """A JSON file's value; `error` naming the file (and the line) when it is missing or not JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except json.JSONDecodeError as e:
        raise error(f"{path}:{e.lineno}: not valid JSON: {e.msg}") from None


def load_map(path: str | Path, names: list[str], base: dict[str, str] | None = None) -> dict[str, str]:
    """A map file ({bone: joint name or null}, bones in VRM 0.x/1.0 or Unity names) over `base`, checked against
    the rig's joint `names`."""
    return apply_map(read_json(path, "bone map"), names, base, str(path))


def apply_map(data, names: list[str], base: dict[str, str] | None = None, where: str = "map") -> dict[str, str]:
    """A bone map ({bone: joint name or null}) over `base`, checked against the rig's joint `names`; errors
    start with `where` (a file's path)."""
    if not isinstance(data, dict):
        raise MapError(f"{where}: expected a JSON object {{humanoid bone: joint name}}")
    old_thumbs = any(str(k).lower().endswith("thumbintermediate") for k in data)
    out = dict(base or {})
    present = set(names)
    for key, joint in data.items():
        bone = canonical_bone(str(key), old_thumbs)
        if bone is None:
            raise MapError(f"{where}: {key!r} is not a humanoid bone name (VRM 1.0 names such as 'leftUpperArm')")
        if joint is None:
            out.pop(bone, None)
            continue
        if not isinstance(joint, str) or not joint:
            raise MapError(f"{where}: {key!r} must map to a joint name or null, got {joint!r}")
        if joint not in present:
            raise MapError(f"{where}: {key!r} names joint {joint!r}, which the rig does not have")
        out[bone] = joint
    joints = list(out.values())
    dupes = sorted({j for j in joints if joints.count(j) > 1})
    if dupes:
        raise MapError(f"{where}: joints mapped to several bones: {dupes}")
    return {b: out[b] for b in HUMAN_BONES if b in out}


def effective_parents(bones) -> dict[str, str | None]:
    """Each of `bones`' nearest ancestor among `bones` in the humanoid tree (None for the top one)."""
    present = set(bones)
    out = {}
    for b in bones:
        p = HUMAN_PARENT[b]
        while p is not None and p not in present:
            p = HUMAN_PARENT[p]
        out[b] = p
    return out
