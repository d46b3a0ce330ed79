"""Audio sources: async iterators of timestamped 16 kHz mono chunks (microphone, WAV file, pushed audio).

Every chunk carries `t_start`, its position on the source's audio clock (samples / SAMPLE_RATE), and
`arrival`, the monotonic time its last sample reached the server (what latency is measured from).
Live sources drop the oldest audio when the consumer falls behind, and count it; file and pushed
sources apply back pressure instead, so nothing is lost.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import AsyncIterator

import numpy as np

from dimgestor.audio import SAMPLE_RATE


ASSETS = Path(__file__).resolve().parents[1] / "dimgestor" / "assets"
DEMO_WAV = ASSETS / "demo_en.wav"


class SourceError(RuntimeError):
    """A source cannot start (no device, no PortAudio, unreadable file); the message says why."""


@dataclass(frozen=True)
class AudioChunk:
    samples: np.ndarray  # (n,) float32 mono 16 kHz
    t_start: float       # seconds on the audio clock
    arrival: float       # time.monotonic() when the chunk's last sample arrived

    @property
    def t_end(self) -> float:
        return self.t_start + len(self.samples) / SAMPLE_RATE


MAX_RATIO_DENOMINATOR = 4000  # bounds the resampling filter (its design takes < 0.1 s, < 2 MB)


def make_resampler(rate: int):
    """A stateful rate converter to 16 kHz: `fn(x) -> y` carrying its filter state across calls.

    The rate ratio is exact when it reduces to a fraction with a denominator <= 4000 (every usual
    rate: 8, 11.025, 22.05, 44.1, 48, 96, 192 kHz...); other rates (e.g. 191999 Hz) use the nearest such
    fraction (within 0.013 %) rather than a filter of millions of taps.
    """
    from fractions import Fraction

    from dimgestor.audio import StreamingResampler

    ratio = Fraction(SAMPLE_RATE, int(rate)).limit_denominator(MAX_RATIO_DENOMINATOR)
    return StreamingResampler(ratio.denominator, ratio.numerator)


class WavSource:
    """A WAV file, paced in real time (or as fast as the consumer takes it), optionally looped."""

    def __init__(self, path: str | Path, realtime: bool = True, loop: bool = False, chunk_ms: int = 20):
        from dimgestor.audio import AudioError, load_wav

        self.path = Path(path)
        if not self.path.is_file():
            raise SourceError(f"{self.path}: audio file not found")
        try:
            self.audio = np.ascontiguousarray(load_wav(self.path), dtype=np.float32)  # 16 kHz mono
        except AudioError as e:
            raise SourceError(str(e)) from None
        if len(self.audio) == 0:
            raise SourceError(f"{self.path}: no audio samples")
        self.realtime, self.loop = realtime, loop
        self.chunk = SAMPLE_RATE * chunk_ms // 1000

    @property
    def duration_s(self) -> float:
        return len(self.audio) / SAMPLE_RATE

    async def __aiter__(self) -> AsyncIterator[AudioChunk]:
        t0 = time.monotonic()
        sent = 0  # samples on the audio clock, across loops
        while True:
            for i in range(0, len(self.audio), self.chunk):
                x = self.audio[i : i + self.chunk]
                t_start = sent / SAMPLE_RATE
                sent += len(x)
                if self.realtime:  # release each chunk when its last sample would have been spoken
                    due = t0 + sent / SAMPLE_RATE
                    await asyncio.sleep(max(0.0, due - time.monotonic()))
                    arrival = due  # like a live input: if the consumer is late, that lateness is latency
                else:
                    await asyncio.sleep(0)
                    arrival = time.monotonic()
                yield AudioChunk(x, t_start, arrival)
            if not self.loop:
                return


class PushSource:
    """16 kHz audio pushed by someone else (a WebSocket client), queued up to `max_backlog_s` seconds.

    `await put(x)` waits while the backlog is at the cap (the pusher stops reading its socket: TCP back
    pressure), so nothing is dropped and memory stays bounded however fast the audio comes.
    """

    def __init__(self, max_backlog_s: float = 30.0):
        self.chunks: deque[AudioChunk] = deque()
        self.max_samples = int(max_backlog_s * SAMPLE_RATE)
        self.queued = 0  # samples waiting to be read
        self.samples_in = 0  # 16 kHz samples so far (the audio clock)
        self.more_s = 0.0  # audio of the message being put that is still to come (put in pieces)
        self.first_at: float | None = None  # time.monotonic() of its first audio
        self.closed = False
        self.changed = asyncio.Event()

    @property
    def full(self) -> bool:
        return self.queued >= self.max_samples

    @property
    def backlog_s(self) -> float:
        return self.queued / SAMPLE_RATE

    @property
    def waiting_s(self) -> float:
        """Audio received and not yet read: queued, and the rest of the message being put (what ranks the
        session as ahead of real time from its first call, not only once its queue has filled)."""
        return self.backlog_s + self.more_s

    async def put(self, x: np.ndarray, more_s: float = 0.0) -> None:
        """Queue `x` (16 kHz), one piece of a message with `more_s` seconds of audio still to come."""
        while self.full and not self.closed:
            self.changed.clear()
            await self.changed.wait()
        self.more_s = more_s
        x = np.asarray(x, dtype=np.float32)
        if len(x) and not self.closed:
            if self.first_at is None:
                self.first_at = time.monotonic()
            self.chunks.append(AudioChunk(x, self.samples_in / SAMPLE_RATE, time.monotonic()))
            self.samples_in += len(x)
            self.queued += len(x)
            self.changed.set()

    async def close(self) -> None:
        self.closed = True
        self.changed.set()

    async def __aiter__(self) -> AsyncIterator[AudioChunk]:
        while True:
            if self.chunks:
                chunk = self.chunks.popleft()
                self.queued -= len(chunk.samples)
                self.changed.set()
                yield chunk
            elif self.closed:
                return
            else:
                self.changed.clear()
                await self.changed.wait()


def _sounddevice():
    try:
        import sounddevice
    except OSError as e:  # the module imports, but the PortAudio shared library is missing
        detail = "" if str(e) == "PortAudio library not found" else f" ({e})"  # (sounddevice's own words, often)
        raise SourceError(f"PortAudio library not found{detail}; install it, e.g. `apt install libportaudio2`") from None
    return sounddevice


def list_input_devices() -> list[dict]:
    """[{index, name, hostapi, channels, rate, default}] for every input device PortAudio sees."""
    sd = _sounddevice()
    try:
        default_in = sd.default.device[0]
        apis = [a["name"] for a in sd.query_hostapis()]
        return [
            {"index": i, "name": d["name"], "hostapi": apis[d["hostapi"]], "channels": d["max_input_channels"],
             "rate": d["default_samplerate"], "default": i == default_in}
            for i, d in enumerate(sd.query_devices()) if d["max_input_channels"] > 0
        ]
    except sd.PortAudioError as e:
        raise SourceError(f"cannot list audio devices: {e}") from None


def _one_line(e: Exception) -> str:
    first, *rest = [line.strip() for line in str(e).splitlines() if line.strip()] or [type(e).__name__]
    return " ".join([first, "; ".join(rest)]) if rest else first


def _input_device(sd, device: int | str | None) -> dict:
    """PortAudio's info for `device` (index, name substring, or None = the default input), or a SourceError
    that says what is wrong with it: no default input, no such device, or a device without input channels."""
    try:
        info = dict(sd.query_devices(device, kind="input"))
    except (sd.PortAudioError, ValueError) as e:
        if device is None:
            raise SourceError("No input device: PortAudio has no default input; list the inputs with "
                              "`dimgestor devices` and pick one with --input-device") from None
        try:  # say so when it names an output-only device
            any_kind = sd.query_devices(device)
        except (sd.PortAudioError, ValueError):
            raise SourceError(f"No input device {device!r}: {_one_line(e)} (list the inputs: dimgestor devices)") from None
        info = dict(any_kind)
    if info["max_input_channels"] < 1:
        raise SourceError(f"No input device: {info['name']!r} has no input channels (an output device?); "
                          "list the inputs with `dimgestor devices`")
    if "index" not in info:
        info["index"] = device if isinstance(device, int) else sd.default.device[0]
    return info


class MicSource:
    """A microphone through PortAudio at the device's own rate (or `rate`), resampled to 16 kHz as it streams.

    The audio callback runs on PortAudio's thread and hands blocks to the event loop; when the
    consumer falls more than `max_buffer_s` behind, the oldest blocks are dropped (`dropped_s`).
    On the loop each block gets `gain_db`, is metered (`meter`: level, "no signal") and, with
    `gate_dbfs`, noise-gated before it is resampled. `warn(text)`, when set, hears when the input goes
    dead for `NO_SIGNAL_S` seconds and when it comes back.
    """

    def __init__(self, device: int | str | None = None, rate: int | None = None, gain_db: float = 0.0,
                 gate_dbfs: float | None = None, block_ms: int = 20, max_buffer_s: float = 5.0):
        from streamer.level import LevelMeter, NoiseGate

        sd = self.sd = _sounddevice()
        info = _input_device(sd, device)
        self.device, self.name = info["index"], info["name"]
        self.rate = int(rate or info["default_samplerate"])
        try:  # a rate the device cannot do fails here, before the model loads, not later in a callback
            sd.check_input_settings(device=self.device, channels=1, samplerate=self.rate, dtype="float32")
        except (sd.PortAudioError, ValueError) as e:
            raise SourceError(f"Input device {self.name!r} cannot capture at {self.rate} Hz ({_one_line(e)}); "
                              f"its default rate is {info['default_samplerate']:.0f} Hz (--rate)") from None
        self.gain = float(10.0 ** (gain_db / 20.0))
        self.gate = NoiseGate(self.rate, gate_dbfs) if gate_dbfs is not None else None
        self.meter = LevelMeter(self.rate)
        self.warn = None
        self.block = max(1, self.rate * block_ms // 1000)
        self.blocks: deque[tuple[np.ndarray, float]] = deque()
        self.max_blocks = max(1, int(max_buffer_s * 1000 / block_ms))
        self.dropped_s = 0.0

    def condition(self, block: np.ndarray) -> np.ndarray:
        """Gain, meter, gate: what the model hears of one captured block (device rate)."""
        if self.gain != 1.0:
            block = np.clip(block * self.gain, -1.0, 1.0)
        was_dead = self.meter.no_signal
        self.meter.update(block)
        if self.warn is not None and was_dead and not self.meter.no_signal:
            self.warn(f"microphone {self.name!r}: signal again ({self.meter.level_dbfs:.0f} dBFS)")
        elif self.warn is not None and self.meter.no_signal and not was_dead:
            self.warn(f"no signal from microphone {self.name!r} for {self.meter.silent_s:.0f} s: is it muted, or the "
                      "wrong device? (list them: dimgestor devices; pick one: --input-device)")
        return self.gate.process(block) if self.gate is not None else block

    async def __aiter__(self) -> AsyncIterator[AudioChunk]:
        loop = asyncio.get_running_loop()
        ready = asyncio.Event()
        resampler = make_resampler(self.rate) if self.rate != SAMPLE_RATE else None

        def on_block(block: np.ndarray) -> None:  # on the event loop
            self.blocks.append((block, time.monotonic()))
            while len(self.blocks) > self.max_blocks:
                old, _ = self.blocks.popleft()
                self.dropped_s += len(old) / self.rate
            ready.set()

        def callback(indata, frames, t, status) -> None:  # on PortAudio's thread
            block = np.nan_to_num(indata[:, 0].astype(np.float32, copy=True), nan=0.0, posinf=0.0, neginf=0.0)
            loop.call_soon_threadsafe(on_block, block)  # a bad driver sample must not poison the model state

        try:
            stream = self.sd.InputStream(device=self.device, channels=1, samplerate=self.rate,
                                         blocksize=self.block, dtype="float32", callback=callback)
        except self.sd.PortAudioError as e:
            raise SourceError(f"No input device: cannot open {self.name!r} at {self.rate} Hz: {_one_line(e)}") from None
        samples = 0
        with stream:
            while True:
                await ready.wait()
                ready.clear()
                while self.blocks:
                    block, arrival = self.blocks.popleft()
                    block = self.condition(block)
                    x = block if resampler is None else np.asarray(resampler.process(block), dtype=np.float32)
                    if len(x):
                        yield AudioChunk(x, samples / SAMPLE_RATE, arrival)
                        samples += len(x)


def open_source(spec: str, device=None, realtime: bool = True, loop: bool = False, **mic):
    """`mic`, `demo` or a WAV path -> a source; `ws` (client audio only) -> None. `mic`: MicSource's options."""
    if spec == "ws":
        return None
    if spec == "mic":
        return MicSource(device, **mic)
    if spec == "demo":
        return WavSource(DEMO_WAV, realtime=realtime, loop=loop)
    return WavSource(spec, realtime=realtime, loop=loop)
