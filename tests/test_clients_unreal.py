"""The Unreal client's engine-independent decoder (clients/unreal/DimgestorProtocol.cpp) compiled with g++
(C++17, no exceptions, like an Unreal module), run on messages recorded from a live `streamer serve`
(JSON and binary), gives back what the server sent, in BVH, Unity and Unreal axes; the ActorComponent, built
against engine stand-ins (clients/unreal/tests/stubs), poses a mesh from those messages like the server's FK; the
face (revision 7) is read from JSON and binary frames laid out by the server's `channels` message and set as morph
targets and curves (MetaHuman's names, or through a name map)."""

import json
import shutil
import subprocess

import numpy as np
import pytest

from helpers.clients import (FLOW_SCRIPT, REPO, SPEECH_WAV, check_axis_conversion, check_decoded, check_flow,
                             global_rotations, live_server, quat_matrix, record, reference_decode)
from helpers.face_frames import check_face_frames, check_recorded_face, face_messages, interpolated

UNREAL = REPO / "clients" / "unreal"
GXX = shutil.which("g++")
pytestmark = [pytest.mark.timeout(180),
              pytest.mark.skipif(not GXX, reason="g++ not installed (Debian: apt-get install g++)")]


@pytest.fixture(scope="module")
def decoder(tmp_path_factory):
    exe = tmp_path_factory.mktemp("unreal") / "decode_recorded"
    cmd = [GXX, "-std=c++17", "-O1", "-Wall", "-Wextra", "-Werror", "-fno-exceptions", "-o", str(exe),
           str(UNREAL / "DimgestorProtocol.cpp"), str(UNREAL / "DimgestorJson.cpp"),
           str(UNREAL / "tests" / "decode_recorded.cpp")]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, f"g++ failed:\n{r.stderr}"
    return exe


def decode(exe, folder):
    r = subprocess.run([str(exe), str(folder)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return [json.loads(line) for line in r.stdout.splitlines()]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, checkpoint):  # noqa: F811
    tmp = tmp_path_factory.mktemp("unreal_rec")
    with live_server(tmp, str(SPEECH_WAV), checkpoint, loop=True) as server:
        return {"json": record(server, tmp / "json", 12, binary=False),
                "binary": record(server, tmp / "binary", 12, binary=True)}


@pytest.mark.parametrize("encoding", ["json", "binary"])
def test_unreal_decoder_gives_back_what_the_server_sent(decoder, recordings, encoding):
    files = recordings[encoding]
    out = decode(decoder, files[0].parent)
    assert all("unreal_rotations" in d for d in out if d["type"] == "frame")
    check_decoded(files, out)
    check_recorded_face(files, out)


def test_unreal_conversion_is_the_same_rotation_in_unreal_axes(decoder, recordings):
    out = [d for d in decode(decoder, recordings["json"][0].parent) if d["type"] == "frame"]
    # BVH (x left, y up, z forward; right-handed) -> Unreal (X forward, Y right, Z up; left-handed).
    to_unreal = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.linalg.det(to_unreal) < 0
    for d in out[:3]:
        check_axis_conversion(to_unreal, np.asarray(d["unreal_rotations"]), np.asarray(d["rotations"]))
        np.testing.assert_allclose(d["unreal_root"], to_unreal @ np.asarray(d["root"]), atol=1e-9)


COMPONENT_SOURCES = ("DimgestorComponent.cpp", "DimgestorProtocol.cpp", "DimgestorJson.cpp", "DimgestorPlayout.cpp",
                     "DimgestorAudioFlow.cpp")
# as the component is built: -Werror, no exceptions
COMPONENT_FLAGS = ("-std=c++17", "-O1", "-Wall", "-Werror", "-Wshadow", "-fno-exceptions",
                   f"-I{UNREAL / 'tests' / 'stubs'}", f"-I{UNREAL}")


@pytest.fixture(scope="module")
def component_objects(tmp_path_factory) -> list[str]:
    """The component's sources on the engine stand-ins, compiled once (COMPONENT_FLAGS) for every check to link."""
    out = tmp_path_factory.mktemp("unreal_component_objects")
    r = subprocess.run([GXX, *COMPONENT_FLAGS, "-c", *(str(UNREAL / f) for f in COMPONENT_SOURCES)], cwd=out,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"g++ failed:\n{r.stderr}"
    return [str(out / f.replace(".cpp", ".o")) for f in COMPONENT_SOURCES]


def build_component_check(out_dir, name: str, objects: list[str]):
    """tests/NAME.cpp compiled with COMPONENT_FLAGS and linked with the component -> the executable."""
    exe = out_dir / name
    r = subprocess.run([GXX, *COMPONENT_FLAGS, "-o", str(exe), str(UNREAL / "tests" / f"{name}.cpp"), *objects],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"g++ failed:\n{r.stderr}"
    return exe


@pytest.fixture(scope="module")
def retarget_check(tmp_path_factory, component_objects):
    return build_component_check(tmp_path_factory.mktemp("unreal_component"), "retarget_check", component_objects)


@pytest.fixture(scope="module")
def face_check(tmp_path_factory, component_objects):
    return build_component_check(tmp_path_factory.mktemp("unreal_face"), "face_check", component_objects)


def run_component_check(tmp_path, name: str, objects: list[str]) -> dict:
    """tests/NAME.cpp with the component on the engine stand-ins, compiled as the component is (-Werror, no
    exceptions) and run -> the JSON object it prints."""
    exe = build_component_check(tmp_path, name, objects)
    r = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_unreal_audio_flow_pauses_at_slow_down_and_resumes_with_bounded_holding(tmp_path):
    """ParseMessage + AudioFlow (DimgestorAudioFlow.h) on the server's slow_down / resume (revision 2): chunks
    are held in order while paused, at most 1 s of them (the oldest dropped and counted), sent at `resume`,
    with an audio_end asked for meanwhile after them; an unknown message type changes nothing."""
    exe = tmp_path / "flow_check"
    cmd = [GXX, "-std=c++17", "-O1", "-Wall", "-Wextra", "-Werror", "-fno-exceptions", "-o", str(exe),
           *(str(UNREAL / f) for f in ("DimgestorProtocol.cpp", "DimgestorJson.cpp", "DimgestorAudioFlow.cpp",
                                       "tests/flow_check.cpp"))]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"g++ failed:\n{r.stderr}"
    script = tmp_path / "flow.txt"
    script.write_text(FLOW_SCRIPT)
    r = subprocess.run([str(exe), "1.0", str(script)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    check_flow([json.loads(line) for line in r.stdout.splitlines()])


def test_unreal_component_holds_its_audio_between_slow_down_and_resume(tmp_path, component_objects):
    """UDimgestorComponent (engine stand-ins) talking: after the server's slow_down nothing more goes out, what
    SendAudio gets is held (at most MaxHeldAudioS = 1 s: the oldest dropped and counted), an EndAudio waits;
    at resume the held chunks go in order, then audio_end. slow_down is no error."""
    out = run_component_check(tmp_path, "component_flow_check", component_objects)
    assert out["ok"] and out["paused"] and not out["paused_after"] and out["last_error"] == "", out
    assert out["sent_while_paused"] == 2, out  # the audio hello and chunk 1, before the slow_down
    assert out["log"] == ['text:{"type":"hello","encoding":"binary","face":"arkit","speaker":"scott"}',
                          "binary:1:1600", "binary:5:1600", "binary:6:1600", 'text:{"type":"audio_end"}'], out["log"]
    assert out["dropped_s"] == pytest.approx(1.2) and "slow down" in out["notice"], out


def test_unreal_component_moves_with_its_session_at_goaway(tmp_path, component_objects):
    """UDimgestorComponent (engine stand-ins) talking when its worker stops (protocol revision 3): goaway, the
    socket closes, the component connects again at once with its audio format and resume_session, holds what
    SendAudio gets, and at session_resumed re-sends its audio from the sample the saved state covers (chunk 2 on),
    then what it held (3, 4), and goes on (5, audio_end). No error."""
    out = run_component_check(tmp_path, "component_handover_check", component_objects)
    assert out["ok"] and out["moving"] == "moving" and out["reconnected"], out
    assert out["handovers"] == 1 and out["resumed"] == 1 and not out["paused_after"] and out["last_error"] == "", out
    hello = 'text:{"type":"hello","encoding":"binary","face":"arkit"}'  # (the stubs' JSON writer: string fields only)
    assert out["first"] == [hello, "binary:1:1600", "binary:2:1600"], out["first"]  # 3 held from the goaway on
    assert out["held_until_resumed"] == 2  # the new connection's hello (with the audio format) and resume_session
    assert out["second"] == [hello, 'text:{"type":"resume_session","token":"k3J-x_9"}', "binary:2:1600",
                             "binary:3:1600", "binary:4:1600", "binary:5:1600", 'text:{"type":"audio_end"}'], out["second"]


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(unit(a) * unit(b), axis=-1), -1.0, 1.0)))


@pytest.mark.parametrize("encoding,yaw,rest", [("binary", 90.0, "tpose"), ("json", -30.0, "tpose"),
                                               ("binary", 90.0, "apose"), ("json", -30.0, "apose")])
def test_unreal_component_retargets_onto_a_mesh_with_other_bone_axes(retarget_check, recordings, encoding, yaw, rest):
    """UDimgestorComponent (on engine stand-ins) fed the recorded messages through its WebSocket events poses a
    Mannequin-named mesh whose bones have other axes, in Unreal axes (cm), turned by SourceToComponent. With the
    skeleton's rest (a T-pose) as the mesh's reference pose, every bone lands where the server skeleton's forward
    kinematics puts its joint; with an A-pose (arms 45 degrees down), every bone points where the skeleton's does
    (within 5 degrees: the positions differ where the rest directions were aligned, not copied)."""
    files = recordings[encoding]
    r = subprocess.run([str(retarget_check), str(files[0].parent), str(yaw), *(["apose"] if rest == "apose" else [])],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stdout.splitlines()]
    reference, out = lines[0]["reference"], [line["bones"] for line in lines[1:]]
    msgs = [reference_decode(p) for p in files]
    hello = next(m for m in msgs if m["type"] == "hello")
    frames = [m for m in msgs if m["type"] == "frame"]
    assert len(out) == len(frames) and f"frames received {len(frames)}, sent 1 text message" in r.stderr
    sk = hello["skeleton"]
    parents, offsets = sk["parents"], np.asarray(sk["offsets"], np.float64)
    c, s_ = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    to_component = np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]) @ np.array([[0, 0, 1], [-1, 0, 0], [0, 1, 0]])
    joint_of = {bone: sk["joints"].index(j) for bone, j in hello["humanoid"].items() if bone in out[0]}
    bone_of = {j: bone for bone, j in joint_of.items()}
    direct = [(b, bone_of[parents[j]]) for b, j in joint_of.items() if parents[j] in bone_of]
    assert len(direct) >= 5, "too few bones with a mapped parent to check"

    def fk(frame, rotations=None):  # BVH space, file units (cm)
        g = global_rotations(parents, np.asarray(frame["rotations"] if rotations is None else rotations, np.float64))
        pos = np.zeros((len(parents), 3))
        for j, p in enumerate(parents):
            pos[j] = frame["root"] if p < 0 else pos[p] + quat_matrix(g[p]) @ offsets[j]
        return pos @ to_component.T

    rest_pos = fk({"root": offsets[0]}, sk["rest_rotations"])
    ref_angle = {(b, p): angle_deg(np.subtract(reference[b], reference[p]), rest_pos[joint_of[b]] - rest_pos[joint_of[p]])
                 for b, p in direct}
    for (b, p), a in ref_angle.items():  # the mesh's reference pose: the skeleton's rest, but the arms 45 degrees down
        lowered = rest == "apose" and p in ("LeftUpperArm", "RightUpperArm", "LeftLowerArm", "RightLowerArm")
        assert a == pytest.approx(45.0 if lowered else 0.0, abs=1e-6), f"reference pose {p}->{b}"
    hips = bone_of[0]
    root0 = to_component @ np.asarray(frames[0]["root"])
    scale = offsets[0][1] / root0[2] if offsets[0][1] > 10 and root0[2] > 10 else 1.0
    worst = 0.0
    for frame, bones in zip(frames, out):
        pos = fk(frame)
        for b, p in direct:
            got, want = np.subtract(bones[b], bones[p]), pos[joint_of[b]] - pos[joint_of[p]]
            if rest == "tpose":
                np.testing.assert_allclose(got, want, atol=1e-3, err_msg=f"frame {frame['index']} {p}->{b}")
            worst = max(worst, angle_deg(got, want))
        np.testing.assert_allclose(np.subtract(bones[hips], out[0][hips]), (pos[0] - root0) * scale, atol=1e-3)
    assert worst < 5.0, f"a bone points {worst:.2f} degrees away from the skeleton's"
    moved = max(np.abs(np.subtract(out[-1][b], out[0][b])).max() for b in joint_of)
    assert moved > 1e-2, "the mesh did not move"


def test_unreal_decoder_names_what_is_wrong_with_bad_input(decoder, tmp_path):
    (tmp_path / "000000.json").write_text('{"type": "frame", "index": 1,\n "root": [1, 2, }')
    (tmp_path / "000001.bin").write_bytes(b"DGF1" + bytes(30))
    (tmp_path / "000002.json").write_text('{"type": "hello", "protocol": 2}')
    (tmp_path / "000003.json").write_text('{"type": "future_thing", "x": [1, {"y": "\\u00e9\\ud83d\\ude00"}]}')
    out = decode(decoder, tmp_path)
    assert "JSON line 2 column 17: expected a value, found '}'" in out[0]["error"]
    assert "34 bytes is not 28 + 16*J" in out[1]["error"]
    assert "server speaks protocol 2, this client 1" in out[2]["error"]
    assert out[3] == {"file": "000003.json", "type": "future_thing"}


# ---- the face (protocol revision 7)

@pytest.mark.parametrize("encoding,name_set", [("binary", "arkit"), ("json", "vrm1"), ("binary", "oculus")])
def test_unreal_decoder_reads_the_face(decoder, tmp_path, encoding, name_set):
    """ParseMessage / DecodeBinaryFrame on what a client that asked for `name_set` receives (made by
    streamer.protocol with streamer.face.face_channel): hello.face, then for binary the `channels` layout (another
    channel, then the face) the frames follow, bytes past it ignored, and a `channels` [] after which frames carry no
    face."""
    expected = face_messages(tmp_path, encoding, name_set)
    out = decode(decoder, tmp_path)
    assert "error" not in str(out), out
    assert out[0]["face"] == {"names": "vrm0", "sets": ["vrm0", "vrm1", "arkit", "oculus"],
                              "labels": ["A", "I", "U", "E", "O", "Blink", "Blink_L", "Blink_R", "Joy"]}
    if encoding == "binary":
        layouts = [d["layout"] for d in out if d["type"] == "channels"]
        joints_end = 28 + 16 * len(expected[0]["rotations"])
        assert layouts == [[["pair", 2, joints_end], ["face", len(expected[0]["face"]), joints_end + 8]], []]
    check_face_frames(out, expected, exact=encoding == "binary")


def test_unreal_decoder_names_what_is_wrong_with_a_face(decoder, tmp_path):
    (tmp_path / "000000.json").write_text('{"type": "frame", "index": 1, "pts": 0, "root": [1, 2, 3], "rotations": [], '
                                          '"face": {"jawOpen": "wide"}}')
    (tmp_path / "000001.json").write_text('{"type": "channels", "channels": [{"name": "face", "size": -1}]}')
    out = decode(decoder, tmp_path)
    assert out[0]["error"] == "frame.face.jawOpen is not a number"
    assert out[1]["error"] == "channels[0]: bad size or offset"


@pytest.mark.parametrize("encoding,metahuman,face_mesh", [("binary", True, True), ("json", False, True),
                                                          ("json", True, False)])
def test_unreal_component_sets_the_face_as_morph_targets_and_curves(face_check, tmp_path, encoding, metahuman,
                                                                   face_mesh):
    """UDimgestorComponent (engine stand-ins) asks for ARKit names in its hello, follows the server's `channels`
    layout, and each tick sets the face it shows (interpolated with the pose) as FaceMesh's morph targets (the face
    names, or the name map's) and as curves (MetaHuman's capitalisation: jawOpen -> JawOpen, or the map's), 0..1;
    without a FaceMesh, curves only."""
    expected = face_messages(tmp_path / "msgs", encoding, "arkit")
    name_map = {"mouthFunnel": "Mouth_O", "eyeBlinkRight": "Blink_R"}
    times = [0.0, 0.0125, 0.07, 0.2375, 0.26]
    names = list(expected[0]["face"])

    def target(n, curve):
        return name_map.get(n) or (n[0].upper() + n[1:] if curve and metahuman else n)

    spec = {"face_names": "arkit", "map": [[k, v] for k, v in name_map.items()], "metahuman": metahuman,
            "face_mesh": face_mesh, "times": times, "curves_to_read": [target(n, True) for n in names] + ["NoSuchCurve"]}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    r = subprocess.run([str(face_check), str(tmp_path / "msgs"), str(tmp_path / "spec.json")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stdout.splitlines()]
    assert lines[0]["hello"] == '{"type":"hello","encoding":"binary","face":"arkit"}'  # (the stubs' writer: strings only)
    out = lines[1:]
    assert [o["t"] for o in out] == times and all(o["frames"] == len(expected) for o in out)
    for o in out:
        face, _ = interpolated(expected[:-1] if encoding == "binary" else expected, o["t"])
        assert o["morphs"].keys() == ({target(n, False) for n in names} if face_mesh else set())
        for n, w in face.items():
            if face_mesh:
                assert o["morphs"][target(n, False)] == pytest.approx(w, abs=1e-6), (o["t"], n)
            assert o["curves"][target(n, True)] == pytest.approx(w, abs=1e-6), (o["t"], n)
        assert o["curves"]["NoSuchCurve"] == 0 and o["curve_count"] == len(names)
    assert len({o["curves"][target("jawOpen", True)] for o in out}) == len(times), "the face did not move"


def test_unreal_component_rests_the_face_when_the_server_withholds_it(face_check, tmp_path):
    """`face_withheld` (a server at capacity for faces) is a notice: bFaceWithheld and FaceNotice say it; and the
    first frame shown without a face sets every morph target and curve the face drove to 0, where before the last face
    stayed (a mouth left open)."""
    from streamer import protocol as P

    expected = face_messages(tmp_path / "msgs", "binary", "arkit")  # (the last frame carries no face)
    notice = "admitted without a face: this worker is at capacity for faces"
    (tmp_path / "msgs" / "000007z.json").write_text(P.error("face_withheld", notice, 5))  # (after the last face)
    names = list(expected[0]["face"])
    curves = [n[0].upper() + n[1:] for n in names]
    times = [expected[-2]["pts"], expected[-1]["pts"], expected[-1]["pts"] + 0.05]
    spec = {"face_names": "arkit", "map": [], "metahuman": True, "face_mesh": True, "times": times,
            "curves_to_read": curves}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    r = subprocess.run([str(face_check), str(tmp_path / "msgs"), str(tmp_path / "spec.json")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    before, *after = [json.loads(line) for line in r.stdout.splitlines()][1:]
    for o in (before, *after):
        assert o["withheld"] and o["face_notice"] == notice, o  # (LastError: the stand-in body mesh matches no bone)
    assert before["morphs"] == pytest.approx(expected[-2]["face"], abs=1e-6) and before["morphs"]["jawOpen"] > 0
    for o in after:
        assert o["morphs"] == dict.fromkeys(names, 0) and o["curves"] == dict.fromkeys(curves, 0), o


def test_unreal_component_rests_the_face_across_a_rebind(face_check, tmp_path):
    """A hello between the last frame shown with a face and the first without (a resumed session: the component
    binds again, and its face name map may have changed) still rests every morph target and curve the face drove:
    they are set to 0 as the binding forgets them, where before they stayed at the last face (a mouth left open)."""
    expected = face_messages(tmp_path / "msgs", "binary", "arkit")  # (the last frame carries no face)
    hello = (tmp_path / "msgs" / "000000.json").read_text()
    (tmp_path / "msgs" / "000007t.tick").write_text("")       # the last face is shown...
    (tmp_path / "msgs" / "000007u.json").write_text(hello)   # ... then the server says hello again
    names = list(expected[0]["face"])
    curves = [n[0].upper() + n[1:] for n in names]
    spec = {"face_names": "arkit", "map": [], "metahuman": True, "face_mesh": True,
            "times": [expected[-1]["pts"], expected[-1]["pts"] + 0.05], "curves_to_read": curves}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    r = subprocess.run([str(face_check), str(tmp_path / "msgs"), str(tmp_path / "spec.json")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    for o in [json.loads(line) for line in r.stdout.splitlines()][1:]:
        assert o["frames"] == len(expected) and not o["withheld"], o
        assert o["morphs"] == dict.fromkeys(names, 0) and o["curves"] == dict.fromkeys(curves, 0), o
