"""A python-osc receiver that keeps raw packets, and the checks a VMC bundle must pass."""

import socket
import threading

import numpy as np
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage
from pythonosc.osc_server import ThreadingOSCUDPServer

from streamer.pose import HUMAN_BODY_BONES

# Argument types per address, as the VMC Marionette spec writes them.
SPEC_TYPES = {
    "/VMC/Ext/Root/Pos": "sfffffff",
    "/VMC/Ext/Bone/Pos": "sfffffff",
    "/VMC/Ext/Blend/Val": "sf",
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
