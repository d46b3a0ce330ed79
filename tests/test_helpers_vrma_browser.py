"""tests/helpers/vrma_browser.py: a hand-built VRMA played by three-vrm-animation on the test avatars in Chromium.
The performer is the avatar's skeleton at 1.2x its size, T-posed facing +Z; over 1 s its left upper arm turns 60
degrees down and its hips walk 36 cm forward. Each of the avatar's bones lands where our forward kinematics puts
the avatar's own skeleton in that pose, the hips positions scaled by the ratio of hips heights (0.95 / 1.14), for
VRM 1.0 and VRM 0.x (facing -Z in its file) alike, and whatever rest rotations the VRMA's nodes carry."""

from __future__ import annotations

import numpy as np
import pytest

from dimgestor import rotations as R
from helpers.browser import read_png
from helpers.vrm_model import BONES, make_vrm
from helpers.vrma_browser import needs_vrma_browser, play_vrma

pytestmark = needs_vrma_browser
pytest.importorskip("pygltflib", reason="install the test extra: pip install -e '.[test]'")
from helpers.animated_gltf import Clip, Rig, world_positions, write_glb, wxyz  # noqa: E402

NAMES = [b for b, _, _ in BONES]
PARENTS = [NAMES.index(p) if p else -1 for _, p, _ in BONES]
REST = np.array([t for _, _, t in BONES])  # the avatar's T-pose, metres
SCALE = 1.2  # the performer's size over the avatar's
ARM, HIPS = NAMES.index("leftUpperArm"), NAMES.index("hips")
KEYS = np.array([0.0, 0.5, 1.0])
DOWN = np.radians([0.0, -30.0, -60.0])  # about +Z: the arm along +X turns towards -Y
ARM_TURN = np.stack([np.zeros(3), np.zeros(3), np.sin(DOWN / 2), np.cos(DOWN / 2)], axis=-1)  # (x, y, z, w)
# The avatar's hips path (the performer's is SCALE times this): from 5 cm left of and 10 cm in front of its rest
# position (a track holds positions, not offsets from rest), 30 cm forward and 5 cm down.
HIPS_PATH = REST[HIPS] + [0.05, 0.0, 0.1] + np.outer(KEYS, [0.0, -0.05, 0.3])
TIMES = [0.0, 0.5, 1.0, 1.5]  # the keys, then past the end (the clip holds its last key)
ARM_LENGTH = 0.27 + 0.24  # upper arm to hand (helpers/vrm_model.py)


def q_mul(a, b):
    """Hamilton product of (x, y, z, w) quaternions."""
    (ax, ay, az, aw), (bx, by, bz, bw) = np.moveaxis(a, -1, 0), np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def write_vrma(path, rest_turn: bool):
    """rest_turn: the performer's upper arm node has a rest rotation of its own (90 degrees about Y, as an exporter
    aligning bones with their local axes writes), its child's translation and rotation undo it (the same T-pose in
    world space), and its keys are local rotations in that frame: the same motion, written another way."""
    rest = np.tile([0.0, 0, 0, 1], (len(NAMES), 1))
    local = REST * SCALE
    turn = ARM_TURN
    if rest_turn:
        rest[ARM] = [0, np.sin(np.pi / 4), 0, np.cos(np.pi / 4)]
        undo = R.quat_conj(wxyz(rest[ARM]))
        local[ARM + 1] = R.quat_rotate(undo, local[ARM + 1])
        rest[ARM + 1] = np.roll(undo, -1)
        turn = q_mul(ARM_TURN, rest[ARM])
    rig = Rig(NAMES, PARENTS, local, rest)
    clip = Clip(KEYS, {ARM: turn}, {HIPS: HIPS_PATH * SCALE})
    t_pose = world_positions(Rig(NAMES, PARENTS, REST * SCALE), Clip(KEYS[:1]))
    assert np.allclose(world_positions(rig, Clip(KEYS[:1])), t_pose)  # the same T-pose either way
    return write_glb(path, rig, clip, humanoid={n: j for j, n in enumerate(NAMES)})


def expected() -> np.ndarray:
    """(len(TIMES), J, 3) the avatar's own skeleton in the pose, by forward kinematics."""
    at_keys = world_positions(Rig(NAMES, PARENTS, REST), Clip(KEYS, {ARM: ARM_TURN}, {HIPS: HIPS_PATH}))
    return np.concatenate([at_keys, at_keys[-1:]])


def skin_pixels(png) -> int:
    img = read_png(png)
    return int(((img[..., 0] > 0.45) & (img[..., 0] > img[..., 2] + 0.15)).sum())  # the avatar's boxes


@pytest.mark.parametrize("version, rest_turn", [("1.0", False), ("0.0", False), ("1.0", True)])
def test_a_vrma_moves_the_avatar_where_forward_kinematics_puts_it(tmp_path, version, rest_turn):
    vrma = write_vrma(tmp_path / "arm_down.vrma", rest_turn)
    got = play_vrma(tmp_path, make_vrm(version), vrma, TIMES, name=f"vrma_{version}{'_rest_turn' * rest_turn}")
    assert got.meta_version == version[0] and got.duration == pytest.approx(1.0)
    np.testing.assert_allclose(got.rest_hips, REST[HIPS] * SCALE, atol=1e-6)

    want = expected()
    for j, bone in enumerate(NAMES):
        np.testing.assert_allclose(got.position(bone), want[:, j], atol=1e-4, err_msg=bone)
    # The same in words: the hand starts at T-pose height and ends ARM_LENGTH * sin 60 lower (and 5 cm more with
    # the hips), 30 cm further forward (the performer's 36 cm scaled to the avatar).
    hand = got.position("leftHand")
    assert hand[0, 1] == pytest.approx(0.95 + 0.10 + 0.15 + 0.18, abs=1e-4)
    assert hand[0, 1] - hand[2, 1] == pytest.approx(ARM_LENGTH * np.sin(np.radians(60)) + 0.05, abs=1e-4)
    assert hand[2, 2] - hand[0, 2] == pytest.approx(0.3, abs=1e-4)

    for png in got.screenshots:
        assert skin_pixels(png) > 300, f"{png}: the avatar is not visible"
    first, moved = read_png(got.screenshots[0]), read_png(got.screenshots[2])
    assert (np.abs(first - moved).max(axis=2) > 0.1).sum() > 100, "the arm did not move on screen"
