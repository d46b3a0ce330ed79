"""The WebSocket server over loopback with real `websockets` clients and a real (tiny) model."""

import asyncio
import json
import socket
import time

import numpy as np
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from dimgestor.training.synthetic import synthetic_speech
from streamer import protocol as P
from streamer.frames import Frame
from helpers.stalls import LoopStalls
from helpers.ws import make_server, recv_json

pytestmark = pytest.mark.timeout(120)


def test_garbage_gets_an_error_and_the_connection_keeps_being_served(bundle):
    async def run():
        ws = make_server(bundle)
        await ws.open()
        async with connect(ws.url) as c:
            assert (await recv_json(c))["type"] == "hello"
            for bad, code in [("{oops", "bad_message"), ('{"type": "jump"}', "bad_message"),
                              (b"\x01", "bad_audio"), ('{"type": "hello", "protocol": 1, "audio": {"rate": 5}}', "bad_audio")]:
                await c.send(bad)
                err = await recv_json(c)
                assert err["type"] == "error" and err["code"] == code and err["message"]
            await c.send(json.dumps({"type": "ping", "t": 1.5}))
            pong = await recv_json(c)
            server_time = pong.pop("server_time_s")  # revision 5: the server's monotonic clock when it answered
            assert pong == {"type": "pong", "t": 1.5} and abs(server_time - time.monotonic()) < 5
        await ws.close()

    asyncio.run(run())


def test_wrong_or_missing_token_is_refused_with_401(bundle):
    async def run():
        ws = make_server(bundle, token="s3cret")
        await ws.open()
        for url in (ws.url, ws.url + "?token=wrong"):
            with pytest.raises(InvalidStatus) as e:
                async with connect(url):
                    pass
            assert e.value.response.status_code == 401
        async with connect(ws.url + "?token=s3cret") as c:
            assert (await recv_json(c))["type"] == "hello"
        await ws.close()

    asyncio.run(run())


def test_client_audio_at_48khz_comes_back_as_its_own_gestures(bundle):
    """PCM16 48 kHz stereo in odd-sized chunks -> this client's own frames, as many as the audio lasts."""
    seconds = 3.0
    audio = synthetic_speech(seconds, rate=48000, seed=1)
    pcm = np.round(np.stack([audio, audio], 1) * 32767 * 0.8).astype("<i2").tobytes()

    async def run():
        ws = make_server(bundle)
        await ws.open()
        async with connect(ws.url) as c:
            hello = await recv_json(c)
            await c.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "binary",
                                     "audio": {"rate": 48000, "format": "pcm16", "channels": 2}}))
            step = 4 * 1234  # whole stereo sample frames, not aligned to anything
            for i in range(0, len(pcm), step):
                await c.send(pcm[i : i + step])
            await c.send(json.dumps({"type": "audio_end"}))
            frames, end = [], None
            while end is None:
                m = await asyncio.wait_for(c.recv(), 30)
                if isinstance(m, bytes):
                    frames.append(P.parse_frame_binary(m))
                elif json.loads(m)["type"] == "end":
                    end = json.loads(m)
        await ws.close()
        return hello, frames, end

    hello, frames, end = asyncio.run(run())
    J = len(hello["skeleton"]["joints"])
    assert end["frames"] == len(frames) == int(seconds * 20)
    assert [f["index"] for f in frames] == list(range(len(frames)))
    assert np.allclose([f["pts"] for f in frames], np.arange(len(frames)) / 20)
    rot = np.stack([f["rotations"] for f in frames])
    assert rot.shape == (len(frames), J, 4) and np.allclose(np.linalg.norm(rot, axis=-1), 1, atol=1e-5)
    assert np.ptp(rot, axis=0).max() > 1e-3  # it moves


def test_timing_follows_each_window_of_a_client_that_asks_and_no_other(bundle):
    """Revision 5: hello `timing: true` -> after each window's frames a `timing` message naming those frames, the
    audio they were made from (enough for each frame's lookahead) and when it arrived, was dispatched and its frames
    were sent, in that order on the server's monotonic clock (the pong's `server_time_s`); the flush at
    `audio_end` has none, and a client that did not ask gets none."""
    audio = np.round(synthetic_speech(2.0, rate=16000, seed=4) * 32767 * 0.8).astype("<i2")

    async def talk(c, timing: bool):
        await recv_json(c)
        await c.send(json.dumps({"type": "hello", "protocol": 1, "timing": timing,
                                 "audio": {"rate": 16000, "format": "pcm16", "channels": 1}}))
        for i in range(0, len(audio), 1600):
            await c.send(audio[i : i + 1600].tobytes())
            await asyncio.sleep(0.02)
        await c.send(json.dumps({"type": "audio_end"}))
        await c.send(json.dumps({"type": "ping"}))
        got = []
        while not got or got[-1]["type"] != "end":
            m = json.loads(await asyncio.wait_for(c.recv(), 30))
            if m["type"] in ("frame", "timing", "end"):
                got.append({**m, "at": time.monotonic()})
            elif m["type"] == "pong":
                server_time = m["server_time_s"]
        return got, server_time

    async def run():
        ws = make_server(bundle)
        await ws.open()
        async with connect(ws.url) as asks, connect(ws.url) as other:
            out = await asyncio.gather(talk(asks, True), talk(other, False))
        await ws.close()
        return out

    (got, server_time), (plain, _) = asyncio.run(run())
    assert [m for m in plain if m["type"] == "timing"] == []
    assert abs(server_time - time.monotonic()) < 30  # the same monotonic clock (one machine)
    frames, lookahead = [], 0.1  # make_server's hello
    timings = 0
    for m in got:
        if m["type"] == "frame":
            frames.append(m)
        elif m["type"] == "timing":
            timings += 1
            window = frames[-m["frames"]:]
            assert [f["index"] for f in window] == list(range(m["first"], m["first"] + m["frames"]))
            assert window[-1]["pts"] + lookahead <= m["audio_until_s"] + 1e-6
            assert m["arrived_s"] <= m["dispatched_s"] <= m["sent_s"] <= m["at"]
    assert timings >= 10 and got[-2]["type"] == "frame"  # the flush's frames: no timing after them
    assert sum(m["type"] == "frame" for m in got) == sum(m["type"] == "frame" for m in plain) == 40


def test_a_client_that_never_reads_does_not_delay_another(bundle):
    """A stalled reader loses frames (counted); a reading client gets every frame promptly: within 0.5 s and however
    long this process's event loop (the server's and both clients') stalled meanwhile (CI's other work)."""
    J = 400  # big frames (6.4 KB) so the stalled client's socket buffers fill up quickly
    rng = np.random.default_rng(0)
    rot = rng.normal(size=(J, 4))
    rot /= np.linalg.norm(rot, axis=-1, keepdims=True)
    n_frames, burst = 600, 6

    stalls = LoopStalls(period_s=0.01)

    async def run():
        watch = asyncio.create_task(stalls.watch())
        ws = make_server(bundle, max_queue=32)
        await ws.open()
        # The stalled client: a tiny receive buffer and a library queue of 1, and it never calls recv().
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.connect(("127.0.0.1", ws.port))
        stalled = await connect(ws.url, sock=s, max_queue=1)
        binary = json.dumps({"type": "hello", "encoding": "binary"})  # cheap to encode: the test measures waiting
        await stalled.send(binary)
        async with connect(ws.url) as fast:
            assert (await recv_json(fast))["type"] == "hello"
            await fast.send(binary)
            while len(ws.clients) < 2 or any(c.encoding != "binary" for c in ws.clients):
                await asyncio.sleep(0.01)
            sent_at, delays = {}, []

            async def reader():
                while len(delays) < n_frames:
                    m = await asyncio.wait_for(fast.recv(), 10)
                    if isinstance(m, bytes):
                        delays.append((sent_at[P.parse_frame_binary(m)["index"]], time.monotonic()))

            task = asyncio.create_task(reader())
            for i in range(0, n_frames, burst):  # bursts, as inference windows make them
                frames = [Frame(k, k / 20, np.zeros(3), rot, np.zeros(1)) for k in range(i, i + burst)]
                for f in frames:
                    sent_at[f.index] = time.monotonic()
                ws.send(frames)
                await asyncio.sleep(0.01)
            await asyncio.wait_for(task, 20)
            slow = next(c for c in ws.clients if c.ws.remote_address[1] == s.getsockname()[1])
            fast_c = next(c for c in ws.clients if c is not slow)
            result = delays, slow.dropped, fast_c.dropped
        stalled.transport.abort()  # it cannot do a closing handshake: it never reads
        await ws.close(within_s=0.3)
        watch.cancel()
        return result

    delays, slow_dropped, fast_dropped = asyncio.run(run())
    assert len(delays) == n_frames and fast_dropped == 0
    for sent, got in delays:
        stalled_s = stalls.within(sent, got)
        assert got - sent < 0.5 + stalled_s, f"a frame took {got - sent:.3f} s ({stalled_s:.3f} s stalled)"
    assert slow_dropped > 0, "the stalled client should have lost frames"


def test_status_arrives_about_once_a_second_with_the_documented_fields(bundle):
    async def run():
        ws = make_server(bundle, status_every=0.3)
        await ws.open()
        async with connect(ws.url) as c:
            await c.recv()  # hello
            st = json.loads(await asyncio.wait_for(c.recv(), 5))
        await ws.close()
        return st

    st = asyncio.run(run())
    assert st["type"] == "status" and st["session"] == "broadcast"
    assert {k: type(st[k]) for k in ("latency_ms", "rtf", "frames_sent", "dropped", "clients")} == {
        "latency_ms": float, "rtf": float, "frames_sent": int, "dropped": int, "clients": int}
    assert st["clients"] == 1 and st["dropped"] == 0


def test_other_protocol_versions_and_refused_audio(bundle):
    async def run():
        ws = make_server(bundle, make_session=None)  # as with --no-client-audio
        await ws.open()
        async with connect(ws.url) as c:
            await recv_json(c)
            await c.send(np.zeros(160, "<i2").tobytes())
            assert (await recv_json(c))["code"] == "audio_disabled"
            await c.send(json.dumps({"type": "hello", "protocol": 2}))
            assert (await recv_json(c))["code"] == "unsupported_protocol"
            await asyncio.wait_for(c.wait_closed(), 5)
            code = c.close_code
        await ws.close()
        return code

    assert asyncio.run(run()) == 1002


def test_source_audio_goes_to_the_viewers_that_ask_replayed_to_late_joiners_and_never_to_talkers(bundle):
    """Revision 1: `source_audio: true` in a client's hello -> DGA1 messages of the server source's audio (the
    recent past replayed to a late joiner); nothing to clients that did not ask, and a client that talks gets
    its own frames and no audio at all from then on: never its own voice back."""
    rng = np.random.default_rng(5)
    source = np.clip(0.3 * rng.standard_normal(int(1.6 * P.AUDIO_RATE)), -0.99, 0.99).astype(np.float32)
    chunk = 320  # 20 ms, as a WAV source reads it
    mic = np.round(synthetic_speech(2.0, rate=16000, seed=2) * 32767 * 0.8).astype("<i2")

    async def collect_until_pong(c, talker=False):
        await c.send(json.dumps({"type": "ping", "t": 9}))
        got, own_frames = [], 0
        while True:
            m = await asyncio.wait_for(c.recv(), 30)
            if isinstance(m, bytes) and m[:4] == P.AUDIO_MAGIC:
                got.append((own_frames, P.parse_source_audio_binary(m)))
            elif isinstance(m, bytes) or json.loads(m)["type"] == "frame":
                own_frames += 1
            elif json.loads(m)["type"] == "pong" and (not talker or own_frames):
                return got, own_frames

    async def broadcast(start, stop):
        for i in range(start, stop, chunk):
            ws.broadcast_audio(i / P.AUDIO_RATE, source[i : i + chunk])
            await asyncio.sleep(0.002)

    async def run():
        nonlocal ws
        ws = make_server(bundle, {"source_audio": {"rate": P.AUDIO_RATE, "format": "pcm16", "channels": 1}})
        await ws.open()
        async with connect(ws.url) as early, connect(ws.url) as deaf, connect(ws.url) as talker:
            for c in (early, deaf, talker):
                hello = await recv_json(c)
            await early.send(json.dumps({"type": "hello", "protocol": 1, "source_audio": True, "encoding": "binary"}))
            await deaf.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "binary"}))
            await talker.send(json.dumps({"type": "hello", "protocol": 1, "source_audio": True, "encoding": "binary",
                                          "audio": {"rate": 16000, "format": "pcm16", "channels": 1}}))
            while len(ws.clients) < 3 or sum(c.source_audio for c in ws.clients) < 2:
                await asyncio.sleep(0.01)
            half = 8 * 1600  # 0.8 s, a whole number of DGA1 messages
            await broadcast(0, half)
            await talker.send(mic.tobytes())  # from now on it talks: its own frames, no source audio
            await talker.send(json.dumps({"type": "audio_end"}))
            async with connect(ws.url) as late:
                await recv_json(late)
                await late.send(json.dumps({"type": "hello", "protocol": 1, "source_audio": True}))
                while sum(c.source_audio for c in ws.clients) < 3:
                    await asyncio.sleep(0.01)
                await broadcast(half, len(source))
                ws.broadcast_end(0)
                results = [await collect_until_pong(c) for c in (early, deaf, late)]
            results.append(await collect_until_pong(talker, talker=True))
        await ws.close()
        return hello, results

    ws = None
    hello, (early, deaf, late, talker) = asyncio.run(run())
    assert hello["revision"] >= 1 and hello["source_audio"]["rate"] == P.AUDIO_RATE

    def audio_of(got):
        pts = [a["pts"] for _, a in got]
        samples = np.concatenate([a["samples"] for _, a in got]) if got else np.zeros(0)
        return pts, samples, {a["rate"] for _, a in got}

    for name, got in (("early", early), ("late", late)):
        pts, samples, rates = audio_of(got[0])
        assert rates == {P.AUDIO_RATE}, name
        # Every sample once, in order, each message stamped with the pts of its first sample.
        assert len(samples) == len(source), f"{name}: {len(samples)} of {len(source)} samples"
        np.testing.assert_allclose(samples, source, atol=1.5 / 32767)
        assert np.allclose(pts, np.cumsum([0] + [len(a["samples"]) for _, a in got[0][:-1]]) / P.AUDIO_RATE)
    assert deaf[0] == [], "a client that did not ask got source audio"
    # The talker: nothing after its first own frame, and whatever came before is the source, never its voice.
    got, own_frames = talker
    assert own_frames > 0
    assert all(before == 0 for before, _ in got), "source audio reached a client that talks"
    pts, samples, _ = audio_of(got)
    n = min(len(samples), len(source))
    np.testing.assert_allclose(samples[:n], source[:n], atol=1.5 / 32767)
