"""Abusive WebSocket clients for tests/test_streamer_abuse.py, run in their own process (spawned)."""

import asyncio
import json

import numpy as np
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from dimgestor.training.synthetic import synthetic_speech

PATTERNS = ("odd_rates", "big_chunks", "deep_json", "session_storm", "bad_rigs", "valid_rig")


async def drain(c):
    try:
        async for _ in c:
            pass
    except ConnectionClosed:
        pass


async def odd_rates(url, stop, started):
    """New odd sample rates in a loop, each with a little audio (each needs a new resampler)."""
    async with connect(url) as c:
        reader = asyncio.create_task(drain(c))
        started.set()
        rate = 191999
        while not stop.is_set():
            await c.send(json.dumps({"type": "hello", "audio": {"rate": rate, "format": "pcm16"}}))
            await c.send(np.zeros(rate // 10, "<i2").tobytes())
            rate -= 7
            await asyncio.sleep(0.01)
        reader.cancel()


async def big_chunks(url, stop, started):
    """1 MiB audio messages (33 s of 16 kHz PCM16 each) as fast as the server takes them."""
    audio = (synthetic_speech(32.768, seed=9) * 20000).astype("<i2").tobytes()[: 1 << 20]
    async with connect(url) as c:
        reader = asyncio.create_task(drain(c))
        started.set()
        while not stop.is_set():
            await c.send(audio)
        reader.cancel()


async def deep_json(url, stop, started):
    """A flood of 40 KB deeply nested JSON messages (and long numbers), never reading the replies."""
    deep, long_number = "[" * 40000, '{"type": "ping", "t": ' + "9" * 39000 + "}"
    async with connect(url, max_queue=1) as c:
        started.set()
        while not stop.is_set():
            for m in (deep, long_number) * 10:
                await c.send(m)
            await asyncio.sleep(0)


async def session_storm(url, stop, started):
    """30 clients, each starting a session and ending it with audio_end, over and over."""
    audio = (synthetic_speech(0.5, seed=2) * 20000).astype("<i2").tobytes()

    async def one():
        async with connect(url) as c:
            reader = asyncio.create_task(drain(c))
            while not stop.is_set():
                await c.send(audio)
                await c.send(json.dumps({"type": "audio_end"}))
                await asyncio.sleep(0.05)
            reader.cancel()

    tasks = [asyncio.create_task(one()) for _ in range(30)]
    await asyncio.sleep(0.5)
    started.set()
    await asyncio.gather(*tasks)


def _bad_rigs() -> list[str]:
    """Malformed and huge `hello.rig`s (issue 52): too many joints, cycles, NaN and 1e30 offsets, a 512-deep chain,
    duplicate and very long names, a map naming missing bones, 512 joints no humanoid bone is recognised in."""
    def rig(J, parents=None, offsets=None, names=None, **more):
        return {"joints": names or [f"j{j}" for j in range(J)], "parents": parents or [-1] + [0] * (J - 1),
                "offsets": offsets or [[0.0, 0.1, 0.0]] * J, "units": "m", **more}
    chain = [-1] + list(range(511))
    rigs = [rig(4000), rig(512), rig(512, parents=chain), rig(3, parents=[-1, 2, 1]),
            rig(3, offsets=[[0, 1e30, 0]] * 3), rig(3, names=["a", "a", "b"]), rig(3, names=["x" * 5000] * 3),
            rig(2, map={"hips": "nowhere", "spine": "missing"})]
    text = [json.dumps({"type": "hello", "rig": r}) for r in rigs]
    text.append(text[4].replace("1e+30", "NaN"))
    return text


async def bad_rigs(url, stop, started):
    """4 clients sending malformed or huge rig hellos in a loop, connecting again whenever they are closed."""
    rigs = _bad_rigs()

    async def one(k):
        i = k
        while not stop.is_set():
            try:
                async with connect(url, max_size=None) as c:
                    reader = asyncio.create_task(drain(c))
                    while not stop.is_set():
                        await c.send(rigs[i % len(rigs)])
                        i += 1
                        await asyncio.sleep(0)
                    reader.cancel()
            except (ConnectionClosed, OSError):
                await asyncio.sleep(0.01)

    tasks = [asyncio.create_task(one(k)) for k in range(4)]
    await asyncio.sleep(0.3)
    started.set()
    await asyncio.gather(*tasks)


async def valid_rig(url, stop, started):
    """One client sending a valid rig (the server's own skeleton, recognised) in a loop, reading every reply."""
    async with connect(url) as c:
        hello = json.loads(await c.recv())
        sk = hello["skeleton"]
        text = json.dumps({"type": "hello", "rig": {"joints": sk["joints"], "parents": sk["parents"],
                                                    "offsets": sk["offsets"], "units": sk.get("units", "m")}})
        started.set()
        while not stop.is_set():
            await c.send(text)
            while json.loads(await c.recv())["type"] not in ("rig", "error"):
                pass


def abuse(name: str, url: str, seconds: float, started) -> None:
    """Run one pattern for `seconds` in this (separate) process, so its client-side work is not measured;
    `started` (a multiprocessing Event) is set once it is connected."""

    async def run():
        stop = asyncio.Event()
        task = asyncio.create_task(globals()[name](url, stop, started))
        while not started.is_set():
            await asyncio.sleep(0.01)
        await asyncio.sleep(seconds)
        stop.set()
        await asyncio.wait({task}, timeout=1.0)  # one blocked in a send (back pressure) is cut off
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)

    asyncio.run(run())
