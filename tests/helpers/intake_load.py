"""A real-time talker beside fast senders at a high rate (192 kHz stereo float32), against a live `dimgestor serve`:
tests/test_streamer_intake.py and benchmarks/intake_fairness.py.

The talker sends 16 kHz PCM16 speech paced in real time; the latency of its frame i is its arrival minus the
moment the audio it needs (frame i's end plus the lookahead) had been sent. The flooders run in a process of
their own (their client-side work is not the talker's), each sending 1 MiB messages as fast as the socket takes
them and ignoring `slow_down`; they count the `slow_down` and `resume` they are told (once it stops, a flooder
that was told `slow_down` waits for its `resume`).
"""

from __future__ import annotations

import asyncio
import json
import multiprocessing
import time

import numpy as np
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from helpers.talkers import Talker

FLOOD_FORMAT = {"rate": 192000, "format": "float32", "channels": 2}
CHUNK_S = 0.05  # the talker's audio per message
RESUME_WAIT_S = 8.0  # how long a flooder told slow_down waits for `resume` once it stopped (what the server
#                     holds of it unread, ~10 messages, is read at its share first)


class PacedHighRate:
    """192 kHz stereo float32 paced in real time in CHUNK_S messages (what a studio interface sends): its intake
    costs ~100x the talker's, well within its share; counts the errors it is told and the frames it gets."""

    def __init__(self):
        self.errors: list[str] = []
        self.frames = 0

    async def run(self, url: str, stop: asyncio.Event) -> None:
        n = int(FLOOD_FORMAT["rate"] * CHUNK_S)
        t = np.arange(n) / FLOOD_FORMAT["rate"]
        chunk = np.repeat((0.3 * np.sin(2 * np.pi * 180 * t)).astype("<f4"), 2).tobytes()
        async with connect(url, max_size=None) as c:
            await c.send(json.dumps({"type": "hello", "audio": FLOOD_FORMAT}))

            async def read():
                async for m in c:
                    d = json.loads(m)
                    self.frames += d["type"] == "frame"
                    if d["type"] == "error":
                        self.errors.append(d["code"])

            reader, t0, k = asyncio.create_task(read()), time.monotonic(), 0
            while not stop.is_set():
                await c.send(chunk)
                k += 1
                await asyncio.sleep(max(0.0, t0 + k * CHUNK_S - time.monotonic()))
            # its frames are read until the close is answered: a client that stopped reading them would hold up
            # the server's close behind its own frames (a busy machine has many on their way: > 10 s once)
            await c.close()
            await asyncio.gather(reader, return_exceptions=True)


async def _flooder(url: str, stop: asyncio.Event, message: bytes, counts, k: int, connected) -> None:
    async with connect(url, max_size=None) as c:
        await c.send(json.dumps({"type": "hello", "audio": FLOOD_FORMAT}))

        resumed = asyncio.Event()

        async def read():
            try:
                async for m in c:
                    if isinstance(m, str):
                        d = json.loads(m)
                        if d["type"] == "error":
                            key = f"{k}:{d['code']}"
                            counts[key] = counts.get(key, 0) + 1
                        elif d["type"] == "resume":
                            counts[f"{k}:resume"] = counts.get(f"{k}:resume", 0) + 1
                            resumed.set()
            except ConnectionClosed:
                pass

        reader = asyncio.create_task(read())
        connected.release()
        counts[f"{k}:sent"] = 0
        while not stop.is_set():
            await c.send(message)
            counts[f"{k}:sent"] += 1
        if counts.get(f"{k}:slow_down"):  # stopped as told: `resume` comes once it is within its share again
            try:
                await asyncio.wait_for(resumed.wait(), RESUME_WAIT_S)
            except asyncio.TimeoutError:
                pass
        reader.cancel()


def flood(url: str, clients: int, seconds: float, started, counts) -> None:
    """`clients` fast 192 kHz stereo float32 senders for `seconds` (in this, a separate, process); `started` (a
    multiprocessing Event) is set once all are connected; `counts` (a managed dict) gets "k:slow_down",
    "k:resume" and "k:sent" (messages) per flooder k."""
    frames = (1 << 20) // 8  # 1 MiB: 131072 stereo float32 frames, 0.68 s at 192 kHz
    t = np.arange(frames) / FLOOD_FORMAT["rate"]
    tone = (0.3 * np.sin(2 * np.pi * 220 * t)).astype("<f4")
    message = np.repeat(tone, 2).tobytes()

    async def run():
        stop, connected = asyncio.Event(), asyncio.Semaphore(0)
        local: dict = {}
        tasks = [asyncio.create_task(_flooder(url, stop, message, local, k, connected)) for k in range(clients)]
        for _ in range(clients):
            await connected.acquire()
        started.set()
        await asyncio.sleep(seconds)
        stop.set()
        await asyncio.wait(tasks, timeout=RESUME_WAIT_S + 2.0)  # one blocked in a send (back pressure) is cut off
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        counts.update(local)

    asyncio.run(run())


async def talker_beside_flood(url: str, clients: int, quiet_s: float = 6.0, flood_s: float = 10.0,
                              settle_s: float = 1.5, paced_high_rate: bool = False) -> dict:
    """One talker: quiet for `quiet_s`, then beside `clients` flooders for `flood_s`, then 2 s more (and until the
    flooders are gone); with `paced_high_rate` a `PacedHighRate` sender throughout. Returns the talker's p95 latency
    quiet and flooded, the flooders' counts, the talker and the paced sender (None without)."""
    talker = Talker(url, quiet_s + flood_s + 60.0, chunk_s=CHUNK_S, binary=False)  # (stopped 2 s after the flood)
    spawn = multiprocessing.get_context("spawn")
    task = asyncio.create_task(talker.run())
    paced, paced_stop = (PacedHighRate() if paced_high_rate else None), asyncio.Event()
    paced_task = asyncio.create_task(paced.run(url, paced_stop)) if paced else None
    t_start = time.monotonic()
    await asyncio.sleep(quiet_s)
    quiet = (t_start + settle_s, time.monotonic())
    counts: dict = {}
    if clients:
        with spawn.Manager() as manager:
            shared, started = manager.dict(), spawn.Event()
            proc = spawn.Process(target=flood, args=(url, clients, flood_s, started, shared), daemon=True)
            proc.start()
            while not started.is_set() and proc.is_alive():
                await asyncio.sleep(0.05)
            t_flood = time.monotonic()
            while proc.is_alive():
                await asyncio.sleep(0.1)
            flooded = (t_flood + 1.0, t_flood + flood_s)
            counts = dict(shared)
    else:
        await asyncio.sleep(flood_s)
        flooded = (quiet[1] + 1.0, time.monotonic())
    await asyncio.sleep(max(0.0, flooded[1] + 2.0 - time.monotonic()))
    talker.stop.set()
    await task
    if paced_task is not None:
        paced_stop.set()
        await asyncio.wait_for(paced_task, 10)
    return {"quiet_p95_s": talker.percentile(*quiet), "flooded_p95_s": talker.percentile(*flooded),
            "counts": counts, "talker": talker, "paced": paced, "quiet": quiet, "flooded": flooded}
