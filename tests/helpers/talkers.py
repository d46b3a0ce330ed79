"""Clients that talk in real time, for the tests and benchmarks of a worker under store faults: each one's frame
arrival times, its largest gap and its latency percentile."""

from __future__ import annotations

import asyncio
import json
import time
import urllib.error
import urllib.request

import numpy as np

from streamer import protocol as P

FPS = 20.0


def speech(seconds: float, seed: int) -> bytes:
    from dimgestor.training.synthetic import synthetic_speech

    return (np.clip(synthetic_speech(seconds, rate=16000, seed=seed), -1, 1) * 20000).astype("<i2").tobytes()


def readyz(http: str) -> tuple[int, str]:
    try:
        with urllib.request.urlopen(http + "readyz", timeout=5) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


class Talker:
    """One client talking in real time: its frames' arrival times (by index) and its messages."""

    def __init__(self, url: str, seconds: float, seed: int):
        self.url, self.pcm = url, speech(seconds, seed)
        self.t0: float | None = None  # when its first audio was sent
        self.arrivals: dict[int, float] = {}
        self.messages: list[tuple[float, dict]] = []  # (arrival, JSON message) other than frames

    async def run(self, stop_after_s: float | None = None) -> None:
        from websockets.asyncio.client import connect

        async with connect(self.url, max_size=2**24) as c:
            assert json.loads(await asyncio.wait_for(c.recv(), 30))["type"] == "hello"
            await c.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "binary"}))

            async def send():
                self.t0 = time.monotonic()
                for k, i in enumerate(range(0, len(self.pcm), 3200)):  # 0.1 s messages, each on time
                    await asyncio.sleep(max(0.0, self.t0 + k * 0.1 - time.monotonic()))
                    await c.send(self.pcm[i : i + 3200])
                await c.send(json.dumps({"type": "audio_end"}))

            sender = asyncio.create_task(send())
            try:
                async for m in c:
                    now = time.monotonic()
                    if isinstance(m, bytes):
                        self.arrivals.setdefault(P.parse_frame_binary(m)["index"], now)
                        continue
                    msg = json.loads(m)
                    self.messages.append((now, msg))
                    if msg["type"] in ("end", "goaway"):
                        break
            finally:
                sender.cancel()

    def of(self, kind: str) -> list[tuple[float, dict]]:
        return [(t, m) for t, m in self.messages if m["type"] == kind]

    def stats(self, q: float = 95) -> tuple[float, float]:
        """(largest gap between two frames' arrivals, the q-th percentile of the latency: a frame's arrival after
        its audio was sent)."""
        index = sorted(self.arrivals)
        t = np.array([self.arrivals[i] for i in index])
        latency = t - (self.t0 + (np.array(index) + 1) / FPS)
        return float(np.diff(t).max()), float(np.percentile(latency, q))


async def talk_together(talkers: list[Talker], during=None):
    """Every talker at once (and `during()` beside them, if given) -> what `during` returned."""
    tasks = [asyncio.create_task(t.run()) for t in talkers]
    side = await during() if during is not None else None
    await asyncio.gather(*tasks)
    return side
