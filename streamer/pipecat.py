"""Voice agents: `GestureProcessor`, a pipecat stage between the TTS and the output transport that gives the
agent's voice a gesturing avatar (docs/pipecat.md).

Each utterance's audio runs through its own engine `Session` (seed + i: past the blend-in, `dimgestor generate`'s
frames), and frame k goes to the sinks at the utterance's start + k / fps on the playout clock the transport
reports (`playout_observer`), i.e. when its audio is heard. The first audio waits (at most `max_hold_s`) for the
first frames, so the body moves with the first word; between utterances a critically damped spring eases to rest.
The face (`dimgestor.face`) comes from the same session as the body, in each frame's channel "face", so it is
released with its frame when its audio is heard; between utterances the mouth rests and the eyes still blink.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
import warnings
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

try:
    from pipecat.frames.frames import (BotStartedSpeakingFrame, BotStoppedSpeakingFrame, CancelFrame, EndFrame,
                                       Frame as PipecatFrame, InterruptionFrame, OutputAudioRawFrame, StartFrame,
                                       SystemFrame, TTSStartedFrame, TTSStoppedFrame)
    from pipecat.observers.base_observer import BaseObserver, FramePushed
    from pipecat.processors.frame_processor import FrameDirection, FrameProcessor
    from pipecat.transports.base_output import BaseOutputTransport
except ImportError as e:  # the engine works without pipecat; only this module needs it
    raise ImportError("streamer.pipecat needs pipecat-ai: pip install 'dimgestor[pipecat]'") from e

from dimgestor.audio import SAMPLE_RATE
from dimgestor.face import FACE_LABELS, FaceOptions
from dimgestor.face.life import Blinks
from dimgestor.face.listener import unavailable as face_unavailable
from dimgestor.face.visemes import V
from dimgestor.rotations import expmap_to_quat, quat_conj, quat_mul, quat_to_expmap
from dimgestor.streaming.stream import MODEL_SPEAKER
from streamer.face import FACE
from streamer.frames import Frame
from streamer.playout import UNCONFIRMED_S, Playout, Utterance
from streamer.sessions import Session
from streamer.sink import Sink
from streamer.sources import PushSource, make_resampler

__all__ = ["GestureProcessor", "GestureStats", "PlayoutObserver", "Released", "RestPose", "Resting"]
log = logging.getLogger("streamer.pipecat")


@dataclass(frozen=True)
class Released:
    """One frame as it went to the sinks: when (monotonic), when it was due, and what made it."""

    frame: Frame
    wall: float
    due: float
    utterance: int  # -1: a rest frame the spring made
    k: int          # the utterance's own frame index (-1 for rest frames)
    audio_s: float | None  # the moment of the utterance's audio it shows (None: rest, or silence in a slow TTS)


@dataclass
class GestureStats:
    utterances: int = 0
    speech_frames: int = 0   # released frames of speech (blended in or exact)
    rest_frames: int = 0     # frames the spring made (between utterances, after interruptions)
    late: int = 0            # speech frames released more than a frame after their audio played
    max_late_s: float = 0.0
    held_s: float = 0.0      # total time the agent's audio was held back at utterance starts
    dropped_unplayed: int = 0  # frames of audio an interruption cut (never sent)
    interruptions: int = 0


class InferenceStats:
    """The model's recent latency and real-time factor for a `WsServer`'s `status` (its `broadcast_stats`): the
    newest utterance's session's (the last one's between utterances; 0 before the first). No `window`: frames go
    out when their audio is heard, not as a window is made, so `timing` messages would misdate them."""

    window = None

    def __init__(self):
        self.session = None  # the newest utterance's `streamer.sessions.Stats`

    @property
    def latency_ms(self) -> float:
        return self.session.latency_ms if self.session is not None else 0.0

    @property
    def rtf(self) -> float:
        return self.session.rtf if self.session is not None else 0.0


@dataclass(frozen=True)
class RestPose:
    """The pose the avatar eases to between utterances, and the tangent space the spring works in."""

    root_pos: np.ndarray
    rotations: np.ndarray  # (J, 4) wxyz
    features: np.ndarray

    def tangent(self, f: Frame) -> np.ndarray:
        """A pose as one vector relative to rest: root offset, rotation vectors, feature offset."""
        rel = quat_to_expmap(quat_mul(quat_conj(self.rotations), np.asarray(f.rotations, dtype=np.float64)))
        return np.concatenate([np.asarray(f.root_pos) - self.root_pos, rel.ravel(), f.features - self.features])

    def pose(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        j = len(self.rotations)
        rot = quat_mul(self.rotations, expmap_to_quat(x[3:3 + 3 * j].reshape(j, 3)))
        return self.root_pos + x[:3], rot, self.features + x[3 + 3 * j:]

    @classmethod
    def of_silence(cls, bundle, steps: int, seed: int, seconds: float = 2.0, speaker=MODEL_SPEAKER) -> "RestPose":
        """The model's pose after `seconds` of silence (the root where a fresh stream starts), as `speaker`."""
        from dimgestor.features import PoseDecoder

        stream = bundle.stream(steps=steps, seed=seed, speaker=speaker)
        normalized = np.concatenate([stream.push(np.zeros(int(seconds * SAMPLE_RATE), np.float32)), stream.finish()])
        feats = np.asarray(bundle.denormalize(normalized), dtype=np.float64)
        pose = PoseDecoder(bundle.skeleton, bundle.feature_spec).decode(feats)
        return cls(np.asarray(pose.root_pos[0]), np.asarray(pose.rotations[-1]), feats[-1])


class _Spring:
    """A critically damped spring in the rest pose's tangent space: x'' = -w^2 x - 2 w x'."""

    def __init__(self, dim: int, omega: float):
        self.x, self.v, self.omega = np.zeros(dim), np.zeros(dim), omega

    def follow(self, x: np.ndarray, dt: float) -> None:
        """A pose the avatar showed (speech): the spring starts from it, with its velocity."""
        self.v, self.x = (x - self.x) / dt, x

    def step(self, dt: float) -> np.ndarray:
        w, e = self.omega, np.exp(-self.omega * dt)
        a = self.v + w * self.x
        self.x, self.v = (self.x + a * dt) * e, (self.v - w * a * dt) * e
        return self.x


class Resting:
    """The avatar between utterances and into the next: a critically damped spring eases the body to rest (and an
    utterance's first `blend_in` frames out of it), the mouth rests and the eyes blink on the frames' clock."""

    def __init__(self, rest: RestPose, fps: float, rest_hz: float, blend_in: int, face: FaceOptions | None,
                 blinks: Blinks):
        self.rest, self.dt, self.blend_in, self.face, self.blinks = rest, 1 / fps, blend_in, face, blinks
        self.spring = _Spring(len(rest.tangent(self.pose_frame())), 2 * np.pi * rest_hz)

    def pose_frame(self) -> Frame:
        """The rest pose as a frame (index 0, pts 0, no channels)."""
        return Frame(0, 0.0, self.rest.root_pos, self.rest.rotations, self.rest.features)

    def speech(self, f: Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """An utterance's frame as it goes out (root, rotations, features): eased in from where the spring is over
        its first `blend_in` frames, then the model's own; the spring follows it."""
        x = self.rest.tangent(f)
        if f.index < self.blend_in:
            w = _smoothstep((f.index + 1) / (self.blend_in + 1))
            x = (1 - w) * self.spring.step(self.dt) + w * x
            pose = self.rest.pose(x)
        else:
            pose = f.root_pos, f.rotations, f.features
        self.spring.follow(x, self.dt)
        return pose

    def frame(self, index: int, pts: float) -> Frame:
        """The next frame between utterances: the spring's step toward rest, and the face at rest."""
        root, rot, feats = self.rest.pose(self.spring.step(self.dt))
        return Frame(index, pts, root, rot, feats, {} if self.face is None else {FACE: self.face_at(pts)})

    def face_at(self, pts: float) -> np.ndarray:
        """The face between utterances: the mouth at rest, the eyes blinking on the frames' clock, the smile."""
        out = np.zeros(len(FACE_LABELS))
        out[V["sil"]] = 1.0
        out[V["blinkLeft"]], out[V["blinkRight"]] = self.blinks.step(pts, False)
        out[V["smile"]] = self.face.smile
        return out


class GestureProcessor(FrameProcessor):
    """Agent audio -> gesture frames to `sinks`, released when their audio is heard (see the module docstring).

    sinks: opened and closed by the caller (a `WsServer` must be listening before the viewer connects).
    bundle or checkpoint: the model (default: the embedded one). on_audio(pts, samples): the agent's audio at
    16 kHz on the frames' clock, given as it is heard, beside its frames (e.g. `WsServer.broadcast_audio`, so the
    web viewer plays it in sync; audio an interruption cut is never given).
    on_release(Released): every frame sent, for measurements. face: how the face is made (each utterance's seeded
    like its body), None for frames without one. speaker: the speaker whose style the avatar plays, of a model
    trained with --speaker-condition (None: none in particular; default: the model's own). scheduler: where
    inference runs (a `streamer.scheduling` scheduler or Executor; None: a shared pool); `executor` is its
    deprecated name.
    """

    def __init__(self, sinks: list[Sink], *, bundle=None, checkpoint: str | None = None, steps: int | None = None,
                 seed: int = 0, window_ms: int = 200, scheduler=None, max_hold_s: float = 0.3,
                 blend_in_s: float = 0.5, rest_hz: float = 1.3,
                 on_audio: Callable[[float, np.ndarray], None] | None = None,
                 on_release: Callable[[Released], None] | None = None, executor=None,
                 face: FaceOptions | None = FaceOptions(), speaker=MODEL_SPEAKER, **kwargs):
        scheduler = _scheduler(scheduler, executor)
        if face is not None and "pocketsphinx" in face.listener and (why := face_unavailable()) is not None:
            raise ImportError(f"GestureProcessor: {why}; or face=None for frames without a face")
        super().__init__(**kwargs)
        if bundle is None:
            from dimgestor.streaming.checkpoint import load_checkpoint

            bundle = load_checkpoint(checkpoint)
        if max_hold_s < 0 or blend_in_s < 0 or rest_hz <= 0:
            raise ValueError(f"need max_hold_s >= 0, blend_in_s >= 0, rest_hz > 0; got {max_hold_s}, {blend_in_s}, "
                             f"{rest_hz}")
        self.bundle, self.sinks = bundle, list(sinks)
        self.speaker = bundle.model.speaker if speaker is MODEL_SPEAKER else speaker
        bundle.model.speaker_number(self.speaker)  # (ValueError naming the model's speakers, before anything runs)
        self.fps = float(bundle.feature_spec.fps)
        self.steps = steps if steps is not None else bundle.config.sample_steps
        self.seed, self.window_ms, self.scheduler = seed, window_ms, scheduler
        self.max_hold_s, self.blend_in = max_hold_s, int(round(blend_in_s * self.fps))
        self.on_audio, self.on_release, self.face = on_audio, on_release, face
        rest = RestPose.of_silence(bundle, self.steps, seed, speaker=self.speaker)
        self.resting = Resting(rest, self.fps, rest_hz, self.blend_in, face,
                               Blinks(seed=seed if face is None else face.seed + seed))
        self.rest = self.resting.rest
        self.stats = GestureStats()
        self.inference = InferenceStats()  # for `status` (WsServer.broadcast_stats), as `streamer serve` sends
        self.origin: float | None = None  # monotonic time of pts 0 (the StartFrame)
        self._changed = asyncio.Event()
        self._utterances: deque[Utterance] = deque()
        self.playout = Playout(self._changed.set)  # when their audio is heard
        self.playout_observer = PlayoutObserver(self.playout)
        self._holding: Utterance | None = None
        self._held: list[tuple[PipecatFrame, FrameDirection, Utterance | None]] = []  # (audio: its utterance)
        self._next_rest_due = 0.0
        self._drift = 0.0  # frames' pts less their due time since the start: playout shifts moved one, not the other
        self._last_pts = self._last_due = None  # the last frame sent's pts and due time (None: none yet)
        self._index = 0
        self._clock_task: asyncio.Task | None = None
        self._hold_task: asyncio.Task | None = None

    # ---- pipecat ---------------------------------------------------------------------------------

    async def process_frame(self, frame: PipecatFrame, direction: FrameDirection):
        await super().process_frame(frame, direction)
        if isinstance(frame, StartFrame):
            await self.push_frame(frame, direction)
            self._start()
            return
        if isinstance(frame, (InterruptionFrame, CancelFrame)):
            await self._interrupt(frame)
            await self.push_frame(frame, direction)
            if isinstance(frame, CancelFrame):
                await self._stop()
            return
        if direction == FrameDirection.UPSTREAM:
            if isinstance(frame, BotStartedSpeakingFrame):
                self.playout.bot_started(time.monotonic(), self._utterances)
            elif isinstance(frame, BotStoppedSpeakingFrame) and self._utterances:
                u = self._utterances[-1]  # ended by the transport (a TTS that sends no TTSStopped), if all heard:
                if u.start is not None and time.monotonic() >= u.start + u.pushed_s - 1 / self.fps:
                    await self._end_utterance()  # (not the next answer, begun while the last one still played)
            await self.push_frame(frame, direction)
            return
        u = None
        if isinstance(frame, OutputAudioRawFrame) and frame.audio:
            u = await self._hear(frame)
        elif isinstance(frame, (TTSStartedFrame, TTSStoppedFrame, EndFrame)):
            await self._end_utterance()  # TTSStarted: what comes next is a new utterance
        if self._holding is not None and not isinstance(frame, SystemFrame):
            self._held.append((frame, direction, u))  # behind the held audio, in order
            return
        await self.push_frame(frame, direction)

    async def cleanup(self):
        await self._stop()
        await super().cleanup()

    # ---- the agent's audio -----------------------------------------------------------------------

    async def _hear(self, frame: OutputAudioRawFrame) -> Utterance:
        """Feed a frame of agent audio to its utterance's session (a new utterance if none is open); schedule
        its playout unless it is held."""
        u = self._utterances[-1] if self._utterances and self._utterances[-1].open else None
        if u is not None and u.rate != frame.sample_rate:
            await self._end_utterance()
            u = None
        if u is None:
            u = self._new_utterance(frame.sample_rate)
            if self.max_hold_s > 0 and self.playout.play_end <= time.monotonic() and self._holding is None:
                self._holding = u  # it would be heard at once: hold it until its first frames are made
                self._hold_task = self.create_task(self._hold(u), name="gesture-hold")
        x = _mono(frame)
        if self._holding is None:  # (held audio goes out later, back to back: no transport gap to fill)
            gap = self._schedule(u, len(x))
            if gap > 0:
                await u.feed(np.zeros(int(round(gap * frame.sample_rate)), np.float32))
        await u.feed(x)
        return u

    def _new_utterance(self, rate: int) -> Utterance:
        from dimgestor.features import PoseDecoder

        number = self.stats.utterances
        self.stats.utterances += 1
        b = self.bundle
        face = None if self.face is None else dataclasses.replace(self.face, seed=self.face.seed + self.seed + number)
        session = Session(b.stream(steps=self.steps, seed=self.seed + number, speaker=self.speaker),
                          PoseDecoder(b.skeleton, b.feature_spec), b.denormalize, self.fps,
                          window_ms=self.window_ms, scheduler=self.scheduler, name=f"utterance-{number}",
                          face=face)  # (seeded as its body is)
        self.inference.session = session.stats
        u = Utterance(number, session, PushSource(max_backlog_s=3600.0),
                      None if rate == SAMPLE_RATE else make_resampler(rate), rate)

        def emit(frames: list[Frame]) -> None:
            u.frames.extend(frames)
            if frames:
                u.first_ready.set()
            self._changed.set()

        async def run() -> None:
            try:
                await session.run(u.source, emit)
            except Exception:
                log.exception("utterance %d: inference failed; the avatar eases to rest", number)
            finally:
                u.done, u.open = True, False
                u.first_ready.set()
                self._changed.set()

        u.task = self.create_task(run(), name=f"gesture-utterance-{number}")
        self._utterances.append(u)
        return u

    def _schedule(self, u: Utterance, samples: int) -> float:
        """`samples` of u's audio go to the transport now (`Playout.schedule`); its first fixes u's pts."""
        first = u.start is None
        gap = self.playout.schedule(u, samples, time.monotonic())
        if first:
            u.pts0 = u.start - self.origin + self._drift
        return gap

    async def _hold(self, u: Utterance) -> None:
        t0 = time.monotonic()
        try:
            await asyncio.wait_for(u.first_ready.wait(), self.max_hold_s)
        except asyncio.TimeoutError:
            pass
        self.stats.held_s += time.monotonic() - t0
        log.debug("utterance %d: audio held %.0f ms", u.number, 1000 * (time.monotonic() - t0))
        while self._held:  # out in order; process_frame keeps appending until the list is empty
            frame, direction, v = self._held.pop(0)
            if v is not None:
                self._schedule(v, len(_mono(frame)))
            await self.push_frame(frame, direction)
        self._holding = self._hold_task = None

    async def _end_utterance(self) -> None:
        """The open utterance's audio has all come: its session flushes its last frames."""
        if self._utterances and self._utterances[-1].open:
            await self._utterances[-1].close()

    async def _interrupt(self, frame: PipecatFrame) -> None:
        """The user barged in (or the pipeline stops): nothing not yet heard will be; ease to rest."""
        now = time.monotonic()
        if isinstance(frame, InterruptionFrame):
            self.stats.interruptions += 1
        if self._hold_task is not None:
            await self.cancel_task(self._hold_task)
        kept = [(f, d) for f, d, _ in self._held if not getattr(f, "interruptible", True)]
        self._held, self._holding, self._hold_task = [], None, None
        for f, d in kept:  # uninterruptible frames still go, in order (held audio is dropped: never heard)
            await self.push_frame(f, d)
        # (detached before any await: the clock task pops finished utterances, and audio after the interruption
        # may start a new one, while the old ones' inference is cancelled)
        gone = list(self._utterances)
        self._utterances.clear()
        self.playout.clear(now)
        if self._last_due is not None:
            self._next_rest_due = self._last_due + 1 / self.fps
        self._changed.set()
        for u in gone:
            self.stats.dropped_unplayed += len(u.frames)
            u.frames.clear()
            await u.source.close()
            if u.task is not None:
                await self.cancel_task(u.task)

    # ---- the clock -------------------------------------------------------------------------------

    def _start(self) -> None:
        self.origin = self._next_rest_due = time.monotonic()
        self._clock_task = self.create_task(self._clock(), name="gesture-clock")

    async def _stop(self) -> None:
        for task in [self._clock_task, self._hold_task, *(u.task for u in self._utterances)]:
            if task is not None and not task.done():
                await self.cancel_task(task)
        self._clock_task = self._hold_task = None

    async def _clock(self) -> None:
        """Release every frame at its due time: the current utterance's, or the spring's between them."""
        dt = 1 / self.fps
        while True:
            now = time.monotonic()
            u = self._utterances[0] if self._utterances else None
            # (an estimated start: the observer reports the real one; a transport it does not see, never)
            started = self.playout.started(u, now)
            # (once begun, an utterance keeps the clock: when its audio pauses, the picture waits with it)
            if started and (u.released or self._next_rest_due >= u.start - dt / 2):
                if u.frames:
                    due = u.start + u.frames[0].pts
                    if due > now and await self._wait(due - now):
                        continue
                    if (self.playout.unheard(u, u.frames[0].pts, due, time.monotonic())
                            and await self._wait(due + UNCONFIRMED_S - now)):
                        continue
                    self._release_speech(u, u.frames.popleft(), due, time.monotonic())
                elif u.done:
                    self._begin(u)
                    u.give_audio(np.inf, self.on_audio)
                    self._utterances.popleft()
                    if self._last_due is not None:
                        self._next_rest_due = self._last_due + dt
                else:
                    await self._wait(None)  # its next frame is late: it goes as soon as it is made
                continue
            due = self._next_rest_due
            if due > now and await self._wait(due - now):
                continue
            self._release_rest(due)

    async def _wait(self, timeout: float | None) -> bool:
        """Sleep until `timeout` or until something changed; True: something changed (look again), also when it
        changed after the timeout fired and before this task ran again (an interruption that emptied the
        utterance the clock was about to release from: a loaded event loop made that gap wide enough)."""
        self._changed.clear()
        try:
            await asyncio.wait_for(self._changed.wait(), timeout)
        except asyncio.TimeoutError:
            pass
        return self._changed.is_set()

    def _begin(self, u: Utterance) -> None:
        """Before u's first frame or audio goes out: its pts come after every frame sent. They were set when its
        audio was pushed, from the wall clock; a rest frame released since (the transport had not yet confirmed
        when u starts, or confirmed it later) may carry a later pts. Frames' pts only increase: u's clock moves
        on, its audio with it (on_audio's pts are the same clock): a viewer stays in sync."""
        if u.released == 0 and self._last_pts is not None:
            u.pts0 = max(u.pts0, self._last_pts + 0.5 / self.fps)

    def _release_speech(self, u: Utterance, f: Frame, due: float, now: float) -> None:
        self._begin(u)
        k = f.index
        root, rot, feats = self.resting.speech(f)
        late = now - due
        if late > 1 / self.fps:
            self.stats.late += 1
        self.stats.max_late_s = max(self.stats.max_late_s, late)
        self.stats.speech_frames += 1
        u.released += 1
        u.give_audio(f.pts + 1 / self.fps, self.on_audio)
        self._send(Frame(self._index, u.pts0 + f.pts, root, rot, feats, f.channels), due, u.number, k,
                   u.audio_at(f.pts), now)

    def _release_rest(self, due: float) -> None:
        pts = due - self.origin + self._drift
        self.stats.rest_frames += 1
        self._send(self.resting.frame(self._index, pts), due, -1, -1, None, time.monotonic())

    def _send(self, frame: Frame, due: float, utterance: int, k: int, audio_s: float | None, now: float) -> None:
        """`now`: the release's instant, the one its lateness was counted from (`Released.wall` says the same)."""
        for sink in self.sinks:
            sink.send([frame])
        self._index += 1
        self._last_pts = frame.pts
        self._drift = frame.pts - (due - self.origin)  # the audio's clock less the wall's (moves at playout shifts)
        self._last_due = due
        self._next_rest_due = due + 1 / self.fps
        if self.on_release is not None:
            self.on_release(Released(frame, now, due, utterance, k, audio_s))

    @property
    def frames_sent(self) -> int:
        return self._index


class PlayoutObserver(BaseObserver):
    """Tells a `GestureProcessor`'s playout (`streamer.playout.Playout`) when the output transport plays each chunk
    of audio: a transport pushes a chunk on once written to its device, so that push's timestamp is when the chunk
    starts to be heard. Add it to the pipeline's observers (`PipelineWorker(..., observers=
    [gestures.playout_observer])`); without it the processor follows its own model of the transport (and
    BotStartedSpeaking), which a stalled event loop or a device that ran dry makes late."""

    def __init__(self, playout: Playout):
        super().__init__(observe_every_push=False)  # (the transport's chunks are its own frames: their first push)
        self.playout = playout
        self._clock_offset_ns: int | None = None

    async def on_push_frame(self, data: FramePushed):
        self.playout.observed = True  # (the StartFrame's push comes before any audio)
        if not (isinstance(data.source, BaseOutputTransport) and data.direction == FrameDirection.DOWNSTREAM
                and isinstance(data.frame, OutputAudioRawFrame) and data.frame.audio):
            return
        if self._clock_offset_ns is None:  # the pipeline clock counts from its start: to time.monotonic
            self._clock_offset_ns = time.monotonic_ns() - data.source.get_clock().get_time()
        f = data.frame
        seconds = len(f.audio) / (2 * f.num_channels * f.sample_rate)
        self.playout.heard((data.timestamp + self._clock_offset_ns) / 1e9, seconds)


def _scheduler(scheduler, executor):
    """GestureProcessor's scheduler= (or executor=, its deprecated name)."""
    if executor is None:
        return scheduler
    if scheduler is not None:
        raise TypeError("GestureProcessor: give scheduler= only (executor= is its deprecated name)")
    warnings.warn("GestureProcessor(executor=...) is deprecated: use scheduler=", DeprecationWarning, stacklevel=3)
    return executor


def _mono(frame: OutputAudioRawFrame) -> np.ndarray:
    """16-bit PCM (interleaved if several channels) -> float32 mono."""
    x = np.frombuffer(frame.audio, dtype="<i2").astype(np.float32) / 32768.0
    if frame.num_channels > 1:
        x = x[: len(x) // frame.num_channels * frame.num_channels].reshape(-1, frame.num_channels).mean(axis=1)
    return x


def _smoothstep(t: float) -> float:
    t = min(max(t, 0.0), 1.0)
    return t * t * (3 - 2 * t)
