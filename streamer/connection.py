"""One WebSocket connection: the I/O around its session machine (`streamer.client_session`).

It reads the socket, carries out the machine's actions (queue this, decode and resample in the worker thread,
start the session's task, save, take a state) and turns what they do into the machine's next events; its
outgoing queue is an `Outbox` (streamer/outbox.py).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections import deque
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Awaitable, Callable

import numpy as np
from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from dimgestor.audio import SAMPLE_RATE
from streamer import client_session as S
from streamer import protocol as P
from streamer.frames import Frame
from streamer.intake import Account, ComputeBudget, submit_for
from streamer.log_limit import ErrorLog
from streamer.metrics import ServerMetrics
from streamer.outbox import FrameTotals, MessageBudget, Outbox
from streamer.saving import ConnectionSaves, StoreCalls
from streamer.sessions import AudioClock, Session
from streamer.sources import PushSource, make_resampler


@dataclass
class Services:
    """What a connection's session uses of its server's."""

    prep: Executor  # the worker thread (a `streamer.intake.FairWorker`): decode, resample, encode (never a store call)
    metrics: ServerMetrics
    make_session: Callable[..., Session] | None  # keyword arguments: Session's own (clock, face=None, ...)
    store: object | None  # a `streamer.handover` store
    store_call: Callable[..., Awaitable]  # await store_call("put", token, data): the store's method on the store's
    #                                       own thread, within a deadline (raises `streamer.store_link.StoreError`)
    max_backlog_s: float
    audio_recent: deque[bytes]  # the server source's recent audio (for a client that asks for it late)
    departures: ErrorLog
    session_ended: Callable[[], None]  # (the server gives freed memory back)
    pose: Callable[[list[Frame]], list[Frame]] | None = None  # frames onto the rig clients get (serve --target)
    skeleton: object | None = None  # the model's skeleton (a client's own rig is fitted to it; None: refused)


class ReadPace:
    """How fast a client's socket is read: its message budget and its share of the worker thread (`account`: its
    work there). Over its share, `over()` is called (the machine says `slow_down`), and `within()` once the share
    has refilled (`resume`)."""

    def __init__(self, over: Callable[[], None], within: Callable[[], None]):
        self.budget = MessageBudget()
        self.account = Account()
        self.compute = ComputeBudget(self.account)
        self.watch: asyncio.Task | None = None  # waits until it is within its share again
        self._over, self._within = over, within

    def wait_s(self, message: str | bytes) -> float:
        """Seconds to wait before reading its next message (after this one)."""
        wait = max(self.budget.wait_s(message), self.compute.wait_s(time.monotonic()))
        if self.compute.over:
            self._over()
            if self.watch is None or self.watch.done():
                self.watch = asyncio.create_task(self._until_within(), name="ws-share")
        return wait

    async def _until_within(self) -> None:
        while (wait := self.compute.refilled_in(time.monotonic())) > 0:
            await asyncio.sleep(wait)
        self._within()


class Client(Outbox, ConnectionSaves):
    """One connection: its session machine, its outgoing queue and counters, and its own audio session if any."""

    def __init__(self, ws: ServerConnection, machine: S.ClientSession, keepalive: S.Keepalive, svc: Services,
                 max_queue: int, totals: FrameTotals | None = None):
        super().__init__(ws, max_queue, totals)
        self.machine, self.keepalive, self.svc = machine, keepalive, svc
        self.source: PushSource | None = None  # its streaming session's audio queue (None: not streaming)
        self.resample_from: int | None = None  # its session's audio rate when not 16 kHz
        self.resampler = None  # lives in the worker (built, used and flushed there)
        self.session: Session | None = None
        self.session_task: asyncio.Task | None = None
        self.frames_queued = 0  # its session's frames in its queue (or sent): a session cut short ends at this
        self.holding = False  # its handler holds a message (the socket is not read meanwhile: back pressure)
        self.closed = False  # the server closed it (an unsupported protocol)
        peer = ws.remote_address
        self.who = f"{peer[0]}:{peer[1]}" if peer else "?"
        self.store = StoreCalls(svc.store_call, svc.metrics, svc.departures, self.who)
        self.errors = ErrorLog(f"client {self.who}")
        self.pace = ReadPace(lambda: self.act(self.machine.handle(S.OverShare())), lambda: self.act(
            self.machine.handle(S.WithinShare(self.source.backlog_s if self.source is not None else 0.0))))
        self.clock = AudioClock()  # shared by its sessions: how far its audio is ahead of real time
        self.pose = None  # its own rig's `streamer.pose.TargetPose` (revision 8 `hello.rig`), None: the server's

    @property
    def encoding(self) -> str:
        return self.machine.encoding

    @property
    def source_audio(self) -> bool:
        return self.machine.source_audio

    @property
    def own(self) -> bool:
        return self.machine.own

    def encode(self, frames: list[Frame], send: S.SendFrames) -> list[str | bytes]:  # worker thread
        """The frames as `send` (the machine's `SendFrames`) says: its encoding and its channels."""
        pose = self.pose or self.svc.pose
        if pose is not None:
            frames = pose(frames)
        return P.encode_frames(frames, send.encoding, send.channels)

    async def read_loop(self) -> None:
        try:
            async for message in self.ws:
                self.keepalive.heard(time.monotonic())
                self.holding = True
                try:
                    if isinstance(message, bytes):
                        await self.on_audio(message)
                    else:  # (a long one, a rig, is parsed on the worker thread: its sender's work, in its turn)
                        parsed = (await self._work(P.parse_text_or_error, message)
                                  if len(message) > P.PARSE_ASIDE_BYTES else None)
                        await self.apply(self.machine.handle(S.Text(message, time.monotonic(), parsed)))
                    if self.closed:
                        break
                except (ConnectionClosed, asyncio.CancelledError):
                    raise
                except Exception as e:  # a bug or a model failure on this client's input: report, keep serving
                    self.errors(logging.ERROR, f"failed on a message: {type(e).__name__}: {e}", exc_info=True)
                    self.note(P.error("internal", f"{type(e).__name__}: {e}"))
                await asyncio.sleep(self.pace.wait_s(message))  # a flood is read only as fast as its budgets
                self.holding = False
        except ConnectionClosed:
            pass

    async def leave(self, tasks: list[asyncio.Future]) -> float | None:
        """The client is gone: cancel everything it has in flight (whatever it waits on), free its slot, its
        queue and its audio now. Returns the seconds of audio queued if a session was cut short, else None."""
        session = self.session_task
        running = session is not None and not session.done()
        backlog_s = self.source.backlog_s if self.source is not None else 0.0
        self.act(self.machine.handle(S.Left()))  # (frees its seat; StopSession)
        pending = [*tasks, *([session] if session is not None else []),
                   *([self.pace.watch] if self.pace.watch is not None else [])]
        for t in pending:
            t.cancel()
        self.queue.clear()
        self.room.set()
        if self.source is not None:
            self.source.chunks.clear()
            self.source.queued = 0
            await self.source.close()
        await asyncio.gather(*pending, return_exceptions=True)
        self.source = self.session = self.session_task = self.resampler = None
        return backlog_s if running else None

    # ---- the session machine's actions: carried out here (`_carry_out`), nowhere else ----

    def act(self, actions: list) -> list:
        """Carry out the actions that take no waiting; returns the others, in order (where nothing can wait:
        the caller's own, Decode, Feed, WaitForSession, SendFrames, and the waiting ones, which `apply` does)."""
        rest = []
        for a in actions:
            rest += self._carry_out(a, can_wait=False)
        return rest

    async def apply(self, actions: list) -> list:
        """Carry out the actions, waiting where they wait; returns those only the caller can (Decode, Feed,
        WaitForSession, SendFrames)."""
        rest = []
        for a in actions:
            done = self._carry_out(a, can_wait=True)
            rest += await done if asyncio.iscoroutine(done) else done
        return rest

    def _carry_out(self, a, can_wait: bool):
        """One action: [] once done, [a] where it is the caller's, or (can_wait) the coroutine that does it and
        returns the caller's actions that follow."""
        match a:
            case S.Send():
                self.put(a.message, a.kind)
            case S.Log():
                self.errors(a.level, a.text)
            case S.Count():
                getattr(self.svc.metrics, a.name).inc()
            case S.Refused():
                self.svc.metrics.refused(a.reason)
            case S.Charge():
                self.pace.budget.tokens -= a.tokens
            case S.ReplaySourceAudio():
                for m in self.svc.audio_recent:  # the audio of the frames still to come to a client that joins now
                    self.put(m, "audio")
            case S.SetSmile():
                if self.session is not None:
                    self.session.set_smile(a.smile)
            case S.TakeSeat() | S.FreeSeat():
                self.machine.seats.carry_out(a)
            case S.StopSession():
                if self.session_task is not None:
                    self.session_task.cancel()
            case S.SetRig() if can_wait:
                return self._fit_rig(a.rig)
            case S.SaveState():
                self._save(a)
            case S.Forget():
                self.store.later("forget", a.token)
            case S.Release():
                self.store.later("release", a.token)
            case S.StartSession() if can_wait:
                return self._start(a)
            case S.EndAudio() if can_wait:
                return self._end_audio()
            case S.TakeState() if can_wait:
                return self._take_state(a.token)
            case S.Close() if can_wait:
                return self._close(a)
            case _:
                return [a]
        return []

    async def _start(self, start: S.StartSession) -> list:
        self._start_session(start)
        if start.restore is not None:
            await self._restore(start.restore)
        return []

    async def _close(self, close: S.Close) -> list:
        await self.drained(asyncio.get_running_loop().time() + close.drain_s)
        await self.ws.close(close.code, close.reason)
        self.closed = True
        return []

    async def _fit_rig(self, rig: dict | None) -> list:
        """The client's rig fitted to the model's skeleton (on the worker thread, as its work: tens of ms) ->
        RigSet, or RigRefused saying why."""
        if rig is None:
            self.pose = None
            return self.act(self.machine.handle(S.RigSet(0)))
        if self.svc.skeleton is None:
            return self.act(self.machine.handle(S.RigRefused("this server does not fit frames to a client's rig")))
        pose = await self._work(_fitted, self.svc.skeleton, rig)
        if isinstance(pose, str):
            return self.act(self.machine.handle(S.RigRefused(pose)))
        self.pose = pose
        return self.act(self.machine.handle(S.RigSet(pose.rig.num_joints, pose.humanoid())))

    async def on_audio(self, data: bytes) -> None:
        machine = self.machine
        decode = await self.apply(machine.handle(S.Audio(data)))
        if not decode:  # refused or ignored
            return
        try:
            x = await self._work(P.decode_audio, data, decode[0].fmt)
        except P.ProtocolError as e:  # bad_audio
            self.act(machine.handle(S.Failed(e)))
            return
        self.pace.account.audio_s += len(x) / decode[0].fmt.rate  # (its share follows what its audio costs here)
        # the previous session is still finishing (or has just failed, its end not yet told to the machine)
        while (then := await self.apply(machine.handle(S.Decoded()))) == [S.WaitForSession()] or (
                then and self.source is None):
            held = self.clock.now()
            await asyncio.wait([self.session_task])
            await asyncio.sleep(0)  # (its done callbacks run first: its `end` and what waited for it)
            self.clock.held(self.clock.now() - held)  # (a client with audio waiting is ahead, not late)
        if not then:
            return
        source, piece, rate = self.source, then[-1].piece, decode[0].fmt.rate
        for a in range(0, len(x), piece):
            y = x[a : a + piece] if self.resample_from is None else await self._work(self._resample, x[a : a + piece])
            self.act(machine.handle(S.Queuing(source.backlog_s, source.full)))
            await source.put(y, more_s=max(0, len(x) - a - piece) / rate)
            if self.source is not source:  # the session failed meanwhile
                return

    def _start_session(self, start: S.StartSession) -> None:
        self.source = source = PushSource(self.svc.max_backlog_s)
        self.resampler, self.resample_from = None, start.rate if start.resample else None
        machine = self.machine
        boundary = (lambda: self.act(machine.handle(S.Boundary(start.session_id, session.stream.state.samples_in)))
                    if start.save_token is not None else None)
        no_face = {} if start.face else {"face": None}  # the client asked for none: its session makes none (nor pays)
        self.session = session = self.svc.make_session(clock=self.clock, on_window=self.svc.metrics.window_done,
                                                       on_boundary=boundary, speaker=start.speaker, **no_face)
        self.frames_queued = 0
        if start.smile is not None:  # the client's own expression (its hello's `smile`)
            session.set_smile(start.smile)

        async def emit(frames: list[Frame]) -> None:
            for a in self.act(machine.handle(S.Frames(len(frames), source.backlog_s, session.stats.window))):
                messages = await self._work(self.encode, frames, a)
                if a.window is not None:
                    messages.append(P.timing(frames[0].index, len(frames), a.window, time.monotonic()))
                if a.layout is not None:  # after the encoding: no frame of the old layout follows it
                    self.put(a.layout)
                await self.put_own(messages)
                self.frames_queued += len(frames)

        async def run() -> S.SessionEnded:
            try:
                frames = await session.run(source, emit)
                if not session.handover:
                    # a save under way is answered before `end` (its `session_saved`, or its refusal counted and
                    # said), so the `Forget` at the end follows it; within the save's deadline (store_link.py)
                    await self.store.periodic_done()
                return S.SessionEnded(frames, handed_over=session.handover)
            except asyncio.CancelledError:
                raise
            except Exception as e:  # the model failed on this audio: the client is told, the server stays up
                self.errors(logging.ERROR, f"session failed: {type(e).__name__}: {e}", exc_info=True)
                if self.source is source:
                    self.source = None
                await source.close()
                return S.SessionEnded(handed_over=session.handover, error=f"{type(e).__name__}: {e}")

        def done(task: asyncio.Task) -> None:
            self.svc.session_ended()  # its queued audio is free: give the pages back (streamer/memory.py)
            ended = S.SessionEnded(cancelled=True) if task.cancelled() else task.result()
            self.act(machine.handle(dataclasses.replace(ended, session_id=start.session_id)))

        self.session_task = asyncio.create_task(run(), name="ws-session")
        self.session_task.add_done_callback(done)

    async def _end_audio(self) -> list:
        """The session's audio ended: it sends its last frames and `end` by itself."""
        if self.source is not None:
            source, self.source = self.source, None
            if self.resampler is not None:
                resampler, self.resampler = self.resampler, None
                tail = await self._work(resampler.flush)
                await source.put(np.asarray(tail, dtype=np.float32))
            await source.close()
        return []

    def _work(self, fn, *args) -> asyncio.Future:
        """fn(*args) on the worker thread, as this client's work (its turn and its share: `streamer.intake`)."""
        return asyncio.wrap_future(submit_for(self.svc.prep, self.pace.account, fn, *args))

    def lag(self) -> tuple[float, float, float] | None:
        """(time.monotonic() of its audio's start, seconds of it received, seconds of them not yet inferred), or
        None without a session fed by its audio (`streamer.health.behind`)."""
        source, session = self.source, self.session
        if source is None or session is None or source.first_at is None:
            return None
        received = source.samples_in / SAMPLE_RATE
        return source.first_at, received, max(0.0, received - session.stats.audio_s)

    def _resample(self, x: np.ndarray) -> np.ndarray:  # worker thread
        if self.resample_from is None:
            return x
        if self.resampler is None:
            self.resampler = make_resampler(self.resample_from)
        return self.resampler.process(x)


def _fitted(skeleton, rig: dict):  # worker thread
    """A `streamer.pose.TargetPose` of `rig` on `skeleton`, or why it cannot be one."""
    from dimgestor.retarget import RigError
    from dimgestor.retarget.names import MapError
    from streamer.pose import TargetPose

    try:
        return TargetPose.from_message(skeleton, rig)
    except (RigError, MapError) as e:
        return str(e)


async def keepalive_loop(client: Client, interval: float) -> None:
    """Ping every `interval`; close (1011) a client not heard from for the keepalive's interval + timeout,
    counted as `Keepalive` says (a long wait for inference under load is the server's doing, not the
    client's: 11 of 31 fast senders were closed in one 60 s flood when frames made were counted, not read)."""
    pong: asyncio.Future | None = None

    def answered(f: asyncio.Future) -> None:
        if not f.cancelled() and f.exception() is None:
            client.keepalive.heard(time.monotonic())

    while True:
        await asyncio.sleep(interval)
        now = time.monotonic()
        close = client.keepalive.tick(now, client.holding, client.frames_sent, client.awaits_reading)
        if close is not None:
            client.errors(logging.WARNING, f"nothing heard for {client.keepalive.silent_s(now):.1f} s (keepalive): "
                                           f"closing ({'holding its audio, ' if client.holding else ''}"
                                           f"{client.frames_sent} frames sent, {len(client.queue)} queued)")
            await client.ws.close(close.code, close.reason)
            return
        if pong is None or pong.done():
            try:
                pong = await client.ws.ping()
            except ConnectionClosed:
                return
            pong.add_done_callback(answered)
