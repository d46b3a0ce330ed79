"""The files `dimgestor generate` writes (.glb, .vrma, .bvh on a target), checked with the tools that open them:
the Khronos glTF validator, Blender (headless) and @pixiv/three-vrm-animation in Chromium; skip where absent."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from dimgestor import rotations as R
from dimgestor.audio import SAMPLE_RATE, load_wav, save_wav
from dimgestor.bvh import BvhMotion, forward_kinematics, write_bvh
from dimgestor.retarget import Retarget, load_rig, resolve_map
from dimgestor.retarget.export import write_motion
from dimgestor.retarget.names import auto_map
from dimgestor.retarget.rig import Rig
from dimgestor.streaming.checkpoint import load_checkpoint
from helpers import warm
from helpers.blender import bone_world_positions, needs_blender
from helpers.clients import REPO, SPEECH_WAV
from helpers.gltf_validator import errors, needs_validator, validate
from helpers.rigs import a_pose
from helpers.vrm_model import BONES, make_vrm
from helpers.vrma_browser import needs_vrma_browser, play_gltf, play_vrma

FPS = 20


@pytest.fixture(scope="module")
def motion():
    """2 s on our skeleton: every joint swinging (±30 degrees about each axis) and the root wandering."""
    sk = load_checkpoint(None).skeleton
    T, J = 2 * FPS, sk.num_joints
    rng = np.random.default_rng(1)
    phase, amp = rng.uniform(0, 6, (1, J, 3)), rng.uniform(0, 0.5, (1, J, 3))
    t = np.arange(T)[:, None, None] / FPS
    q = R.expmap_to_quat(amp * np.sin(2 * np.pi * 0.8 * t + phase))
    tr = np.broadcast_to(sk.offsets, (T, J, 3)).copy()
    tr[:, 0] += [8.0, 2.0, 6.0] * np.sin(t[:, 0] + phase[:, 0])
    return BvhMotion.from_pose(sk, 1 / FPS, q, tr)


@pytest.fixture(scope="module")
def files(motion, tmp_path_factory):
    """Each kind of file once: ours as GLB and VRMA, on an A-pose BVH as BVH and GLB, on both test VRMs as GLB."""
    d = tmp_path_factory.mktemp("files")
    rig = a_pose(motion.skeleton)
    write_bvh(d / "apose.bvh", BvhMotion(rig, 1 / FPS, np.zeros((1, rig.num_channels))))
    (d / "avatar1.vrm").write_bytes(make_vrm("1.0", expressions=True))
    (d / "avatar0.vrm").write_bytes(make_vrm("0.0"))
    face = {"aa": np.linspace(0, 1, motion.num_frames), "blink": np.zeros(motion.num_frames)}
    out = {"ours.glb": (None, None), "ours.vrma": (None, face), "apose.bvh": (d / "apose.bvh", None),
           "apose.glb": (d / "apose.bvh", None), "avatar1.glb": (d / "avatar1.vrm", None),
           "avatar0.glb": (d / "avatar0.vrm", None)}
    for name, (target, f) in out.items():
        write_motion(d / f"out_{name}", motion, target, face=f)
    return d


@needs_validator
@pytest.mark.parametrize("name", ["ours.glb", "ours.vrma", "apose.glb", "avatar1.glb", "avatar0.glb"])
def test_the_validator_reports_no_errors(files, name):
    report = validate(files / f"out_{name}")
    assert report["issues"]["numErrors"] == 0, errors(report)
    ours = [m for m in report["issues"]["messages"] if m["severity"] <= 1 and "extensions" not in m.get("pointer", "")]
    if name in ("ours.glb", "apose.glb", "ours.vrma"):  # (the test avatars bring their own VRM 0 warning)
        assert not ours, ours


def _ours_world(motion) -> np.ndarray:
    return forward_kinematics(motion)


@needs_blender
def test_blender_opens_our_glb_and_bvh_where_we_put_every_bone(motion, files, tmp_path):
    want = _ours_world(motion)  # (T, J, 3) centimetres
    glb = bone_world_positions(files / "out_ours.glb")
    assert len(glb.times) == motion.num_frames and np.allclose(glb.times, np.arange(motion.num_frames) / FPS)
    order = [glb.names.index(n) for n in motion.skeleton.names]
    assert np.abs(glb.positions[:, order] - want * 0.01).max() < 1e-4  # metres: 0.1 mm
    write_bvh(tmp_path / "ours.bvh", motion)
    bvh = bone_world_positions(tmp_path / "ours.bvh")
    keep = [j for j, n in enumerate(motion.skeleton.names) if n in bvh.names]
    got = bvh.positions[:, [bvh.names.index(motion.skeleton.names[j]) for j in keep]]
    assert np.abs(got - want[:, keep]).max() < 1e-2  # centimetres (BVH writes 6 decimals)


@needs_blender
def test_blender_opens_the_retargeted_bvh_and_glb(motion, files):
    target = load_rig(files / "apose.bvh")
    source = Rig.from_skeleton(motion.skeleton)
    rt = Retarget(source, target, resolve_map(source), resolve_map(target))
    _, want = target.world(*rt(motion.rotations(), motion.translations()))  # metres (the A-pose rig's unit)
    for name in ("apose.bvh", "apose.glb"):
        got = bone_world_positions(files / f"out_{name}")
        order = [got.names.index(n) for n in target.names if n in got.names]
        keep = [j for j, n in enumerate(target.names) if n in got.names]
        assert len(keep) >= 52
        assert np.abs(got.positions[:, order] - want[:, keep]).max() < 1e-4, name


@needs_blender
def test_blender_converts_our_glb_to_fbx_as_the_docs_say(motion, files, tmp_path):
    """docs/avatars.md's FBX command, run as written (on files here), then the FBX read back: every bone there,
    where ours is at frame 5 (0.25 s: Blender's frame 6 at its 24 fps; its FBX round trip starts the action one
    frame later, so 7)."""
    import json
    import re
    import subprocess

    from helpers.blender import BLENDER

    doc = (REPO / "docs" / "avatars.md").read_text()
    expr = re.search(r'blender -b --python-expr "(.*?)"\n', doc).group(1)
    fbx, out = tmp_path / "speech.fbx", tmp_path / "bones.json"
    expr = expr.replace("'speech.glb'", repr(str(files / "out_ours.glb"))).replace("'speech.fbx'", repr(str(fbx)))
    run = subprocess.run([BLENDER, "-b", "--factory-startup", "--python-expr", _numpy_shim() + expr],
                         capture_output=True, text=True, timeout=180)
    if not fbx.exists() and "No module named 'numpy'" in run.stdout + run.stderr:
        pytest.skip("Blender's Python has no numpy, which its glTF importer needs (Debian: apt-get install "
                    "python3-numpy)")
    assert fbx.exists(), run.stdout[-2000:] + run.stderr[-2000:]
    script = f"""
import bpy, json
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.fbx(filepath={str(fbx)!r})
arm = [o for o in bpy.data.objects if o.type == 'ARMATURE'][0]
bpy.context.scene.frame_set(7)
heads = {{b.name: list(arm.matrix_world @ b.head) for b in arm.pose.bones}}
json.dump({{"heads": heads, "action": bool(arm.animation_data and arm.animation_data.action)}}, open({str(out)!r}, "w"))
"""
    run = subprocess.run([BLENDER, "-b", "--factory-startup", "--python-expr", script],
                         capture_output=True, text=True, timeout=180)
    assert out.exists(), run.stdout[-2000:] + run.stderr[-2000:]
    got = json.loads(out.read_text())
    assert got["action"] and sorted(got["heads"]) == sorted(motion.skeleton.names)
    want = _ours_world(motion)[5] * 0.01
    for j, name in enumerate(motion.skeleton.names):
        x, y, z = got["heads"][name]
        assert np.allclose([x, z, -y], want[j], atol=1e-3), name  # Blender is Z up: file (x, y, z) = (X, Z, -Y)


def _numpy_shim() -> str:
    """What docs/avatars.md tells Debian 12's Blender 3.4 users to prepend: its glTF importer uses np.bool, which
    numpy 1.24 removed (harmless where np.bool exists)."""
    return "import numpy; numpy.bool = bool; "


AVATAR_BONES = [b for b, _, _ in BONES]


def _only(motion: BvhMotion, bones: list[str]) -> BvhMotion:
    """`motion` with every joint but those of `bones` (and the root's position) held at rest."""
    _, mapping = auto_map(motion.skeleton.names, motion.skeleton.parents)
    keep = [motion.skeleton.index(mapping[b]) for b in bones if b in mapping]
    q = motion.rotations()
    held = np.setdiff1d(np.arange(motion.skeleton.num_joints), keep)
    q[:, held] = [1.0, 0.0, 0.0, 0.0]
    return BvhMotion.from_pose(motion.skeleton, motion.frame_time, q, motion.translations())


@needs_vrma_browser
@pytest.mark.parametrize("version", ["1.0", "0.0"])
def test_three_vrm_animation_plays_our_vrma_on_a_vrm(motion, files, tmp_path, version):
    """Our .vrma on the test avatar (VRM 1.0, and 0.x facing -Z in its file): its arms and legs point where ours do
    at the first frame and later ones, within 5 degrees; a screenshot of each."""
    times = [0.0, 0.6, 1.35]
    motion = _only(motion, AVATAR_BONES)  # a bone the avatar lacks (upperChest) cannot show on it
    write_motion(tmp_path / "ours.vrma", motion)
    played = play_vrma(tmp_path, make_vrm(version), tmp_path / "ours.vrma", times, name=f"ours_vrm{version[0]}")
    assert played.duration == pytest.approx((motion.num_frames - 1) / FPS, abs=1e-4)
    want = _ours_world(motion)[[round(t * FPS) for t in times]]
    names = motion.skeleton.names
    limbs = {("leftUpperArm", "leftLowerArm"): ("LeftArm", "LeftForeArm"),
             ("leftLowerArm", "leftHand"): ("LeftForeArm", "LeftHand"),
             ("rightUpperArm", "rightLowerArm"): ("RightArm", "RightForeArm"),
             ("rightLowerArm", "rightHand"): ("RightForeArm", "RightHand"),
             ("leftUpperLeg", "leftLowerLeg"): ("LeftUpLeg", "LeftLeg"), ("rightLowerLeg", "rightFoot"): ("RightLeg", "RightFoot")}
    for (a, b), (x, y) in limbs.items():
        theirs = played.position(b) - played.position(a)
        ours = want[:, names.index(y)] - want[:, names.index(x)]
        cos = np.sum(theirs * ours, -1) / np.linalg.norm(theirs, axis=-1) / np.linalg.norm(ours, axis=-1)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 5.0, (a, b)
    assert all(png.stat().st_size > 2000 for png in played.screenshots)


@needs_vrma_browser
def test_three_vrm_animation_plays_our_vrmas_face(motion, files, tmp_path):
    """The .vrma's expressions on a VRM with them: `aa` opens over the clip as written, `blink` stays shut."""
    times = [0.0, 0.5, 1.0, 1.5]
    played = play_vrma(tmp_path, make_vrm("1.0", expressions=True), files / "out_ours.vrma", times, name="face")
    aa = np.linspace(0, 1, motion.num_frames)[[round(t * FPS) for t in times]]
    assert np.allclose(played.expressions["aa"], aa, atol=1e-3)
    assert np.allclose(played.expressions["blink"], 0.0) and played.expressions["ih"].max() == 0.0


@needs_vrma_browser
@pytest.mark.parametrize("name", ["ours.glb", "apose.glb"])
def test_three_js_plays_our_glb_where_we_put_every_bone(motion, files, tmp_path, name):
    """Our .glb in three.js (GLTFLoader, AnimationMixer) in Chromium: every bone where our forward kinematics
    puts it (ours, and retargeted onto the A-pose rig), at the first frame and later ones."""
    frames = [0, 13, 31]
    played = play_gltf(tmp_path, files / f"out_{name}", [k / FPS for k in frames], name=name.replace(".", "_"))
    if name == "ours.glb":
        names, want = motion.skeleton.names, _ours_world(motion)[frames] * 0.01
    else:
        target = load_rig(files / "apose.bvh")
        source = Rig.from_skeleton(motion.skeleton)
        rt = Retarget(source, target, resolve_map(source), resolve_map(target))
        names, want = target.names, target.world(*rt(motion.rotations(), motion.translations()))[1][frames]
    assert sorted(played.bones) == sorted(names)
    got = played.positions[:, [played.bones.index(n) for n in names]]
    assert np.abs(got - want).max() < 1e-4  # metres (float32 in the file)


@pytest.mark.parametrize("name, rig", [("ours.glb", None), ("apose.glb", "apose.bvh")])
def test_the_stick_figure_is_thin_whatever_the_rigs_unit(motion, files, name, rig):
    """The .glb's bones are thin double pyramids (at most 3 cm across) around the rest skeleton, in metres, for a
    centimetre rig (ours) and a metre one (the A-pose copy): the mesh spans the skeleton plus at most 3 cm."""
    import pygltflib

    from dimgestor.retarget.export import metres_per_unit

    gltf = pygltflib.GLTF2().load_binary(str(files / f"out_{name}"))
    position = gltf.accessors[gltf.meshes[0].primitives[0].attributes.POSITION]
    rig = Rig.from_skeleton(motion.skeleton) if rig is None else load_rig(files / rig)
    rest = rig.rest_world()[1] * metres_per_unit(rig)
    assert np.all(np.asarray(position.min) >= rest.min(axis=0) - 0.031)
    assert np.all(np.asarray(position.max) <= rest.max(axis=0) + 0.031)


@pytest.mark.parametrize("args, message", [
    (["--out", "{d}/x.fbx"], "expected a .bvh, .glb, .vrma or .npz (BEAT2 / SMPL-X) path"),
    (["--out", "{d}/x.npz", "--target", "{d}/avatar1.vrm"], "a .npz take is on the SMPL-X skeleton"),
    (["--out", "{d}/x.npz", "--target", "{d}/apose.bvh"], "apose.bvh: not on the SMPL-X skeleton"),
    (["--out", "{d}/x.vrma", "--target", "{d}/apose.bvh"], "a VRM Animation plays on any VRM as it is"),
    (["--out", "{d}/x.bvh", "--target", "{d}/avatar1.vrm"], "a .bvh output needs a BVH target skeleton"),
    (["--out", "{d}/x.glb", "--target-map", "{d}/map.json"], "--target-map needs --target"),
    (["--out", "{d}/x.glb", "--target", "{d}/missing.glb"], "missing.glb: no such file"),
])
def test_generate_refuses_a_bad_output_or_target_in_one_line_before_any_work(files, capsys, args, message):
    from dimgestor_app.cli import main

    wav = files / "speech.wav"
    wav.write_bytes(b"not read: the arguments fail first")
    assert main(["generate", "--audio", str(wav), *[a.format(d=files) for a in args]]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1


# `dimgestor generate` in its own process, every open of one file counted by Python's audit hook
COUNTING_OPENS = """import os, sys
watched, opened = sys.argv[1], []
sys.addaudithook(lambda event, args: opened.append(1) if event == "open" and isinstance(args[0], (str, os.PathLike))
                 and os.fspath(args[0]) == watched else None)
from dimgestor_app.cli import main
code = main(sys.argv[2:])
print(f"opened {len(opened)}")
sys.exit(code)
"""


@pytest.mark.parametrize("rig", ["avatar1.vrm", "apose.bvh"])
def test_generate_reads_the_target_rig_once(files, tmp_path, rig):
    """`generate --target X --out Y.glb`: the rig, its bone map and (a GLB or VRM) the file the animation is added
    to all come from one read of X."""
    wav, script, out = tmp_path / "speech.wav", tmp_path / "count_opens.py", tmp_path / "out.glb"
    save_wav(wav, load_wav(SPEECH_WAV)[: SAMPLE_RATE], SAMPLE_RATE)
    script.write_text(COUNTING_OPENS)
    run = warm.run([sys.executable, str(script), str(files / rig), "generate", "--audio", str(wav), "--out", str(out),
                    "--target", str(files / rig), "--steps", "2"], cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"},
                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=120)
    assert run.returncode == 0, run.stdout
    assert f"wrote {out}" in run.stdout and "bones mapped" in run.stdout, run.stdout
    assert "opened 1" in run.stdout, run.stdout


def test_a_recording_that_cannot_become_its_glb_keeps_its_bvh_and_says_so(motion, tmp_path, capsys):
    """`serve --record OUT.glb`: when the .glb cannot be made at the end (here its target rig vanished), the BVH
    written as the motion came stays, and one line says where it is."""
    from streamer.record import RecordingSink

    sink = RecordingSink(tmp_path / "talk.glb", motion.skeleton, None, target=str(tmp_path / "gone.bvh"))
    sink._convert(_write(motion, tmp_path / "talk.bvh"))
    err = capsys.readouterr().err
    assert "could not write" in err and "gone.bvh: no such file" in err
    assert f"the recording is in {tmp_path / 'talk.bvh'}" in err
    assert (tmp_path / "talk.bvh").exists() and not (tmp_path / "talk.glb").exists()


def _write(motion: BvhMotion, path):
    write_bvh(path, motion)
    return path
