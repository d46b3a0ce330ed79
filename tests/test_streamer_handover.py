"""Sessions that outlive their worker (issue 22, item 3): a worker given SIGTERM saves each client session to the
state store and sends `goaway` with a resume token; the client resumes on another worker, and the frames go on
as in an uninterrupted run."""
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from streamer import protocol as P
from streamer.handover import MemoryStore, open_store

from helpers.clients import CLIENT, REPO, free_port, live_server, reference_decode, run_client

pytestmark = pytest.mark.timeout(240)


def test_a_memory_store_gives_a_state_once_and_forgets_it_after_its_ttl():
    now = [0.0]
    store = MemoryStore(ttl_s=10.0, now=lambda: now[0])
    store.put("a", b"state a")
    store.put("b", b"state b")
    assert store.take("a") == b"state a" and store.take("a") is None  # a token resumes once
    now[0] = 10.5
    assert store.take("b") is None  # expired
    assert open_store(None) is None and isinstance(open_store("memory"), MemoryStore)
    with pytest.raises(SystemExit, match="redis://"):
        open_store("postgres://x")


def test_resume_session_is_parsed_and_checked():
    assert P.parse_text('{"type": "resume_session", "token": "abc"}') == {"type": "resume_session", "token": "abc"}
    for bad in ('{"type": "resume_session"}', '{"type": "resume_session", "token": 5}',
                '{"type": "resume_session", "token": "%s"}' % ("x" * 200)):
        with pytest.raises(P.ProtocolError, match="token"):
            P.parse_text(bad)


def _wav(path, seconds: float, rate: int = 16000) -> None:
    import wave

    from dimgestor.audio import resample
    from dimgestor.synthetic import synthetic_speech

    x = resample(synthetic_speech(seconds, rate=16000, seed=5), 16000, rate)
    with wave.open(str(path), "wb") as w:
        w.setnchannels(1), w.setsampwidth(2), w.setframerate(rate)
        w.writeframes((np.clip(x, -1, 1) * 20000).astype("<i2").tobytes())


def _frames(folder):
    msgs = [reference_decode(p) for p in sorted(folder.iterdir())]
    return msgs, [m for m in msgs if m["type"] == "frame"]


def _interrupted_client(a, b, wav, moved, signum: int, after: int, *extra: str) -> str:
    """The Python client sending `wav` to worker `a` (then `b`), its messages saved in `moved`; once `after`
    messages have come (mid-sentence), `signum` goes to `a`. -> the client's stderr, after it exits 0."""
    client = subprocess.Popen([sys.executable, str(CLIENT), "--url", a.ws_url, "--url", b.ws_url, "--wav", str(wav),
                               "--save", str(moved), "--quiet", *extra], cwd=REPO, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (moved.is_dir() and sum(1 for _ in moved.iterdir()) > after):
        time.sleep(0.05)
    a.proc.send_signal(signum)
    _, err = client.communicate(timeout=60)
    assert client.returncode == 0, err[-2000:]
    return err


@pytest.fixture
def redis_url(tmp_path):
    pytest.importorskip("redis", reason="the redis client is not installed (pip install 'dimgestor[cluster]')")
    exe = shutil.which("redis-server")
    if exe is None:
        pytest.skip("redis-server is not installed (Debian: apt-get install redis-server)")
    port = free_port()
    proc = subprocess.Popen([exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                             "--dir", str(tmp_path)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    import redis

    client = redis.Redis(port=port)
    for _ in range(100):
        try:
            client.ping()
            break
        except redis.ConnectionError:
            time.sleep(0.05)
    yield f"redis://127.0.0.1:{port}/0"
    proc.terminate()
    proc.wait(10)


@pytest.mark.parametrize("rate", [16000, 48000])  # 48 kHz: the worker's resampler is handed over too
def test_a_session_resumes_on_another_worker_after_sigterm_and_goes_on_exactly(tmp_path, checkpoint, redis_url, rate):
    wav = tmp_path / "speech.wav"
    _wav(wav, 8.0, rate)
    store = ("--state-store", redis_url, "--window-ms", "100")
    with live_server(tmp_path, "ws", checkpoint, extra=store) as a, live_server(tmp_path, "ws", checkpoint,
                                                                              extra=store) as b:
        moved = tmp_path / "moved"
        err = _interrupted_client(a, b, wav, moved, signal.SIGTERM, 40)
        assert a.proc.wait(20) == 0, a.log_tail()
        assert "resumed from sample" in err, err
        whole = tmp_path / "whole"
        run_client("--url", b.ws_url, "--wav", str(wav), "--save", str(whole), "--quiet", "--fast")
    msgs, frames = _frames(moved)
    goaway = [m for m in msgs if m["type"] == "goaway"]
    resumed = [m for m in msgs if m["type"] == "error"]
    assert len(goaway) == 1 and not resumed, msgs[-5:]
    assert 0 < goaway[0]["frames"] < len(frames) and goaway[0]["samples"] > 0
    assert [f["index"] for f in frames] == list(range(len(frames)))  # none lost, none twice
    assert msgs[-1] == {"type": "end", "frames": len(frames)}
    _, reference = _frames(whole)
    assert len(reference) == len(frames) == 8 * 20
    rot = np.array([f["rotations"] for f in frames])
    ref = np.array([f["rotations"] for f in reference])
    assert np.abs(rot - ref).max() < 1e-3  # the streaming = offline tolerance, after the resume too
    root = np.array([f["root"] for f in frames])
    assert np.abs(root - np.array([f["root"] for f in reference])).max() < 1e-2


def test_an_unknown_token_gets_resume_failed_and_the_connection_goes_on(tmp_path, checkpoint):
    import asyncio
    import json

    from websockets.asyncio.client import connect

    async def talk(url):
        async with connect(url) as ws:
            assert json.loads(await ws.recv())["type"] == "hello"
            await ws.send(json.dumps({"type": "resume_session", "token": "no-such-token"}))
            reply = json.loads(await ws.recv())
            await ws.send(json.dumps({"type": "ping", "t": 1}))
            while (pong := json.loads(await ws.recv()))["type"] != "pong":
                pass
            return reply, pong

    with live_server(tmp_path, "ws", checkpoint, extra=("--state-store", "memory")) as server:
        reply, pong = asyncio.run(talk(server.ws_url))
    assert reply["type"] == "error" and reply["code"] == "resume_failed" and "unknown or expired" in reply["message"]
    assert pong["t"] == 1  # the same connection still serves


def test_a_stopping_worker_refuses_new_handshakes_with_503_and_leaves_tokens_for_another(bundle):
    """While it drains, a worker answers a new WebSocket handshake with 503 (nginx passes it on to another worker)
    and a resume_session on a connection it still holds with `busy`, without taking the token."""
    import asyncio
    import json

    from websockets.asyncio.client import connect
    from websockets.exceptions import InvalidStatus

    from helpers.ws import make_server, recv_json, running

    store = MemoryStore()
    store.put("saved-elsewhere", b"a session's state")

    async def talk(url, server):
        async with connect(url) as ws:
            assert (await recv_json(ws))["type"] == "hello"
            server.closing = server.metrics.readiness.draining = True  # as close() sets them on SIGTERM
            try:
                with pytest.raises(InvalidStatus) as refused:
                    async with connect(url):
                        pass
                await ws.send(json.dumps({"type": "resume_session", "token": "saved-elsewhere"}))
                return refused.value.response, await recv_json(ws)
            finally:
                server.closing = server.metrics.readiness.draining = False

    with running(make_server(bundle, store=store)) as server:
        response, reply = asyncio.run(talk(f"ws://127.0.0.1:{server.port}/", server))
    assert response.status_code == 503 and b"draining" in response.body
    assert reply["type"] == "error" and reply["code"] == "busy" and "token stays valid" in reply["message"]
    assert store.take("saved-elsewhere") == b"a session's state"


def test_audio_decoded_while_the_worker_starts_to_stop_does_not_start_a_new_session(bundle):
    """A race seen under load (benchmarks/cluster_load.py): an audio message whose decoding began before SIGTERM
    and ended after the hand-over had detached the session started a fresh one, and that empty session was what
    got saved (goaway with samples 0, frames 0): the client then sent its whole file again. It is ignored now,
    like any audio that comes while the session is saved, and the goaway covers what the session had."""
    import asyncio
    import json

    import numpy as np
    from websockets.asyncio.client import connect

    from helpers.ws import SlowExecutor, make_server, recv_json

    async def scenario():
        server = make_server(bundle, store=MemoryStore())
        server.prep = SlowExecutor(1, delay_s=0.3)  # decoding (and every other prep job) takes 0.3 s
        await server.open()
        try:
            async with connect(f"ws://127.0.0.1:{server.port}/") as ws:
                assert (await recv_json(ws))["type"] == "hello"
                await ws.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "json",
                                          "audio": {"rate": 16000, "format": "float32", "channels": 1}}))
                speech = (0.1 * np.sin(np.arange(16000) * 0.05)).astype("<f4")
                await ws.send(speech.tobytes())
                while (await recv_json(ws))["type"] != "frame":  # the session runs
                    pass
                await ws.send(speech[:3200].tobytes())  # decoded from now until 0.3 s later ...
                await asyncio.sleep(0.1)
                closing = asyncio.create_task(server.close())  # ... while the worker starts to stop
                while (msg := await recv_json(ws))["type"] != "goaway":
                    pass
                await closing
                await asyncio.sleep(0.5)  # (the message decoded meanwhile has been handled by now)
                return msg, server.metrics.sessions_started._value.get()
        finally:
            server.prep.shutdown(wait=False)

    goaway, started = asyncio.run(scenario())
    assert goaway["samples"] == 16000 and goaway["frames"] > 0, goaway
    assert started == 1  # no second session began on the stopping worker


def test_after_sigkill_a_session_resumes_from_its_last_periodic_save_exactly(tmp_path, checkpoint, redis_url):
    """Issue 22 item 4 with --save-state-every: the worker is killed (no goaway, no close frame); the client
    reconnects to another worker and resumes from the last `session_saved`, and the motion it ends with is the
    uninterrupted run's (the frames after the save come twice, equal; --bvh keeps one per index)."""
    from dimgestor.bvh import forward_kinematics, read_bvh

    wav = tmp_path / "speech.wav"
    _wav(wav, 8.0)
    store = ("--state-store", redis_url, "--save-state-every", "1", "--window-ms", "100")
    with live_server(tmp_path, "ws", checkpoint, extra=store) as a, live_server(tmp_path, "ws", checkpoint,
                                                                              extra=store) as b:
        moved, bvh = tmp_path / "moved", tmp_path / "moved.bvh"
        err = _interrupted_client(a, b, wav, moved, signal.SIGKILL, 70, "--bvh", str(bvh))  # after a few saves
        whole = tmp_path / "whole.bvh"
        run_client("--url", b.ws_url, "--wav", str(wav), "--bvh", str(whole), "--quiet", "--fast")
    assert "resuming from the last saved state" in err and "resumed from sample" in err, err
    msgs, frames = _frames(moved)
    saved = [m for m in msgs if m["type"] == "session_saved"]
    gaps = np.diff([0] + [s["samples"] for s in saved])
    assert saved and (gaps >= 16000).all() and (gaps < 16000 + 3200).all(), gaps  # each 1 s of audio (+ a window)
    assert all(0 < s["frames"] * 800 <= s["samples"] for s in saved), saved  # (frames lag by the lookahead)
    indices = [f["index"] for f in frames]
    assert sorted(set(indices)) == list(range(8 * 20))  # every frame, some twice (after the last save)
    assert msgs[-1] == {"type": "end", "frames": 8 * 20}
    got, want = read_bvh(bvh), read_bvh(whole)
    assert got.num_frames == want.num_frames == 8 * 20
    assert np.abs(forward_kinematics(got) - forward_kinematics(want)).max() < 1e-3  # cm (bit-exact here)


def _with_nan_in_the_denoiser(data: bytes) -> bytes:
    """A saved state with one NaN written into its denoiser's SSM state (well-formed, bad values)."""
    import json
    import struct

    _, _, n = struct.unpack_from("<7sHI", data)
    leaf = json.loads(data[13:13 + n])["state"]["f"]["denoiser"]["f"]["ssm"]
    b = bytearray(data)
    b[13 + n + leaf["at"]:13 + n + leaf["at"] + 4] = np.float32(np.nan).tobytes()
    return bytes(b)


def _patched(data: bytes, change) -> bytes:
    import json
    import struct

    _, _, n = struct.unpack_from("<7sHI", data)
    header = json.loads(data[13:13 + n])
    change(header)
    text = json.dumps(header).encode()
    return data[:9] + struct.pack("<I", len(text)) + text + data[13 + n:]


async def _resume_then_talk(ws, token: str, seconds: float = 1.0):
    """resume_session with `token`, then (whatever the answer) `seconds` of our audio and audio_end: -> (the answer,
    every message after it up to `end`)."""
    import json

    from helpers.ws import recv_json

    await ws.send(json.dumps({"type": "resume_session", "token": token}))
    reply = await recv_json(ws)
    speech = (0.1 * np.sin(np.arange(int(16000 * seconds)) * 0.05)).astype("<f4")
    await ws.send(speech.tobytes())
    await ws.send(json.dumps({"type": "audio_end"}))
    msgs = []
    while (msg := await recv_json(ws, timeout=30))["type"] != "end":
        msgs.append(msg)
    return reply, msgs + [msg]


def test_a_resume_that_fails_validation_gets_resume_failed_and_the_stream_goes_on_from_its_own_audio(bundle):
    """Issue 40 items 4 and 5: a stored state of another model, cut short, or well-formed with bad values gets
    `resume_failed` with the reason, and nothing else (no stray `end`): the client's own audio then starts a fresh
    stream at frame 0 on the same connection, in the seat the failed resume freed (one seat here)."""
    import asyncio
    import json

    from websockets.asyncio.client import connect

    from dimgestor import savestate
    from dimgestor.stream import GestureStream
    from helpers.stream import noise_audio, random_tiny_model
    from helpers.ws import make_server, recv_json, running
    from streamer.sessions import Session

    session = Session.from_bundle(bundle, steps=2, seed=3, window_ms=100)  # as make_server's sessions
    frames = session.infer(noise_audio(1.0))
    good = session.snapshot(len(frames), rate=16000, encoding="json")
    bad = {
        "another model": savestate.dumps(GestureStream(random_tiny_model(), steps=2)),
        "cut short": good[:-100],
        r"state\.denoiser\.ssm holds 1 values that are NaN": _with_nan_in_the_denoiser(good),
        r"state\.samples_in is -1000000000000": _patched(good, lambda h: h["state"]["f"]["samples_in"].update(
            v=-10 ** 12)),
        r"meta\.decoder is not an object": _patched(good, lambda h: h["meta"].pop("decoder")),
        r"state\.frontend\.tail at byte 'x'": _patched(good, lambda h: h["state"]["f"]["frontend"]["f"]["tail"].update(
            at="x")),
    }
    store = MemoryStore()

    async def talk(url):
        async with connect(url) as ws:
            assert (await recv_json(ws))["type"] == "hello"
            await ws.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "json",
                                      "audio": {"rate": 16000, "format": "float32", "channels": 1}}))
            out = []
            for i, (reason, data) in enumerate(bad.items()):
                store.put(f"token-{i}", data)
                out.append((reason, *await _resume_then_talk(ws, f"token-{i}")))
            return out

    with running(make_server(bundle, store=store, max_sessions=1)) as server:
        results = asyncio.run(talk(f"ws://127.0.0.1:{server.port}/"))
        resumed = server.metrics.sessions_resumed._value.get()
    for reason, reply, msgs in results:
        assert reply["type"] == "error" and reply["code"] == "resume_failed", (reason, reply)
        assert re.search(reason, reply["message"]) and "\n" not in reply["message"], (reason, reply)
        frames = [m for m in msgs if m["type"] == "frame"]
        assert [m["type"] for m in msgs if m["type"] != "frame"] == ["end"], (reason, msgs)  # no stray `end`
        assert [f["index"] for f in frames] == list(range(20)) and msgs[-1] == {"type": "end", "frames": 20}
    assert resumed == 0


def test_a_bad_state_in_redis_gets_resume_failed_with_the_reason_and_no_traceback(tmp_path, checkpoint, redis_url):
    """A state written bad into a real redis-server (NaN in a session's saved denoiser state): the worker answers
    `resume_failed` naming the field, serves the client's own audio afresh, and logs no traceback."""
    import asyncio
    import json

    from websockets.asyncio.client import connect

    from helpers.ws import recv_json

    store = open_store(redis_url)
    speech = (0.1 * np.sin(np.arange(16000 * 3) * 0.05)).astype("<f4")
    hello = json.dumps({"type": "hello", "protocol": 1, "encoding": "json",
                        "audio": {"rate": 16000, "format": "float32", "channels": 1}})

    async def talk(url):
        async with connect(url) as ws:  # a session saved every second, then the connection lost
            assert (await recv_json(ws))["type"] == "hello"
            await ws.send(hello)
            await ws.send(speech.tobytes())
            while (saved := await recv_json(ws, timeout=30))["type"] != "session_saved":
                pass
        await asyncio.sleep(0.5)
        store.put(saved["resume_token"], _with_nan_in_the_denoiser(store.take(saved["resume_token"])))
        async with connect(url) as ws:
            assert (await recv_json(ws))["type"] == "hello"
            await ws.send(hello)
            return await _resume_then_talk(ws, saved["resume_token"])

    extra = ("--state-store", redis_url, "--save-state-every", "1", "--window-ms", "100")
    with live_server(tmp_path, "ws", checkpoint, extra=extra) as server:
        reply, msgs = asyncio.run(talk(server.ws_url))
        log = server.log.read_text(errors="replace")
    assert reply["type"] == "error" and reply["code"] == "resume_failed", reply
    assert "state.denoiser.ssm holds 1 values that are NaN" in reply["message"], reply
    assert [m["index"] for m in msgs if m["type"] == "frame"] == list(range(20)) and msgs[-1]["frames"] == 20
    assert "a saved session state was refused (saved stream state: state.denoiser.ssm" in log, log[-3000:]
    assert "Traceback" not in log and "internal" not in log, log[-3000:]


def test_the_python_client_finishes_its_file_when_the_resume_after_a_goaway_fails(tmp_path, checkpoint,
                                                                                   tiny_checkpoint, redis_url):
    """Issue 40 item 4, a rolling upgrade: the worker that stops hands the session over, but the one the client
    resumes on runs other weights, so the saved state is refused (`resume_failed`). The client goes on with a
    fresh stream from the frame it lacks and ends with every frame of its file (it exited at 109 of 599)."""
    from dimgestor.bvh import read_bvh

    wav = tmp_path / "speech.wav"
    _wav(wav, 8.0)
    store = ("--state-store", redis_url, "--window-ms", "100")
    with live_server(tmp_path, "ws", checkpoint, extra=store) as a, live_server(tmp_path, "ws", tiny_checkpoint,
                                                                              extra=store) as b:
        moved, bvh = tmp_path / "moved", tmp_path / "moved.bvh"
        err = _interrupted_client(a, b, wav, moved, signal.SIGTERM, 40, "--bvh", str(bvh))
        assert a.proc.wait(20) == 0, a.log_tail()
        log = b.log.read_text(errors="replace")
    assert "resume failed (resume_failed: saved stream state is of another model" in err, err
    msgs, frames = _frames(moved)
    goaway = [m for m in msgs if m["type"] == "goaway"]
    assert len(goaway) == 1 and 0 < goaway[0]["frames"] < 8 * 20
    ends = [m for m in msgs if m["type"] == "end"]
    assert ends == [{"type": "end", "frames": 8 * 20 - goaway[0]["frames"]}], ends  # the fresh stream's, no other
    fresh = [f["index"] for f in frames[goaway[0]["frames"]:]]
    assert fresh == list(range(8 * 20 - goaway[0]["frames"]))  # a new stream: its frames start over at 0
    assert read_bvh(bvh).num_frames == 8 * 20  # the whole file's motion, the fresh stream's after the first's
    assert "Traceback" not in log, log[-3000:]


def test_the_python_client_finishes_its_file_on_an_earlier_worker_that_sends_a_stray_end(tmp_path, checkpoint, bundle,
                                                                                        redis_url, monkeypatch):
    """During a rolling upgrade a client may resume on a worker of the release before, which answered a refused
    resume with `resume_failed` and then a stray `end {"frames": 0}`: the Python client takes no `end` before its
    own audio_end, and finishes its file all the same."""
    from types import SimpleNamespace

    from dimgestor.bvh import read_bvh
    from helpers.ws import make_server, running
    from streamer import client_session as S

    def earlier(self, e):  # the release before: the session started for the refused state flushed, with its `end`
        return [*self._end_audio(), *self._on_Failed(S.Failed(P.ProtocolError("resume_failed", e.message)))]
    monkeypatch.setattr(S.ClientSession, "_on_NotRestored", earlier)

    wav = tmp_path / "speech.wav"
    _wav(wav, 8.0)
    store = ("--state-store", redis_url, "--window-ms", "100")
    with live_server(tmp_path, "ws", checkpoint, extra=store) as a, running(make_server(  # (other weights)
            bundle, store=open_store(redis_url))) as old:
        moved, bvh = tmp_path / "moved", tmp_path / "moved.bvh"
        err = _interrupted_client(a, SimpleNamespace(ws_url=f"ws://127.0.0.1:{old.port}/"), wav, moved,
                                  signal.SIGTERM, 40, "--bvh", str(bvh))
    assert "resume failed (resume_failed: saved stream state is of another model" in err, err
    msgs, _ = _frames(moved)
    assert [m for m in msgs if m["type"] == "end"][0] == {"type": "end", "frames": 0}  # the stray one came ...
    assert read_bvh(bvh).num_frames == 8 * 20  # ... and the client went on to the end of its file
