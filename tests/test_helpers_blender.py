"""tests/helpers/blender.py: headless Blender reads back a BVH and an animated glTF we wrote, and each bone lands
where our own forward kinematics puts it, in the file's coordinates, at the file's frame times."""

from __future__ import annotations

import numpy as np
import pytest

from dimgestor import rotations as R
from dimgestor.bvh import BvhMotion, Skeleton, forward_kinematics, read_bvh, write_bvh
from helpers.blender import bone_world_positions, needs_blender

pytestmark = needs_blender


def test_a_bvh_in_blender_matches_forward_kinematics(tmp_path):
    """Ten frames, a moving root, a different rotation order per joint, centimetre-like file units."""
    skeleton = Skeleton(
        names=["Hips", "Spine", "Head", "LeftArm", "LeftHand"], parents=[-1, 0, 1, 1, 3],
        offsets=[[0, 90, 0], [0, 10, 0], [0, 30, 0], [5, 25, 0], [25, 0, 0]],
        channels=[["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"],
                  ["Zrotation", "Xrotation", "Yrotation"], ["Xrotation", "Yrotation", "Zrotation"],
                  ["Yrotation", "Zrotation", "Xrotation"], ["Zrotation", "Yrotation", "Xrotation"]],
        end_sites={2: [0, 10, 0], 4: [10, 0, 0]})
    T = 10
    k = np.arange(T)[:, None]
    values = np.zeros((T, skeleton.num_channels))
    values[:, :3] = [3, 90, -2] + k * [1.5, 0.5, 2.0]
    values[:, 3:] = np.random.default_rng(0).uniform(-70, 70, (1, skeleton.num_channels - 3)) * np.sin(0.3 * k + 0.2)
    path = tmp_path / "walk.bvh"
    write_bvh(path, BvhMotion(skeleton, 1 / 30, values))

    got = bone_world_positions(path)
    assert got.names == skeleton.names
    np.testing.assert_allclose(got.times, np.arange(T) / 30, atol=1e-9)
    np.testing.assert_allclose(got.positions, forward_kinematics(read_bvh(path)), atol=1e-3)


def test_an_animated_gltf_in_blender_matches_forward_kinematics(tmp_path):
    """Keys at 30 fps (Blender's scene runs at 24: most fall between its frames), a moving root, a joint with a rest
    rotation of its own."""
    pytest.importorskip("pygltflib", reason="install the test extra: pip install -e '.[test]'")
    from helpers.animated_gltf import Clip, Rig, world_positions, write_glb

    rig = Rig(["root", "spine", "head", "arm", "hand"], [-1, 0, 1, 1, 3],
              [[0, 1, 0], [0, 0.2, 0], [0, 0.3, 0], [0.1, 0.2, 0], [0.3, 0, 0]],
              [[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 1], [0, 0, np.sin(0.4), np.cos(0.4)], [0, 0, 0, 1]])
    K = 10
    rng = np.random.default_rng(1)
    turns = {j: np.roll(R.quat_normalize(rng.normal(size=(K, 4)) * [4, 1, 1, 1]), -1, axis=-1) for j in (0, 1, 3, 4)}
    clip = Clip(np.arange(K) / 30, turns, {0: [0, 1, 0] + np.arange(K)[:, None] * [0.01, 0.005, 0.02]})
    path = write_glb(tmp_path / "clip.glb", rig, clip)

    got = bone_world_positions(path)
    assert got.names == rig.names
    np.testing.assert_allclose(got.times, clip.times, atol=1e-6)
    np.testing.assert_allclose(got.positions, world_positions(rig, clip), atol=1e-3)  # metres


def test_a_file_blender_cannot_read_is_an_error(tmp_path):
    path = tmp_path / "broken.glb"
    path.write_bytes(b"not a glTF")
    with pytest.raises(RuntimeError, match="blender failed"):
        bone_world_positions(path)
