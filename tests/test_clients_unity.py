"""The Unity client's decoder (clients/unity/DimgestorProtocol.cs) compiled with mcs, run with mono on
messages recorded from a live `streamer serve` (JSON and binary), gives back what the server sent; the
MonoBehaviour, built against stand-ins of the UnityEngine types it uses, retargets onto an avatar with other
bone axes like the server's FK, and really connects to a live server, talks and gestures; the face (revision 7) is
read from JSON and binary frames laid out by the server's `channels` message and set on blendshapes through a name
map, and on a VRM through UniVRM's proxy."""

import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from helpers.clients import (FLOW_SCRIPT, REPO, SPEECH_WAV, check_axis_conversion, check_decoded, check_flow,
                             global_rotations, live_server, quat_matrix, record, reference_decode)
from helpers.face_frames import check_face_frames, check_recorded_face, face_messages, interpolated

UNITY = REPO / "clients" / "unity"
MCS, MONO = shutil.which("mcs"), shutil.which("mono")
pytestmark = [pytest.mark.timeout(180),
              pytest.mark.skipif(not (MCS and MONO), reason="mcs/mono not installed (Debian: apt-get install "
                                 "mono-mcs; .ci/run installs it)")]


# The MonoBehaviour and what it needs, with the stand-ins of the UnityEngine types it uses.
CLIENT_SOURCES = tuple(UNITY / f for f in ("DimgestorProtocol.cs", "DimgestorJson.cs", "DimgestorPlayout.cs",
                                           "DimgestorAudioFlow.cs", "DimgestorRestAlignment.cs", "DimgestorClient.cs",
                                           "DimgestorFace.cs", "tests/UnityEngineStubs.cs"))


def mcs(out, *sources, library=False, defines=()):
    cmd = [MCS, "-langversion:7", "-warnaserror", f"-out:{out}", *(["-target:library"] if library else []),
           *(f"-define:{d}" for d in defines), *map(str, sources)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"mcs failed:\n{r.stdout}\n{r.stderr}"


@pytest.fixture(scope="module")
def decoder(tmp_path_factory):
    exe = tmp_path_factory.mktemp("unity") / "DecodeRecorded.exe"
    mcs(exe, UNITY / "DimgestorProtocol.cs", UNITY / "DimgestorJson.cs", UNITY / "tests" / "DecodeRecorded.cs")
    return exe


def decode(exe, folder):
    r = subprocess.run([MONO, str(exe), str(folder)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return [json.loads(line) for line in r.stdout.splitlines()]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, checkpoint):  # noqa: F811
    tmp = tmp_path_factory.mktemp("unity_rec")
    with live_server(tmp, str(SPEECH_WAV), checkpoint, loop=True) as server:
        # (binary: the frames sent before the server takes the client's hello come as JSON, 4 under a heavy
        # load once, so 24 are kept for at least 12 binary ones)
        return {"json": record(server, tmp / "json", 12, binary=False),
                "binary": record(server, tmp / "binary", 24, binary=True)}


@pytest.mark.parametrize("encoding", ["json", "binary"])
def test_unity_decoder_gives_back_what_the_server_sent(decoder, recordings, encoding):
    files = recordings[encoding]
    assert sum(p.suffix == (".bin" if encoding == "binary" else ".json") for p in files) >= 12
    out = decode(decoder, files[0].parent)
    check_decoded(files, out)
    check_recorded_face(files, out)


def test_unity_conversion_is_the_same_rotation_in_unity_axes(decoder, recordings):
    out = [d for d in decode(decoder, recordings["binary"][0].parent) if d["type"] == "frame"]
    mirror_x = np.diag([-1.0, 1.0, 1.0])  # BVH right-handed Y-up -> Unity left-handed Y-up
    for d in out[:3]:
        check_axis_conversion(mirror_x, np.asarray(d["unity_rotations"]), np.asarray(d["rotations"]))


def test_unity_decoder_names_what_is_wrong_with_bad_input(decoder, tmp_path):
    (tmp_path / "000000.json").write_text('{"type": "frame", "index": 1,\n "root": [1, 2, }')
    (tmp_path / "000001.bin").write_bytes(b"DGF1" + bytes(30))
    (tmp_path / "000002.json").write_text('{"type": "frame", "index": 1, "pts": 0, "root": [1, 2, 3], "rotations": [[1, 0, 0]]}')
    (tmp_path / "000003.json").write_text('{"type": "future_thing", "x": [1, {"y": "\\u00e9"}]}')
    out = decode(decoder, tmp_path)
    assert "JSON line 2 column 17: expected a value, found '}'" in out[0]["error"]
    assert "34 bytes is not 28 + 16*J" in out[1]["error"]
    assert "frame.rotations[0] is not [w, x, y, z]" in out[2]["error"]
    assert out[3] == {"file": "000003.json", "type": "future_thing"}  # unknown types are ignored, not errors


def test_unity_audio_flow_pauses_at_slow_down_and_resumes_with_bounded_holding(tmp_path):
    """Protocol.Parse + AudioFlow (DimgestorAudioFlow.cs) on the server's slow_down / resume (revision 2): chunks
    are held in order while paused, at most 1 s of them (the oldest dropped and counted), sent at `resume`,
    with an audio_end asked for meanwhile after them; an unknown message type changes nothing."""
    exe = tmp_path / "FlowCheck.exe"
    mcs(exe, UNITY / "DimgestorProtocol.cs", UNITY / "DimgestorJson.cs", UNITY / "DimgestorAudioFlow.cs",
        UNITY / "tests" / "FlowCheck.cs")
    script = tmp_path / "flow.txt"
    script.write_text(FLOW_SCRIPT)
    r = subprocess.run([MONO, str(exe), "1.0", str(script)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    check_flow([json.loads(line) for line in r.stdout.splitlines()])


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    cos = np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def check_retarget(tmp_path, folder, hello: dict, frames: list[dict], yaw: float, arms_down: float) -> float:
    """RetargetCheck on the messages in `folder` (`hello`, `frames`): in a T-pose bind pose every bone segment is the
    server skeleton's (Unity space, metres); in an A-pose each points where the skeleton's does within 5 degrees.
    Returns the worst angle."""
    exe = tmp_path / "RetargetCheck.exe"
    mcs(exe, *CLIENT_SOURCES, UNITY / "tests" / "StubAvatar.cs", UNITY / "tests" / "RetargetCheck.cs")
    r = subprocess.run([MONO, str(exe), str(folder), str(yaw), str(arms_down)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stdout.splitlines()]
    assert lines[0]["rest"]
    rest, out = lines[0]["bones"], lines[1:]
    assert [o["index"] for o in out] == [f["index"] for f in frames]
    sk, to_unity = hello["skeleton"], np.array([-0.01, 0.01, 0.01])
    parents, offsets = sk["parents"], np.asarray(sk["offsets"], np.float64)
    joint_of = {bone: sk["joints"].index(j) for bone, j in hello["humanoid"].items() if bone in out[0]["bones"]}
    bone_of = {j: bone for bone, j in joint_of.items()}
    direct = [(b, bone_of[parents[j]]) for b, j in joint_of.items() if parents[j] in bone_of]
    assert len(direct) >= 5, "too few bones with a mapped parent to check"

    def fk(frame):
        g = global_rotations(parents, np.asarray(frame["rotations"], np.float64))
        pos = np.zeros((len(parents), 3))
        for j, p in enumerate(parents):
            pos[j] = frame["root"] if p < 0 else pos[p] + quat_matrix(g[p]) @ offsets[j]
        return pos * to_unity

    if arms_down:  # the bind pose really is an A-pose: each upper arm that far below the skeleton's rest arm
        rest_pos = fk({"rotations": sk["rest_rotations"], "root": offsets[0]})
        for side in ("Left", "Right"):
            upper, lower = joint_of[f"{side}UpperArm"], joint_of[f"{side}LowerArm"]
            avatar_arm = np.asarray(rest[f"{side}LowerArm"]) - np.asarray(rest[f"{side}UpperArm"])
            assert angle_deg(avatar_arm, rest_pos[lower] - rest_pos[upper]) == pytest.approx(arms_down, abs=0.01)
            assert avatar_arm[1] < rest_pos[lower][1] - rest_pos[upper][1]

    hips = bone_of[0]
    root0 = np.asarray(frames[0]["root"]) * to_unity
    avatar_height, source_height = offsets[0][1] * 0.01, root0[1]
    scale = avatar_height / source_height if avatar_height > 0.1 and source_height > 0.1 else 1.0
    worst = 0.0
    for frame, got in zip(frames, out):
        pos = fk(frame)
        bones = {b: np.asarray(v) for b, v in got["bones"].items()}
        for b, p in direct:  # the bone segment points where the server skeleton's does
            want = pos[joint_of[b]] - pos[joint_of[p]]
            worst = max(worst, angle_deg(bones[b] - bones[p], want))
            if not arms_down:
                np.testing.assert_allclose(bones[b] - bones[p], want, atol=2e-4,
                                           err_msg=f"frame {frame['index']} {p}->{b}")
        np.testing.assert_allclose(bones[hips] - np.asarray(out[0]["bones"][hips]),
                                   (pos[0] - root0) * scale, atol=2e-4, err_msg=f"hips, frame {frame['index']}")
    assert worst < 5.0, f"a bone points {worst:.2f} degrees away from the server skeleton's"
    moved = max(np.abs(np.asarray(out[-1]["bones"][b]) - np.asarray(out[0]["bones"][b])).max() for b in joint_of)
    assert moved > 1e-3, "the avatar did not move"
    return worst


@pytest.mark.parametrize("yaw,arms_down", [(0.0, 0.0), (37.0, 0.0), (37.0, 45.0)],
                         ids=["t-pose", "t-pose-turned", "a-pose-turned"])
def test_unity_client_retargets_onto_an_avatar_with_other_bone_axes(tmp_path, recordings, yaw, arms_down):
    """DimgestorClient's Bind/Apply on a stand-in avatar (random bone axes, turned root) put every bone where
    the server skeleton's forward kinematics puts its joint, in Unity space (mirror X, metres). When the avatar's
    bind pose is an A-pose (arms 45 degrees down) instead of the skeleton's T-pose, its bones cannot all land on
    the joints; each bone then points where the skeleton's does, within 5 degrees."""
    msgs = [reference_decode(p) for p in recordings["binary"]]
    hello = next(m for m in msgs if m["type"] == "hello")
    frames = [m for m in msgs if m["type"] == "frame"]
    check_retarget(tmp_path, recordings["binary"][0].parent, hello, frames, yaw, arms_down)


def humanoid_with_fingers() -> tuple[list[str], list[int], np.ndarray, dict[str, str]]:
    """A ZEGGS-like T-posed skeleton (cm, facing +Z, left at +X) with legs, an unmapped joint in the spine, an
    upper chest, jaw and eyes, and five fingers on each hand (the thumb forward); and its humanoid map."""
    names, parents, offsets, humanoid = [], [], [], {}

    def add(name, parent, offset, bone=None):
        names.append(name)
        parents.append(names.index(parent) if parent else -1)
        offsets.append(offset)
        if bone:
            humanoid[bone] = name

    add("Hips", None, (0, 95, 0), "Hips")
    for side, x in (("Left", 1), ("Right", -1)):
        add(f"{side}UpLeg", "Hips", (9 * x, -3, 0), f"{side}UpperLeg")
        add(f"{side}Leg", f"{side}UpLeg", (0, -42, 1), f"{side}LowerLeg")
        add(f"{side}Foot", f"{side}Leg", (0, -42, -2), f"{side}Foot")
        add(f"{side}ToeBase", f"{side}Foot", (0, -6, 12), f"{side}Toes")
    add("Spine", "Hips", (0, 10, 0), "Spine")
    add("Spine1", "Spine", (0, 12, -1))
    add("Spine2", "Spine1", (0, 12, 0), "Chest")
    add("Spine3", "Spine2", (0, 10, 0), "UpperChest")
    add("Neck", "Spine3", (0, 12, 1), "Neck")
    add("Head", "Neck", (0, 10, 2), "Head")
    add("Jaw", "Head", (0, -3, 6), "Jaw")
    for side, x in (("Left", 1), ("Right", -1)):
        add(f"{side}Eye", "Head", (3 * x, 4, 8), f"{side}Eye")
        add(f"{side}Shoulder", "Spine3", (4 * x, 8, 0), f"{side}Shoulder")
        add(f"{side}Arm", f"{side}Shoulder", (13 * x, 0, 0), f"{side}UpperArm")
        add(f"{side}ForeArm", f"{side}Arm", (27 * x, 0, 0), f"{side}LowerArm")
        add(f"{side}Hand", f"{side}ForeArm", (24 * x, 0, 0), f"{side}Hand")
        for finger, bone, first in (("Thumb", "Thumb", (3, -1, 3)), ("Index", "Index", (9, 0, 2.2)),
                                    ("Middle", "Middle", (9.5, 0, 0.3)), ("Ring", "Ring", (9, 0, -1.8)),
                                    ("Pinky", "Little", (8, 0, -3.5))):
            joint = f"{side}Hand{finger}"
            add(f"{joint}1", f"{side}Hand", (first[0] * x, first[1], first[2]), f"{side}{bone}Proximal")
            add(f"{joint}2", f"{joint}1", (3.5 * x, 0, 0), f"{side}{bone}Intermediate")
            add(f"{joint}3", f"{joint}2", (2.5 * x, 0, 0), f"{side}{bone}Distal")
    return names, parents, np.asarray(offsets, np.float64), humanoid


@pytest.mark.parametrize("arms_down", [0.0, 45.0], ids=["t-pose", "a-pose"])
def test_unity_client_retargets_a_full_humanoid_with_fingers(tmp_path, arms_down):
    """The same on a skeleton with legs, upper chest, jaw, eyes and fingers, posed at random: in an A-pose the
    hand is aligned along its middle finger, so every finger still points where the skeleton's does."""
    from streamer.protocol import SkeletonInfo, hello as hello_message

    names, parents, offsets, humanoid = humanoid_with_fingers()
    hello = json.loads(json.dumps(hello_message(SkeletonInfo(names, parents, offsets), humanoid, 30, 0.0, False)))
    rng = np.random.default_rng(3)
    frames = []
    for i in range(8):
        axes = rng.normal(size=(len(names), 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        angles = np.radians(rng.uniform(-30, 30, size=(len(names), 1)))  # every joint turned up to 30 degrees
        q = np.concatenate([np.cos(angles / 2), np.sin(angles / 2) * axes], axis=1)
        frames.append({"type": "frame", "index": i, "pts": i / 30, "root": (offsets[0] + rng.normal(size=3)).tolist(),
                       "rotations": q.tolist()})
    folder = tmp_path / "msgs"
    folder.mkdir()
    for k, m in enumerate([hello, *frames]):
        (folder / f"{k:03d}.json").write_text(json.dumps(m))
    check_retarget(tmp_path, folder, hello, frames, 37.0, arms_down)


def test_unity_client_really_connects_talks_and_gestures(tmp_path, checkpoint):  # noqa: F811
    """DimgestorClient run as Unity runs it (OnEnable, LateUpdate at 60 Hz, SendAudio/EndAudio from another
    thread) with Mono's ClientWebSocket against a live server: its own audio comes back as gestures, shown
    smoothly (pose changes on most display ticks, not once per 200 ms burst), and with a server that makes a face
    the ARKit face it asked for moves a face mesh's jaw and eyelids."""
    exe = tmp_path / "LiveCheck.exe"
    mcs(exe, *CLIENT_SOURCES, UNITY / "tests" / "StubAvatar.cs", UNITY / "tests" / "LiveCheck.cs")
    seconds = 4
    with live_server(tmp_path, "ws", checkpoint) as server:
        r = subprocess.run([MONO, str(exe), server.ws_url, str(SPEECH_WAV), str(seconds)], capture_output=True,
                           text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["state"] == "open" and out["sent"] and out["error"] == "", out
    assert out["frames"] >= seconds * 20 - 2, out
    assert out["moved"] > 1e-3 and out["changed"] > 1.5 * out["frames"], out
    if out["server_face"]:  # revision 7: it asked for ARKit names; the mouth opens and moves with the speech
        assert out["face_weights_set"] == 4 and out["face_changed"] > out["frames"] / 2, out
        assert out["face_max"][0] > 10 and "jawOpen" not in out["face_unmatched"], out
    else:  # a server without a face: the client sets none
        assert out["face_weights_set"] == 0 and out["face_unmatched"] == "", out


def test_unity_client_holds_its_audio_between_slow_down_and_resume_live(tmp_path, bundle):
    """The same run against a server slower than real time whose backlog holds 0.5 s (in process; its session
    buffers 2 s more itself, so it is full about 4 s into our talk): the client
    gets `slow_down`, holds what SendAudio gives it, sends it at `resume`, and every second of its audio comes
    back as frames, with no error."""
    from streamer.sessions import Session

    from helpers.ws import SlowExecutor, make_server, running

    exe = tmp_path / "LiveCheck.exe"
    mcs(exe, *CLIENT_SOURCES, UNITY / "tests" / "StubAvatar.cs", UNITY / "tests" / "LiveCheck.cs")
    seconds = 5
    executor = SlowExecutor(1, delay_s=3.0)  # at most 1 s of audio per call: a third of real time
    ws = make_server(bundle, max_backlog_s=0.5, files=None)
    ws.make_session = lambda **kw: Session.from_bundle(bundle, steps=2, window_ms=100, scheduler=executor, **kw)
    with running(ws):
        r = subprocess.run([MONO, str(exe), ws.url, str(SPEECH_WAV), str(seconds)], capture_output=True,
                           text=True, timeout=120)
    executor.shutdown()
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["sent"] and out["error"] == "", out
    assert out["pauses"] >= 1 and out["resumes"] == out["pauses"] and not out["paused"], out
    assert out["dropped_s"] == 0 and out["frames"] >= seconds * 20 - 2, out


@pytest.mark.skipif(not (shutil.which("redis-server") and (shutil.which("nginx") or os.path.exists("/usr/sbin/nginx"))),
                    reason="nginx and redis-server are needed (.ci/run installs both): the cluster's balancer and store")
def test_unity_client_moves_with_its_session_when_its_worker_stops(tmp_path, checkpoint):  # noqa: F811
    """Issue 22: DimgestorClient talking through nginx (deploy/local-cluster: 2 workers + Redis) gets `goaway`
    when its worker is stopped (SIGTERM) mid-talk, resumes on the other worker (re-sending its audio from the
    sample the saved state covers, holding SendAudio's chunks meanwhile) and every second of its audio comes back
    as frames, with no error."""
    import re
    import signal
    import time
    import urllib.request

    from helpers.cluster import Cluster

    exe = tmp_path / "LiveCheck.exe"
    mcs(exe, *CLIENT_SOURCES, UNITY / "tests" / "StubAvatar.cs", UNITY / "tests" / "LiveCheck.cs")
    seconds = 6

    def streams(port: int) -> float:
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
        return float(re.search(r"^dimgestor_streams (\S+)$", text, re.M).group(1))

    cluster = Cluster("--", "--checkpoint", str(checkpoint), "--steps", "2", "--window-ms", "100", "--status-every", "0")
    try:
        cluster.wait_for(r"^ready: ")
        workers = cluster.workers()
        client = subprocess.Popen([MONO, str(exe), cluster.url, str(SPEECH_WAV), str(seconds)], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        deadline, ours = time.monotonic() + 60, []
        while not ours and time.monotonic() < deadline:
            ours = [pid for port, pid in workers.values() if streams(port) >= 1]
            time.sleep(0.2)
        time.sleep(2.0)  # mid-talk
        os.kill(ours[0], signal.SIGTERM)
        out, err = client.communicate(timeout=120)
    finally:
        cluster.stop()
    assert client.returncode == 0, err
    out = json.loads(out)
    assert out["handovers"] == 1 and out["resumed"] == 1, out
    assert out["sent"] and out["error"] == "" and out["dropped_s"] == 0, out
    assert out["frames"] >= seconds * 20 - 2 and out["moved"] > 1e-3, out


def test_unity_monobehaviour_compiles_against_unityengine_stubs(tmp_path):
    mcs(tmp_path / "DimgestorClient.dll", *CLIENT_SOURCES, library=True)
    # With UniVRM (the DIMGESTOR_UNIVRM define) against stand-ins of the UniVRM 0.x types it uses.
    mcs(tmp_path / "DimgestorClientVrm.dll", *CLIENT_SOURCES, UNITY / "tests" / "UniVrmStubs.cs", library=True,
        defines=["DIMGESTOR_UNIVRM"])
    # The stubs must only declare what Unity really has; the client must use nothing Unity lacks.
    stub = (UNITY / "tests" / "UnityEngineStubs.cs").read_text()
    assert "namespace UnityEngine" in stub and "GetBoneTransform(HumanBodyBones" in stub
    client = (UNITY / "DimgestorClient.cs").read_text()
    assert "ClientWebSocket" in client and "GetBoneTransform(" in client
    face = (UNITY / "DimgestorFace.cs").read_text()
    assert "SetBlendShapeWeight(" in face and "VRMBlendShapeProxy" in face
    assert "using VRM" not in face + client, "UniVRM must stay optional: only under #if DIMGESTOR_UNIVRM"


# ---- the face (protocol revision 7)

@pytest.mark.parametrize("encoding,name_set", [("binary", "arkit"), ("json", "vrm1"), ("binary", "oculus")])
def test_unity_decoder_reads_the_face(decoder, tmp_path, encoding, name_set):
    """MessageDecoder on what a client that asked for `name_set` receives (made by streamer.protocol with
    streamer.face.face_channel): hello.face, then for binary the `channels` layout (another channel, then the face)
    that the frames follow, bytes past it ignored, and a `channels` [] after which frames carry no face."""
    expected = face_messages(tmp_path, encoding, name_set)
    out = decode(decoder, tmp_path)
    assert "error" not in str(out), out
    hello = out[0]
    assert hello["face"]["names"] == "vrm0" and hello["face"]["sets"] == ["vrm0", "vrm1", "arkit", "oculus"]
    assert hello["face"]["labels"] == ["A", "I", "U", "E", "O", "Blink", "Blink_L", "Blink_R", "Joy"]
    if encoding == "binary":
        layouts = [d["layout"] for d in out if d["type"] == "channels"]
        joints_end = 28 + 16 * len(expected[0]["rotations"])
        assert layouts == [[["pair", 2, joints_end], ["face", len(expected[0]["face"]), joints_end + 8]], []]
    check_face_frames(out, expected, exact=encoding == "binary")


def run_face_check(tmp_path, folder, spec: dict, vrm: bool = False) -> tuple[list, list[dict]]:
    exe = tmp_path / "FaceCheck.exe"
    mcs(exe, *CLIENT_SOURCES, *([UNITY / "tests" / "UniVrmStubs.cs"] if vrm else []), UNITY / "tests" / "FaceCheck.cs",
        defines=["DIMGESTOR_UNIVRM"] if vrm else [])
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    r = subprocess.run([MONO, str(exe), str(folder), str(tmp_path / "spec.json")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stdout.splitlines()]
    return lines[0]["hellos"], lines[1:]


def test_unity_client_sets_the_face_on_blendshapes_through_the_name_map(tmp_path):
    """DimgestorClient's ApplyFace (what LateUpdate runs with the frame it shows) on two stand-in meshes, with ARKit
    frames decoded from binary: each face name drives the blendshape the map names (else its own name: exact,
    ignoring case, or after a '.'), weight x 100, interpolated with the pose between frames; the map overrides
    the same-named blendshape; what drives nothing is listed; and the hello asks for the configured set."""
    expected = face_messages(tmp_path / "msgs", "binary", "arkit")
    meshes = [["blendShape1.jawOpen", "EYEBLINKLEFT", "mouthSmileLeft", "Mouth_O", "Blink_R_shape", "eyeblinkright_2",
               "unused"], ["jawOpen", "mouthFunnel"]]
    name_map = [["mouthFunnel", "Mouth_O"], ["eyeBlinkRight", "Blink_R_shape"], ["eyeBlinkRight", "EyeBlinkRight_2"]]
    drives = [{"blendShape1.jawOpen": "jawOpen", "EYEBLINKLEFT": "eyeBlinkLeft", "mouthSmileLeft": "mouthSmileLeft",
               "Mouth_O": "mouthFunnel", "Blink_R_shape": "eyeBlinkRight", "eyeblinkright_2": "eyeBlinkRight"},
              {"jawOpen": "jawOpen"}]  # (the second mesh's mouthFunnel is not driven: the map sends it to Mouth_O)
    times = [0.0, 0.0125, 0.07, 0.1, 0.2375, 0.26]
    hellos, out = run_face_check(tmp_path, tmp_path / "msgs", {"meshes": meshes, "map": name_map, "times": times})
    assert [h.get("face") for h in hellos] == ["arkit", "vrm0", 'a"b\\', None, None]
    assert [h.get("speaker") for h in hellos] == [None, None, None, None, 'sc"ott']  # (revision 9)
    assert hellos[1]["audio"] == {"rate": 48000, "format": "float32", "channels": 2} and hellos[0]["encoding"] == "binary"
    assert [o["t"] for o in out] == times
    unmatched = sorted(set(expected[0]["face"]) - {n for d in drives for n in d.values()})
    for o in out:
        face, root = interpolated(expected[:-1], o["t"])  # (the last frame has no face: the one before stays)
        np.testing.assert_allclose([o["face"][n] for n in face], list(face.values()), rtol=0, atol=1e-9)
        if o["t"] < expected[-2]["pts"]:  # the pose at the same instant as the face
            np.testing.assert_allclose(o["root"], interpolated(expected, o["t"])[1], atol=1e-5)
        for got, want in zip(o["weights"], drives):
            assert got.keys() == want.keys(), o["t"]
            for shape, name in want.items():
                assert got[shape] == pytest.approx(100 * face[name], abs=1e-4), (o["t"], shape)
        assert o["unmatched"].split(", ") == unmatched
    assert any(0 < w < 100 for o in out for w in o["weights"][0].values())


def test_unity_client_rests_the_face_when_the_server_withholds_it(tmp_path):
    """`face_withheld` (a server at capacity for faces) is a notice: faceWithheld and faceNotice say it, lastError
    stays empty; and the first frame shown without a face sets every blendshape the face drove to 0, where before
    the last face stayed (a mouth left open)."""
    from streamer import protocol as P

    expected = face_messages(tmp_path / "msgs", "binary", "arkit")  # (the last frame carries no face)
    notice = "admitted without a face: this worker is at capacity for faces"
    (tmp_path / "msgs" / "000007z.json").write_text(P.error("face_withheld", notice, 5))  # (after the last face)
    meshes = [["jawOpen", "eyeBlinkLeft", "unused"]]
    times = [expected[-2]["pts"], expected[-1]["pts"], expected[-1]["pts"] + 0.05]
    _, out = run_face_check(tmp_path, tmp_path / "msgs", {"meshes": meshes, "map": [], "times": times})
    assert all(o["withheld"] and o["face_notice"] == notice and o["last_error"] == "" for o in out), out
    before, *after = out
    assert before["weights"][0] == pytest.approx({n: 100 * expected[-2]["face"][n] for n in ("jawOpen", "eyeBlinkLeft")})
    assert before["weights"][0]["jawOpen"] > 0
    assert all(o["face"] == {} and o["weights"][0] == {"jawOpen": 0, "eyeBlinkLeft": 0} for o in after), after


def test_unity_client_sets_a_vrm_through_univrm(tmp_path):
    """With DIMGESTOR_UNIVRM, ApplyFace gives a VRM's VRMBlendShapeProxy (a stand-in with UniVRM's key rules) the
    vrm0 face of JSON frames: presets by preset (A I U E O Blink Blink_L Blink_R), a name the map sends elsewhere as
    a custom clip (Joy -> Smile), weights 0..1, interpolated, then Apply."""
    expected = face_messages(tmp_path / "msgs", "json", "vrm0")
    times = [0.0, 0.03, 0.11]
    _, out = run_face_check(tmp_path, tmp_path / "msgs", {"meshes": [], "map": [["Joy", "Smile"]], "times": times,
                                                          "vrm": True}, vrm=True)
    for o in out:
        face, _ = interpolated(expected, o["t"])
        assert o["vrm"][-1] == "apply" and len(o["vrm"]) == len(face) + 1
        got = dict(x.split("=") for x in o["vrm"][:-1])
        key = {n: "Unknown_Smile" if n == "Joy" else n for n in face}
        assert got.keys() == set(key.values())
        for n, w in face.items():
            assert float(got[key[n]]) == pytest.approx(w, abs=1e-6), (o["t"], n)
