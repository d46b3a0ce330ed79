"""A frame is a pose plus named channels: a channel made by the session reaches a WebSocket client (JSON and
binary), a VMC receiver and a recording through each sink's public map only; with every map empty each wire
carries exactly the pose-only frames of protocol revision 5."""

import asyncio
import csv
import json
import struct
import threading

import numpy as np
import pytest
from websockets.asyncio.client import connect

from dimgestor.audio import save_wav
from dimgestor.training.synthetic import synthetic_skeleton, synthetic_speech
from streamer import protocol as P
from streamer import record, vmc
from streamer.frames import Channel, Frame
from streamer.pose import HumanoidRig, load_humanoid_map
from streamer.record import RecordingSink, channels_path
from streamer.sessions import Session
from streamer.sources import WavSource
from streamer.vmc import BlendValues, VmcEncoder, VmcOptions, VmcSink, reference_bundle
from helpers.vmc import bundles, osc_server
from helpers.ws import make_server, recv_json

pytestmark = pytest.mark.timeout(120)

WAVE = Channel("test_wave", 3, "test only: two motion features and a constant", ("first", "second", "seven"))


class WaveMaker:
    """The test channel's producer: a window's values from its features, each call kept to compare with."""

    def __init__(self):
        self.made: list[np.ndarray] = []
        self.lock = threading.Lock()

    def __call__(self, feats: np.ndarray) -> np.ndarray:
        values = np.stack([feats[:, 0], 2.0 * feats[:, 1], np.full(len(feats), 7.0)], axis=1)
        with self.lock:
            self.made.append(values)
        return values

    def values(self) -> np.ndarray:
        return np.concatenate(self.made)


@pytest.fixture
def wave(monkeypatch):
    """The test channel added where it is made (the session) and in each sink's map: nothing else."""
    maker = WaveMaker()
    monkeypatch.setattr(Session, "channels", {WAVE.name: maker})
    monkeypatch.setitem(P.WS_CHANNELS, WAVE.name, WAVE)
    monkeypatch.setitem(vmc.VMC_CHANNELS, WAVE.name, BlendValues(WAVE))
    monkeypatch.setitem(record.RECORD_CHANNELS, WAVE.name, WAVE)
    return maker


def rig_of(sk):
    return HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())


def pose_frame(J=13, index=7, channels=None):
    rng = np.random.default_rng(index)
    q = rng.normal(size=(J, 4))
    return Frame(index, index / 20, rng.normal(size=3) * 50, q / np.linalg.norm(q, axis=-1, keepdims=True),
                 np.zeros(5), channels or {})


# ---- the wires, without sockets ------------------------------------------------------------------


def test_without_channels_every_wire_is_revision_5():
    """No channel on (the maps empty): the JSON and binary frames are the pose-only ones, byte for byte, even for a
    frame that carries a channel no map names; the hello announces no channel."""
    f = pose_frame(channels={"unmapped": np.ones(4)})
    assert P.frame_json(f) == json.dumps({"type": "frame", "index": 7, "pts": 0.35,
                                          "root": np.round(f.root_pos, 5).tolist(),
                                          "rotations": np.round(f.rotations, 6).tolist()}, separators=(",", ":"))
    head = struct.pack("<4sId3f", b"DGF1", f.index, f.pts, *f.root_pos)
    assert P.frame_binary(f) == head + f.rotations.astype("<f4").tobytes()
    assert P.encode_frames([f], "binary") == [P.frame_binary(pose_frame())]
    assert P.encode_frames([f], "json") == [P.frame_json(pose_frame())]
    sk = synthetic_skeleton()
    h = P.hello(P.SkeletonInfo.from_skeleton(sk), {}, 20, 0.25, True)
    # (revision 7 adds the face, which a client has only when the server makes one: still no channel here)
    assert h["channels"] == [] and h["binary_frame_bytes"] == 28 + 16 * len(sk.names) and h["revision"] == P.REVISION
    enc = VmcEncoder(rig_of(sk))
    addresses = [a for msgs in enc.messages(pose_frame(len(sk.names), channels={"unmapped": np.ones(4)}))
                 for a, _ in msgs]
    assert "/VMC/Ext/Blend/Val" not in addresses


def test_json_and_binary_round_trip_through_the_hello_layout():
    sk = synthetic_skeleton()
    J = len(sk.names)
    other = Channel("other", 2)
    chans = {WAVE.name: WAVE, other.name: other}
    layout = P.channel_layout(J, chans)
    assert layout == [{"name": "test_wave", "size": 3, "offset": 28 + 16 * J, "labels": list(WAVE.labels),
                       "description": WAVE.description},
                      {"name": "other", "size": 2, "offset": 28 + 16 * J + 12}]
    f = pose_frame(J, channels={"test_wave": np.array([0.25, -1.5, 7.0]), "other": np.array([3.0, np.nan])})
    d = P.parse_frame_binary(P.frame_binary(f, chans), J, layout)
    assert d["index"] == 7 and np.allclose(d["rotations"], f.rotations, atol=1e-6)
    assert d["channels"]["test_wave"].tolist() == [0.25, -1.5, 7.0]
    assert d["channels"]["other"][0] == 3.0
    j = json.loads(P.frame_json(f, chans))  # finite numbers only: NaN is sent as 0
    assert j["channels"] == {"test_wave": [0.25, -1.5, 7.0], "other": [3.0, 0.0]}
    # a frame without the channel (a rest pose) carries zeros; a later revision's extra bytes are ignored
    rest = P.frame_binary(pose_frame(J), chans) + b"\0" * 8
    assert P.parse_frame_binary(rest, J, layout)["channels"]["other"].tolist() == [0.0, 0.0]
    assert json.loads(P.frame_json(pose_frame(J), chans))["channels"]["test_wave"] == [0.0, 0.0, 0.0]
    # a revision 5 reader (no layout) still gets the header; a buffer shorter than the layout is refused
    with pytest.raises(ValueError, match="layout"):
        P.parse_frame_binary(P.frame_binary(f, chans)[:-4], J, layout)
    with pytest.raises(ValueError, match="DGF1"):
        P.parse_frame_binary(b"DGF1")


def test_a_channel_of_the_wrong_size_or_a_bad_spec_is_a_clear_error():
    f = pose_frame(channels={"test_wave": np.ones(4)})
    with pytest.raises(ValueError, match="test_wave has shape"):
        P.frame_binary(f, {WAVE.name: WAVE})
    with pytest.raises(ValueError, match="letters"):
        Channel("a b", 1)
    with pytest.raises(ValueError, match="positive"):
        Channel("x", 0)
    with pytest.raises(ValueError, match="labels"):
        Channel("x", 2, labels=("a",))


@pytest.mark.parametrize("max_bytes", [0, 300])
def test_vmc_channel_messages_equal_the_reference(max_bytes):
    """The packed bundles equal python-osc's on the reference messages; Blend/Val come before Blend/Apply."""
    sk = synthetic_skeleton()
    enc = VmcEncoder(rig_of(sk), VmcOptions(max_bytes=max_bytes), channels={WAVE.name: BlendValues(WAVE)})
    f = pose_frame(len(sk.names), channels={"test_wave": np.array([0.5, 0.25, 7.0])})
    groups = enc.messages(f)
    assert enc.packets(f) == [reference_bundle(g) for g in groups]
    flat = [m for g in groups for m in g]
    vals = [args for a, args in flat if a == "/VMC/Ext/Blend/Val"]
    assert vals == [["first", 0.5], ["second", 0.25], ["seven", 7.0]]
    addresses = [a for a, _ in flat]
    assert addresses.index("/VMC/Ext/Blend/Apply") > max(i for i, a in enumerate(addresses) if a.endswith("Val"))
    unlabelled = BlendValues(Channel("bare", 2)).messages(np.array([1.0, 2.0]))
    assert unlabelled == [("/VMC/Ext/Blend/Val", ["bare_0", 1.0]), ("/VMC/Ext/Blend/Val", ["bare_1", 2.0])]


# ---- end to end ----------------------------------------------------------------------------------


def test_a_test_channel_reaches_a_websocket_client_a_vmc_receiver_and_a_recording(bundle, tmp_path, wave):
    """The session's frames, sent to the three sinks alike (as `streamer.server.run` does): the client that
    follows the broadcast, the VMC receiver and the recording's CSV each get the values the session made."""
    audio = synthetic_speech(1.6, seed=2)
    save_wav(tmp_path / "a.wav", audio, 16000)
    osc, rec = osc_server()

    async def run():
        ws = make_server(bundle)
        sinks = [ws, VmcSink("127.0.0.1", osc.server_address[1], rig_of(bundle.skeleton), pace=False),
                 RecordingSink(tmp_path / "out.bvh", bundle.skeleton, bundle.feature_spec)]
        for s in sinks:
            await s.open()
        async with connect(ws.url) as c:
            hello = await recv_json(c)
            await c.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "binary"}))
            while not any(c.encoding == "binary" for c in ws.clients):  # the server has read our hello
                await asyncio.sleep(0.01)
            session = Session.from_bundle(bundle, steps=2, seed=3, window_ms=100)
            n = await session.run(WavSource(tmp_path / "a.wav", realtime=False),
                                  lambda fs: [s.send(fs) for s in sinks])
            got = []
            while len(got) < n:
                m = await asyncio.wait_for(c.recv(), 30)
                if isinstance(m, bytes):
                    got.append(P.parse_frame_binary(m, len(hello["skeleton"]["joints"]), hello["channels"]))
        for s in sinks:
            await s.close()
        return hello, n, got

    hello, n, got = asyncio.run(run())
    made = wave.values()
    assert n == len(made) == 32
    J = len(bundle.skeleton.names)
    assert hello["channels"] == [{"name": "test_wave", "size": 3, "offset": 28 + 16 * J,
                                  "labels": ["first", "second", "seven"], "description": WAVE.description}]
    assert hello["binary_frame_bytes"] == 28 + 16 * J + 12
    assert [g["index"] for g in got] == list(range(n))
    assert np.allclose([g["channels"]["test_wave"] for g in got], made, rtol=1e-6, atol=1e-6)

    for _ in range(100):  # UDP on loopback: give the receiver's thread a moment
        if len(bundles(rec.packets)) >= n:
            break
        threading.Event().wait(0.02)
    osc.shutdown()
    sent = [[(p[0], p[1]) for a, tags, p in msgs if a == "/VMC/Ext/Blend/Val" and tags == "sf"]
            for msgs in bundles(rec.packets)]
    assert len(sent) == n and all([name for name, _ in s] == list(WAVE.labels) for s in sent)
    assert np.allclose([[v for _, v in s] for s in sent], made, rtol=1e-6, atol=1e-6)

    with open(channels_path(tmp_path / "out.bvh")) as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["index", "pts", "test_wave.first", "test_wave.second", "test_wave.seven"]
    table = np.array(rows[1:], dtype=float)
    assert table[:, 0].tolist() == list(range(n)) and np.allclose(table[:, 1], np.arange(n) / 20)
    assert np.allclose(table[:, 2:], made, rtol=1e-5, atol=1e-6)
    assert (tmp_path / "out.bvh").read_text().count("\n") > n  # the pose is recorded as before


@pytest.mark.parametrize("encoding", ["json", "binary"])
def test_a_clients_own_session_sends_the_channel_in_its_encoding(bundle, wave, encoding):
    audio = np.round(synthetic_speech(1.2, seed=6) * 32767 * 0.8).astype("<i2")

    async def run():
        ws = make_server(bundle)
        await ws.open()
        async with connect(ws.url) as c:
            hello = await recv_json(c)
            await c.send(json.dumps({"type": "hello", "protocol": 1, "encoding": encoding}))
            await c.send(audio.tobytes())
            await c.send(json.dumps({"type": "audio_end"}))
            frames, end = [], None
            while end is None:
                m = await asyncio.wait_for(c.recv(), 30)
                if isinstance(m, bytes):
                    frames.append(P.parse_frame_binary(m, len(hello["skeleton"]["joints"]), hello["channels"]))
                elif (d := json.loads(m))["type"] == "frame":
                    frames.append(d)
                elif d["type"] == "end":
                    end = d
        await ws.close()
        return frames, end

    frames, end = asyncio.run(run())
    made = wave.values()
    assert end["frames"] == len(frames) == len(made) == 24
    assert np.allclose([f["channels"]["test_wave"] for f in frames], made, rtol=1e-5, atol=1e-5)


def test_the_pipecat_processor_passes_a_speech_frames_channels_on(bundle, monkeypatch):
    """GestureProcessor re-stamps each speech frame it releases: the channels go with it (a rest frame has none
    but the processor's resting face, so its sinks send zeros for the rest). On a fake clock."""
    from types import SimpleNamespace

    from streamer import pipecat as sp
    from streamer.playout import Utterance

    sent = []
    monkeypatch.setattr(sp, "time", SimpleNamespace(monotonic=lambda: 0.0))
    g = sp.GestureProcessor([SimpleNamespace(send=sent.extend)], bundle=bundle)
    g.origin, g.playout.observed = 0.0, True
    u = Utterance(0, None, None, None, 16000)
    g._schedule(u, 320)
    rest = g.resting.pose_frame()
    values = {WAVE.name: np.array([1.0, 2.0, 3.0])}
    g._release_speech(u, Frame(0, 0.0, rest.root_pos, rest.rotations, rest.features, values), u.start, 0.0)
    g._release_rest(0.05)
    assert sent[0].channels is values and set(sent[1].channels) == {"face"}


def test_a_maker_of_the_wrong_number_of_rows_is_a_clear_error_where_it_is_made(bundle):
    session = Session.from_bundle(bundle, steps=2, seed=3)
    session.channels = {WAVE.name: lambda feats: np.zeros((len(feats) + 1, 3))}
    with pytest.raises(ValueError, match="rows for"):
        session.infer(synthetic_speech(0.5, seed=1))
