"""VMC over OSC: a python-osc server receives one bundle per frame with the spec's argument types."""

import asyncio
import socket
import threading

import numpy as np
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage
from pythonosc.osc_server import ThreadingOSCUDPServer

from dimgestor.bvh import read_bvh
from dimgestor.rotations import quat_normalize
from dimgestor.synthetic import synthetic_skeleton
from streamer.engine import Frame
from streamer.pose import HUMAN_BODY_BONES, HumanoidRig, load_humanoid_map
from streamer.vmc import VmcSink

# Argument types per address, as the VMC Marionette spec writes them.
SPEC_TYPES = {
    "/VMC/Ext/Root/Pos": "sfffffff",
    "/VMC/Ext/Bone/Pos": "sfffffff",
    "/VMC/Ext/Blend/Apply": "",
    "/VMC/Ext/OK": "i",
    "/VMC/Ext/T": "f",
}


def type_tags(msg: OscMessage) -> str:
    """The OSC type tag string of a message, read from its datagram."""
    d = msg.dgram
    start = d.index(b",", len(msg.address))
    return d[start + 1 : d.index(b"\0", start)].decode()


class Recorder(Dispatcher):
    """A python-osc dispatcher that also keeps each raw packet, to see bundle boundaries and type tags."""

    def __init__(self):
        super().__init__()
        self.packets: list[bytes] = []
        self.received = threading.Event()

    def call_handlers_for_packet(self, data, client_address):
        self.packets.append(data)
        self.received.set()
        return super().call_handlers_for_packet(data, client_address)


def osc_server():
    rec = Recorder()
    rec.set_default_handler(lambda address, *args: None)
    server = ThreadingOSCUDPServer(("127.0.0.1", 0), rec)
    # `--fast` sends a whole clip's bundles (~5 KB each with 52 bones) in bursts; the default 208 KiB
    # receive buffer overflows while the Python thread catches up, and UDP drops what does not fit
    for opt in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):  # FORCE passes rmem_max as root
        try:
            server.socket.setsockopt(socket.SOL_SOCKET, opt, 16 << 20)
            break
        except (OSError, TypeError):
            continue
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, rec


def bundles(packets):
    out = []
    for p in packets:
        if OscBundle.dgram_is_bundle(p):
            out.append([(m.address, type_tags(m), m.params) for m in OscBundle(p)])
    return out


def check_vmc_bundle(msgs, bones_expected=None):
    addresses = [a for a, _, _ in msgs]
    assert addresses[0] == "/VMC/Ext/Root/Pos" and msgs[0][2][0] == "root"
    assert addresses[-3:] == ["/VMC/Ext/Blend/Apply", "/VMC/Ext/OK", "/VMC/Ext/T"]
    bones = [p[0] for a, _, p in msgs if a == "/VMC/Ext/Bone/Pos"]
    assert bones and set(bones) <= set(HUMAN_BODY_BONES) and len(set(bones)) == len(bones)
    if bones_expected is not None:
        assert set(bones) == set(bones_expected)
    for a, tags, params in msgs:
        assert tags == SPEC_TYPES[a], (a, tags)
        if a.endswith("/Pos"):
            q = np.array(params[4:8])
            assert abs(np.linalg.norm(q) - 1) < 1e-5
    return bones


def test_vmc_sink_sends_spec_typed_bundles(zeggs_dir):
    skel = read_bvh(next(zeggs_dir.glob("*.bvh"))).skeleton
    rig = HumanoidRig.build(skel.names, skel.parents, skel.offsets, load_humanoid_map())
    server, rec = osc_server()
    rng = np.random.default_rng(0)
    frames = [Frame(i, i / 20, np.array([0.0, 90.0, 0.0]), quat_normalize(rng.normal(size=(len(skel.names), 4))),
                    np.zeros(3)) for i in range(5)]

    async def run():
        sink = VmcSink("127.0.0.1", server.server_address[1], rig, pace=True, jitter_s=0.05)
        sink.start()
        sink.on_frames(frames)
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
        sink.start()
        sink.on_frames(frames)  # one burst, as inference makes them
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
