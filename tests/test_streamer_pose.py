"""Humanoid retargeting and the BVH -> Unity conversion, checked by forward kinematics."""

import json

import numpy as np
import pytest

from dimgestor.bvh import read_bvh
from dimgestor.rotations import quat_mul, quat_normalize, quat_rotate
from dimgestor.training.synthetic import synthetic_skeleton
from streamer.pose import (HUMAN_BODY_BONES, HumanoidMapError, HumanoidRig, load_humanoid_map,
                           to_unity_position, to_unity_quat)


def fk(parents, offsets, root_pos, rotations):
    """World positions and rotations (n, J, .) of a skeleton; the root uses root_pos."""
    n, J = rotations.shape[:2]
    wq, wp = np.zeros((n, J, 4)), np.zeros((n, J, 3))
    for j, p in enumerate(parents):
        if p < 0:
            wq[:, j], wp[:, j] = rotations[:, j], root_pos
        else:
            wq[:, j] = quat_mul(wq[:, p], rotations[:, j])
            wp[:, j] = wp[:, p] + quat_rotate(wq[:, p], np.broadcast_to(offsets[j], (n, 3)))
    return wp, wq


def random_pose(n, J, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)) * 10, quat_normalize(rng.normal(size=(n, J, 4)))


def same_rotation(a, b, atol=1e-9):
    return np.allclose(np.abs(np.sum(a * b, -1)), 1.0, atol=atol)


def test_shipped_map_names_unity_bones_and_zeggs_joints(zeggs_dir):
    m = load_humanoid_map()
    assert set(m) <= set(HUMAN_BODY_BONES)
    skel = read_bvh(next(zeggs_dir.glob("*.bvh"))).skeleton
    missing = [j for j in m.values() if j not in skel.names]
    assert not missing, f"map joints not in the ZEGGS skeleton: {missing}"
    rig = HumanoidRig.build(skel.names, skel.parents, skel.offsets, m)
    assert len(rig.bones) == len(m) == 52
    # Spine1 and Neck1 are folded into the bones below them.
    assert rig.paths[rig.bones.index("Chest")] == (skel.index("Spine1"), skel.index("Spine2"))
    assert rig.paths[rig.bones.index("Head")] == (skel.index("Neck1"), skel.index("Head"))


def test_humanoid_chain_reproduces_skeleton_world_pose(zeggs_dir):
    """Bones posed with the rig's local transforms land where the skeleton's joints are."""
    skel = read_bvh(next(zeggs_dir.glob("*.bvh"))).skeleton
    rig = HumanoidRig.build(skel.names, skel.parents, skel.offsets, load_humanoid_map())
    root, rot = random_pose(5, len(skel.names))
    wp, wq = fk(skel.parents, skel.offsets, root, rot)
    lp, lq = rig.local_pose(root, rot)
    bp, bq = _fk_bones(rig, lp, lq)
    assert np.allclose(bp, wp[:, list(rig.joints)], atol=1e-9)
    assert same_rotation(bq, wq[:, list(rig.joints)])


def _fk_bones(rig, lp, lq):
    n, B = lq.shape[:2]
    wq, wp = np.zeros((n, B, 4)), np.zeros((n, B, 3))
    for b, p in enumerate(rig.parents):
        if p < 0:
            wq[:, b], wp[:, b] = lq[:, b], lp[:, b]
        else:
            wq[:, b] = quat_mul(wq[:, p], lq[:, b])
            wp[:, b] = wp[:, p] + quat_rotate(wq[:, p], lp[:, b])
    return wp, wq


def test_unity_conversion_is_the_x_mirror_of_the_posed_skeleton():
    """FK in Unity space of the converted local pose == the BVH world pose with x negated (and cm -> m)."""
    sk = synthetic_skeleton()
    root, rot = random_pose(4, len(sk.names), seed=1)
    wp, wq = fk(sk.parents, sk.offsets, root, rot)
    up, uq = fk(sk.parents, to_unity_position(sk.offsets), to_unity_position(root), to_unity_quat(rot))
    assert np.allclose(up, wp * np.array([-0.01, 0.01, 0.01]), atol=1e-12)
    # Mirrored rotation matrices: M R M with M = diag(-1, 1, 1).
    assert same_rotation(uq, to_unity_quat(wq))
    assert np.allclose(np.linalg.norm(uq, axis=-1), 1.0)
    # A rotation about +Y by a in BVH is about +Y by -a in Unity.
    a = 0.3
    q = np.array([np.cos(a / 2), 0, np.sin(a / 2), 0])
    assert np.allclose(to_unity_quat(q), [np.cos(a / 2), 0, -np.sin(a / 2), 0])


def test_map_errors_name_the_file_and_the_problem(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"LeftArm": "LeftArm"}))
    with pytest.raises(HumanoidMapError, match=r"bad.json.*'LeftArm' is not a Unity HumanBodyBones"):
        load_humanoid_map(bad)
    bad.write_text('{"Hips": "Hips",\n "Spine": }')
    with pytest.raises(HumanoidMapError, match=r"bad.json:2: not valid JSON"):
        load_humanoid_map(bad)
    bad.write_text(json.dumps({"Hips": "Hips", "Spine": "Hips"}))
    with pytest.raises(HumanoidMapError, match="several bones"):
        load_humanoid_map(bad)
    with pytest.raises(HumanoidMapError, match="not found"):
        load_humanoid_map(tmp_path / "nope.json")


def test_override_map_on_synthetic_skeleton(tmp_path):
    sk = synthetic_skeleton()
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"Hips": sk.names[0], "Head": "NotThere"}))
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map(path))
    assert rig.bones == ("Hips",) and rig.mapping(sk.names) == {"Hips": sk.names[0]}


def test_vectorised_local_pose_equals_the_per_bone_walk(zeggs_dir):
    """The fast path (all bones per step) == the reference walk, for every frame count incl. 1."""
    sk = read_bvh(next(zeggs_dir.glob("*.bvh"))).skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    assert max(len(p) for p in rig.paths) >= 2  # ZEGGS leaves joints out of the map: chains longer than 1
    for n in (1, 7):
        root, rot = random_pose(n, len(sk.names), seed=n)
        fast, ref = rig.local_pose(root, rot), rig.local_pose_reference(root, rot)
        np.testing.assert_allclose(fast[0], ref[0], atol=1e-12)
        np.testing.assert_allclose(fast[1], ref[1], atol=1e-12)


def test_rest_hips_height_is_the_standing_hips_height(zeggs_dir):
    sk = read_bvh(next(zeggs_dir.glob("*.bvh"))).skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    assert 80 < rig.rest_hips_height() < 95  # ZEGGS: cm
    sk2 = synthetic_skeleton()
    rig2 = HumanoidRig.build(sk2.names, sk2.parents, sk2.offsets, {"Hips": sk2.names[0]})
    assert rig2.rest_hips_height() > 0
