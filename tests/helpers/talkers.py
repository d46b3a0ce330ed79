"""Clients that talk in real time, for the tests and benchmarks of a worker under load or faults: each one's frame
arrival times, its largest gap and its latency."""

from __future__ import annotations

import asyncio
import bisect
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
    """One client talking in real time: `seconds` of speech (`seed`) in `chunk_s` messages, each sent when its audio
    starts (paced from the first), until all is sent or `stop` is set; then, with `finish`, `audio_end` and what the
    server says until its `end` (or a `goaway`), without it the connection closed. Frames come in binary (`binary`)
    or JSON. Kept: when each frame came (by index), every other message, and each frame's latency: its arrival
    after the audio it needs (its end plus the hello's lookahead) had been sent.

    The one talker of the tests and benchmarks (store faults, intake fairness, abusive clients)."""

    def __init__(self, url: str, seconds: float, seed: int = 5, chunk_s: float = 0.1, binary: bool = True,
                 finish: bool = True, face: str | None = None):
        self.url, self.pcm, self.chunk_s, self.binary, self.finish = url, speech(seconds, seed), chunk_s, binary, finish
        self.face = face  # the face's name set its hello asks for (None: it asks nothing)
        self.stop = asyncio.Event()
        self.t0: float | None = None  # when its first audio was sent
        self.sent: list[tuple[float, float]] = []  # (audio seconds sent so far, when)
        self._sent_s: list[float] = []  # (the first column, to search)
        self.arrivals: dict[int, float] = {}
        self.frames = 0  # frames received (a repeated index counts again)
        self.latency: list[tuple[float, float, float]] = []  # (when its audio had been sent, arrival, seconds)
        self.messages: list[tuple[float, dict]] = []  # (arrival, JSON message) other than frames
        self.fps, self.lookahead_s = FPS, 0.0

    async def run(self) -> None:
        from websockets.asyncio.client import connect

        async with connect(self.url, max_size=None) as c:
            hello = json.loads(await asyncio.wait_for(c.recv(), 30))
            assert hello["type"] == "hello", hello
            self.fps, self.lookahead_s = hello["fps"], hello["lookahead_s"]
            if self.binary or self.face is not None:
                await c.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "binary" if self.binary else "json",
                                         **({"face": self.face} if self.face is not None else {})}))
            sender = asyncio.create_task(self._send(c))
            try:
                async for m in c:
                    now = time.monotonic()
                    if isinstance(m, bytes):
                        self._frame(P.parse_frame_binary(m)["index"], now)
                        continue
                    msg = json.loads(m)
                    if msg["type"] == "frame":
                        self._frame(msg["index"], now)
                        continue
                    self.messages.append((now, msg))
                    if msg["type"] in ("end", "goaway"):
                        break
            finally:
                sender.cancel()

    async def _send(self, c) -> None:
        step = round(16000 * self.chunk_s) * 2  # bytes of PCM16
        self.t0 = time.monotonic()
        for k, i in enumerate(range(0, len(self.pcm), step)):
            await asyncio.sleep(max(0.0, self.t0 + k * self.chunk_s - time.monotonic()))
            if self.stop.is_set():
                break
            await c.send(self.pcm[i : i + step])
            self.sent.append((min(i + step, len(self.pcm)) / 32000, time.monotonic()))
            self._sent_s.append(self.sent[-1][0])
        if self.finish:
            await c.send(json.dumps({"type": "audio_end"}))
        else:
            await c.close()

    def _frame(self, index: int, now: float) -> None:
        self.frames += 1
        self.arrivals.setdefault(index, now)
        need = (index + 1) / self.fps + self.lookahead_s - 1e-6
        k = bisect.bisect_left(self._sent_s, need)
        if k < len(self.sent):
            done = self.sent[k][1]
            self.latency.append((done, now, now - done))

    def of(self, kind: str) -> list[tuple[float, dict]]:
        return [(t, m) for t, m in self.messages if m["type"] == kind]

    @property
    def errors(self) -> list[dict]:
        return [m for _, m in self.of("error")]

    @property
    def end(self) -> dict | None:
        return self.of("end")[-1][1] if self.of("end") else None

    @property
    def sent_s(self) -> float:
        return self.sent[-1][0] if self.sent else 0.0

    def stats(self, q: float = 95) -> tuple[float, float]:
        """(largest gap between two frames' arrivals, the q-th percentile of the latency)."""
        t = np.array([self.arrivals[i] for i in sorted(self.arrivals)])
        return float(np.diff(t).max()), float(np.percentile([v for _, _, v in self.latency], q))

    def percentile(self, t0: float, t1: float, q: float = 95) -> float:
        """Of the frames whose audio was sent between t0 and t1 (however late they came); inf for under 10."""
        lat = [v for sent, _, v in self.latency if t0 <= sent <= t1]
        return float(np.percentile(lat, q)) if len(lat) >= 10 else float("inf")

    def median(self, t0: float, t1: float) -> float:
        """Of the frames that came between t0 and t1; inf for 10 or fewer."""
        lat = [v for _, at, v in self.latency if t0 <= at <= t1]
        return float(np.median(lat)) if len(lat) > 10 else float("inf")


async def talk_together(talkers: list[Talker], during=None):
    """Every talker at once (and `during()` beside them, if given) -> what `during` returned."""
    tasks = [asyncio.create_task(t.run()) for t in talkers]
    side = await during() if during is not None else None
    await asyncio.gather(*tasks)
    return side
