"""A pipecat voice pipeline with a gesturing avatar: a TTS-like stage speaks a WAV file in bursts faster than
real time, `streamer.pipecat.GestureProcessor` turns the voice into gestures, and an output transport plays the
audio in real time (to nowhere: a machine without a sound device, like a server; the web viewer plays it).

    python examples/pipecat_avatar.py --wav speech.wav --ws 127.0.0.1:8765 [--vmc 127.0.0.1:39539] [--burst 5]
        [--face vrm0|vrm1|arkit|oculus|none]

It waits for its first WebSocket client (open http://127.0.0.1:8765/ and press Sound), then speaks the file
(`--times` over, `--pause` seconds apart) and exits once it is heard. The face speaks with the body; VMC sends it
in `--face`'s blendshape names (VRM 0 presets by default, as `dimgestor serve`). Needs `pip install
'dimgestor[pipecat]'`. The guide: docs/pipecat.md. `--ws` and `--vmc` take HOST:PORT as `dimgestor serve`'s do.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipecat.frames.frames import (EndFrame, OutputAudioRawFrame, StartFrame, TTSAudioRawFrame, TTSSpeakFrame,
                                   TTSStartedFrame, TTSStoppedFrame)
from pipecat.pipeline.pipeline import Pipeline
from pipecat.pipeline.worker import PipelineParams, PipelineWorker
from pipecat.processors.frame_processor import FrameDirection, FrameProcessor
from pipecat.transports.base_output import BaseOutputTransport
from pipecat.transports.base_transport import TransportParams
from pipecat.workers.runner import WorkerRunner


class WavTTS(FrameProcessor):
    """Speaks `audio` (int16 at `rate`) for every TTSSpeakFrame, as a streaming TTS does: TTSStarted, bursts of
    `burst_s` seconds of audio each `burst_s / speed` seconds (in `frame_ms` frames), TTSStopped."""

    def __init__(self, audio: np.ndarray, rate: int, speed: float = 5.0, burst_s: float = 1.0, frame_ms: int = 20):
        super().__init__()
        if speed <= 0 or burst_s <= 0 or frame_ms <= 0:
            raise ValueError(f"need speed, burst_s and frame_ms > 0; got {speed}, {burst_s}, {frame_ms}")
        self.audio, self.rate = np.asarray(audio, dtype=np.int16), rate
        self.speed, self.burst_s, self.frame = speed, burst_s, max(1, rate * frame_ms // 1000)
        self.bursts: list[float] = []  # monotonic time each burst was pushed

    async def process_frame(self, frame, direction: FrameDirection):
        await super().process_frame(frame, direction)
        if isinstance(frame, TTSSpeakFrame):
            await self.speak()
        else:
            await self.push_frame(frame, direction)

    async def speak(self) -> None:
        await self.push_frame(TTSStartedFrame())
        step = max(1, int(self.burst_s * self.rate))
        t0 = time.monotonic()
        for n, i in enumerate(range(0, len(self.audio), step)):
            await asyncio.sleep(max(0.0, t0 + n * self.burst_s / self.speed - time.monotonic()))
            self.bursts.append(time.monotonic())
            burst = self.audio[i:i + step]
            for j in range(0, len(burst), self.frame):
                await self.push_frame(TTSAudioRawFrame(burst[j:j + self.frame].tobytes(), self.rate, 1))
        await self.push_frame(TTSStoppedFrame())


@dataclass(frozen=True)
class Played:
    start: float  # monotonic time its first sample is heard
    samples: int
    rate: int


class PacedAudioOutput(BaseOutputTransport):
    """An output transport that plays audio in real time to nowhere, like a sound card: a chunk starts when the
    one before it has played (or now, if the device is idle); a write returns once its chunk is playing. Every
    chunk's start is recorded in `played` (monotonic), the playout clock a test compares gestures with."""

    def __init__(self, rate: int = 24000, on_play=None):
        super().__init__(TransportParams(audio_out_enabled=True, audio_out_sample_rate=rate,
                                         audio_out_end_silence_secs=0))
        self.played: list[Played] = []
        self.on_play = on_play  # (start, int16 samples, rate): e.g. a level meter
        self._free_at = 0.0

    async def start(self, frame: StartFrame):
        await super().start(frame)
        await self.set_transport_ready(frame)

    async def write_audio_frame(self, frame: OutputAudioRawFrame) -> bool:
        now = time.monotonic()
        start = max(now, self._free_at)
        await asyncio.sleep(start - now)
        n = len(frame.audio) // (2 * frame.num_channels)
        self._free_at = start + n / frame.sample_rate
        self.played.append(Played(start, n, frame.sample_rate))
        if self.on_play is not None:
            self.on_play(start, np.frombuffer(frame.audio, dtype="<i2"), frame.sample_rate)
        return True


def load_speech(path: str | Path, rate: int) -> np.ndarray:
    """A WAV file as int16 mono at `rate` (what a TTS would send)."""
    from dimgestor.audio import load_wav

    x = load_wav(path, target_rate=rate)  # float mono; raises AudioError with the reason
    return (np.clip(x, -1.0, 1.0) * 32767).astype(np.int16)


def hello_for(bundle, window_ms: int) -> dict:
    """The WebSocket hello of a server whose own audio is the agent's voice (sent to clients that ask)."""
    from streamer import protocol as P
    from streamer.pose import HumanoidRig, load_humanoid_map

    sk = bundle.skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    fps = bundle.feature_spec.fps
    return P.hello(P.SkeletonInfo.from_skeleton(sk), rig.mapping(sk.names),
                   int(fps) if float(fps).is_integer() else fps, bundle.model.lookahead_s, accepts_audio=False,
                   window_ms=window_ms, source="file",
                   source_audio={"rate": P.AUDIO_RATE, "format": "pcm16", "channels": 1})


async def run(args, speech: np.ndarray, bundle) -> int:
    from streamer.pipecat import GestureProcessor
    from streamer.ws import WsConfig, WsServer

    ws = WsServer(WsConfig(args.ws[0], args.ws[1], origins=("*",)), hello_for(bundle, args.window_ms), None)
    sinks = [ws]
    if args.vmc is not None:
        from streamer.face import FACE, face_channel
        from streamer.pose import HumanoidRig, load_humanoid_map
        from streamer.vmc import BlendValues, VmcSink

        sk = bundle.skeleton
        rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
        face = {} if args.face == "none" else {FACE: BlendValues(face_channel(args.face))}  # Blend/Val per name
        sinks.append(VmcSink(args.vmc[0], args.vmc[1], rig, pace=False, channels=face))  # the processor paces
    for sink in sinks:
        await sink.open()
    try:
        for line in ws.describe().splitlines():
            print(f"pipecat_avatar: {line}", file=sys.stderr, flush=True)
        from dimgestor.face import FaceOptions

        gestures = GestureProcessor(sinks, bundle=bundle, steps=args.steps, seed=args.seed,
                                    window_ms=args.window_ms, on_audio=ws.broadcast_audio,
                                    face=None if args.face == "none" else FaceOptions())
        ws.broadcast_stats = gestures.inference  # each second's `status`: the model's latency and real-time factor
        tts = WavTTS(speech, args.rate, speed=args.burst, burst_s=args.burst_s)
        output = PacedAudioOutput(args.rate)
        worker = PipelineWorker(Pipeline([tts, gestures, output]), idle_timeout_secs=None, enable_rtvi=False,
                                params=PipelineParams(audio_out_sample_rate=args.rate),
                                observers=[gestures.playout_observer])  # when the transport really plays
        print("pipecat_avatar: waiting for a WebSocket client", file=sys.stderr, flush=True)
        while not ws.clients:
            await asyncio.sleep(0.02)
        await worker.queue_frames([TTSSpeakFrame(str(args.wav))])

        async def script() -> None:
            for _ in range(args.times - 1):
                await asyncio.sleep(len(speech) / args.rate + args.pause)
                await worker.queue_frames([TTSSpeakFrame(str(args.wav))])
            await worker.queue_frames([EndFrame()])

        talk = asyncio.create_task(script())
        runner = WorkerRunner(handle_sigint=False)  # (pipecat 1.14's names for PipelineTask and PipelineRunner)
        await runner.add_workers(worker)
        await runner.run()
        await talk
        ws.broadcast_end(gestures.frames_sent)
        s = gestures.stats
        print(f"pipecat_avatar: {s.utterances} utterances, {s.speech_frames} speech frames, {s.rest_frames} rest "
              f"frames, {s.late} late (max {s.max_late_s * 1000:.0f} ms), audio held {s.held_s * 1000:.0f} ms",
              file=sys.stderr, flush=True)
    finally:
        for sink in sinks:
            await sink.close(drain=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    from streamer.cli import host_port

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--wav", required=True, help="the speech the agent says (any WAV)")
    p.add_argument("--ws", type=host_port, default=("127.0.0.1", 8765), metavar="HOST:PORT",
                   help="WebSocket and web viewer (default 127.0.0.1:8765)")
    p.add_argument("--vmc", type=host_port, default=None, metavar="HOST:PORT", help="also send VMC (OSC/UDP) there")
    p.add_argument("--face", default="vrm0", help="the face's blendshape names over VMC: vrm0 (default), vrm1, arkit, "
                   "oculus, or none (no face)")
    p.add_argument("--burst", type=float, default=5.0, help="TTS speed: audio made per second of wall time (5)")
    p.add_argument("--burst-s", type=float, default=1.0, help="audio per TTS burst, seconds (1.0)")
    p.add_argument("--rate", type=int, default=24000, help="the TTS's sample rate (24000)")
    p.add_argument("--times", type=int, default=1, help="say it this many times (1)")
    p.add_argument("--pause", type=float, default=1.0, help="seconds of silence between times (1.0)")
    p.add_argument("--checkpoint", default=None, help="model (default: the embedded one)")
    p.add_argument("--steps", type=int, default=None, help="DDIM steps K (default: the checkpoint's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--window-ms", type=int, default=200)
    p.add_argument("-v", "--verbose", action="store_true", help="pipecat's debug log too")
    args = p.parse_args(argv)
    from loguru import logger  # pipecat's logger (a dependency of pipecat-ai): its debug lines only with -v

    logger.remove()
    logger.add(sys.stderr, level="DEBUG" if args.verbose else "WARNING")
    if not Path(args.wav).is_file():
        p.error(f"--wav {args.wav}: no such file")
    if args.face != "none":
        from dimgestor.face import check_name_set

        try:
            check_name_set(args.face)
        except ValueError as e:
            p.error(f"--face: {e}")
    if args.times < 1 or args.burst <= 0 or args.burst_s <= 0 or args.rate <= 0:
        p.error("--times, --burst, --burst-s and --rate must be positive")
    from dimgestor.audio import AudioError
    from dimgestor.streaming.checkpoint import CheckpointError, load_checkpoint

    try:
        speech = load_speech(args.wav, args.rate)
        bundle = load_checkpoint(args.checkpoint)
    except (AudioError, CheckpointError, OSError, ValueError) as e:
        p.error(str(e))
    if not len(speech):
        p.error(f"--wav {args.wav}: no audio samples")
    try:
        return asyncio.run(run(args, speech, bundle))
    except OSError as e:  # e.g. the WebSocket port is taken
        print(f"pipecat_avatar: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
