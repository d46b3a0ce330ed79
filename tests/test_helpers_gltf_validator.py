"""tests/helpers/gltf_validator.py: the Khronos glTF validator passes the tiny files the tests write (an animated
skinned GLB, a VRMA, the test VRM avatars) and catches a broken one."""

from __future__ import annotations

import numpy as np
import pytest

from helpers.gltf_validator import errors, needs_validator, validate
from helpers.vrm_model import make_vrm

pytestmark = needs_validator
pygltflib = pytest.importorskip("pygltflib", reason="install the test extra: pip install -e '.[test]'")
from helpers.animated_gltf import Clip, Rig, write_glb  # noqa: E402

RIG = Rig(["hips", "spine", "head"], [-1, 0, 1], [[0, 1, 0], [0, 0.2, 0], [0, 0.3, 0]])
TURN = np.array([[0, 0, 0, 1], [0, np.sin(0.3), 0, np.cos(0.3)]])  # 0.6 rad about Y
CLIP = Clip(np.array([0.0, 0.5]), {1: TURN}, {0: np.array([[0, 1, 0], [0.1, 1, 0]])})


def test_an_animated_skinned_glb_is_valid(tmp_path):
    report = validate(write_glb(tmp_path / "clip.glb", RIG, CLIP))
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]
    assert report["info"]["animationCount"] == 1 and report["info"]["hasSkins"]


def test_a_vrma_is_valid_glTF(tmp_path):
    report = validate(write_glb(tmp_path / "clip.vrma", RIG, CLIP, humanoid={"hips": 0, "spine": 1, "head": 2}))
    assert report["issues"]["numErrors"] == 0, errors(report)
    assert report["info"]["extensionsUsed"] == ["VRMC_vrm_animation"]  # reported as unsupported (an info), no more


@pytest.mark.parametrize("version", ["1.0", "0.0"])
def test_the_test_avatars_are_valid(tmp_path, version):
    (tmp_path / "avatar.vrm").write_bytes(make_vrm(version, expressions=True))
    report = validate(tmp_path / "avatar.vrm")
    assert report["issues"]["numErrors"] == 0, errors(report)


def test_an_accessor_past_the_end_of_its_buffer_is_an_error(tmp_path):
    path = write_glb(tmp_path / "clip.glb", RIG, CLIP)
    gltf = pygltflib.GLTF2().load(str(path))
    gltf.accessors[0].count *= 100  # POSITION: now far more vertices than its bufferView holds
    gltf.save_binary(str(path))
    report = validate(path)
    assert report["issues"]["numErrors"] > 0
    assert any(" at /accessors/0" in e for e in errors(report)), errors(report)


def test_a_file_that_is_not_glTF_raises(tmp_path):
    (tmp_path / "nothing.glb").write_bytes(b"hello")
    with pytest.raises(RuntimeError, match="could not detect glTF format"):
        validate(tmp_path / "nothing.glb")
