"""The face over the WebSocket (protocol revision 7) as a user gets it: `dimgestor serve` in a subprocess and real
websockets clients on loopback. JSON frames carry the face in every frame, binary frames only after the client
asked (then after a `channels` message with the layout), a client's set is its own, unknown sets are refused with
the known ones on a connection that keeps serving, "none" means no face, and a client's smile is its own."""

import asyncio
import json

import numpy as np
import pytest
from websockets.asyncio.client import connect

from dimgestor.audio import load_wav
from dimgestor.face.names import ARKIT, NAME_SETS, names_of
from streamer.face import face_channel
from helpers.serve import WAV_SECONDS, follow, serve
from streamer import protocol as P

pytestmark = pytest.mark.timeout(240)

SETS = list(NAME_SETS)  # vrm0, vrm1, arkit, oculus


async def talk(url: str, hello: dict | None, pcm: bytes, before: list[dict] = ()) -> tuple[dict, list]:
    """One client: read the server's hello, send `before` (each answered), our hello, the audio in 1 s messages and
    audio_end; returns the server's hello and every message after ours until `end` (JSON parsed, status left out,
    binary frames as bytes), with the answers to `before` first."""
    msgs = []
    async with connect(url, max_size=8 * 2**20) as c:
        server_hello = json.loads(await asyncio.wait_for(c.recv(), 30))
        for m in before:
            await c.send(json.dumps(m))
            while (reply := json.loads(await asyncio.wait_for(c.recv(), 30)))["type"] == "status":
                pass
            msgs.append(reply)
        if hello is not None:
            await c.send(json.dumps({"type": "hello", "protocol": 1, **hello}))
        for i in range(0, len(pcm), 32000):
            await c.send(pcm[i:i + 32000])
        await c.send(json.dumps({"type": "audio_end"}))
        while True:
            m = await asyncio.wait_for(c.recv(), 60)
            if isinstance(m, str) and (m := json.loads(m))["type"] == "status":
                continue
            msgs.append(m)
            if isinstance(m, dict) and m["type"] == "end":
                return server_hello, msgs


def frames_of(msgs: list) -> list:
    return [m for m in msgs if isinstance(m, bytes) or m["type"] == "frame"]


def faces(frames: list[dict], names) -> np.ndarray:
    """(T, len(names)) from JSON frames, each of which must carry exactly `names`, in order, within 0..1 and with
    at most 4 decimals."""
    assert all(list(f["face"]) == list(names) for f in frames), set(map(len, (f.get("face", ()) for f in frames)))
    table = np.array([list(f["face"].values()) for f in frames])
    assert table.min() >= 0 and table.max() <= 1 and np.allclose(table, np.round(table, 4), rtol=0, atol=1e-12)
    return table


@pytest.fixture(scope="module")
def pcm(wav) -> bytes:
    return np.round(load_wav(wav) * 32767 * 0.8).astype("<i2").tobytes()


@pytest.fixture(scope="module")
def talker(tiny_checkpoint):
    """`serve --source ws` (clients' own audio only, the default --face vrm0)."""
    s = serve(tiny_checkpoint, "--source", "ws")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    yield url
    s.proc.terminate()
    s.finish()


def test_a_talker_gets_a_face_once_it_asks_and_old_clients_get_the_frames_they_know(talker, pcm):
    # a client that never asks (written for revision 6 or before): its own audio makes no face (nor costs one)
    hello, msgs = asyncio.run(talk(talker, None, pcm))
    assert hello["revision"] == P.REVISION and hello["channels"] == []
    assert hello["face"] == {"names": "vrm0", "sets": SETS, "labels": list(names_of("vrm0"))}
    frames = frames_of(msgs)
    assert len(frames) == WAV_SECONDS * 20 and not any("face" in f for f in frames)

    # asking for the server's set: every JSON frame has it
    _, msgs = asyncio.run(talk(talker, {"face": "vrm0"}, pcm))
    frames = frames_of(msgs)
    assert len(frames) == WAV_SECONDS * 20 and msgs[-1] == {"type": "end", "frames": len(frames)}
    table = faces(frames, names_of("vrm0"))
    assert table[:, :5].max() > 0.1  # the mouth moves with the speech
    assert not table[:, 8].any()  # Joy: the server's smile, 0 by default

    # a binary client that never asks (written for revision 5 or 6): the pose alone, no `channels` message
    hello, msgs = asyncio.run(talk(talker, {"encoding": "binary"}, pcm))
    J = len(hello["skeleton"]["joints"])
    assert all(isinstance(m, bytes) for m in msgs[:-1]) and {len(m) for m in msgs[:-1]} == {28 + 16 * J}
    assert len(msgs) - 1 == WAV_SECONDS * 20


def test_a_client_that_asks_for_arkit_gets_arkit_names_in_json_and_the_layout_and_floats_in_binary(talker, pcm):
    _, as_json = asyncio.run(talk(talker, {"face": "arkit"}, pcm))
    hello, as_binary = asyncio.run(talk(talker, {"face": "arkit", "encoding": "binary"}, pcm))
    J = len(hello["skeleton"]["joints"])
    layout = [{"name": "face", "size": 52, "offset": 28 + 16 * J, "labels": list(ARKIT),
               "description": "face blendshape weights 0..1, arkit names"}]
    assert as_json[0] == as_binary[0] == {"type": "channels", "channels": layout}  # before the first frame
    assert not [m for m in as_json[1:] if m["type"] == "channels"]  # once

    json_face = faces(frames_of(as_json), ARKIT)  # ARKit's 52 names only
    binary = frames_of(as_binary)
    assert len(binary) == len(json_face) == WAV_SECONDS * 20 and {len(b) for b in binary} == {28 + 16 * J + 208}
    binary_face = np.array([np.frombuffer(b, "<f4", count=52, offset=layout[0]["offset"]) for b in binary])
    assert np.abs(binary_face - json_face).max() <= 6e-5  # the same face (the face depends on the audio alone)
    assert binary_face[:, ARKIT.index("jawOpen")].max() > 0.1


def test_an_unknown_set_is_refused_with_the_known_ones_and_the_connection_keeps_serving(talker, pcm):
    _, msgs = asyncio.run(talk(talker, None, pcm, before=[{"type": "hello", "face": "vrm2", "encoding": "binary"},
                                                          {"type": "ping", "n": 1}]))
    error, pong = msgs[:2]
    assert error["type"] == "error" and error["code"] == "bad_message"
    assert "vrm2" in error["message"] and all(s in error["message"] for s in SETS)
    assert pong["type"] == "pong" and pong["n"] == 1
    # the refused hello changed nothing: still JSON, and no face asked
    frames = frames_of(msgs[2:])
    assert frames and all(isinstance(f, dict) and "face" not in f for f in frames)


def test_none_means_no_face_and_a_smile_is_the_clients_own(talker, pcm):
    async def both():  # at once: each session holds its own smile
        return await asyncio.gather(talk(talker, {"face": "none"}, pcm), talk(talker, {"face": "vrm0", "smile": 1.0}, pcm))

    (_, none), (_, smiling) = asyncio.run(both())
    assert none[0] == {"type": "channels", "channels": []}
    smiling = [m for m in smiling if not (isinstance(m, dict) and m["type"] == "channels")]
    assert all(set(f) == {"type", "index", "pts", "root", "rotations"} for f in frames_of(none[1:]))
    joy = faces(frames_of(smiling), names_of("vrm0"))[:, 8]
    assert joy.min() >= 0.5  # held under the speech (half of it at a fully open jaw)


def test_the_servers_source_sends_its_face_to_watchers_in_the_servers_set(tiny_checkpoint, wav):
    s = serve(tiny_checkpoint, "--source", str(wav), "--fast", "--wait-client", "--face", "oculus")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    hello, msgs = asyncio.run(follow(url))
    assert s.finish() == 0, s.output
    assert hello["face"]["names"] == "oculus" and hello["channels"] == []
    frames = frames_of(msgs)
    assert len(frames) == WAV_SECONDS * 20
    faces(frames, names_of("oculus"))


def test_a_server_without_a_face_sends_none_and_ignores_a_clients_ask(tiny_checkpoint, wav):
    s = serve(tiny_checkpoint, "--source", str(wav), "--fast", "--wait-client", "--face", "none")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    hello, msgs = asyncio.run(follow(url, {"face": "arkit"}))
    assert s.finish() == 0, s.output
    assert "face" not in hello
    assert not [m for m in msgs if m["type"] in ("channels", "error")]
    frames = frames_of(msgs)
    assert len(frames) == WAV_SECONDS * 20 and not [f for f in frames if "face" in f]


def test_one_broadcast_reaches_each_watcher_in_its_own_set_and_encoding(bundle, tmp_path):
    """The server's source (in process): four watchers of the same frames, JSON as it comes, JSON in ARKit names,
    binary as it comes (revision 5's frames) and binary in Oculus names (after a `channels` message), each get the
    face the session made, in their own form."""
    from dimgestor.audio import save_wav
    from dimgestor.face import FaceOptions, convert
    from dimgestor.training.synthetic import synthetic_speech
    from streamer import protocol as P
    from streamer.sessions import Session
    from streamer.sources import WavSource
    from helpers.ws import make_server, recv_json

    save_wav(tmp_path / "a.wav", synthetic_speech(1.6, seed=2), 16000)
    asks = [None, {"face": "arkit"}, {"encoding": "binary"}, {"encoding": "binary", "face": "oculus"}]

    async def run():
        ws = make_server(bundle, {"face": P.face_hello("vrm0")})  # (what `serve` says with its default --face)
        await ws.open()
        clients = [await connect(ws.url) for _ in asks]
        for c, ask in zip(clients, asks):
            await recv_json(c)
            if ask:
                await c.send(json.dumps({"type": "hello", **ask}))
        while sorted(str(c.machine.face) + c.encoding for c in ws.clients) != [
                "Nonebinary", "Nonejson", "arkitjson", "oculusbinary"]:  # the server has read our hellos
            await asyncio.sleep(0.01)
        made = []
        session = Session.from_bundle(bundle, steps=2, seed=3, window_ms=100, face=FaceOptions())
        n = await session.run(WavSource(tmp_path / "a.wav", realtime=False), lambda fs: (made.extend(fs), ws.send(fs)))
        got = []
        for c in clients:
            msgs = []
            while len(frames_of(msgs)) < n:
                m = await asyncio.wait_for(c.recv(), 30)
                if isinstance(m, bytes) or (m := json.loads(m))["type"] != "status":
                    msgs.append(m)
            got.append(msgs)
            await c.close()
        await ws.close()
        return made, got

    made, (plain, arkit, old, oculus) = asyncio.run(run())
    J = len(bundle.skeleton.names)
    canonical = np.array([f.channels["face"] for f in made])
    assert np.allclose(faces(frames_of(plain), names_of("vrm0")), convert(canonical, "vrm0"), atol=5e-5)
    assert np.allclose(faces(frames_of(arkit), ARKIT), convert(canonical, "arkit"), atol=5e-5)
    assert arkit[0]["type"] == "channels" and arkit[0]["channels"][0]["size"] == 52  # (the binary layout it asked)
    assert {len(m) for m in old} == {28 + 16 * J}
    assert oculus[0] == {"type": "channels", "channels": P.channel_layout(J, {"face": face_channel("oculus")})}
    assert {len(m) for m in oculus[1:]} == {28 + 16 * J + 4 * 17}
    values = np.array([np.frombuffer(m, "<f4", offset=28 + 16 * J) for m in oculus[1:]])
    assert np.allclose(values, convert(canonical, "oculus"), atol=1e-6)
