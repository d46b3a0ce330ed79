"""Live VMC output read by independent receivers: PyPI `vmcp` (a VMC protocol implementation on osc4py3)
and npm `osc` under node with EVMC4U's per-address type checks. Every bundle of a live run (each
receiver option) must parse, the bones vmcp receives, put through forward kinematics, must equal
the `--record` BVH of the same run, and the face it receives (Blend/Val of every name of the --face set, then
Blend/Apply) must equal the face track recorded beside that BVH."""

import csv
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dimgestor.audio import load_wav, save_wav
from dimgestor.bvh import read_bvh
from dimgestor.face import names_of
from dimgestor.rotations import quat_mul, quat_rotate
from streamer.pose import HumanoidRig, load_humanoid_map, to_unity_quat
from streamer.sources import DEMO_WAV
from streamer.vmc import UPPER_BODY
from helpers import warm
from helpers.udp_capture import UdpCapture

REPO = Path(__file__).resolve().parents[1]
NODE_DIR = REPO / "tests" / "node"
pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]
MODES = {  # (the face: vrm0 by default)
    "default": [],
    "all-positions-scaled-rooted-no-face": ["--vmc-positions", "all", "--vmc-hips-height", "0.9", "--vmc-root",
                                            "0.5,0,1,90", "--face", "none"],
    "upper-split-arkit": ["--vmc-bones", "upper", "--vmc-max-bytes", "1400", "--face", "arkit"],
}


def face_set(mode: str) -> str:
    return "none" if mode.endswith("no-face") else "arkit" if mode.endswith("arkit") else "vrm0"


Capture = UdpCapture  # every datagram, raw


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    path = tmp_path_factory.mktemp("vmc") / "clip.wav"
    save_wav(path, load_wav(DEMO_WAV)[: 16000 * 5 // 2], 16000)
    return path


@pytest.fixture(scope="module", params=list(MODES))
def live_run(request, clip, tmp_path_factory):
    """`dimgestor serve` (embedded model, real time) -> VMC to a capture socket, and --record of the same run."""
    cap = Capture()
    cap.start()
    out = tmp_path_factory.mktemp("vmc") / "rec.bvh"
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "serve", "--source", str(clip), "--no-ws",
                  "--vmc", f"127.0.0.1:{cap.port}", "--record", str(out), "--status-every", "0",
                  *MODES[request.param]],
                 cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=240)
    time.sleep(0.3)
    cap.stop = True
    cap.join(2)
    assert r.returncode == 0, r.stderr
    return request.param, cap.datagrams, read_bvh(out), out.with_name("rec.face.csv")


@pytest.fixture(scope="module")
def vmcp_osc():
    """One vmcp OSC system (osc4py3 keeps global state: one per process)."""
    pytest.importorskip("osc4py3", reason="install the test extra: pip install -e '.[test]'")
    from vmcp.osc import OSC
    from vmcp.osc.backend.osc4py3 import as_eventloop as backend

    osc = OSC(backend)
    with osc.open():
        yield osc


def vmcp_receive(osc, datagrams, name):
    """Replay the captured datagrams to a vmcp receiver; the events it decodes, in order."""
    from vmcp.events import (BlendShapeApplyEvent, BlendShapeEvent, BoneTransformEvent, RelativeTimeEvent,
                             RootTransformEvent, StateEvent)

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    events = []
    rx = osc.create_receiver("127.0.0.1", port, name).open()
    backend = osc.backend
    handlers = [rx.register_handler(ev.ADDRESS_PATTERN,  # as vmcp.facades.on_receive, keeping the handles
                                    lambda *a, ev=ev: events.append(ev.from_message_data(*a)),
                                    backend.ARG_READERNAME + backend.ARG_ADDRESS + backend.ARG_DATA)
                for ev in (RootTransformEvent, BoneTransformEvent, BlendShapeEvent, BlendShapeApplyEvent, StateEvent,
                           RelativeTimeEvent)]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for d in datagrams:
            tx.sendto(d, ("127.0.0.1", port))
            osc.run()
    n_t = sum(d.count(b"/VMC/Ext/T\0") for d in datagrams)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and sum(isinstance(e, RelativeTimeEvent) for e in events) < n_t:
        osc.run()
        time.sleep(0.001)
    for h in handlers:  # vmcp 1.0.6's Receiver.close() unregisters while iterating its dict: do it first
        rx.unregister_handler(h)
    rx.close()
    return events


def frames_of(events):
    """vmcp events -> [(T, root (pos, xyzw), {bone: (pos, xyzw)})], one per /VMC/Ext/T after bone data."""
    from vmcp.events import BoneTransformEvent, RelativeTimeEvent, RootTransformEvent

    frames, root, bones = [], None, {}
    for e in events:
        if isinstance(e, RootTransformEvent):
            root = (np.array([e.position.x, e.position.y, e.position.z]),
                    np.array([e.rotation.x, e.rotation.y, e.rotation.z, e.rotation.w]))
        elif isinstance(e, BoneTransformEvent):
            bones[str(e.joint.value if hasattr(e.joint, "value") else e.joint)] = (
                np.array([e.position.x, e.position.y, e.position.z]),
                np.array([e.rotation.x, e.rotation.y, e.rotation.z, e.rotation.w]))
        elif isinstance(e, RelativeTimeEvent) and bones:
            frames.append((float(e.delta), root, bones))
            bones = {}
    return frames


def faces_of(events):
    """vmcp events -> [(T, [(name, value)...] before Blend/Apply, [name...] after it)], one per /VMC/Ext/T after bone
    data; None in place of the list before Apply when no Apply came."""
    from vmcp.events import BlendShapeApplyEvent, BlendShapeEvent, BoneTransformEvent, RelativeTimeEvent

    faces, vals, late, applied, bones = [], [], [], False, False
    for e in events:
        if isinstance(e, BoneTransformEvent):
            bones = True
        elif isinstance(e, BlendShapeEvent):
            (late if applied else vals).append((str(e.key.value if hasattr(e.key, "value") else e.key), e.value))
        elif isinstance(e, BlendShapeApplyEvent):
            applied = True
        elif isinstance(e, RelativeTimeEvent) and bones:
            faces.append((float(e.delta), vals if applied else None, [n for n, _ in late]))
            vals, late, applied, bones = [], [], False, False
    return faces


def read_face_track(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array(rows[1:], dtype=float)


def wxyz(q_xyzw):
    return np.concatenate([q_xyzw[..., 3:], q_xyzw[..., :3]], -1)


def recorded_world(motion):
    """World rotations (wxyz) and positions (metres) of every joint of a BVH, in Unity's frame."""
    from dimgestor.bvh import forward_kinematics

    local = motion.rotations()
    world_q = np.empty_like(local)
    for j, a in enumerate(motion.skeleton.parents):
        world_q[:, j] = local[:, j] if a < 0 else quat_mul(world_q[:, a], local[:, j])
    return to_unity_quat(world_q), forward_kinematics(motion) * 0.01 * np.array([-1, 1, 1])


def same_rotation(a, b):
    return min(np.abs(a - b).max(), np.abs(a + b).max())  # q and -q are one rotation


def test_vmcp_parses_every_bundle_and_fk_equals_the_recording(live_run, vmcp_osc):
    mode, datagrams, motion, _ = live_run
    sk = motion.skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    frames = frames_of(vmcp_receive(vmcp_osc, datagrams, f"dimgestor-{mode}"))
    # Paced live output on a loaded 2-core machine may drop a late frame; what arrives must be whole.
    assert len(frames) >= 0.7 * motion.num_frames, f"{len(frames)} frames received, {motion.num_frames} recorded"
    if mode.startswith("upper-split"):
        assert all(len(d) <= 1400 for d in datagrams)
        assert sum(d.startswith(b"#bundle") for d in datagrams) >= 2 * len(frames)
    expected = set(rig.bones) if not mode.startswith("upper-split") else set(rig.bones) & set(UPPER_BODY)
    world_q, world_p = recorded_world(motion)
    parent = {b: (rig.bones[p] if p >= 0 else None) for b, p in zip(rig.bones, rig.parents)}
    scale = 0.9 / (rig.rest_hips_height() * 0.01) if mode.startswith("all") else 1.0
    root_p, root_q = (np.array([0.5, 0, 1.0]), np.array([np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0])) \
        if mode.startswith("all") else (np.zeros(3), np.array([1.0, 0, 0, 0]))
    for t, root, bones in frames:
        i = round(t * 20)
        assert 0 <= i < motion.num_frames and set(bones) == expected, (t, sorted(bones))
        np.testing.assert_allclose(root[0], root_p, atol=1e-6)
        assert same_rotation(wxyz(root[1]), root_q) < 1e-6
        gq, gp = {}, {}
        for b in rig.bones:  # parents first
            if b not in bones:
                continue
            p, q, up = bones[b][0], wxyz(bones[b][1]), parent[b]
            j = rig.joints[rig.bones.index(b)]
            # local rotation: the recording's world rotation relative to the humanoid parent's
            want = world_q[i, j] if up is None else quat_mul(world_q[i, rig.joints[rig.bones.index(up)]] * [1, -1, -1, -1],
                                                            world_q[i, j])
            assert same_rotation(q, want) < 2e-3, (mode, t, b)
            if up is None or up in gq:  # forward kinematics down the received chain from the root
                pq, pp = (root_q, root_p) if up is None else (gq[up], gp[up])
                gq[b], gp[b] = quat_mul(pq, q), pp + quat_rotate(pq, p)
                assert same_rotation(gq[b], quat_mul(root_q, world_q[i, j])) < 2e-3, (mode, t, b)
                if mode.startswith("all") or b == "Hips":
                    np.testing.assert_allclose(gp[b], root_p + quat_rotate(root_q, world_p[i, j] * scale), atol=2e-3,
                                               err_msg=f"{mode}: {b} at {t}")


def test_vmcp_gets_the_face_in_the_configured_names_then_apply_equal_to_the_recorded_track(live_run, vmcp_osc):
    """Each frame vmcp decodes carries one Blend/Val per name of the --face set (vrm0 by default; only ARKit's 52
    with --face arkit), all before the frame's Blend/Apply, with the values of the track recorded beside the BVH;
    --face none: no Blend/Val and no track."""
    mode, datagrams, motion, track = live_run
    name_set = face_set(mode)
    faces = faces_of(vmcp_receive(vmcp_osc, datagrams, f"dimgestor-face-{mode}"))
    assert len(faces) >= 0.7 * motion.num_frames
    assert all(vals is not None and not late for _, vals, late in faces), "every frame: Blend/Apply after its values"
    if name_set == "none":
        assert all(vals == [] for _, vals, _ in faces) and not track.exists()
        return
    header, table = read_face_track(track)
    assert header[:10] == ["time", "A", "I", "U", "E", "O", "Blink", "Blink_L", "Blink_R", "Joy"]
    assert len(header) == 1 + 9 + 52 and len(table) == motion.num_frames
    names = list(names_of(name_set))
    columns = [header.index(n) for n in names]
    for t, vals, _ in faces:
        assert [n for n, _ in vals] == names, (mode, t)
        i = round(t * 20)
        np.testing.assert_allclose([v for _, v in vals], table[i, columns], rtol=0, atol=1e-4, err_msg=f"{mode} {t}")
    if name_set == "arkit":
        assert not {"A", "I", "U", "E", "O", "Blink", "Joy"} & {n for _, vals, _ in faces for n, _ in vals}
    opened = table[:, [header.index(n) for n in ("A", "I", "U", "E", "O")]].max(axis=1)
    assert opened.max() > 0.3, "the clip's speech opens the mouth"


@pytest.mark.skipif(shutil.which("node") is None, reason="node not installed (Debian: apt install nodejs)")
def test_npm_osc_parser_accepts_every_bundle_with_evmc4u_types(live_run, tmp_path):
    if not (NODE_DIR / "node_modules" / "osc").is_dir():
        pytest.skip(f"npm osc not installed: run `make setup` (npm ci in {NODE_DIR})")
    mode, datagrams, motion, _ = live_run
    f = tmp_path / "datagrams.bin"
    f.write_bytes(b"".join(struct.pack(">I", len(d)) + d for d in datagrams))
    r = subprocess.run(["node", str(NODE_DIR / "check-vmc.js"), str(f)], capture_output=True, text=True, timeout=60)
    out = json.loads(r.stdout)
    assert r.returncode == 0 and not out["errors"], out["errors"][:10]
    assert out["datagrams"] == len(datagrams)
    frames = [fr for fr in out["frames"] if fr[1] > 0]
    assert 0.7 * motion.num_frames <= len(frames) <= motion.num_frames
    assert out["messages"]["/VMC/Ext/OK"] >= len(frames)
    assert out["messages"]["/VMC/Ext/Bone/Pos"] == sum(n for _, n in frames)
    names = 0 if face_set(mode) == "none" else len(names_of(face_set(mode)))
    assert out["messages"].get("/VMC/Ext/Blend/Val", 0) == names * len(frames)
