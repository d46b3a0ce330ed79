"""Session: one audio source -> gesture frames, window by window, inference off the event loop.

A session owns one `GestureStream` (the model's streaming state) and one `PoseDecoder` (the root
integration). Its scheduler (`streamer.scheduling`) says when a window of audio is due and how a long take
is cut into calls (`WindowPolicy`), and runs the calls: batched with the other sessions' windows
(`StreamBatcher`, `streamer serve`'s default) or each alone (`RankedScheduler`, `--no-batch`). Calls are ranked
real time first, then backlogs (`AudioClock`). Each frame is stamped with
pts = index / fps on the audio clock.
"""

from __future__ import annotations

import asyncio
import dataclasses
import inspect
import math
import time
import warnings
from collections import deque
from concurrent.futures import Executor
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, AsyncIterable, Callable, Mapping

import numpy as np

from dimgestor.audio import SAMPLE_RATE
from dimgestor.streaming.savestate_checks import StateError, finite_number, is_int, show
from dimgestor.streaming.stream import MODEL_SPEAKER
from streamer.face import FACE
from streamer.frames import Frame
from streamer.protocol import MAX_RATE, MIN_RATE
from streamer.scheduling import Scheduler, as_scheduler
from streamer.sources import AudioChunk, make_resampler

__all__ = ["Session", "Stats", "AudioClock", "WindowTiming", "check_meta"]

if TYPE_CHECKING:
    from dimgestor.face import FaceOptions
    from streamer.capacity import FaceCost
    from streamer.face_process import FaceProcess


@dataclass(frozen=True)
class WindowTiming:
    """One window on the server's monotonic clock: the audio it needed (up to `audio_until_s` on the stream's
    clock) was all there at `arrived_s`, and inference on it began at `dispatched_s` (protocol `timing`)."""

    audio_until_s: float
    arrived_s: float
    dispatched_s: float


@dataclass
class Stats:
    """Running measurements of one session; averages are exponential over recent windows."""

    windows: int = 0
    frames: int = 0
    audio_s: float = 0.0
    infer_s: float = 0.0
    latency_ms: float = 0.0  # last sample of a window in -> its frames out
    rtf: float = 0.0         # inference time / audio time
    ended: bool = False
    window: WindowTiming | None = None  # the window whose frames are being emitted now

    def update(self, audio_s: float, infer_s: float, latency_s: float, frames: int, alpha: float = 0.2) -> None:
        a = 1.0 if self.windows == 0 else alpha
        self.windows += 1
        self.frames += frames
        self.audio_s += audio_s
        self.infer_s += infer_s
        self.latency_ms += a * (1000 * latency_s - self.latency_ms)
        if audio_s > 0:
            self.rtf += a * (infer_s / audio_s - self.rtf)


class _AudioBuffer:
    """Bounded audio buffer between the source reader and the inference loop (back pressure when full)."""

    def __init__(self, max_samples: int):
        self.chunks: deque[AudioChunk] = deque()
        self.samples = 0
        self.max_samples = max_samples
        self.closed = False
        self.error: BaseException | None = None
        self.changed = asyncio.Event()

    async def put(self, chunk: AudioChunk) -> None:
        while self.samples >= self.max_samples:
            self.changed.clear()
            await self.changed.wait()
        self.chunks.append(chunk)
        self.samples += len(chunk.samples)
        self.changed.set()

    def close(self, error: BaseException | None = None) -> None:
        self.closed, self.error = True, error
        self.changed.set()

    async def take(self, window: int, whole: bool = False) -> list[AudioChunk]:
        """Everything buffered once a window is (or the source ended); whole: only the whole windows buffered
        until the source ends, a chunk cut at the last one's end (its rest opens the next window), as a
        batching scheduler's `WindowPolicy` asks."""
        while self.samples < window and not self.closed:
            self.changed.clear()
            await self.changed.wait()
        if self.error is not None:
            raise self.error
        if self.closed or not whole:
            chunks, self.chunks, self.samples = list(self.chunks), deque(), 0
        else:
            chunks, left = [], self.samples // window * window
            self.samples -= left
            while left:
                chunk = self.chunks.popleft()
                if len(chunk.samples) > left:  # the rest of this chunk opens the next window
                    rest = AudioChunk(chunk.samples[left:], chunk.t_start + left / SAMPLE_RATE, chunk.arrival)
                    self.chunks.appendleft(rest)
                    chunk = AudioChunk(chunk.samples[:left], chunk.t_start, chunk.arrival)
                chunks.append(chunk)
                left -= len(chunk.samples)
        self.changed.set()
        return chunks


class AudioClock:
    """Ranks a stream's calls: real time first, the latest first; then backlogs, the least served first.

    A call is real time when less audio waits behind it than the call holds (a talker, a microphone, a window
    late after a stall): its rank is minus how late its inference runs (the time elapsed since the stream's
    audio began less the audio inferred, at most `max_credit_s`), <= 0. A call with more waiting behind it is
    backlog: 1 + how far its inference is ahead of the latest it may be, >= 1, so among fast senders held back
    by the server the one served least goes first (equals: first come, first served), whatever their queues.
    How far ahead counts only up to `max_lead_s`: fast senders further ahead than that tie and take turns
    (first come, first served). Uncapped, one served alone at a flood's start (40 s ahead after a second)
    waited until the 30 others had caught up: no frame for 40 s, and the keepalive closed it (6 of 31, measured).

    A real-time sender stays about one window late, whatever the jitter of its packets: its first call's audio
    took that call's length to arrive, so the clock starts that long before the first call. Time in which the
    client sent nothing earns at most `max_credit_s` of catching up (time in which the server was slow earns
    it all). Shared by the successive sessions of one client (so restarting sessions earns no priority).
    Time the server held a client's received audio while its previous session finished (`held`) earns nothing
    either: that client is ahead. (Credited as the server's slowness, a crowd of 30 fast senders ending 0.5 s
    sessions over and over ranked as real time, 2 s late, and their windows and finishes ran before a talker's:
    its frames 0.35-0.68 s late against 0.06 quiet, measured.)
    """

    def __init__(self, max_credit_s: float = 2.0, max_lead_s: float = 2.0, now: Callable[[], float] = time.monotonic):
        self.t0: float | None = None
        self.audio_s = 0.0  # handed to inference
        self.max_credit_s, self.max_lead_s = max_credit_s, max_lead_s
        self.now = now

    def rank(self, call_s: float = 0.0, waiting_s: float = 0.0) -> float:
        """A call of `call_s` seconds of audio, with `waiting_s` more received and waiting behind it."""
        now = self.now()
        if self.t0 is None:
            self.t0 = now - call_s
        silent = (now - self.t0) - (self.audio_s + call_s + waiting_s)  # the client sent less than real time
        if silent > self.max_credit_s:
            self.t0 += silent - self.max_credit_s
        late = min((now - self.t0) - self.audio_s, self.max_credit_s)
        return -late if waiting_s <= call_s else 1.0 + self.max_credit_s - max(late, -self.max_lead_s)

    def held(self, seconds: float) -> None:
        """The client's audio waited `seconds` here, received, for its previous session to finish: not lateness."""
        if self.t0 is not None and seconds > 0:
            self.t0 += seconds


class NonFiniteFrames(RuntimeError):
    """A window's frames held NaN or infinite values (a bad state or input got through): none of them is sent."""


class Session:
    """One audio stream -> frames. Build with `from_bundle`; drive with `run(source, emit)`.

    scheduler: a `streamer.scheduling.Scheduler`, any `concurrent.futures.Executor`, or None (a shared pool);
    `executor` is its deprecated name. The scheduler uses only `stream` and `frames_of` (`WindowSource`).
    face: how its face is made (None: its frames carry none). clock: ranks its calls (a client's successive
    sessions share one; None: its own). on_window: told each window's latency (s), e.g. the metrics. on_boundary:
    called after each window (state, decoder and frames agree: a periodic save's moment). state_key: the workers'
    shared secret that seals its saved states (serve --state-secret-file; None: plain SHA-256, integrity only).
    face_cost: a `streamer.capacity.FaceCost` its faces are timed into (what admission learns a face's cost from).
    """

    def __init__(self, stream, decoder, denormalize: Callable[[np.ndarray], np.ndarray], fps: int,
                 window_ms: int = 200, scheduler: Scheduler | Executor | None = None, name: str = "session", *,
                 executor: Executor | None = None, face: "FaceOptions | None" = None, clock: AudioClock | None = None,
                 on_window: Callable[[float], None] | None = None, on_boundary: Callable[[], None] | None = None,
                 state_key: bytes | None = None, face_cost: "FaceCost | None" = None,
                 face_process: "FaceProcess | None" = None):
        if executor is not None:
            if scheduler is not None:
                raise TypeError("Session: give scheduler= only (executor= is its deprecated name)")
            warnings.warn("Session(executor=...) is deprecated: use scheduler=", DeprecationWarning, stacklevel=2)
            scheduler = executor
        self.scheduler = as_scheduler(scheduler)
        self.windows = self.scheduler.windows(window_ms)
        self.stream, self.decoder, self.denormalize = stream, decoder, denormalize
        self.fps, self.name = fps, name
        self.stats = Stats()
        self.clock = clock if clock is not None else AudioClock()
        self.on_window, self.on_boundary = on_window, on_boundary
        self.handover = False  # set before the source closes: stop after its audio, unfinished (handover.py)
        # The face (`dimgestor.face`): made from the same audio in the same call as the body's frames, into each
        # frame's channel "face". None: frames carry no face.
        self.face_options = face
        self.face_cost = face_cost
        self._face = None
        self._face_start = (0, 0)  # (sample, frame) where the face begins: a restored session's position
        self._face_audio: deque[np.ndarray] = deque()  # a call's audio, from its submission to its frames
        self._face_paid = 0.0  # this session's share of a batch's face (`frames_many`), seconds
        self.face_process = face_process  # where its face is made (None: here, in the batch's thread)
        self._face_token = None  # its face's exchange with the face process, begun with the batch (`faces_begin`)
        self._finishing = False
        self._inflight = None  # the call being inferred (a scheduler's future): the face outlives it
        self.state_key = state_key  # (`dimgestor.streaming.savestate`; never shown)

    @classmethod
    def from_bundle(cls, bundle, steps: int | None = None, seed: int = 0, smoothing="config", root: str = "free",
                    tether_s: float = 5.0, guidance: float | None = None, speaker=MODEL_SPEAKER, **kw) -> "Session":
        """speaker: a name, None (no speaker in particular) or MODEL_SPEAKER (the model's own: `GestureStream`);
        kw: Session's own (window_ms, scheduler, name, face=FaceOptions() for a face, clock, on_window, ...)."""
        from dimgestor.features import PoseDecoder

        decoder = PoseDecoder(bundle.skeleton, bundle.feature_spec, root=root, tether_s=tether_s)
        stream = bundle.stream(steps=steps, seed=seed, smoothing=smoothing, guidance=guidance, speaker=speaker)
        return cls(stream, decoder, bundle.denormalize, bundle.feature_spec.fps, **kw)

    @property
    def lookahead_s(self) -> float:
        return float(self.stream.lookahead_s)

    # The channels this session's frames carry beside the pose: name -> maker of a window's values from its
    # denormalized features, (n, D) -> (n, size). Where a new channel is made; each sink's map says if it is sent.
    channels: Mapping[str, Callable[[np.ndarray], np.ndarray]] = MappingProxyType({})

    def frames_of(self, normalized: np.ndarray) -> list[Frame]:
        """The stream's newest n frames as normalized features (n, D) -> Frames (decoded poses, stamped).
        A scheduler that pushed the stream itself (a batch) calls it; the pose decoder moves on."""
        n = len(normalized)
        if n == 0:
            return []
        first = self.stream.frames_out - n
        feats = np.asarray(self.denormalize(normalized), dtype=np.float64)
        pose = self.decoder.decode(feats)
        made = {name: np.asarray(make(feats)) for name, make in self.channels.items()}
        if self.face_options is not None:
            t = time.perf_counter()
            made[FACE] = self._face_rows(n)
            spent, self._face_paid = time.perf_counter() - t + self._face_paid, 0.0
            if self.face_cost is not None:  # (what admission learns a face's cost from: streamer.capacity)
                self.face_cost.add(spent, n / self.fps)
        if any(len(v) != n for v in made.values()):
            raise ValueError(f"a channel maker gave {[len(v) for v in made.values()]} rows for {n} frames")
        # the last check before any sink: a NaN or infinite value ends the stream (its client is told), never sent
        if bad := [name for name, v in (("root", pose.root_pos), ("rotations", pose.rotations), *made.items())
                   if not np.isfinite(v).all()]:
            raise NonFiniteFrames(f"frames {first}..{first + n - 1}: {', '.join(bad)} not finite (the stream stops "
                                  "before them)")
        return [Frame(first + i, (first + i) / self.fps, np.asarray(pose.root_pos[i]),
                      np.asarray(pose.rotations[i]), feats[i], {name: v[i] for name, v in made.items()})
                for i in range(n)]

    @classmethod
    def faces_begin(cls, sessions: list["Session"]) -> None:
        """Before a batch's bodies are stepped: the faces made in a face process (`streamer.face_process`) are sent
        their windows' audio, so that the child makes them while this thread steps the bodies (`frames_many` takes
        their rows). Sessions whose face is made here are left as they are."""
        groups: dict[int, list[Session]] = {}
        for s in sessions:
            s._face_where()
            if s.face_options is not None and s.face_process is not None and s._face_audio and s._face_token is None:
                groups.setdefault(id(s.face_process), []).append(s)
        for group in groups.values():
            try:
                token = group[0].face_process.begin([s._face_stream() for s in group],
                                                    [np.concatenate(s._face_audio) for s in group])
            except BaseException as e:  # noqa: BLE001 - each of these faces' failure, raised in its frames
                token = e
            for s in group:
                s._face_audio.clear()
                s._face_token = token

    @classmethod
    def frames_many(cls, sessions: list["Session"], outputs: list[np.ndarray]) -> list[list[Frame] | BaseException]:
        """`frames_of` of several sessions' outputs from one batch (a scheduler's): their faces made together
        (`FaceStream.push_many`: one product per layer of the listener for all of them; or taken from the face
        process, `faces_begin`), then each session's frames; a session's failure is its own entry (a failure of
        the faces' shared step, each face session's)."""
        failed: dict[int, BaseException] = {}
        for s in sessions:
            s._face_where()
        faces = [s for s in sessions if s.face_options is not None and s.face_process is None and s._face_audio]
        if faces:
            from dimgestor.face import FaceStream

            t = time.perf_counter()
            try:
                FaceStream.push_many([s._face_stream() for s in faces],
                                     [np.concatenate(s._face_audio) for s in faces])
            except BaseException as e:  # noqa: BLE001 - each face session's own failure
                failed.update({id(s): e for s in faces})
            for s in faces:
                s._face_audio.clear()
                s._face_paid += (time.perf_counter() - t) / len(faces)
        remote = [s for s in sessions if s.face_options is not None and s.face_process is not None]
        cls.faces_begin(remote)  # (any not begun with the batch: now)
        failed.update(_faces_taken([s for s in remote if s._face_token is not None]))
        out: list[list[Frame] | BaseException] = []
        for s, r in zip(sessions, outputs):
            if id(s) in failed:
                out.append(failed[id(s)])
                continue
            try:
                out.append(s.frames_of(r))
            except BaseException as e:  # noqa: BLE001
                out.append(e)
        return out

    def infer(self, samples: np.ndarray) -> list[Frame]:
        """One window's frames, inferred in the calling thread (what a scheduler runs for `submit_push`)."""
        self._hear(samples)
        return self.frames_of(self.stream.push(samples))

    def _hear(self, samples: np.ndarray) -> None:
        """Keep a call's audio for its face (`_face_rows` takes it); without a face, nothing is kept."""
        if self.face_options is not None:
            self._face_audio.append(samples)

    def infer_finish(self) -> list[Frame]:
        """The frames after the audio ended, in the calling thread (a scheduler's worker)."""
        self._finishing = True
        return self.frames_of(self.stream.finish())

    def set_smile(self, smile: float) -> None:
        """The expression held under the speech from the next frames on (0..1); no-op without a face."""
        self.face_options = self.face_options and dataclasses.replace(self.face_options, smile=float(smile))
        if self._face is not None:
            self._face.smile = float(smile)

    def _face_rows(self, n: int) -> np.ndarray:
        """The face of the stream's newest n frames, from the audio given since the last call (the call's own)."""
        self._face_stream()
        if self._face_token is not None and (failed := _faces_taken([self])):
            raise failed[id(self)]
        while self._face_audio:
            self._face.push(self._face_audio.popleft())
        if self._finishing and self._face.frames_ready < n:
            self._face.finish()
        return self._face.take(n)

    def _face_stream(self):
        """The session's `FaceStream` (in its face process: a `RemoteFace`), made on first use (at a restored
        session's position)."""
        if self._face is None:
            lookahead = np.floor(min(self.lookahead_s, 0.3) * 100 + 1e-6) / 100  # on the listener's 10 ms grid
            sample, frame = self._face_start
            self._face_where()
            if self.face_process is not None:
                self._face = self.face_process.face(self.fps, lookahead, self.face_options, sample, frame)
            else:
                from dimgestor.face import FaceStream

                self._face = FaceStream(self.fps, lookahead, self.face_options, start_sample=sample,
                                        start_frame=frame)
        return self._face

    def _face_where(self) -> None:
        """A face not made yet, whose face process has ended, is made in this process instead."""
        if self._face is None and self.face_process is not None and self.face_process.ended:
            self.face_process = None

    def snapshot(self, frames: int, state=None, **meta) -> bytes:
        """The session as bytes (`dimgestor.streaming.savestate`): the stream's state (default: its own now), the pose
        decoder's root and the `frames` made so far, with `meta` (e.g. the client's rate) beside them, sealed
        with `state_key`."""
        from dimgestor.streaming import savestate

        meta = {"frames": int(frames), "decoder": dataclasses.asdict(self.decoder.state), **meta}
        return savestate.dumps(self.stream, state, meta, key=self.state_key)

    def restore(self, data: bytes) -> dict:
        """Go on from `snapshot`'s bytes (taken by any worker on the same model and `state_key`); returns their meta.
        Raises `savestate.StateError` when they cannot be resumed exactly (the session is then unchanged): every
        field is checked first, the stream's (`savestate.loads`) and the meta's (`check_meta`)."""
        from dimgestor.features import RootState
        from dimgestor.streaming import savestate

        state, meta = savestate.loads(self.stream, data, key=self.state_key)
        check_meta(meta, state, self.decoder)
        root = meta["decoder"]
        self.stream.state = state
        # (as floats: an int past int64, which the checks take as a finite number, would make numpy's arrays objects)
        self.decoder.state = RootState(**{**root, **{k: float(root[k]) for k in ("x", "z", "heading")},
                                          "drift": tuple(map(float, root["drift"]))})
        if self._face is not None:
            self._face.close()
        self._face, self._face_start = None, (int(state.samples_in), int(self.stream.frames_out))  # listens afresh
        self.clock.audio_s = state.samples_in / SAMPLE_RATE
        return meta

    async def run(self, source: AsyncIterable[AudioChunk], emit: Callable[[list[Frame]], object]) -> int:
        """Stream `source` to the end, calling emit(frames) per call's frames; returns the frame count.

        emit may return an awaitable (a sink applying back pressure): the session waits for it.
        """
        buffer = _AudioBuffer(self.windows.buffer)
        reader = asyncio.create_task(self._read(source, buffer), name=f"{self.name}-reader")

        def waiting_s() -> float:  # received, not yet taken: this session's buffer and its source's queue
            return buffer.samples / SAMPLE_RATE + float(getattr(source, "waiting_s", 0.0))

        try:
            while chunks := await buffer.take(self.windows.window, self.windows.whole):
                await self._window(chunks, emit, waiting_s)
                if self.on_boundary is not None:
                    self.on_boundary()
            if self.handover:  # the state goes on elsewhere: no silence padded, no last frames
                return self.stream.frames_out
            self.stats.window = None  # the flush's frames wait for no audio
            self._inflight = finish = self.scheduler.submit_ranked(self.clock.rank(), self.infer_finish)
            frames = await asyncio.wrap_future(finish)
            await _emit(emit, frames)
            self.stats.frames += len(frames)
            self.stats.ended = True
            return self.stream.frames_out
        finally:
            # The face's listener's decoder goes back to the pool (a handed-over one's too), once no call of this
            # session is being inferred: a cancelled run leaves its call running on the inference thread, and a
            # decoder given back under it would be used by two threads (pocketsphinx then crashes the process).
            if self._inflight is None:
                self._close_face()
            else:
                self._inflight.add_done_callback(lambda _: self._close_face())
            if not reader.done():
                reader.cancel()
            await asyncio.gather(reader, return_exceptions=True)

    def _close_face(self) -> None:
        if self._face is not None:
            self._face.close()

    @staticmethod
    async def _read(source: AsyncIterable[AudioChunk], buffer: _AudioBuffer) -> None:
        try:
            async for chunk in source:
                await buffer.put(chunk)
            buffer.close()
        except BaseException as e:  # surfaces in the inference loop, cancellation included
            buffer.close(e if not isinstance(e, asyncio.CancelledError) else None)
            raise

    async def _window(self, chunks: list[AudioChunk], emit: Callable[[list[Frame]], object],
                      waiting_s: Callable[[], float] = lambda: 0.0) -> None:
        """One due window: its calls in turn, each call's frames emitted as they come, each ranked by
        `AudioClock` with what waits behind it."""
        samples = np.concatenate([c.samples for c in chunks])
        self.stats.window = WindowTiming(chunks[-1].t_end, chunks[-1].arrival, time.monotonic())
        infer_s, n = 0.0, 0
        calls = self.windows.calls(samples)
        for k, call in enumerate(calls):
            t0 = time.perf_counter()
            later = sum(len(c) for c in calls[k + 1:]) / SAMPLE_RATE
            rank = self.clock.rank(len(call) / SAMPLE_RATE, later + waiting_s())
            self._hear(call)  # (the worker's frames_of takes it: calls of a session never overlap)
            self._inflight = self.scheduler.submit_push(self, call, rank)
            frames = await asyncio.wrap_future(self._inflight)
            self.clock.audio_s += len(call) / SAMPLE_RATE
            infer_s += time.perf_counter() - t0
            n += len(frames)
            await _emit(emit, frames)
        latency_s = time.monotonic() - chunks[-1].arrival
        self.stats.update(len(samples) / SAMPLE_RATE, infer_s, latency_s, n)
        if self.on_window is not None:
            self.on_window(latency_s)


async def _emit(emit: Callable[[list[Frame]], object], frames: list[Frame]) -> None:
    if inspect.isawaitable(r := emit(frames)):
        await r


def _faces_taken(sessions: list[Session]) -> dict[int, BaseException]:
    """The answers of the sessions' begun face exchanges (`Session.faces_begin`), each face's rows queued on it
    and its share of the child's time paid -> {id(session): the exception that failed its face}."""
    failed: dict[int, BaseException] = {}
    groups: dict[int, list[Session]] = {}
    for s in sessions:  # (a token: an exchange's number, or the exception that kept it from being sent)
        token = s._face_token
        groups.setdefault(token if isinstance(token, int) else id(token), []).append(s)
    for group in groups.values():
        token = group[0]._face_token
        for s in group:
            s._face_token = None
        try:
            if isinstance(token, BaseException):
                raise token
            answer, cpu_s = group[0].face_process.wait(token)
        except BaseException as e:  # noqa: BLE001 - each of these faces' failure
            failed.update({id(s): e for s in group})
            continue
        for s in group:
            s._face_paid += cpu_s / len(group)
            try:
                s._face.receive(answer)
            except BaseException as e:  # noqa: BLE001
                failed[id(s)] = e
    return failed


def reach(skeleton) -> float:
    """The farthest the root may move in one frame, in file units: the skeleton's total bone length (more than
    its height; 20 of them a second is beyond any motion, and a number no overflow comes near)."""
    return float(np.linalg.norm(skeleton.offsets, axis=1).sum()) or 1.0


def check_meta(meta: dict, state, decoder=None) -> None:
    """`Session.snapshot`'s meta beside a checked stream `state`: StateError, naming the field, unless it is what a
    session saves (frames made, the pose decoder's root, the client's rate, encoding and resampler). With the
    session's `decoder` (a `PoseDecoder`), its root must also lie where its frames could have taken it (`reach`)."""
    from dimgestor.features import RootState

    def refuse(field: str, why: str):
        raise StateError(f"saved session state: meta.{field} {why}")

    if meta.get("frames") != state.frames_out or not is_int(meta["frames"]):
        refuse("frames", f"is {show(meta.get('frames'))}, the state made {state.frames_out}")
    root = meta.get("decoder")
    names = [f.name for f in dataclasses.fields(RootState)]
    if not isinstance(root, dict) or set(root) != set(names):
        refuse("decoder", f"is not an object of {names}")
    if not all(finite_number(root[k]) for k in ("x", "z", "heading")):
        refuse("decoder", "x, z and heading are finite numbers")
    if not isinstance(root["drift"], list) or len(root["drift"]) != 3 or not all(map(finite_number, root["drift"])):
        refuse("decoder.drift", "is 3 finite numbers")
    if not is_int(root["frames"]) or not 0 <= root["frames"] <= state.frames_out:
        refuse("decoder.frames", f"is {show(root['frames'])}, not 0..{state.frames_out}")
    if decoder is not None:
        step, frames, start = reach(decoder.skeleton), state.frames_out + 1, decoder.anchor
        for k, most in (("x", frames * step), ("z", frames * step), ("heading", frames * math.pi)):
            if abs(float(root[k]) - getattr(start, k)) > most:
                refuse(f"decoder.{k}", f"is {show(root[k])}: {frames - 1} frames move it {most:.4g} at most")
        if not all(abs(float(v)) <= most for v, most in zip(root["drift"], (step, step, math.pi))):
            refuse("decoder.drift", f"is {show(root['drift'])}, beyond a frame's largest step ({step:.4g}, "
                   f"{step:.4g}, pi)")
    if meta.get("encoding", "json") not in ("json", "binary"):
        refuse("encoding", "is json or binary")
    rate = meta.get("rate", SAMPLE_RATE)
    if not is_int(rate) or not MIN_RATE <= rate <= MAX_RATE:
        refuse("rate", f"is {show(rate)}, not an integer in {MIN_RATE}..{MAX_RATE}")
    if meta.get("resampler") is not None:
        try:
            make_resampler(rate).check_state(meta["resampler"])
        except ValueError as e:
            refuse("resampler", f"does not fit: {e}")
        if meta["resampler"]["m_out"] != state.samples_in:
            refuse("resampler", f"gave {meta['resampler']['m_out']} samples, the state took {state.samples_in}")
