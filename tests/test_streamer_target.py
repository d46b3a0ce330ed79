"""`dimgestor serve --target RIG`: WebSocket clients and VMC receivers get the motion on the user's rig (here an
A-posed copy of the model's skeleton, renamed and resized), equal to retargeting what it sends without a target;
`--record OUT.glb` writes the same on it."""

from __future__ import annotations

import asyncio
import json
import numpy as np
import pytest

from dimgestor.bvh import BvhMotion, write_bvh
from dimgestor.retarget import Retarget, Rig, load_rig, resolve_map
from dimgestor.streaming.checkpoint import load_checkpoint
from helpers.rigs import a_pose
from helpers.serve import WAV_SECONDS, follow, serve
from helpers.vmc import bundles, osc_server
from streamer.pose import HUMAN_BODY_BONES

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def apose(tiny_checkpoint, tmp_path_factory):
    """The tiny model's skeleton A-posed (45 degrees), renamed as the Unreal Mannequin, in metres, as a BVH."""
    sk = a_pose(load_checkpoint(tiny_checkpoint).skeleton)
    path = tmp_path_factory.mktemp("rig") / "mannequin.bvh"
    write_bvh(path, BvhMotion(sk, 0.05, np.zeros((1, sk.num_channels))))
    return path


def test_clients_and_vmc_get_the_motion_on_the_target(tiny_checkpoint, wav, apose, tmp_path):
    server, rec = osc_server()
    s = serve(tiny_checkpoint, "--source", str(wav), "--fast", "--wait-client", "--seed", "3", "--steps", "2",
              "--target", str(apose), "--vmc", f"127.0.0.1:{server.server_address[1]}",
              "--record", str(tmp_path / "talk.glb"))
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    hello, msgs = asyncio.run(follow(url))
    assert s.finish() == 0, s.output
    server.shutdown()

    rig = load_rig(apose)
    sk = hello["skeleton"]
    assert sk["joints"] == rig.names and sk["units"] == "m" and np.allclose(sk["offsets"], rig.translations)
    assert hello["humanoid"]["LeftUpperArm"] == "upperarm_l" and set(hello["humanoid"]) <= set(HUMAN_BODY_BONES)
    frames = [m for m in msgs if m["type"] == "frame"]
    assert len(frames) == int(WAV_SECONDS * 20)
    streamed = np.array([f["rotations"] for f in frames])
    root = np.array([f["root"] for f in frames])

    # The same stream on the model's skeleton, retargeted here.
    plain = serve(tiny_checkpoint, "--source", str(wav), "--fast", "--wait-client", "--seed", "3", "--steps", "2")
    hello0, msgs0 = asyncio.run(follow(plain.wait_for(r"WebSocket\s+(ws://\S+)").group(1)))
    assert plain.finish() == 0, plain.output
    ours = load_checkpoint(tiny_checkpoint).skeleton
    q0 = np.array([m["rotations"] for m in msgs0 if m["type"] == "frame"])
    t0 = np.broadcast_to(ours.offsets, q0.shape[:2] + (3,)).copy()
    t0[:, 0] = [m["root"] for m in msgs0 if m["type"] == "frame"]
    source = Rig.from_skeleton(ours)
    rt = Retarget(source, rig, resolve_map(source), resolve_map(rig), move="root")
    q, t = rt(q0, t0)
    assert np.abs(np.abs(np.sum(streamed * q, axis=-1)) - 1).max() < 1e-4  # the same rotations (up to sign)
    assert np.abs(root - t[:, 0]).max() < 1e-4

    # On the A-pose rig the arms point where ours do (the Mannequin's A-pose error is gone).
    _, ps = source.world(q0, t0)
    tt = np.broadcast_to(rig.translations, q.shape[:2] + (3,)).copy()
    tt[:, 0] = root
    _, pt = rig.world(streamed, tt)
    for a, b in (("LeftArm", "LeftForeArm"), ("RightForeArm", "RightHand")):
        ja, jb = ours.index(a), ours.index(b)
        u, v = ps[:, jb] - ps[:, ja], pt[:, jb] - pt[:, ja]  # (the copy keeps our joint order)
        cos = np.sum(u * v, -1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1.0

    # VMC: the target's humanoid bones, their local rotations on the target rig.
    got = bundles(rec.packets)
    assert len(got) == len(frames)
    bone = {p[0]: p for a, _, p in got[10] if a == "/VMC/Ext/Bone/Pos"}
    assert set(bone) == set(hello["humanoid"])
    arm = rig.index("upperarm_l")
    x, y, z, w = bone["LeftUpperArm"][4:8]
    want = streamed[10, arm] * [1, 1, -1, -1]  # (Unity: the X axis mirrored)
    assert abs(abs(np.dot([w, x, y, z], want)) - 1) < 1e-4

    # The recording: OUT.bvh as it came, OUT.glb on the target at the end.
    assert (tmp_path / "talk.bvh").exists() and (tmp_path / "talk.glb").exists()
    assert "talk.glb (glTF binary" in s.output


def test_a_bad_target_stops_serve_with_its_name(tiny_checkpoint, wav, tmp_path):
    bad = tmp_path / "rig.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 x 0\n")
    s = serve(tiny_checkpoint, "--source", str(wav), "--fast", "--target", str(bad))
    assert s.finish() == 2
    assert f"--target: {bad}:4: expected a number" in s.output


async def _talk(url: str, audio: np.ndarray, rig: dict | None = None) -> tuple[dict, list[dict]]:
    """A client with its own audio (16 kHz pcm16): its hello (with `rig`), the audio, its frames; (rig reply, frames)."""
    import json

    from websockets.asyncio.client import connect

    reply, frames = {}, []
    async with connect(url) as c:
        json.loads(await c.recv())  # the server's hello
        await c.send(json.dumps({"type": "hello", "protocol": 1, **({"rig": rig} if rig is not None else {})}))
        if rig is not None:
            while reply.get("type") not in ("rig", "error"):
                reply = json.loads(await asyncio.wait_for(c.recv(), 30))
        pcm = (np.clip(audio, -1, 1) * 32767).astype("<i2").tobytes()
        for k in range(0, len(pcm), 6400):
            await c.send(pcm[k:k + 6400])
        await c.send(json.dumps({"type": "audio_end"}))
        while True:
            m = json.loads(await asyncio.wait_for(c.recv(), 60))
            if m["type"] == "frame":
                frames.append(m)
            elif m["type"] == "end":
                return reply, frames


def test_a_client_gets_its_own_rig(tiny_checkpoint, wav, apose):
    """Revision 8: a client's hello.rig (its joints, rest pose and units) -> its frames on that rig, equal to
    retargeting what a client without one gets; a rig whose joints are not recognised is refused, saying why."""
    from dimgestor.audio import SAMPLE_RATE, load_wav

    audio = load_wav(wav, SAMPLE_RATE)
    rig = load_rig(apose)
    message = {"joints": rig.names, "parents": rig.parents, "offsets": rig.translations.tolist(),
               "rest_rotations": rig.rotations.tolist(), "units": "m"}
    s = serve(tiny_checkpoint, "--source", "ws", "--seed", "3", "--steps", "2")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    try:
        reply, mine = asyncio.run(_talk(url, audio, message))
        _, plain = asyncio.run(_talk(url, audio))
        odd = dict(message, joints=[f"bone{j}" for j in range(len(rig.names))])
        refused, _ = asyncio.run(_talk(url, audio[:3200], odd))
    finally:
        s.proc.terminate()
        s.finish()
    assert reply["type"] == "rig" and reply["joints"] == rig.num_joints
    assert reply["humanoid"]["LeftUpperArm"] == "upperarm_l"
    assert refused["type"] == "error" and refused["code"] == "bad_rig" and "cannot tell which" in refused["message"]
    assert len(mine) == len(plain) > 0
    ours = load_checkpoint(tiny_checkpoint).skeleton
    q0 = np.array([m["rotations"] for m in plain])
    t0 = np.broadcast_to(ours.offsets, q0.shape[:2] + (3,)).copy()
    t0[:, 0] = [m["root"] for m in plain]
    source = Rig.from_skeleton(ours)
    q, t = Retarget(source, rig, resolve_map(source), resolve_map(rig), move="root")(q0, t0)
    got = np.array([m["rotations"] for m in mine])
    assert got.shape == q.shape and np.abs(np.abs(np.sum(got * q, axis=-1)) - 1).max() < 1e-4
    assert np.abs(np.array([m["root"] for m in mine]) - t[:, 0]).max() < 1e-4


@pytest.mark.parametrize("rig, message", [
    ("bones", "expected an object"),
    ({"joints": [], "parents": [], "offsets": []}, "joints must be a list of 1..512 names"),
    ({"joints": ["a", "a"], "parents": [-1, 0], "offsets": [[0, 0, 0]] * 2}, "distinct"),
    ({"joints": ["a", "b"], "parents": [-1, 1], "offsets": [[0, 0, 0]] * 2}, "parent comes before it"),
    ({"joints": ["a", "b"], "parents": [-1, 0], "offsets": [[0, 0, 0], [0, "x", 0]]}, "offsets must be 2 lists"),
    ({"joints": ["a"], "parents": [-1], "offsets": [[0, 0, 0]], "rest_rotations": [[2, 0, 0, 0]]}, "unit quaternions"),
    ({"joints": ["a"], "parents": [-1], "offsets": [[0, 0, 0]], "units": "in"}, "units must be"),
    ({"joints": ["a"], "parents": [-1], "offsets": [[0, 0, 0]], "map": {"hips": 3}}, "map must be"),
    ({"joints": ["a", "b"], "parents": [-1, 0], "offsets": [[0, 0, 0], [0, 1e300, 0]]}, "one of 1e.300 m; each at most 1000 m"),
    ({"joints": ["a", "b"], "parents": [-1, 0], "offsets": [[0, 0, 0], [0, 2e5, 0]], "units": "cm"}, "one of 2e.03 m"),
])
def test_a_malformed_rig_gets_an_error_that_says_what_is_wrong(rig, message):
    import json

    from streamer import protocol as P

    with pytest.raises(P.ProtocolError, match=message) as e:
        P.parse_text(json.dumps({"type": "hello", "rig": rig}))
    assert e.value.code == "bad_rig"


def test_the_session_machine_takes_a_rig_and_lays_out_its_frames():
    from streamer import client_session as S

    machine = S.ClientSession(S.Seats(S.Terms(max_sessions=2, joints=75)), new_token=lambda: "t")
    rig = {"joints": ["a", "b"], "parents": [-1, 0], "offsets": [[0, 0, 0], [0, 1, 0]]}
    import json
    actions = machine.handle(S.Text(json.dumps({"type": "hello", "rig": rig})))
    assert [type(a) for a in actions] == [S.SetRig] and actions[0].rig["joints"] == ["a", "b"]
    sent = machine.handle(S.RigSet(2, {"Hips": "a"}))
    reply = json.loads(sent[0].message)
    assert reply == {"type": "rig", "joints": 2, "humanoid": {"Hips": "a"}, "channels": reply["channels"]}
    assert machine._send_frames(None).layout is not None and machine.joints == 2  # binary offsets: 2 joints now
    assert json.loads(machine.handle(S.RigRefused("why"))[1].message)["code"] == "bad_rig"
    back = machine.handle(S.RigSet(0))
    assert json.loads(back[0].message)["joints"] == 75 and "humanoid" not in json.loads(back[0].message)


def test_refused_rigs_cost_their_sender_and_the_eighth_closes_its_connection():
    """Issue 52: a refused rig (malformed, or its bones not recognised) costs the client's message budget (its next
    messages are read later), and after MAX_REFUSED_RIGS the connection is closed with 1008, whether the rig was
    refused as it was read, or when it was fitted; a long hello parsed off the event loop is the same message."""
    import json

    from streamer import client_session as S
    from streamer import protocol as P

    machine = S.ClientSession(S.Seats(S.Terms(max_sessions=2, joints=75)), new_token=lambda: "t")
    malformed = json.dumps({"type": "hello", "rig": {"joints": ["a", "a"], "parents": [-1, 0], "offsets": [[0] * 3] * 2}})
    for k in range(1, P.MAX_REFUSED_RIGS + 1):
        if k % 2:
            actions = machine.handle(S.Text(malformed))
        elif k % 4:
            actions = machine.handle(S.Text(malformed, 0.0, P.parse_text_or_error(malformed)))
        else:
            actions = machine.handle(S.RigRefused("cannot tell which of its joints are the humanoid bones"))
        assert [json.loads(a.message)["code"] for a in actions if isinstance(a, S.Send)] == ["bad_rig"]
        assert [a.tokens for a in actions if isinstance(a, S.Charge)] == [P.REFUSED_RIG_TOKENS]
        closes = [a for a in actions if isinstance(a, S.Close)]
        assert closes == ([] if k < P.MAX_REFUSED_RIGS else [S.Close(1008, f"{k} rigs refused", drain_s=1.0)])
    parsed = P.parse_text_or_error(json.dumps({"type": "hello", "rig": {"joints": ["a"], "parents": [-1],
                                                                        "offsets": [[0, 0, 0]]}}))
    assert parsed["rig"]["joints"] == ["a"]  # (a good one parsed aside is the same dict)


@pytest.fixture(scope="module")
def mannequin(tiny_checkpoint):
    """(the tiny model's skeleton, the hello.rig of its A-posed Mannequin copy in metres, frames on the skeleton:
    random joint rotations, the root up to 10 m away)."""
    from dimgestor import rotations as R
    from dimgestor.retarget import Rig
    from streamer.frames import Frame

    skeleton = load_checkpoint(tiny_checkpoint).skeleton
    rig = Rig.from_skeleton(a_pose(skeleton))
    message = {"joints": rig.names, "parents": rig.parents, "offsets": rig.translations.tolist(),
               "rest_rotations": rig.rotations.tolist(), "units": "m"}
    rng = np.random.default_rng(0)
    q = R.quat_normalize(rng.normal(size=(6, skeleton.num_joints, 4)))
    frames = [Frame(k, k / 20, rng.uniform(-1000, 1000, 3), q[k], np.zeros(3)) for k in range(len(q))]
    return skeleton, message, frames


def test_any_rig_a_client_sends_is_refused_with_a_reason_or_gives_finite_frames(mannequin):
    """Issue 52, item 3: a client's rig fuzzed (offsets scaled by anything from 0 to 1e300 or made NaN or
    infinite, rest rotations of any length or none, other units, joints cut off): `bad_rig` as it is read (or
    `bad_message`, for a number JSON does not have), or refused with a reason when it is fitted, or its frames and
    its hello's offsets are finite."""
    from hypothesis import given, settings, strategies as st

    from dimgestor.retarget import RigError
    from dimgestor.retarget.names import MapError
    from streamer import protocol as P
    from streamer.pose import TargetPose

    skeleton, base, frames = mannequin
    J = len(base["joints"])
    scale = st.sampled_from([0.0, 1e-300, 1e-30, 1e-6, 0.5, 1.0, 3.0, 1e3, 1e6, 1e12, 1e300])
    odd = st.floats(allow_nan=True, allow_infinity=True, width=64)

    @settings(max_examples=300, deadline=None, derandomize=True)
    @given(st.data())
    def check(data):
        rig = json.loads(json.dumps(base))
        n = data.draw(st.integers(1, J))  # joints cut off (a parent always comes before its children)
        rig = {k: v[:n] if isinstance(v, list) else v for k, v in rig.items()}
        for j in data.draw(st.lists(st.integers(0, n - 1), max_size=4)):
            if data.draw(st.booleans()):
                rig["offsets"][j] = [x * data.draw(scale) for x in rig["offsets"][j]]
            else:
                rig["offsets"][j][data.draw(st.integers(0, 2))] = data.draw(odd)
        how = data.draw(st.sampled_from(["keep", "none", "scaled", "odd"]))
        if how == "none":
            del rig["rest_rotations"]
        elif how != "keep":
            j = data.draw(st.integers(0, n - 1))
            rig["rest_rotations"][j] = ([x * data.draw(scale) for x in rig["rest_rotations"][j]] if how == "scaled"
                                        else [data.draw(odd) for _ in range(4)])
        rig["units"] = data.draw(st.sampled_from(["m", "cm", "mm"]))
        try:
            parsed = P.parse_text(json.dumps({"type": "hello", "rig": rig}))
        except P.ProtocolError as e:
            # (NaN and Infinity are not JSON numbers: the message itself is malformed)
            assert e.code == "bad_rig" or e.code == "bad_message" and "JSON number" in str(e), e
            assert str(e) and "\n" not in str(e)
            return
        try:
            pose = TargetPose.from_message(skeleton, parsed["rig"])
        except (RigError, MapError) as e:
            assert str(e)
            return
        assert np.isfinite(pose.skeleton_info().offsets).all()
        for f in pose(frames):
            assert np.isfinite(f.rotations).all() and np.isfinite(f.root_pos).all(), rig

    check()
