"""Retargeting (dimgestor/retarget): our motion onto rigs with other rest poses, proportions, names and joints."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dimgestor import rotations as R
from dimgestor.bvh import BvhMotion, read_bvh, write_bvh
from dimgestor.retarget import Retarget, Rig, RigError, load_rig, resolve_map
from dimgestor.retarget.names import MapError, auto_map, load_map
from dimgestor.streaming.checkpoint import load_checkpoint
from helpers.rigs import a_pose, renamed, subset, with_rest_rotations

LIMIT_DEG = 5.0


@pytest.fixture(scope="module")
def skeleton():
    return load_checkpoint(None).skeleton


@pytest.fixture(scope="module")
def clip(skeleton):
    """3 s of motion on every joint (±35 degrees about each axis, each joint its own phase) and a wandering root."""
    T, J = 60, skeleton.num_joints
    rng = np.random.default_rng(0)
    phase, amp = rng.uniform(0, 6, (1, J, 3)), rng.uniform(0, 0.6, (1, J, 3))
    t = np.arange(T)[:, None, None] / 20
    rotations = R.expmap_to_quat(amp * np.sin(2 * np.pi * 0.7 * t + phase))
    translations = np.broadcast_to(skeleton.offsets, (T, J, 3)).copy()
    translations[:, 0] += 10 * np.sin(t[:, 0] + phase[:, 0])
    return rotations, translations


def _retarget(skeleton, target: Rig, target_map=None) -> Retarget:
    source = Rig.from_skeleton(skeleton, "ours")
    return Retarget(source, target, resolve_map(source), target_map or resolve_map(target))


def bone_angles(rt: Retarget, skeleton, clip, local_q, local_t, corresponding=None, target=None) -> dict[str, float]:
    """Per carried humanoid bone, the worst angle over the clip between its world direction on the target and on
    ours: towards the next carried bone, or for an end bone towards its first child joint (`corresponding`: our
    joint -> the target's, where the target has it; `target`: the rig to pose, default the retarget's)."""
    _, ps = rt.source.world(*clip)
    _, pt = (target or rt.target).world(local_q, local_t)
    out = {}
    for k, label in enumerate(rt.labels):
        if label not in rt.bones:
            continue
        s, t = rt.source_joints[k], rt.target_joints[k]
        if rt.children[k]:
            cs, ct = rt.source_joints[rt.children[k][0]], rt.target_joints[rt.children[k][0]]
        else:
            kids = [j for j, p in enumerate(skeleton.parents) if p == s and corresponding and j in corresponding]
            if not kids:
                continue
            cs, ct = kids[0], corresponding[kids[0]]
        a, b = ps[:, cs] - ps[:, s], pt[:, ct] - pt[:, t]
        cos = np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
        out[label] = float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())
    return out


def test_onto_the_same_skeleton_is_the_identity(skeleton, clip):
    rig = Rig.from_skeleton(skeleton)
    rt = _retarget(skeleton, rig)
    assert len(rt.labels) == skeleton.num_joints  # the humanoid bones and every other joint by its name
    q, t = rt(*clip)
    assert np.allclose(np.abs(np.sum(q * clip[0], axis=-1)), 1.0, atol=1e-9)
    assert np.allclose(t, clip[1], atol=1e-9)


@pytest.mark.parametrize("convention", ["unreal", "mixamo", "smplx", "vroid", "vrm"])
def test_names_of_each_convention_are_recognised(skeleton, convention):
    names = renamed(skeleton.names, skeleton.parents, convention)
    found, mapping = auto_map(names, skeleton.parents)
    _, ours = auto_map(skeleton.names, skeleton.parents)
    assert found == convention
    assert {b: skeleton.names[names.index(j)] for b, j in mapping.items()} == ours  # the same 52 bones


def test_mixamo_namespace_and_unity_names(skeleton):
    mixamo = [f"mixamorig:{n}" for n in skeleton.names]
    assert auto_map(mixamo, skeleton.parents)[1]["leftUpperArm"] == "mixamorig:LeftArm"
    unity = ["Hips", "Spine", "Chest", "Neck", "Head", "LeftUpperArm", "LeftThumbProximal", "LeftThumbIntermediate",
             "LeftThumbDistal"]
    found = auto_map(unity, [-1, 0, 1, 2, 3, 2, 5, 6, 7])[1]
    assert (found["leftThumbMetacarpal"], found["leftThumbProximal"]) == ("LeftThumbProximal", "LeftThumbIntermediate")


@pytest.mark.parametrize("rest", ["bvh", "gltf"])
@pytest.mark.parametrize("degrees", [45.0, 0.0, 70.0])
def test_an_a_pose_copy_with_other_names_and_lengths_follows_every_bone(skeleton, clip, rest, degrees):
    """Renamed (Unreal Mannequin), arms 0.9x, legs 1.1x, hands 1.2x, in metres, arms lowered `degrees` (45: the
    Mannequin's A-pose); as a BVH (rest = no rotation) or with a random rest frame per joint (as glTF skins)."""
    target = Rig.from_skeleton(a_pose(skeleton, degrees), "apose.bvh")
    if rest == "gltf":
        target = with_rest_rotations(target)
    rt = _retarget(skeleton, target)
    assert len(rt.bones) == 52
    q, t = rt(*clip)
    angles = bone_angles(rt, skeleton, clip, q, t, corresponding={j: j for j in range(skeleton.num_joints)})
    assert len(angles) == 52  # every bone, fingers included, end bones towards their end joints
    assert max(angles.values()) <= LIMIT_DEG, {b: round(a, 2) for b, a in angles.items() if a > LIMIT_DEG}


def test_root_motion_is_scaled_by_leg_length(skeleton, clip):
    target = Rig.from_skeleton(a_pose(skeleton, lengths={"leg": 1.3}), "apose.bvh")
    rt = _retarget(skeleton, target)
    assert rt.scale == pytest.approx(0.013)  # legs 1.3x, in metres
    q, t = rt(*clip)
    _, ps = rt.source.world(*clip)
    _, pt = target.world(q, t)
    assert np.allclose(pt[:, 0] - pt[:1, 0], 0.013 * (ps[:, 0] - ps[:1, 0]), atol=1e-9)


def test_a_rig_facing_the_other_way_turns_the_motion_with_it(skeleton, clip):
    """VRM 0.x faces -Z: the same rig turned half a turn about Y gets the motion turned with it."""
    rig = Rig.from_skeleton(a_pose(skeleton), "turned")
    turned = Rig(rig.names, rig.parents, rig.translations, rig.rotations, rig.scales, path="turned",
                 base_rotation=R.quat_from_axis_angle(1, np.pi))
    rt = _retarget(skeleton, turned)
    q, t = rt(*clip)
    unturned = Rig(rig.names, rig.parents, rig.translations, rig.rotations, rig.scales, path="unturned")
    angles = bone_angles(rt, skeleton, clip, q, t, target=unturned)  # directions in the rig's own frame
    assert max(angles.values()) <= LIMIT_DEG


def test_a_rig_without_fingers_and_with_extra_bones(skeleton, clip):
    no_fingers = subset(a_pose(skeleton), drop=lambda n: any(f in n for f in ("thumb", "index", "middle", "ring", "pinky")),
                        extra={"prop_r": ("hand_r", (0.0, 0.1, 0.05)), "twist_l": ("upperarm_l", (0.1, 0.0, 0.0))})
    target = Rig.from_skeleton(no_fingers, "nofingers.bvh")
    rt = _retarget(skeleton, target)
    assert not any("Index" in b or "Thumb" in b for b in rt.bones) and "leftHand" in rt.bones
    q, t = rt(*clip)
    angles = bone_angles(rt, skeleton, clip, q, t)
    assert {"leftUpperArm", "leftLowerArm", "rightUpperLeg", "spine"} <= set(angles)
    assert max(angles.values()) <= LIMIT_DEG
    for extra in ("prop_r", "twist_l"):  # extra bones keep their rest pose
        j = target.index(extra)
        assert np.allclose(q[:, j], target.rotations[j]) and np.allclose(t[:, j], target.translations[j])


def test_a_map_file_overrides_names_and_is_checked(skeleton, tmp_path):
    target = Rig.from_skeleton(a_pose(skeleton), "apose.bvh")
    good = tmp_path / "map.json"
    good.write_text(json.dumps({"leftHand": "x_LeftForeArmEnd", "rightToes": None}))
    mapping = resolve_map(target, good)
    assert mapping["leftHand"] == "x_LeftForeArmEnd" and "rightToes" not in mapping
    missing = tmp_path / "missing.json"
    missing.write_text(json.dumps({"leftUpperArm": "upperarm_left"}))
    with pytest.raises(MapError, match="'leftUpperArm' names joint 'upperarm_left', which the rig does not have"):
        resolve_map(target, missing)
    unknown = tmp_path / "unknown.json"
    unknown.write_text(json.dumps({"leftWing": "upperarm_l"}))
    with pytest.raises(MapError, match="'leftWing' is not a humanoid bone"):
        load_map(unknown, target.names)
    broken = tmp_path / "broken.json"
    broken.write_text('{"hips": "pelvis",\n "spine": }')
    with pytest.raises(MapError, match=r"broken.json:2: not valid JSON"):
        load_map(broken, target.names)


def test_a_map_that_nests_bones_differently_is_refused(skeleton, tmp_path):
    target = Rig.from_skeleton(a_pose(skeleton), "apose.bvh")
    crossed = tmp_path / "crossed.json"
    crossed.write_text(json.dumps({"leftHand": "hand_r", "rightHand": "hand_l"}))
    with pytest.raises(RigError, match="bone '(left|right)Hand' \\(joint 'hand_[lr]'\\) is not under '(left|right)LowerArm'"):
        _retarget(skeleton, target, resolve_map(target, crossed))


def test_unrecognised_names_ask_for_a_map(skeleton):
    names = [f"bone{j}" for j in range(skeleton.num_joints)]
    rig = Rig(names, list(skeleton.parents), skeleton.offsets, R.quat_identity((skeleton.num_joints,)),
              np.ones(skeleton.num_joints), path="odd.bvh")
    with pytest.raises(RigError, match="odd.bvh: cannot tell which of its 75 joints.*bone map"):
        resolve_map(rig)


def test_bvh_on_the_target_skeleton_round_trips(skeleton, clip, tmp_path):
    """`Retarget.motion` writes the target's joint names, offsets and channel order; reading it back gives the pose."""
    target_skeleton = a_pose(skeleton)
    target_skeleton.channels[1] = ["Xrotation", "Yrotation", "Zrotation"]  # another channel order on one joint
    rig_file = tmp_path / "rig.bvh"
    write_bvh(rig_file, BvhMotion(target_skeleton, 0.05, np.zeros((1, target_skeleton.num_channels))))
    target = load_rig(rig_file)
    rt = _retarget(skeleton, target)
    ours = BvhMotion.from_pose(skeleton, 0.05, *clip)
    out = tmp_path / "out.bvh"
    write_bvh(out, rt.motion(ours))
    back = read_bvh(out)
    assert back.skeleton.names == target_skeleton.names and back.skeleton.channels == target_skeleton.channels
    assert np.allclose(back.skeleton.offsets, target_skeleton.offsets, atol=1e-6)
    q, t = rt(ours.rotations(), ours.translations())
    _, want = target.world(q, t)
    _, got = target.world(back.rotations(), back.translations())
    assert np.abs(got - want).max() < 1e-5


@pytest.mark.parametrize("content, message", [
    (None, "no such file"),
    ("HIERARCHY\nROOT Hips\n{\n OFFSET 0 zero 0\n", r"rig.bvh:4: expected a number for the OFFSET"),
    ("not a rig", "unknown rig format"),
])
def test_a_bad_target_file_names_the_file_and_the_fault(tmp_path, content, message):
    path = tmp_path / ("rig.bvh" if content is None or content.startswith("HIER") else "rig.fbx")
    if content is not None:
        path.write_text(content)
    with pytest.raises(RigError, match=message):
        load_rig(path)


def test_a_bad_gltf_names_the_file(tmp_path):
    junk = tmp_path / "junk.glb"
    junk.write_bytes(b"glTF\x02\x00\x00\x00garbage")
    with pytest.raises(RigError, match="junk.glb: not a readable glTF"):
        load_rig(junk)
    empty = tmp_path / "empty.gltf"
    empty.write_text(json.dumps({"asset": {"version": "2.0"}, "nodes": [{"name": "a"}]}))
    with pytest.raises(RigError, match="empty.gltf: no skin and no VRM humanoid"):
        load_rig(empty)
