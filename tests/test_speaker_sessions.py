"""A speaker chosen per session (issue 51): a model trained with --speaker-condition plays, on each client's own
session, the speaker its hello asks (protocol revision 9); streams of several speakers batch together and each
equals its own offline generation; a saved state resumes only as its own speaker."""

import asyncio
import json

import numpy as np
import pytest
from websockets.asyncio.client import connect

from dimgestor.streaming import savestate
from dimgestor.streaming.batch import push_many
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.streaming.savestate_checks import StateError
from dimgestor.streaming.stream import GestureStream, generate_offline
from dimgestor.training.synthetic import synthetic_speech
from helpers.checkpoint import make_tiny_checkpoint
from helpers.ws import make_server, recv_json
from streamer import protocol as P
from streamer.client_session import Audio, ClientSession, Decoded, Seats, Send, StartSession, Terms, Text
from streamer.scheduling import StreamBatcher
from streamer.sessions import Session

pytestmark = pytest.mark.timeout(180)
NAMES = ("alice", "bob")


@pytest.fixture(scope="module")
def speakers_bundle(tmp_path_factory):
    """A tiny model with two speakers, every weight shaken so that each speaker's vector shows in the motion."""
    return load_checkpoint(make_tiny_checkpoint(tmp_path_factory.mktemp("speakers"), jitter=0.2, speakers=NAMES,
                                                 lookahead_ms=100, down_kernel=15))  # (ONNX: whole frames of lookahead)


def offline(model, audio, speaker, seed=4):
    model.use_speaker(speaker)
    try:
        return generate_offline(model, audio, steps=2, seed=seed)
    finally:
        model.use_speaker(None)


def test_streams_of_several_speakers_batch_together_and_each_equals_its_offline_frames(speakers_bundle):
    model = speakers_bundle.model
    audio = synthetic_speech(1.3, seed=1)
    want = {name: offline(model, audio, name) for name in (None, *NAMES)}
    assert min(np.abs(want[a] - want[b]).max() for a, b in ((None, "alice"), (None, "bob"), ("alice", "bob"))) > 1e-2
    names = [None, "alice", "bob", "alice"]
    streams = [GestureStream(model, steps=2, seed=4, speaker=n) for n in names]
    out = [[] for _ in streams]
    for a in range(0, len(audio), 700):  # one condition call and one denoiser batch for the four a window
        for o, frames in zip(out, push_many(streams, [audio[a:a + 700]] * len(streams))):
            o.append(frames)
    for s, o, n in zip(streams, out, names):
        got = np.concatenate([*o, s.finish()])
        assert got.shape == want[n].shape and np.abs(got - want[n]).max() < 1e-4, n


def test_a_stream_plays_the_models_own_speaker_unless_told_and_refuses_one_it_does_not_know(speakers_bundle):
    model = speakers_bundle.model
    model.use_speaker("bob")
    try:
        assert GestureStream(model).speaker == "bob" and GestureStream(model, speaker=None).speaker is None
    finally:
        model.use_speaker(None)
    assert GestureStream(model).speaker is None
    with pytest.raises(ValueError, match="speaker 'carol': this model knows alice, bob"):
        GestureStream(model, speaker="carol")


def test_a_saved_state_resumes_as_its_own_speaker_only(speakers_bundle, tiny_checkpoint):
    model, audio = speakers_bundle.model, synthetic_speech(1.5, seed=2)
    first = GestureStream(model, steps=2, seed=1, speaker="alice")
    head = first.push(audio[:9000])
    data = savestate.dumps(first)
    again = GestureStream(model, steps=2, seed=1, speaker="alice")
    again.state, _ = savestate.loads(again, data)
    got = np.concatenate([head, again.push(audio[9000:]), again.finish()])
    assert np.abs(got - offline(model, audio, "alice", seed=1)).max() < 1e-4
    with pytest.raises(StateError, match=r"other sampling settings \(speaker\): saved \['alice'\], here \['bob'\]"):
        savestate.loads(GestureStream(model, steps=2, seed=1, speaker="bob"), data)
    # a model without speakers saves the settings it saved before (its states stay readable across the change)
    assert "speaker" not in savestate.stream_settings(load_checkpoint(tiny_checkpoint).stream())


# ---- the client's hello (the session machine, without sockets) ----

def machine(**terms) -> ClientSession:
    return ClientSession(Seats(Terms(max_sessions=4, **terms)), new_token=lambda: "t")


def hello(c: ClientSession, **fields) -> list[dict]:
    return [json.loads(a.message) for a in c.handle(Text(json.dumps({"type": "hello", **fields}), now=0.0))
            if isinstance(a, Send)]


def started(c: ClientSession) -> StartSession:
    c.handle(Audio(np.zeros(1600, "<i2").tobytes()))
    return next(a for a in c.handle(Decoded()) if isinstance(a, StartSession))


def test_a_clients_hello_picks_its_sessions_speaker_and_an_unknown_one_is_refused_with_the_known_names():
    terms = dict(speakers=NAMES, speaker="alice")
    assert started(machine(**terms)).speaker == "alice"  # the server's --speaker unless the client asks
    c = machine(**terms)
    assert hello(c, speaker="bob") == []
    assert started(c).speaker == "bob"
    c = machine(**terms)
    assert hello(c, speaker=None) == []
    assert started(c).speaker is None  # null: no speaker in particular
    c = machine(**terms)
    [err] = hello(c, speaker="carol", encoding="binary")
    assert err["code"] == "bad_message" and err["message"] == "speaker 'carol': this server's model knows alice, bob"
    assert c.encoding == "json" and started(c).speaker == "alice"  # nothing of the refused hello applied
    [err] = hello(machine(), speaker="alice")  # a model without speakers
    assert "trained without --speaker-condition" in err["message"]
    assert hello(machine(), speaker=None) == []
    for bad in (7, "", "x" * 129, ["alice"]):
        [err] = hello(machine(**terms), speaker=bad)
        assert err["code"] == "bad_message" and "speaker must be a speaker's name" in err["message"]


def test_a_server_on_onnx_runtime_plays_its_one_speaker_and_says_so():
    """ONNX Runtime's graph holds one speaker's vector: a client may ask that one, and no other (nor none)."""
    c = machine(speakers=NAMES, speaker="alice", speaker_fixed=True)
    assert hello(c, speaker="alice") == []
    for other in ("bob", None):
        [err] = hello(c, speaker=other)
        assert "this server plays speaker 'alice' only (its ONNX Runtime backend" in err["message"]
    assert P.speakers_hello(NAMES, "alice", fixed=True) == {"names": ["alice"], "default": "alice", "choice": False}
    assert P.speakers_hello(NAMES, None, fixed=False) == {"names": ["alice", "bob"], "default": None, "choice": True}
    # (an export of no speaker in particular offers no name)
    assert P.speakers_hello(NAMES, None, fixed=True) == {"names": [], "default": None, "choice": False}


# ---- through a real WebSocket server ----

def test_clients_of_one_server_each_get_the_speaker_their_hello_asked_batched_together(speakers_bundle):
    bundle = speakers_bundle
    batcher = StreamBatcher()
    audio = synthetic_speech(2.0, seed=5)
    pcm = (np.clip(audio, -1, 1) * 32767).astype("<i2")
    heard = pcm.astype(np.float32) / 32768.0  # (what the server decodes)
    asks = {"alice": {"speaker": "alice"}, "bob": {"speaker": "bob"}, "default": {}}

    def make_session(**kw):
        return Session.from_bundle(bundle, steps=2, seed=3, window_ms=100, scheduler=batcher, **kw)

    async def client(url, ask):
        async with connect(url) as c:
            first = await recv_json(c)
            await c.send(json.dumps({"type": "hello", **ask}))
            for a in range(0, len(pcm), 1600):
                await c.send(pcm[a:a + 1600].tobytes())
            await c.send(json.dumps({"type": "audio_end"}))
            rotations = []
            while (d := await recv_json(c, timeout=60))["type"] != "end":
                assert d["type"] != "error", d
                if d["type"] == "frame":
                    rotations.append(d["rotations"])
            return first, np.array(rotations)

    async def run():
        ws = make_server(bundle, {"speakers": P.speakers_hello(NAMES, None, fixed=False)}, make_session=make_session)
        await ws.open()
        try:
            return dict(zip(asks, await asyncio.gather(*(client(ws.url, a) for a in asks.values()))))
        finally:
            await ws.close()

    try:
        got = asyncio.run(run())
    finally:
        batcher.shutdown()
    assert got["default"][0]["speakers"] == {"names": ["alice", "bob"], "default": None, "choice": True}
    assert got["default"][0]["revision"] == P.REVISION == 9
    want = {}
    for name, speaker in (("alice", "alice"), ("bob", "bob"), ("default", None)):
        local = Session.from_bundle(bundle, steps=2, seed=3, window_ms=100, speaker=speaker)
        frames = []
        asyncio.run(local.run(_chunks(heard), frames.extend))
        want[name] = np.stack([f.rotations for f in frames])
        assert got[name][1].shape == want[name].shape and np.abs(got[name][1] - want[name]).max() < 1e-4, name
    assert np.abs(want["alice"] - want["bob"]).max() > 1e-2 and np.abs(want["alice"] - want["default"]).max() > 1e-2
    assert batcher.stats.batches > 0


async def _chunks(audio, n=1600):
    from streamer.sources import AudioChunk

    for a in range(0, len(audio), n):
        yield AudioChunk(audio[a:a + n], a / 16000, 0.0)


def test_serve_offers_the_models_speakers_with_its_own_as_the_default_and_onnx_runtime_its_one(speakers_bundle,
                                                                                                 tmp_path):
    from streamer.options import ServeOptions
    from streamer.server import build

    options = dict(source="ws", checkpoint=str(speakers_bundle.path), ws=("127.0.0.1", 0), steps=2, status_every=0,
                   face="none", speaker="bob")
    p = build(ServeOptions(**options))
    assert p.ws.hello["speakers"] == {"names": ["alice", "bob"], "default": "bob", "choice": True}
    assert p.ws.seats.terms.speaker == "bob" and p.ws.seats.terms.speakers == NAMES
    assert p.make_session().stream.speaker == "bob"  # (the server's own source, and a client that does not ask)
    assert p.make_session(speaker="alice").stream.speaker == "alice"
    assert p.make_session(speaker=None).stream.speaker is None
    pytest.importorskip("onnxruntime")
    # (--no-batch: the single-stream graph only, a third of the export; what the hello says does not depend on it)
    p = build(ServeOptions(**options, backend="onnxruntime", onnx_cache=str(tmp_path / "cache"), no_batch=True))
    assert p.ws.hello["speakers"] == {"names": ["bob"], "default": "bob", "choice": False}
    assert p.ws.seats.terms.speaker_fixed
    with pytest.raises(ValueError, match="plays 'bob' only"):
        p.make_session(speaker="alice")


def test_a_voice_agents_gesture_processor_plays_the_speaker_it_is_given(speakers_bundle):
    pytest.importorskip("pipecat", reason="pipecat-ai is not installed (pip install 'dimgestor[pipecat]')")
    from streamer.pipecat import GestureProcessor

    made = {name: GestureProcessor([], bundle=speakers_bundle, steps=2, face=None, speaker=name) for name in NAMES}
    assert made["bob"].speaker == "bob" and GestureProcessor([], bundle=speakers_bundle, face=None).speaker is None
    # its rest pose between utterances is that speaker's too
    assert np.abs(made["alice"].rest.features - made["bob"].rest.features).max() > 1e-2
    with pytest.raises(ValueError, match="speaker 'carol': this model knows alice, bob"):
        GestureProcessor([], bundle=speakers_bundle, face=None, speaker="carol")


def test_the_python_client_asks_for_a_speaker_and_gets_generate_s_motion_of_that_speaker(speakers_bundle, tmp_path):
    """clients/python/client.py --speaker bob against `dimgestor serve`: its BVH is `generate --speaker bob`'s (every
    joint within 0.01 cm), not the one of no speaker in particular; a name the model does not know is answered with
    the names it knows."""
    import sys

    from dimgestor.bvh import forward_kinematics, read_bvh
    from helpers import warm
    from helpers.clients import REPO, SPEECH_WAV, live_server, run_client

    checkpoint = str(speakers_bundle.path)
    with live_server(tmp_path, "ws", speakers_bundle.path, extra=("--face", "none")) as server:
        r = run_client("--url", server.ws_url, "--wav", str(SPEECH_WAV), "--fast", "--speaker", "bob", "--bvh",
                       str(tmp_path / "bob.bvh"), "--quiet")
        bad = run_client("--url", server.ws_url, "--speaker", "carol", "--seconds", "2", "--quiet")
    assert "speakers alice, bob (default none in particular)" in r.stdout
    assert "speaker 'carol': this server's model knows alice, bob" in bad.stdout
    fk = {}
    for speaker in ("bob", None):
        offline = tmp_path / f"offline_{speaker}.bvh"
        g = warm.run([sys.executable, "-m", "dimgestor_app.cli", "generate", "--checkpoint", checkpoint, "--audio",
                      str(SPEECH_WAV), "--out", str(offline), "--steps", "2", "--seed", "0", "--root", "tether",
                      *(["--speaker", speaker] if speaker else [])], cwd=REPO, capture_output=True, text=True,
                     timeout=120)
        assert g.returncode == 0, g.stderr
        fk[speaker] = forward_kinematics(read_bvh(offline))
    got = forward_kinematics(read_bvh(tmp_path / "bob.bvh"))
    # (this shaken model's angles reach thousands of degrees: float rounding shows at 1e-3 cm)
    assert got.shape == fk["bob"].shape and np.abs(got - fk["bob"]).max() < 1e-2
    assert np.abs(got - fk[None]).max() > 1.0
