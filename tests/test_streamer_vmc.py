"""VMC over OSC: a python-osc server receives one bundle per frame with the spec's argument types, the face as
Blend/Val of every name of the sink's set before Blend/Apply."""

import asyncio
import os
import threading
import time

import pytest

import numpy as np
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage

from dimgestor.bvh import read_bvh
from dimgestor.face import FACE_LABELS, NAME_SETS, convert, names_of
from dimgestor.face.visemes import V
from dimgestor.rotations import quat_normalize
from dimgestor.training.synthetic import synthetic_skeleton
from streamer.face import FACE
from streamer.frames import Frame
from streamer.pose import HumanoidRig, load_humanoid_map
from streamer.vmc import VMC_CHANNELS, VmcEncoder, VmcOptions, VmcSink, face_channels, reference_bundle
from helpers.stalls import runnable_waiting_s
from helpers.vmc import bundles, check_vmc_bundle, osc_server, type_tags

def test_vmc_sink_sends_spec_typed_bundles(zeggs_dir):
    skel = read_bvh(next(zeggs_dir.glob("*.bvh"))).skeleton
    rig = HumanoidRig.build(skel.names, skel.parents, skel.offsets, load_humanoid_map())
    server, rec = osc_server()
    rng = np.random.default_rng(0)
    frames = [Frame(i, i / 20, np.array([0.0, 90.0, 0.0]), quat_normalize(rng.normal(size=(len(skel.names), 4))),
                    np.zeros(3)) for i in range(5)]

    async def run():
        sink = VmcSink("127.0.0.1", server.server_address[1], rig, pace=True, jitter_s=0.05)
        await sink.open()
        sink.send(frames)
        await sink.close()
        return sink

    sink = asyncio.run(run())
    for _ in range(100):  # UDP on loopback: give the server thread a moment (5 bundles + OK + T)
        if len(rec.packets) >= 7:
            break
        threading.Event().wait(0.02)
    server.shutdown()
    got = bundles(rec.packets)
    assert sink.sent == 5 and len(got) == 5
    for msgs in got:
        check_vmc_bundle(msgs, bones_expected=rig.bones)
    # Hips carries the root position, converted to Unity metres with x mirrored.
    hips = next(p for a, _, p in got[0] if a == "/VMC/Ext/Bone/Pos" and p[0] == "Hips")
    assert np.allclose(hips[1:4], [0.0, 0.9, 0.0], atol=1e-6)
    # After the frames: the idle heartbeat (OK 0, T) as separate messages.
    plain = [OscMessage(p) for p in rec.packets if not OscBundle.dgram_is_bundle(p)]
    assert [(m.address, type_tags(m)) for m in plain[-2:]] == [("/VMC/Ext/OK", "i"), ("/VMC/Ext/T", "f")]
    assert plain[-2].params == [0]


def test_paced_frames_follow_their_pts():
    sk = synthetic_skeleton()
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    server, _ = osc_server()
    times = []
    frames = [Frame(i, i / 20, np.zeros(3), np.tile([1.0, 0, 0, 0], (len(sk.names), 1)), np.zeros(3)) for i in range(6)]

    async def run():
        sink = VmcSink("127.0.0.1", server.server_address[1], rig, pace=True, jitter_s=0.02)
        await sink.open()
        sink.send(frames)  # one burst, as inference makes them
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        while sink.sent < 6:
            await asyncio.sleep(0.005)
            times.append((sink.sent, loop.time() - t0))
        await sink.close()

    asyncio.run(run())
    server.shutdown()
    first_all = next(t for n, t in times if n == 6)
    assert first_all >= 0.2  # 6 frames at 20 fps span 0.25 s, not one burst


def zeggs_rig(zeggs_dir):
    skel = read_bvh(next(zeggs_dir.glob("*.bvh"))).skeleton
    return skel, HumanoidRig.build(skel.names, skel.parents, skel.offsets, load_humanoid_map())


@pytest.mark.parametrize("options", [
    VmcOptions(), VmcOptions(positions="all"), VmcOptions(bones="upper"), VmcOptions(hips_height_m=1.1),
    VmcOptions(root=(0.5, 0.0, -1.0, 135.0)), VmcOptions(max_bytes=1400), VmcOptions(bones="upper", max_bytes=256)])
def test_struct_packed_bundles_equal_python_osc(zeggs_dir, options):
    """The fast packer == python-osc's builders on the reference messages, byte for byte; splits stay under the limit."""
    skel, rig = zeggs_rig(zeggs_dir)
    enc = VmcEncoder(rig, options)
    rng = np.random.default_rng(1)
    f = Frame(7, 0.35, np.array([3.0, 88.0, -4.0]), quat_normalize(rng.normal(size=(len(skel.names), 4))), np.zeros(3))
    packets = enc.packets(f)
    assert packets == [reference_bundle(m) for m in enc.messages(f)]
    if options.max_bytes:
        assert len(packets) > 1 and all(len(p) <= options.max_bytes for p in packets)
    msgs = [m for p in packets for m in bundles([p])[0]]
    check_vmc_bundle(msgs, bones_expected=enc.names)
    assert msgs[-1][2] == [pytest.approx(0.35)]  # /VMC/Ext/T: the frame's pts


def test_receiver_options_change_what_is_sent(zeggs_dir):
    skel, rig = zeggs_rig(zeggs_dir)
    rng = np.random.default_rng(2)
    f = Frame(0, 0.0, np.array([10.0, 80.0, 5.0]), quat_normalize(rng.normal(size=(len(skel.names), 4))), np.zeros(3))
    by_name = lambda enc: dict(zip(enc.names, enc.bone_values(f)))  # noqa: E731
    hips_only, every = by_name(VmcEncoder(rig)), by_name(VmcEncoder(rig, VmcOptions(positions="all")))
    np.testing.assert_allclose(hips_only["Hips"], every["Hips"])  # Hips: its posed position, either way
    rest = VmcEncoder(rig).rest[rig.bones.index("Chest")]
    np.testing.assert_allclose(hips_only["Chest"][:3], rest)  # others: their rest offset, whatever the pose
    assert not np.allclose(every["Chest"][:3], rest)
    np.testing.assert_allclose(hips_only["Chest"][3:], every["Chest"][3:])  # rotations are the same
    tall = by_name(VmcEncoder(rig, VmcOptions(hips_height_m=1.8)))
    ratio = 1.8 / (rig.rest_hips_height() * 0.01)
    np.testing.assert_allclose(tall["Hips"][:3], hips_only["Hips"][:3] * ratio)
    upper = VmcEncoder(rig, VmcOptions(bones="upper")).names
    assert "LeftHand" in upper and "RightIndexProximal" in upper
    assert not {"Hips", "Head", "Neck", "LeftUpperLeg", "LeftFoot"} & set(upper)
    with pytest.raises(ValueError, match="max bytes"):
        VmcOptions(max_bytes=100)
    with pytest.raises(ValueError, match="hips height"):
        VmcOptions(hips_height_m=0)


def test_a_late_frame_is_dropped_not_burst_and_close_is_quick():
    """Frames queued during a stall are dropped at their turn (counted), and Ctrl-C (drain 0) returns at once."""
    rig = HumanoidRig.build(*(lambda s: (s.names, s.parents, s.offsets))(synthetic_skeleton()),
                            {"Hips": synthetic_skeleton().names[0]})
    server, rec = osc_server()
    J = len(synthetic_skeleton().names)

    async def run():
        sink = VmcSink("127.0.0.1", server.server_address[1], rig, jitter_s=0.05)
        await sink.open()
        sink.send([Frame(i, i / 20, np.zeros(3), np.tile([1.0, 0, 0, 0], (J, 1)), np.zeros(3)) for i in range(4)])
        await asyncio.sleep(0.3)
        time.sleep(1.0)  # the event loop stalls while frames 4.. arrive "in time" for a clock that moved on
        sink.send([Frame(i, i / 20, np.zeros(3), np.tile([1.0, 0, 0, 0], (J, 1)), np.zeros(3)) for i in range(4, 60)])
        await asyncio.sleep(1.5)
        waiting0, t = runnable_waiting_s(os.getpid()), time.monotonic()
        await sink.close(drain=False)
        return sink, time.monotonic() - t, runnable_waiting_s(os.getpid()) - waiting0

    sink, close_s, waited = asyncio.run(run())
    server.shutdown()
    assert sink.pacer.stats.dropped_late > 0 and sink.dropped >= sink.pacer.stats.dropped_late
    assert sink.sent + sink.dropped == 60
    # at once, but for the time this thread waited, runnable, for a CPU (the machine's other work)
    assert close_s - waited < 0.5, f"close took {close_s:.2f} s, of which {waited:.2f} s waiting for a CPU"


# ---- the face: /VMC/Ext/Blend/Val per name of the --face set, then /VMC/Ext/Blend/Apply --------------------------


def synthetic_rig():
    sk = synthetic_skeleton()
    return sk, HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())


def speaking_face():
    """A canonical face with every value apart (an open A, a half blink, raised brows, a smile)."""
    face = np.linspace(0.05, 0.95, len(FACE_LABELS))
    face[V["PP"]] = 0.0
    return face


@pytest.mark.parametrize("name_set", list(NAME_SETS))
@pytest.mark.parametrize("max_bytes", [0, 300])
def test_the_face_is_every_name_of_its_set_before_apply(name_set, max_bytes):
    """Each frame: the bones, one Blend/Val (s)name (f)value per name of the set in its order and nothing else,
    then Blend/Apply after the last of them (in the last datagram when split); packed == python-osc's reference."""
    sk, rig = synthetic_rig()
    enc = VmcEncoder(rig, VmcOptions(max_bytes=max_bytes), channels=face_channels(name_set))
    face = speaking_face()
    f = Frame(3, 0.15, np.zeros(3), quat_normalize(np.random.default_rng(3).normal(size=(len(sk.names), 4))),
              np.zeros(3), {FACE: face})
    packets = enc.packets(f)
    assert packets == [reference_bundle(m) for m in enc.messages(f)]
    got = bundles(packets)
    if max_bytes:
        assert len(packets) > 1 and all(len(p) <= max_bytes for p in packets)
    msgs = [m for b in got for m in b]
    check_vmc_bundle(msgs, bones_expected=enc.names)
    addresses = [a for a, _, _ in msgs]
    vals = [p for a, _, p in msgs if a == "/VMC/Ext/Blend/Val"]
    assert [name for name, _ in vals] == list(names_of(name_set))
    np.testing.assert_allclose([v for _, v in vals], convert(face, name_set).astype(np.float32), rtol=0, atol=0)
    last_val = max(i for i, a in enumerate(addresses) if a == "/VMC/Ext/Blend/Val")
    assert addresses.index("/VMC/Ext/Blend/Apply") == last_val + 1 > max(
        i for i, a in enumerate(addresses) if a == "/VMC/Ext/Bone/Pos")
    assert "/VMC/Ext/Blend/Apply" in [a for a, _, _ in got[-1]]  # with the frame's OK and T
    if name_set == "arkit":
        assert set(names_of("arkit")) >= {name for name, _ in vals} and "A" not in {name for name, _ in vals}


def test_a_frame_without_a_face_sends_the_resting_face_and_none_sends_no_face():
    """A rest frame (made without a face, e.g. pipecat's spring between utterances) sends every name at 0;
    `--face none` sends no Blend/Val at all; an unknown set is refused with the known ones."""
    sk, rig = synthetic_rig()
    pose = np.tile([1.0, 0, 0, 0], (len(sk.names), 1))
    rest = Frame(0, 0.0, np.zeros(3), pose, np.zeros(3))
    for name_set in NAME_SETS:
        vals = [p for a, _, p in bundles(VmcEncoder(rig, channels=face_channels(name_set)).packets(rest))[0]
                if a == "/VMC/Ext/Blend/Val"]
        assert [n for n, _ in vals] == list(names_of(name_set)) and all(v == 0.0 for _, v in vals), name_set
    assert face_channels("none") == {}
    msgs = bundles(VmcEncoder(rig, channels=face_channels("none")).packets(
        Frame(0, 0.0, np.zeros(3), pose, np.zeros(3), {FACE: speaking_face()})))[0]
    assert "/VMC/Ext/Blend/Val" not in [a for a, _, _ in msgs] and msgs[-3][0] == "/VMC/Ext/Blend/Apply"
    with pytest.raises(ValueError, match="vrm0, vrm1, arkit, oculus"):
        face_channels("vrm2")


def test_each_sink_sends_the_face_in_its_own_names():
    """Two sinks on one stream, two name sets: each receiver gets its own names; the module's map stays empty."""
    sk, rig = synthetic_rig()
    pose = np.tile([1.0, 0, 0, 0], (len(sk.names), 1))
    frames = [Frame(i, i / 20, np.zeros(3), pose, np.zeros(3), {FACE: speaking_face() * (i + 1) / 4}) for i in range(3)]
    servers = [osc_server() for _ in range(2)]

    async def run():
        sinks = [VmcSink("127.0.0.1", srv.server_address[1], rig, pace=False, channels=face_channels(s))
                 for (srv, _), s in zip(servers, ("vrm0", "arkit"))]
        for s in sinks:
            await s.open()
            s.send(frames)
        for s in sinks:
            await s.close()

    asyncio.run(run())
    for _ in range(100):
        if all(len(bundles(rec.packets)) >= 3 for _, rec in servers):
            break
        threading.Event().wait(0.02)
    for (srv, rec), name_set in zip(servers, ("vrm0", "arkit")):
        srv.shutdown()
        got = bundles(rec.packets)
        assert len(got) == 3
        for f, msgs in zip(frames, got):
            vals = [p for a, _, p in msgs if a == "/VMC/Ext/Blend/Val"]
            assert [n for n, _ in vals] == list(names_of(name_set))
            np.testing.assert_allclose([v for _, v in vals], convert(f.channels[FACE], name_set), atol=1e-6)
    assert VMC_CHANNELS == {}
