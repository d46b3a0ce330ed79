"""One client cannot hurt another: `streamer serve` under abusive clients, watched by two bystanders.

One server (a subprocess, a tiny model, a looping WAV broadcast in real time) runs through a quiet
phase and then one phase per abusive pattern. Throughout, a watcher follows the broadcast (its largest
gap between frames is measured) and a talker streams its own audio in real time (the latency of each
of its frames: arrival minus the moment its audio was complete; the median per phase).
"""

import asyncio
import json
import multiprocessing
import time

import numpy as np
import pytest
from websockets.asyncio.client import connect

from dimgestor.synthetic import synthetic_speech
from streamer_abusers import PATTERNS, abuse
from helpers.serve import serve

pytestmark = pytest.mark.timeout(150)
PHASE_S = 3.0
CHUNK_S = 0.05


class Watcher:
    def __init__(self):
        self.arrivals: list[float] = []

    async def run(self, url, stop):
        async with connect(url) as c:
            while not stop.is_set():
                try:
                    m = await asyncio.wait_for(c.recv(), 0.5)
                except asyncio.TimeoutError:
                    continue
                if json.loads(m)["type"] == "frame":
                    self.arrivals.append(time.monotonic())

    def max_gap(self, t0, t1):
        t = [a for a in self.arrivals if t0 <= a <= t1]
        return max(np.diff([t0, *t, t1]))


class Talker:
    """Sends speech in real time in 100 ms chunks; latency of frame i = its arrival - when its audio was complete."""

    def __init__(self, seconds):
        self.audio = (synthetic_speech(seconds, seed=5) * 20000).astype("<i2")
        self.sent: list[tuple[float, float]] = []  # (audio seconds sent so far, time)
        self.latency: list[tuple[float, float]] = []  # (arrival, seconds)
        self.errors: list[dict] = []

    async def run(self, url, stop):
        async with connect(url) as c:
            hello = json.loads(await c.recv())
            need = lambda i: (i + 1) / hello["fps"] + hello["lookahead_s"]  # noqa: E731

            async def read():
                async for m in c:
                    d = json.loads(m)
                    if d["type"] == "error":
                        self.errors.append(d)
                    if d["type"] == "frame":
                        now = time.monotonic()
                        done = next((t for a, t in self.sent if a >= need(d["index"]) - 1e-6), None)
                        if done is not None:
                            self.latency.append((now, now - done))

            reader = asyncio.create_task(read())
            step, t0 = int(16000 * CHUNK_S), time.monotonic()
            for k, i in enumerate(range(0, len(self.audio), step)):
                if stop.is_set():
                    break
                await c.send(self.audio[i : i + step].tobytes())
                self.sent.append(((i + step) / 16000, time.monotonic()))
                await asyncio.sleep(max(0.0, t0 + (k + 1) * CHUNK_S - time.monotonic()))
            reader.cancel()

    def median(self, t0, t1):
        lat = [v for t, v in self.latency if t0 <= t <= t1]
        return float(np.median(lat)) if len(lat) > 10 else float("inf")


def test_abusive_clients_do_not_hurt_bystanders(tiny_checkpoint, wav):
    s = serve(tiny_checkpoint, "--source", str(wav), "--loop", "--status-every", "0")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    spawn = multiprocessing.get_context("spawn")

    async def run():
        stop = asyncio.Event()
        watcher, talker = Watcher(), Talker(120.0)  # longer than the test; stopped at its end
        bystanders = [asyncio.create_task(watcher.run(url, stop)), asyncio.create_task(talker.run(url, stop))]
        await asyncio.sleep(1.0)  # settle
        phases = {}
        t = time.monotonic()
        await asyncio.sleep(PHASE_S)
        phases["quiet"] = (t + 0.5, time.monotonic())
        for name in PATTERNS:
            started = spawn.Event()
            abuser = spawn.Process(target=abuse, args=(name, url, PHASE_S, started), daemon=True)
            abuser.start()
            while not started.is_set():  # connected and abusing
                await asyncio.sleep(0.05)
            await asyncio.sleep(0.5)
            t = time.monotonic()
            await asyncio.sleep(PHASE_S - 0.5)
            phases[name] = (t, time.monotonic())
            while abuser.is_alive():
                await asyncio.sleep(0.1)
        stop.set()
        await asyncio.gather(*bystanders, return_exceptions=True)
        return watcher, talker, phases

    watcher, talker, phases = asyncio.run(run())
    s.proc.terminate()
    assert s.finish(10) == 0, s.output
    quiet = talker.median(*phases["quiet"])
    report = {name: (round(watcher.max_gap(*span), 3), round(talker.median(*span), 3)) for name, span in phases.items()}
    print("max watcher gap s, median talker latency s:", report, "\nserver output:\n" + s.output)
    # 2x the quiet latency, plus 25 ms for what a shared 2-core machine's scheduler adds to a ~60 ms median
    # on its own (seen: 124 ms against 2 x 58 ms under a load average of 8, with no abuser effect elsewhere)
    allowed = 2 * quiet + 0.025
    for name in PATTERNS:
        gap, latency = report[name]
        assert gap < 0.5, f"{name}: the watcher waited {gap:.3f} s for a frame ({report})"
        assert latency <= allowed, f"{name}: talker latency {latency:.3f} s vs {quiet:.3f} s quiet ({report})"
    assert not talker.errors, talker.errors[:3]
    assert "Traceback" not in s.output and len(s.output.splitlines()) < 20, s.output[-3000:]  # no log floods
