"""Headless Blender as an independent reader of exported motion: import a .glb/.gltf (its glTF importer) or a .bvh
(its BVH importer), play the animation and read back where each bone is, in the file's own coordinates, to compare
with our forward kinematics. One Blender process per file (it takes about a second to start), every key in one go.

Blender is Z up: both importers turn the file's Y up into Z up, file (x, y, z) -> Blender (x, -z, y) (the glTF
importer always; the BVH importer with axis_forward -Z, axis_up Y, its defaults), lengths unchanged (glTF metres,
BVH file units at global_scale 1). Positions come back turned the other way, into the file's frame."""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from helpers.clients import REPO

BLENDER = shutil.which("blender")
SCRIPT = REPO / "tests" / "blender" / "bone_positions.py"
SKIP_REASON = None if BLENDER else "blender not installed (Debian: apt-get install blender python3-numpy)"
needs_blender = pytest.mark.skipif(BLENDER is None, reason=SKIP_REASON or "")
NO_NUMPY = 3  # the script's exit status when Blender's Python lacks numpy (its glTF importer needs it)
BLENDER_TO_FILE = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # Blender (X, Y, Z) -> file (X, Z, -Y)


class BonePositions(NamedTuple):
    names: list[str]  # armature bones: glTF skin joints' node names, BVH joint names (End Sites have none)
    times: np.ndarray  # (T,) seconds from the animation's start, one per key (see bone_world_positions)
    positions: np.ndarray  # (T, J, 3) bone heads in world space, file coordinates and units


def bone_world_positions(path: str | Path, timeout: float = 120) -> BonePositions:
    """Where Blender puts each bone's head (the joint) at each key of the file's animation.

    BVH: every frame of the file, frame k at k * Frame Time. glTF: every keyframe time of the first animation (the
    union over its channels), in seconds; Blender keys time t at frame t * fps and is evaluated there, between two
    frames when t is not on one. Between keys Blender interpolates quaternion components linearly, not by slerp,
    so only the keys are sampled. A file without animation gives its rest pose once, at time 0. glTF nodes become
    bones only as a skin's joints: the bare nodes of a VRMA come in as empties, which this does not read."""
    if BLENDER is None:
        pytest.skip(SKIP_REASON)
    with tempfile.TemporaryDirectory(prefix="blender-") as tmp:
        out = Path(tmp) / "positions.json"
        cmd = [BLENDER, "-b", "--factory-startup", "--python-exit-code", "1", "--python", str(SCRIPT), "--",
               str(Path(path).resolve()), str(out)]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        if r.returncode == NO_NUMPY:
            pytest.skip("Blender's Python has no numpy, which its glTF importer needs (Debian: apt-get install "
                        "python3-numpy)")
        if r.returncode != 0 or not out.exists():
            raise RuntimeError(f"blender failed on {path} (exit {r.returncode}):\n{(r.stdout + r.stderr)[-3000:]}")
        d = json.loads(out.read_text())
    positions = np.asarray(d["positions"], np.float64).reshape(len(d["times"]), len(d["names"]), 3)
    return BonePositions(d["names"], np.asarray(d["times"]), positions @ BLENDER_TO_FILE.T)
