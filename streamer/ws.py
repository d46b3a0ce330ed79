"""WebSocket server for protocol v1 (docs/protocol.md): broadcast frames, per-client audio sessions.

The I/O shell around each client's session machine (`streamer.client_session`): it turns the socket, the worker
thread and the session's task into events and carries out the actions. Every client has one bounded outgoing
queue and one sender task (`streamer.connection`); the HTTP side of the port is `streamer.handshake`'s.

Nothing a client sends costs the event loop more than constant work: audio is decoded, resampled and its
frames encoded in a worker thread, in pieces, one job per client at a time, the client that has used the thread
least first (fair shares in compute: `streamer.intake`; one over its share is read more slowly and told
`slow_down`), and inference runs in the sessions' scheduler. A client's session lives
exactly as long as its connection: the connection closing cancels whatever its handler is blocked on, frees
its slot and its queued audio at once and logs one (rate-limited) line. The keepalive is the server's own
(`Keepalive`): while the server holds a client's data unread on purpose (its backlog is full), its pongs cannot
be read either, so that time counts against it only when nothing moves at all.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from websockets.asyncio.server import ServerConnection, serve

from streamer import client_session as S
from streamer import protocol as P
from streamer import request_checks as RC
from streamer.connection import Client, FrameTotals, Services, keepalive_loop
from streamer.frames import Frame
from streamer.handshake import Front, own_origins, refusal
from streamer.intake import FairWorker
from streamer.log_limit import ErrorLog
from streamer.memory import Trimmer
from streamer.metrics import ServerMetrics
from streamer.options import MAX_SESSIONS, PING_INTERVAL_S, PING_TIMEOUT_S
from streamer.sessions import Session
from streamer.saving import ServerStore
from streamer.viewer import ViewerFiles
from streamer.waiting import WaitingRoom

__all__ = ["Attached", "WsConfig", "WsServer", "own_origins"]

AUDIO_BATCH_S = 0.1   # source audio per DGA1 message: few messages, well ahead of the frames it goes with
AUDIO_RECENT_S = 3.0  # source audio replayed to a client that asks late: covers lookahead, window and latency
HANDOVER_S = 5.0  # on SIGTERM with a state store: how long sessions may take to finish the audio held and be saved


@dataclass(frozen=True)
class WsConfig:
    """How the WebSocket server listens and what it allows: the `serve` options that concern it, fixed at start.

    also: more (host, port) addresses serving the same (the deprecated --http). token: required as ?token=...
    when set. origins: the `Origin` headers accepted at the handshake besides none at all (native clients send
    none; browsers always send one) and the server's own (its viewer's pages); "*" accepts any. ping_interval,
    ping_timeout: the keepalive (seconds; None: none): a client from which nothing was heard for their sum, while
    the server was reading it or while nothing moved, is closed (1011). max_waiting, request_timeout_s:
    connections that have not sent a whole request (`WaitingRoom`). serve_metrics: answer `/metrics` (`/healthz`
    and `/readyz` always are: `streamer.health`). save_every_s: periodic saves of the sessions (with a store).
    face: the name set of the face the server's frames carry unless a client asks another (`ServeFace.names`; the
    hello says it), None: the server makes no face.
    """

    host: str = "127.0.0.1"
    port: int = 8765
    also: tuple[tuple[str, int], ...] = ()
    token: str | None = None
    origins: tuple[str, ...] = ()
    max_sessions: int = MAX_SESSIONS
    max_queue: int = 64  # a client's outgoing messages
    max_backlog_s: float = 30.0  # a session's audio queue
    status_every: float = 1.0
    ping_interval: float | None = PING_INTERVAL_S
    ping_timeout: float = PING_TIMEOUT_S
    max_waiting: int = 64
    request_timeout_s: float = 10.0
    serve_metrics: bool = True
    save_every_s: float | None = None
    face: str | None = None


@dataclass(frozen=True)
class Attached:
    """What the server is given beside its sessions.

    files: the web viewer's files on the same port (None: none). metrics: the worker's `ServerMetrics` (None:
    a registry of its own). store: a `streamer.handover` store: sessions are handed over when the server stops,
    and saved periodically. pose: frames -> frames on the hello's skeleton (a `streamer.pose.TargetPose`; None:
    as made). skeleton: the model's (clients' own rigs are fitted to it; None: they are refused).
    broadcast_stats: the `Stats` of the server's own source, if any. source_dropped_s: () -> seconds of live
    input dropped, if a live source.
    """

    files: ViewerFiles | None = field(default_factory=ViewerFiles)
    metrics: ServerMetrics | None = None
    store: object | None = None
    pose: object | None = None
    skeleton: object | None = None
    broadcast_stats: object | None = None
    source_dropped_s: Callable[[], float] | None = None
    admission: object | None = None  # a `streamer.capacity.Admission` (None: sessions limited by the seats alone)


def seat_terms(config: WsConfig, hello: dict, accepts_audio: bool, resumable: bool) -> S.Terms:
    """The terms every client's session is served on (`client_session.Terms`), from the config and the hello
    (what it offers and its skeleton)."""
    speakers = hello.get("speakers") or {}  # (revision 9: a model with a speaker condition)
    return S.Terms(config.max_sessions, accepts_audio=accepts_audio, offers_source_audio="source_audio" in hello,
                   max_backlog_s=config.max_backlog_s, resumable=resumable,
                   save_every_s=config.save_every_s if resumable else None,
                   face=config.face,
                   joints=len(hello.get("skeleton", {}).get("joints", ())),
                   speakers=tuple(speakers.get("names", ())), speaker=speakers.get("default"),
                   speaker_fixed=not speakers.get("choice", True))


class WsServer:
    """Serves hello/frames/status to clients; a `Sink` (streamer/sink.py) of the server's source. A request
    that is not a WebSocket upgrade gets a file of the web viewer (`attached.files`) on the same port.
    `make_session(**settings)` makes a client's own audio session, `settings` being `Session`'s own keyword
    arguments (its clock, on_window, on_boundary, face=None for a client that asked for no face); None: clients'
    audio is refused (--no-client-audio)."""

    def __init__(self, config: WsConfig, hello: dict, make_session: Callable[..., Session] | None,
                 attached: Attached = Attached()):
        if config.face is not None:  # (the hello says what the config says)
            hello = {**hello, "face": P.face_hello(config.face)}
        self.config, self.hello, self.make_session, self.attached = config, hello, make_session, attached
        self.addresses = [(config.host, config.port), *config.also]  # (the real ports once open)
        self.port = config.port
        self.origins = {o for o in map(RC.allowed_origin, config.origins) if o is not None}
        self.waiting_room = WaitingRoom(config.max_waiting, config.request_timeout_s)
        self.store = attached.store
        self.broadcast_stats = attached.broadcast_stats  # (settable: a source attached later, e.g. a pipecat stage)
        self.departures = ErrorLog("sessions", what="departures")
        self.stored = ServerStore(self.store, self.departures) if self.store is not None else None
        self.seats = S.Seats(seat_terms(config, hello, make_session is not None, self.store is not None),
                             attached.admission)
        self.trimmer = Trimmer()
        self._trim_timer: asyncio.TimerHandle | None = None
        self.metrics = attached.metrics if attached.metrics is not None else ServerMetrics()
        self.front = Front(self.waiting_room, self.metrics, config.serve_metrics, attached.files, self.refusal)
        self.clients: set[Client] = set()
        self.broadcast_ended = False
        self.broadcast_frames = 0
        self.prep = FairWorker("ws-prep")  # decode, resample, encode: each client's work in its fair turn
        self.audio_pending: list[tuple[float, np.ndarray]] = []  # source audio not yet sent (< AUDIO_BATCH_S)
        self.audio_recent: deque[bytes] = deque(maxlen=int(AUDIO_RECENT_S / AUDIO_BATCH_S))  # for late joiners
        self._servers: list = []
        self._status_task: asyncio.Task | None = None
        self._lease_task: asyncio.Task | None = None
        self.totals = FrameTotals()
        self.metrics.streams.append(lambda: self.live_sessions)
        self.metrics.clients = lambda: len(self.clients)
        self.metrics.sinks["ws"] = lambda: (self.totals.sent, self.totals.dropped)
        self.metrics.queues["dimgestor_client_queue_messages"] = lambda: sum(len(c.queue) for c in self.clients)
        self.metrics.queues["dimgestor_audio_backlog_seconds"] = lambda: sum(
            c.source.backlog_s for c in self.clients if c.source is not None)
        self.metrics.readiness.lags = lambda: [c.lag() for c in self.clients]
        if self.stored is not None:
            self.metrics.store = self.metrics.readiness.store = self.stored.link

    @property
    def closing(self) -> bool:
        return self.seats.closing

    @closing.setter
    def closing(self, value: bool) -> None:
        self.seats.closing = value

    # ---- lifecycle -------------------------------------------------------------------------------

    async def open(self) -> None:
        try:
            for host, port in self.addresses:
                self._servers.append(await serve(
                    self._handle, host, port, process_request=self.front.process_request,
                    create_connection=self.waiting_room.connection,
                    open_timeout=2 * self.waiting_room.timeout_s,  # reading the request, then sending the answer
                    max_size=P.HARD_MAX_BYTES, max_queue=4, close_timeout=0.5,
                    ping_interval=None,  # our own keepalive (connection.keepalive_loop): knows back pressure
                    compression=None))  # no deflate: CPU per frame per client, and a bomb risk
        except OSError as e:
            for server in self._servers:
                server.close()
            where = " or ".join(f"{_url_host(h)}:{p}" for h, p in self.addresses)
            raise OSError(f"cannot listen on {where}: {e.strerror or e}") from None
        # the real ports when 0 was asked; the viewer's pages are the server's own origins
        self.addresses = [(host, s.sockets[0].getsockname()[1]) for (host, _), s in zip(self.addresses, self._servers)]
        self.port = self.addresses[0][1]
        if "*" not in self.origins:
            self.origins |= {o for host, port in self.addresses for o in own_origins(host, port)}
        self._status_task = asyncio.create_task(self._status_loop(), name="ws-status")
        if self.seats.terms.save_every_s is not None:
            self._lease_task = asyncio.create_task(self.stored.keep_leases(lambda: self.clients), name="ws-leases")

    @property
    def url(self) -> str:
        return f"ws://{_url_host(self.config.host)}:{self.port}/"

    @property
    def viewer_urls(self) -> list[str]:
        """Where a browser finds the viewer (one per address), if it is served."""
        return [f"http://{_url_host(host)}:{port}/" for host, port in self.addresses] if self.attached.files else []

    @property
    def live_sessions(self) -> int:
        """Client sessions still running, including those flushing after `audio_end`."""
        return self.seats.taken

    def describe(self) -> str:
        hint = "?token=..." if self.config.token else ""
        lines = [f"WebSocket  {self.url}{hint}  (protocol v1, docs/protocol.md)"]
        lines += [f"web viewer {url}{'  (open it as ...?token=YOUR_TOKEN)' if self.config.token else ''}"
                  for url in self.viewer_urls]
        return "\n".join(lines)

    def status(self) -> str:
        return (f"clients {len(self.clients)} | dropped {sum(c.dropped for c in self.clients)} | "
                f"own sessions {sum(1 for c in self.clients if c.session is not None)}")

    def refusal(self, target: str, origins: list[str], version: str = "HTTP/1.1") -> tuple[object, str]:
        """The handshake's checks (`streamer.handshake.refusal`) with this server's allow-list and token."""
        return refusal(target, origins, version, self.origins, self.config.token)

    async def close(self, drain: bool = True, within_s: float = 1.5) -> None:
        """End every client's stream, deliver what is queued and close, all within ~within_s (whether the source
        ended or was stopped: `drain` makes no difference here). A session whose audio has all come (after its
        `audio_end`) finishes as usual, its last frames and `end`, if it can within 0.4 within_s (HANDOVER_S
        with a state store); with a store the others are handed over (`goaway`, `ServerStore.hand_over`), without
        one they get `end` at once."""
        self._flush_audio()  # the source's last audio before its `end`
        loop = asyncio.get_running_loop()
        self.closing = self.metrics.readiness.draining = True
        if self._trim_timer is not None:
            self._trim_timer.cancel()
        # (a session that ends meanwhile clears its client's session_task: keep the tasks as they are now)
        own = {c: c.session_task for c in self.clients if c.session_task is not None and not c.session_task.done()}
        finishing = {c: task for c, task in own.items() if c.source is None}  # past audio_end: nothing to move
        moving = {c: task for c, task in own.items() if c not in finishing}
        until = loop.time() + (HANDOVER_S if self.store else within_s * 0.4)
        if self.stored is not None:
            self.stored.drain_until = until  # no store call outlives the hand-over's bound
        handed = await self.stored.hand_over(moving, until) if self.store and moving else set()
        if finishing:
            await asyncio.wait(finishing.values(), timeout=max(0.0, until - loop.time()))
        for c, task in own.items():
            if c not in handed:
                task.cancel()  # (a finished one stays as it is)
        await asyncio.gather(*own.values(), return_exceptions=True)
        ended = {c for c, task in finishing.items() if not task.cancelled() and task.exception() is None}
        for c in list(self.clients):
            if c in handed or c in ended:  # (goaway sent; or its own `end`, after its last frames)
                continue
            # (a session cut short: the frames it queued, not those it counted: a window's frames may have been
            # encoding when it was cancelled, and they never come)
            if c in own and self.store is not None and c in moving:  # told why; it goes on elsewhere, afresh
                c.put(P.goaway_unsaved(c.frames_queued, self.stored.unsaved.get(
                    c, "the session did not finish the audio held within the hand-over's bound")))
            elif c in own:
                c.put(P.end(c.frames_queued))
            elif not c.own and not self.broadcast_ended:
                c.put(P.end(self.broadcast_frames))
        self.broadcast_ended = True  # (no status after that `end` while the queues drain: seen under load)
        deadline = loop.time() + within_s * 0.6
        await asyncio.gather(*(c.drained(deadline) for c in list(self.clients)))
        await asyncio.gather(*(c.ws.close(1012, "restart: resume_session with the goaway's token") for c in handed),
                             return_exceptions=True)
        if self._status_task:
            self._status_task.cancel()
        if self._lease_task:  # (the sessions are gone: their leases run out by themselves)
            self._lease_task.cancel()
        if self._servers:
            for server in self._servers:
                server.close()  # closing handshakes (1001 going away), each given close_timeout
            try:
                await asyncio.wait_for(asyncio.gather(*(s.wait_closed() for s in self._servers)),
                                       max(0.1, within_s * 0.4))
            except asyncio.TimeoutError:
                for c in list(self.clients):
                    c.ws.transport.abort()
        self.prep.shutdown(wait=False, cancel_futures=True)
        if self.stored is not None:
            self.stored.link.close()

    # ---- broadcast (the server's own source) -----------------------------------------------------

    def send(self, frames: list[Frame]) -> None:
        """The server source's frames, to every client that follows it (never awaits a client)."""
        if not frames:
            return
        self.broadcast_frames += len(frames)
        encoded: dict[tuple, list] = {}  # (encoding, channels) -> messages: each form encoded once
        stats = self.broadcast_stats
        window = stats.window if stats is not None else None
        timing = None
        for c in list(self.clients):
            for a in c.act(c.machine.handle(S.Broadcast(len(frames), window))):
                key = (a.encoding, tuple(a.channels.values()), id(c.pose))  # (a client's own rig: its own form)
                if key not in encoded:
                    encoded[key] = c.encode(frames, a)
                if a.layout is not None:
                    c.put(a.layout)
                for m in encoded[key]:
                    c.put(m, "frame")
                if a.window is not None:
                    timing = timing or P.timing(frames[0].index, len(frames), a.window, time.monotonic())
                    c.put(timing, "note")

    def broadcast_audio(self, pts: float, samples: np.ndarray) -> None:
        """The server source's audio, sent in DGA1 messages of AUDIO_BATCH_S to clients that asked for it."""
        self.audio_pending.append((pts, samples))
        if sum(len(x) for _, x in self.audio_pending) >= AUDIO_BATCH_S * P.AUDIO_RATE:
            self._flush_audio()

    def _flush_audio(self) -> None:
        if not self.audio_pending:
            return
        message = P.source_audio_binary(self.audio_pending[0][0], np.concatenate([x for _, x in self.audio_pending]))
        self.audio_pending = []
        self.audio_recent.append(message)
        for c in self.clients:
            if c.source_audio and not c.own:
                c.put(message, "audio")

    def broadcast_end(self, frames: int) -> None:
        self.broadcast_ended = True  # `end` is the last message its followers get
        self._flush_audio()
        for c in self.clients:
            if not c.own:
                c.put(P.end(frames))

    # ---- one connection --------------------------------------------------------------------------

    async def _handle(self, ws: ServerConnection) -> None:
        from .handover import new_token

        c = self.config
        svc = Services(self.prep, self.metrics, self.make_session, self.store,
                       self.stored.call if self.stored is not None else None, c.max_backlog_s,
                       self.audio_recent, self.departures, self._trim_later, self.attached.pose,
                       self.attached.skeleton)
        client = Client(ws, S.ClientSession(self.seats, new_token), S.Keepalive(
            c.ping_interval or 0.0, c.ping_timeout, time.monotonic()), svc, c.max_queue, self.totals)
        self.clients.add(client)
        client.put(json.dumps(self.hello))
        tasks = [asyncio.create_task(client.send_loop(), name="ws-sender"),
                 asyncio.create_task(client.read_loop(), name="ws-reader"),
                 asyncio.ensure_future(ws.wait_closed())]
        if c.ping_interval:
            tasks.append(asyncio.create_task(keepalive_loop(client, c.ping_interval), name="ws-keepalive"))
        try:  # whichever ends first (the connection closed, the sender failed, the reader is done) ends it all
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            await self._leave(client, tasks)

    async def _leave(self, client: Client, tasks: list[asyncio.Future]) -> None:
        self.clients.discard(client)
        backlog_s = await client.leave(tasks)
        if backlog_s is not None and not self.closing:  # (said once per 10 s, however many leave)
            self.departures(logging.WARNING, f"client {client.who} left with its audio session running: session "
                                             f"cancelled, {backlog_s:.1f} s of queued audio and its slot freed")

    def _trim_later(self) -> None:
        """Trim the allocator a second after a session ended, or once the last trim is every_s old (one
        pending at a time, so the sessions of a flood that end over minutes are all given back)."""
        if self._trim_timer is None and self.trimmer.available and not self.closing:
            wait = max(1.0, self.trimmer.wait_s())
            self._trim_timer = asyncio.get_running_loop().call_later(wait, self._trim_now)

    def _trim_now(self) -> None:
        self._trim_timer = None
        if not self.closing:
            asyncio.get_running_loop().run_in_executor(self.prep, self.trimmer.trim)

    # ---- status ----------------------------------------------------------------------------------

    async def _status_loop(self) -> None:
        while True:
            await asyncio.sleep(self.config.status_every)
            for c in list(self.clients):
                if self.broadcast_ended and not c.own:
                    continue
                stats = c.session.stats if c.session is not None else self.broadcast_stats
                lat, rtf = (stats.latency_ms, stats.rtf) if stats is not None else (0.0, 0.0)
                extra = {"session": "own" if c.own else "broadcast"}
                if not c.own and self.attached.source_dropped_s is not None:
                    extra["audio_dropped_s"] = round(self.attached.source_dropped_s(), 3)
                c.note(P.status(lat, rtf, c.frames_sent, c.dropped, len(self.clients), **extra))


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host
