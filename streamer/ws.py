"""WebSocket server for protocol v1 (docs/protocol.md): broadcast frames, per-client audio sessions.

Every client has one bounded outgoing queue and one sender task. Broadcast frames put in a full queue
drop the oldest droppable message and are counted, so broadcasting never awaits a slow client; a
client's own frames are never dropped: its session waits for room instead.

Nothing a client sends costs the event loop more than constant work: audio is decoded, resampled
and its frames encoded in a worker thread, in pieces, one job per client at a time (so the jobs of
all clients interleave first come first served), and inference runs in the sessions' executor.

A client's session lives exactly as long as its connection: whatever its handler is blocked on (room in
the backlog, room in the client's queue, a flush, the previous session finishing), the connection closing
cancels it, frees its slot and its queued audio at once and logs one (rate-limited) line. The keepalive is
this module's own: while the server holds a client's data unread on purpose (its backlog is full), the
client's pongs cannot be read either, so that time counts against it only when nothing moves at all.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import dataclasses
import logging
import socket
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from http import HTTPStatus
from typing import Callable, Iterable

import numpy as np
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from dimgestor.audio import SAMPLE_RATE
from streamer import health
from streamer import protocol as P
from streamer import request_checks as RC
from streamer.frames import Frame
from streamer.log_limit import ErrorLog
from streamer.memory import Trimmer
from streamer.metrics import ServerMetrics
from streamer.options import MAX_SESSIONS, PING_INTERVAL_S, PING_TIMEOUT_S
from streamer.sessions import AudioClock, Session
from streamer.sources import PushSource, make_resampler
from streamer.viewer import Answer, ViewerFiles, is_upgrade
from streamer.waiting import WaitingRoom

log = logging.getLogger("streamer.ws")
AUDIO_BATCH_S = 0.1   # source audio per DGA1 message: few messages, well ahead of the frames it goes with
AUDIO_RECENT_S = 3.0  # source audio replayed to a client that asks late: covers lookahead, window and latency

PIECE_S = 0.5  # client audio is resampled in pieces of at most this many seconds (of its own rate)
DROPPABLE = ("frame", "note", "audio")  # broadcast frames; status, pong and error replies; source audio


class MessageBudget:
    """Token bucket on a client's messages: `rate` per second, bursts of `burst`; a text message also costs
    one token per KiB (parsing is the event loop's work). Over budget, the client is read more slowly."""

    def __init__(self, rate: float = 250.0, burst: float = 500.0):
        self.rate, self.burst = rate, burst
        self.tokens, self.t = burst, time.monotonic()

    def wait_s(self, message: str | bytes) -> float:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
        self.t = now
        self.tokens -= 1 + (len(message) / 1024 if isinstance(message, str) else 0)
        return max(0.0, -self.tokens / self.rate)


@dataclass
class FrameTotals:
    """Frames sent and dropped over all clients, past and present (the metrics' `sink="ws"` counts)."""

    sent: int = 0
    dropped: int = 0


class Client:
    """One connection: its encoding, its outgoing queue and counters, and its own audio session if any."""

    def __init__(self, ws: ServerConnection, max_queue: int, totals: FrameTotals | None = None):
        self.ws = ws
        self.encoding = "json"
        self.audio = P.AudioFormat()
        self.queue: deque[tuple[str, str | bytes]] = deque()  # (kind, message)
        self.max_queue = max_queue
        self.ready = asyncio.Event()  # something to send
        self.room = asyncio.Event()  # the queue has room
        self.frames_sent = 0
        self.dropped = 0
        self.totals = totals if totals is not None else FrameTotals()  # the server's, shared by all its clients
        self.own = False  # true once it sent audio: from then on it gets its own frames, not the broadcast
        self.source_audio = False  # asked for the server source's audio (hello "source_audio": true)
        self.timing = False  # asked for each window's `timing` (hello "timing": true)
        self.source: PushSource | None = None
        self.resampler = None  # lives in the worker (built, used and flushed there)
        self.session: Session | None = None
        self.session_task: asyncio.Task | None = None
        self.session_frames = 0  # frames its current session has produced
        self.slowed = False  # told that its audio arrives faster than it is processed (until `resume`)
        self.heard = time.monotonic()  # when the last message or pong came from it
        self.holding = False  # its handler holds a message (the socket is not read meanwhile: back pressure)
        self.sending = False  # send_loop is handing a message to the socket
        self.after_session: list[str] = []  # replies due once the running session has sent its `end`
        self.refused = False  # its current audio was refused a session (counted once in the metrics)
        self.handing_over = False  # the server is stopping and saves its session (its audio is ignored meanwhile)
        self.saved_token: str | None = None  # its session's periodic saves go under this token (--save-state-every)
        self.saved_audio_s = 0.0  # the audio its last periodic save covers
        peer = ws.remote_address
        self.who = f"{peer[0]}:{peer[1]}" if peer else "?"
        self.errors = ErrorLog(f"client {self.who}")
        self.budget = MessageBudget()
        self.clock = AudioClock()  # shared by its sessions: how far its audio is ahead of real time

    def put(self, message: str | bytes, kind: str = "ctl") -> None:
        """Queue a message. "ctl" (hello, end) and "own" frames always go in; a droppable one ("frame",
        "note") finds a full queue -> the oldest droppable message goes (itself if none is older)."""
        if len(self.queue) >= self.max_queue and kind in DROPPABLE:
            victim = next((i for i, (k, _) in enumerate(self.queue) if k in DROPPABLE), None)
            lost = kind == "frame" if victim is None else self.queue[victim][0] == "frame"
            self.dropped += lost
            self.totals.dropped += lost
            if victim is None:
                return
            del self.queue[victim]
        self.queue.append((kind, message))
        self.ready.set()

    def note(self, message: str) -> None:
        self.put(message, "note")

    async def put_own(self, messages: list[str | bytes]) -> None:
        """This client's own frames: wait (bounded by the client reading) for room, never drop."""
        while len(self.queue) >= self.max_queue:
            self.room.clear()
            await self.room.wait()
        for m in messages:
            self.put(m, "own")

    def encode(self, frames: list[Frame]) -> list[str | bytes]:  # worker thread
        return P.encode_frames(frames, self.encoding)

    async def send_loop(self) -> None:
        while True:
            while not self.queue:
                self.ready.clear()
                await self.ready.wait()
            kind, message = self.queue.popleft()
            self.room.set()
            self.sending = True
            try:
                await self.ws.send(message)
            finally:
                self.sending = False
            sent = kind in ("frame", "own")
            self.frames_sent += sent
            self.totals.sent += sent

    @property
    def awaits_reading(self) -> bool:
        """Something waits for the client to read it: messages queued, or one being sent (blocked while the
        client's socket is full)."""
        return bool(self.queue) or self.sending

    async def drained(self, deadline: float) -> None:
        """Wait until everything queued so far has been handed to the socket, or the loop time `deadline`."""
        loop = asyncio.get_running_loop()
        while self.queue and loop.time() < deadline:
            await asyncio.sleep(0.01)


def own_origins(host: str, port: int) -> list[str]:
    """The Origin values a browser sends for pages loaded from host:port (all the names it may be reached by)."""
    names = {host}
    if host in ("0.0.0.0", "::", ""):
        names = {"127.0.0.1", "::1", "localhost"}
        try:
            hostname = socket.gethostname()
            names |= {hostname, socket.getfqdn()}
            names |= {ai[4][0] for ai in socket.getaddrinfo(hostname, None)}
        except OSError:
            pass
    if names & {"127.0.0.1", "::1", "localhost"}:
        names |= {"127.0.0.1", "::1", "localhost"}
    return [f"http://{f'[{n}]' if ':' in n else n}:{port}" for n in sorted(names)]


HANDOVER_S = 5.0  # on SIGTERM with a state store: how long sessions may take to finish the audio held and be saved


class WsServer:
    """Serves hello/frames/status to clients; a `Sink` (streamer/sink.py) of the server's source. A request
    that is not a WebSocket upgrade gets a file of the web viewer (`files`; None: no files) on the same port.

    origins: the `Origin` headers accepted at the handshake besides none at all (native clients send
    none; browsers always send one) and the server's own (its viewer's pages); "*" accepts any. token:
    required as ?token=... when set. also: more (host, port) addresses serving the same (the deprecated
    --http). ping_interval, ping_timeout: the keepalive (seconds; None: none): a client from which nothing
    was heard for their sum, while the server was reading it or while nothing moved, is closed (1011).
    max_waiting, request_timeout_s: connections that have not sent a whole request (`WaitingRoom`).
    metrics: the worker's `ServerMetrics` (None: a registry of its own); `/healthz` and `/readyz` are always
    answered, `/metrics` unless serve_metrics is false (`streamer.health`).
    """

    def __init__(self, host: str, port: int, hello: dict, make_session: Callable[[], Session] | None,
                 token: str | None = None, max_queue: int = 64, max_sessions: int = MAX_SESSIONS,
                 status_every: float = 1.0, broadcast_stats=None, source_dropped_s=None,
                 origins: Iterable[str] = (), max_backlog_s: float = 30.0,
                 ping_interval: float | None = PING_INTERVAL_S, ping_timeout: float = PING_TIMEOUT_S,
                 files: ViewerFiles | None = ViewerFiles(), also: Iterable[tuple[str, int]] = (),
                 max_waiting: int = 64, request_timeout_s: float = 10.0, metrics: ServerMetrics | None = None,
                 serve_metrics: bool = True, store=None, save_every_s: float | None = None):
        self.host, self.port = host, port
        self.addresses = [(host, port), *also]  # (the real ports once open)
        self.files = files
        self.waiting_room = WaitingRoom(max_waiting, request_timeout_s)
        self.hello = hello
        self.make_session = make_session  # None: clients may not send audio
        self.store = store  # a streamer.handover store: sessions are handed over when the server stops (None: ended)
        self.save_every_s = save_every_s if store is not None else None  # periodic saves (_save_between_windows)
        self._saving: set[asyncio.Task] = set()
        self.token = token
        self.origins = {o for o in map(RC.allowed_origin, origins) if o is not None}
        self.max_queue, self.max_sessions = max_queue, max_sessions
        self.max_backlog_s = max_backlog_s
        self.ping_interval, self.ping_timeout = ping_interval, ping_timeout
        self.trimmer = Trimmer()
        self._trim_timer: asyncio.TimerHandle | None = None
        self.refusals = ErrorLog("refused handshakes", what="refusals")  # one line per 10 s, whatever the flood
        self.departures = ErrorLog("sessions", what="departures")
        self.file_failures = ErrorLog("viewer", what="failed requests")
        self.status_every = status_every
        self.broadcast_stats = broadcast_stats  # Stats of the server's own source, if any
        self.source_dropped_s = source_dropped_s  # () -> seconds of live input dropped, if a live source
        self.clients: set[Client] = set()
        self.broadcast_ended = False
        self.broadcast_frames = 0
        self.closing = False
        self.prep = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ws-prep")  # decode, resample, encode
        self.audio_pending: list[tuple[float, np.ndarray]] = []  # source audio not yet sent (< AUDIO_BATCH_S)
        self.audio_recent: deque[bytes] = deque(maxlen=int(AUDIO_RECENT_S / AUDIO_BATCH_S))  # for late joiners
        self._servers: list = []
        self._status_task: asyncio.Task | None = None
        self.totals = FrameTotals()
        self.metrics = metrics if metrics is not None else ServerMetrics()
        self.serve_metrics = serve_metrics
        self.metrics.streams.append(lambda: self.live_sessions)
        self.metrics.clients = lambda: len(self.clients)
        self.metrics.sinks["ws"] = lambda: (self.totals.sent, self.totals.dropped)
        self.metrics.queues["dimgestor_client_queue_messages"] = lambda: sum(len(c.queue) for c in self.clients)
        self.metrics.queues["dimgestor_audio_backlog_seconds"] = lambda: sum(
            c.source.backlog_s for c in self.clients if c.source is not None)

    # ---- lifecycle -------------------------------------------------------------------------------

    async def open(self) -> None:
        try:
            for host, port in self.addresses:
                self._servers.append(await serve(
                    self._handle, host, port, process_request=self._process_request,
                    create_connection=self.waiting_room.connection,
                    open_timeout=2 * self.waiting_room.timeout_s,  # reading the request, then sending the answer
                    max_size=P.HARD_MAX_BYTES, max_queue=4, close_timeout=0.5,
                    ping_interval=None,  # our own keepalive (_keepalive): knows back pressure
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

    @property
    def url(self) -> str:
        return f"ws://{_url_host(self.host)}:{self.port}/"

    @property
    def viewer_urls(self) -> list[str]:
        """Where a browser finds the viewer (one per address), if it is served."""
        return [f"http://{_url_host(host)}:{port}/" for host, port in self.addresses] if self.files else []

    @property
    def live_sessions(self) -> int:
        """Client sessions still running, including those flushing after `audio_end`."""
        return sum(1 for c in self.clients if c.session_task is not None and not c.session_task.done())

    def describe(self) -> str:
        hint = "?token=..." if self.token else ""
        lines = [f"WebSocket  {self.url}{hint}  (protocol v1, docs/protocol.md)"]
        lines += [f"web viewer {url}{'  (open it as ...?token=YOUR_TOKEN)' if self.token else ''}"
                  for url in self.viewer_urls]
        return "\n".join(lines)

    def status(self) -> str:
        return (f"clients {len(self.clients)} | dropped {sum(c.dropped for c in self.clients)} | "
                f"own sessions {sum(1 for c in self.clients if c.session is not None)}")

    async def close(self, drain: bool = True, within_s: float = 1.5) -> None:
        """End every client's stream, deliver what is queued and close, all within ~within_s (whether the source
        ended or was stopped: `drain` makes no difference here). A session whose audio has all come (after its
        `audio_end`) finishes as usual, its last frames and `end`, if it can within 0.4 within_s (HANDOVER_S
        with a state store); with a store the others are handed over (`goaway`, _hand_over), without one they
        get `end` at once."""
        self._flush_audio()  # the source's last audio before its `end`
        loop = asyncio.get_running_loop()
        self.closing = True
        self.metrics.readiness.draining = True
        if self._trim_timer is not None:
            self._trim_timer.cancel()
        # (a session that ends meanwhile clears its client's session_task: keep the tasks as they are now)
        own = {c: c.session_task for c in self.clients if c.session_task is not None and not c.session_task.done()}
        finishing = {c: task for c, task in own.items() if c.source is None}  # past audio_end: nothing to move
        moving = {c: task for c, task in own.items() if c not in finishing}
        until = loop.time() + (HANDOVER_S if self.store else within_s * 0.4)
        handed = await self._hand_over(moving, until) if self.store and moving else set()
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
            if c in own:
                c.put(P.end(c.session_frames))
            elif not c.own and not self.broadcast_ended:
                c.put(P.end(self.broadcast_frames))
        deadline = loop.time() + within_s * 0.6
        await asyncio.gather(*(c.drained(deadline) for c in list(self.clients)))
        await asyncio.gather(*(c.ws.close(1012, "restart: resume_session with the goaway's token") for c in handed),
                             return_exceptions=True)
        if self._status_task:
            self._status_task.cancel()
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

    async def _hand_over(self, own: dict[Client, asyncio.Task], deadline: float) -> set[Client]:
        """Each session finishes the audio it holds (until `deadline`), then its state goes to the store and the
        client gets `goaway` with the token (streamer/handover.py). Returns the clients handed over; the others
        (not done in time, a store that failed) are ended as without a store."""
        from dimgestor import savestate

        from .handover import new_token

        loop = asyncio.get_running_loop()
        sources = []
        for c in own:  # all of them before any await: audio that arrives meanwhile is ignored, never refused
            if c.session is None:  # (left meanwhile)
                continue
            c.handing_over = c.session.handover = True
            sources.append(c.source)
            c.source = None
        for source in sources:
            if source is not None:
                await source.close()
        done, _ = await asyncio.wait(own.values(), timeout=max(0.0, deadline - loop.time()))
        handed = set()
        for c, task in own.items():
            if task not in done or task.cancelled() or task.exception() is not None or c.session is None:
                continue  # (not finished in time, failed, or its client left)
            session, rate = c.session, c.audio.rate
            state = session.stream.state
            meta = self._session_meta(c, session)
            token = new_token()

            def save(c=c, meta=meta, state=state, session=session) -> tuple[bytes, int]:
                # (in the prep thread, after any resampling under way there) Audio at another rate than 16 kHz
                # goes on exactly when the resampler is saved too, and every output it gave reached the stream:
                # the client then re-sends from the resampler's own input count.
                samples = state.samples_in * rate // SAMPLE_RATE
                r = c.resampler
                if r is not None and r.outputs == state.samples_in:
                    meta["resampler"], samples = r.get_state(), r.inputs
                return savestate.dumps(session.stream, state, meta), samples

            try:
                data, samples = await loop.run_in_executor(self.prep, save)
                await loop.run_in_executor(self.prep, self.store.put, token, data)
            except Exception as e:  # the store is down: this client's session ends as without one
                self.departures(logging.WARNING, f"session of {c.who} not saved ({type(e).__name__}: {e}): ended")
                continue
            c.put(P.goaway(token, samples, c.session_frames, rate))
            handed.add(c)
            self.metrics.sessions_handed_over.inc()
        return handed

    @staticmethod
    def _session_meta(client: Client, session) -> dict:
        """What a saved state needs beside the stream's: the pose decoder's root, the frame count, the format."""
        return {"frames": client.session_frames, "decoder": dataclasses.asdict(session.decoder.state),
                "rate": client.audio.rate, "encoding": client.encoding}

    def _save_between_windows(self, client: Client, session) -> None:
        """--save-state-every: between two windows (the state, the decoder and the frames sent agree), once the
        session's audio is save_every_s past its last save, its state goes to the store under the client's
        standing token (one key per session, overwritten) and the client gets `session_saved`. A crash loses
        at most that much: the client resumes from the save."""
        from dimgestor import savestate

        state = session.stream.state
        audio_s = state.samples_in / SAMPLE_RATE
        if client.handing_over or client.session is not session or audio_s - client.saved_audio_s < self.save_every_s:
            return
        client.saved_audio_s = audio_s
        # copied now (a few ms for a megabyte): the next window moves the state on
        data = savestate.dumps(session.stream, state, self._session_meta(client, session))
        samples, frames, token = state.samples_in * client.audio.rate // SAMPLE_RATE, client.session_frames, \
            client.saved_token
        loop = asyncio.get_running_loop()

        async def store() -> None:
            try:
                await loop.run_in_executor(self.prep, self.store.put, token, data)
            except Exception as e:  # the store is down: the session goes on unsaved, said (rate-limited)
                self.departures(logging.WARNING, f"periodic save of {client.who}'s session failed "
                                                 f"({type(e).__name__}: {e})")
                return
            if client.session is session and not client.handing_over:
                client.put(P.session_saved(token, samples, frames, client.audio.rate))
                self.metrics.sessions_saved.inc()

        task = loop.create_task(store())
        self._saving.add(task)
        task.add_done_callback(self._saving.discard)

    async def _resume(self, client: Client, token: str) -> None:
        """resume_session: the state saved under `token` (by any worker) becomes this client's session; its
        audio goes on from the sample the state covers."""
        from dimgestor import savestate
        from dimgestor.features import RootState

        if self.store is None:
            raise P.ProtocolError("resume_failed", "this server keeps no session states (--state-store)")
        if self.closing:  # the token is not taken: it resumes on another worker
            raise P.ProtocolError("busy", "this worker is stopping: resume_session on another (the token stays valid)")
        if client.source is not None or (client.session_task is not None and not client.session_task.done()):
            raise P.ProtocolError("resume_failed", "resume_session before any audio (or after audio_end's `end`)")
        if self.make_session is None:
            raise P.ProtocolError("audio_disabled", "this server does not accept client audio")
        if self.live_sessions >= self.max_sessions:
            self._refused(client, "busy")
            raise P.ProtocolError("busy", f"at most {self.max_sessions} client audio sessions at once")
        loop = asyncio.get_running_loop()
        try:
            data = await loop.run_in_executor(self.prep, self.store.take, token)
        except Exception as e:
            raise P.ProtocolError("resume_failed", f"the state store failed: {type(e).__name__}: {e}") from None
        if data is None:
            raise P.ProtocolError("resume_failed", "unknown or expired resume token: start a new stream")
        self._start_session(client)
        session = client.session
        try:
            state, meta = await loop.run_in_executor(self.prep, savestate.loads, session.stream, data)
        except savestate.StateError as e:
            await self._end_session(client)
            raise P.ProtocolError("resume_failed", str(e)) from None
        session.stream.state = state
        root = dict(meta["decoder"])
        session.decoder.state = RootState(**{**root, "drift": tuple(root.get("drift", (0.0, 0.0, 0.0)))})
        client.session_frames = int(meta["frames"])
        client.saved_audio_s = state.samples_in / SAMPLE_RATE  # (its periodic saves go on from here)
        session.clock.audio_s = state.samples_in / SAMPLE_RATE
        samples = state.samples_in * client.audio.rate // SAMPLE_RATE
        saved = meta.get("resampler")
        if saved is not None and int(meta.get("rate", 0)) == client.audio.rate:  # its rate converter goes on too
            client.resampler = make_resampler(client.audio.rate)
            client.resampler.set_state(saved)
            samples = client.resampler.inputs
        self.metrics.sessions_resumed.inc()
        client.put(P.session_resumed(samples, client.session_frames, client.audio.rate))

    def _process_request(self, connection, request):
        """`/healthz`, `/readyz`, `/metrics` and the pages of the viewer are answered here; a WebSocket
        handshake is checked (origin, then token: a refusal is a 4xx and at most one log line per 10 s). Never
        raises (a raise would be a 500 and a traceback in the log)."""
        self.waiting_room.requested(connection)
        if not is_upgrade(request.headers.get_all("Upgrade")):
            method = getattr(request, "method", "GET")  # (websockets < 17 passes GET requests only)
            try:
                ops = health.answer(method, request.path, self.metrics.readiness,
                                    self.metrics if self.serve_metrics else None)
                if ops is not None:  # (no token asked: see streamer.health)
                    return ops.response()
                if self.files is not None:
                    return self.files.answer(method, request.path).response()
            except Exception as e:  # a bug: one line (rate-limited), no traceback, and an answer all the same
                self.file_failures(logging.ERROR, f"failed on a request: {type(e).__name__}: {e}")
                return Answer(HTTPStatus.INTERNAL_SERVER_ERROR, b"internal error\n").response()
        try:
            status, why = self.refusal(request.path, request.headers.get_all("Origin"),
                                       getattr(request, "protocol", "HTTP/1.1"))  # (websockets >= 15 parses it)
        except Exception as e:  # a bug here must not become a 500 with a traceback per request
            status, why = HTTPStatus.BAD_REQUEST, f"malformed request ({type(e).__name__})"
        if status is None and self.metrics.readiness.draining:
            # A new session here would end within a second: 503, so a balancer passes the handshake on to another
            # worker (deploy/nginx.conf: proxy_next_upstream http_503) and a client retries elsewhere.
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, "draining: this worker is stopping; connect "
                                                                      "to another\n")
        if status is None:
            return None
        self.refusals(logging.INFO, f"{why}")
        return connection.respond(status, {HTTPStatus.FORBIDDEN: "origin not allowed (see dimgestor serve --allow-origin)\n",
                                           HTTPStatus.UNAUTHORIZED: "missing or wrong token (use ?token=...)\n"}
                                  .get(status, "bad request\n"))

    def refusal(self, target: str, origins: list[str], version: str = "HTTP/1.1") -> tuple[HTTPStatus | None, str]:
        """(None, "") to accept a handshake for request target `target` with these Origin headers, else
        (status, why): 400 for a malformed target or Origin (or two of them) or an HTTP version other than
        1.1 (the WebSocket handshake's own; the library would answer 505), 403 for an origin not allowed, 401
        for a missing or wrong token. Pure: reads only the allow-list and the token."""
        if RC.split_target(target) is None or version != "HTTP/1.1":
            return HTTPStatus.BAD_REQUEST, "a malformed request target or HTTP version"
        given = RC.single(origins)
        if given is RC.REPEATED:
            return HTTPStatus.BAD_REQUEST, f"{len(origins)} Origin headers"
        if given is not None and "*" not in self.origins:
            origin = RC.origin(given)
            if origin is None:
                return HTTPStatus.BAD_REQUEST, "a malformed Origin header"
            if origin not in self.origins:
                return HTTPStatus.FORBIDDEN, f"origin {origin[:100]!r} (not in the allow-list; see --allow-origin)"
        if self.token is None:
            return None, ""
        token = RC.query_value(target, "token")
        if token is None or not hmac.compare_digest(token.encode("utf-8", "surrogatepass"), self.token.encode()):
            return HTTPStatus.UNAUTHORIZED, "a missing or wrong token"
        return None, ""

    # ---- broadcast (the server's own source) -----------------------------------------------------

    def send(self, frames: list[Frame]) -> None:
        """The server source's frames, to every client that follows it (never awaits a client)."""
        if not frames:
            return
        self.broadcast_frames += len(frames)
        encoded: dict[str, list] = {}
        window = self.broadcast_stats.window if self.broadcast_stats is not None else None
        timing = None
        for c in self.clients:
            if c.own:
                continue
            if c.encoding not in encoded:
                encoded[c.encoding] = c.encode(frames)
            for m in encoded[c.encoding]:
                c.put(m, "frame")
            if c.timing and window is not None:
                timing = timing or P.timing(frames[0].index, len(frames), window, time.monotonic())
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
        client = Client(ws, self.max_queue, self.totals)
        self.clients.add(client)
        client.put(json.dumps(self.hello))
        tasks = [asyncio.create_task(client.send_loop(), name="ws-sender"),
                 asyncio.create_task(self._read_loop(client), name="ws-reader"),
                 asyncio.ensure_future(ws.wait_closed())]
        if self.ping_interval:
            tasks.append(asyncio.create_task(self._keepalive(client), name="ws-keepalive"))
        try:  # whichever ends first (the connection closed, the sender failed, the reader is done) ends it all
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            await self._leave(client, tasks)

    async def _read_loop(self, client: Client) -> None:
        ws = client.ws
        try:
            async for message in ws:
                client.heard, client.holding = time.monotonic(), True
                try:
                    if isinstance(message, bytes):
                        await self._on_audio(client, message)
                    else:
                        await self._on_text(client, message)
                except P.ProtocolError as e:
                    client.errors(logging.INFO, f"{e.code}: {e}")
                    client.note(P.error(e.code, str(e)))
                    if e.code == "unsupported_protocol":
                        await client.drained(asyncio.get_running_loop().time() + 1.0)
                        await ws.close(1002, "unsupported protocol version")
                        break
                except (ConnectionClosed, asyncio.CancelledError):
                    raise
                except Exception as e:  # a bug or a model failure on this client's input: report, keep serving
                    client.errors(logging.ERROR, f"failed on a message: {type(e).__name__}: {e}", exc_info=True)
                    client.note(P.error("internal", f"{type(e).__name__}: {e}"))
                await asyncio.sleep(client.budget.wait_s(message))  # a flood is read only as fast as the budget
                client.holding = False
        except ConnectionClosed:
            pass

    async def _keepalive(self, client: Client) -> None:
        """Ping every ping_interval; close (1011) a client not heard from for ping_interval + ping_timeout.

        While its handler holds one of its messages (its backlog is full: TCP back pressure), the server
        reads none of its frames, pongs included, so it is blamed for silence only when it does not read:
        frames wait for it (queued, or a send under way) and none went out in a whole ping interval. A client
        whose session the server has not served meanwhile (nothing waits for it) is not blamed: a long wait
        for inference under load is the server's doing, and closing for it left the client's audio unserved
        (11 of 31 fast senders closed in one 60 s flood, where earlier rules counted frames made, not read).
        """
        pong: asyncio.Future | None = None
        sent = None

        def answered(f: asyncio.Future) -> None:
            if not f.cancelled() and f.exception() is None:
                client.heard = time.monotonic()

        while True:
            await asyncio.sleep(self.ping_interval)
            now = time.monotonic()
            if client.holding and (client.frames_sent != sent or not client.awaits_reading):
                client.heard = now
            sent = client.frames_sent
            if now - client.heard > self.ping_interval + self.ping_timeout:
                client.errors(logging.WARNING, f"nothing heard for {now - client.heard:.1f} s (keepalive): closing "
                                               f"({'holding its audio, ' if client.holding else ''}"
                                               f"{client.frames_sent} frames sent, {len(client.queue)} queued)")
                await client.ws.close(1011, "keepalive ping timeout")
                return
            if pong is None or pong.done():
                try:
                    pong = await client.ws.ping()
                except ConnectionClosed:
                    return
                pong.add_done_callback(answered)

    async def _leave(self, client: Client, tasks: list[asyncio.Future]) -> None:
        """The client is gone: cancel everything it has in flight (whatever it waits on), free its slot, its
        queue and its audio now, and say so once (rate-limited) if a session was cut short."""
        self.clients.discard(client)
        session = client.session_task
        running = session is not None and not session.done()
        backlog_s = client.source.backlog_s if client.source is not None else 0.0
        pending = [*tasks, *([session] if session is not None else [])]
        for t in pending:
            t.cancel()
        client.queue.clear()
        client.room.set()
        if client.source is not None:
            client.source.chunks.clear()
            client.source.queued = 0
            await client.source.close()
        await asyncio.gather(*pending, return_exceptions=True)
        client.source = client.session = client.session_task = client.resampler = None
        client.after_session.clear()
        if running and not self.closing:
            self.departures(logging.WARNING, f"client {client.who} left with its audio session running: session "
                                             f"cancelled, {backlog_s:.1f} s of queued audio and its slot freed")

    async def _on_text(self, client: Client, text: str) -> None:
        msg = P.parse_text(text)
        if msg["type"] == "ping":
            client.note(P.dumps({**msg, "type": "pong", "server_time_s": round(time.monotonic(), 6)}))
        elif msg["type"] == "hello":
            client.encoding = msg.get("encoding", client.encoding)
            client.timing = msg.get("timing", client.timing)
            if msg.get("source_audio") and not client.source_audio and "source_audio" in self.hello:
                for m in self.audio_recent:  # the audio of the frames still to come to a client that joins now
                    client.put(m, "audio")
            client.source_audio = bool(msg.get("source_audio", client.source_audio)) and "source_audio" in self.hello
            if "audio" in msg and msg["audio"] != client.audio:
                client.budget.tokens -= 25  # a new resampler is designed: costs as much as 25 messages
                await self._end_session(client)  # later audio starts a session at the new rate
                client.audio = msg["audio"]
        elif msg["type"] == "resume_session":
            await self._resume(client, msg["token"])
        elif msg["type"] == "audio_end":
            client.refused = False  # its next audio is another attempt
            if client.source is not None:
                await self._end_session(client)
            elif client.session_task is None or client.session_task.done():
                client.put(P.end(0))  # no audio since the last end: an empty stream, ended
            else:  # the previous session is still finishing: its `end` first, then this empty stream's
                client.after_session.append(P.end(0))

    async def _on_audio(self, client: Client, data: bytes) -> None:
        if self.make_session is None:
            self._refused(client, "audio_disabled")
            raise P.ProtocolError("audio_disabled", "this server does not accept client audio")
        if self.closing:
            if client.handing_over:  # its state is being saved: the client re-sends from the goaway's sample
                return
            self._refused(client, "draining")
            raise P.ProtocolError("busy", "the server is shutting down")
        fmt = client.audio
        P.check_audio(data, fmt)
        loop = asyncio.get_running_loop()
        x = await loop.run_in_executor(self.prep, P.decode_audio, data, fmt)  # raises bad_audio
        if client.source is None:
            if client.session_task is not None and not client.session_task.done():
                await asyncio.shield(client.session_task)  # the previous session is still finishing
                await asyncio.sleep(0)  # (its done callbacks run first: its `end` and what waited for it)
            if self.closing:  # began during the awaits: a session detached for hand-over must not start anew
                if client.handing_over:
                    return
                self._refused(client, "draining")
                raise P.ProtocolError("busy", "the server is shutting down")
            if self.live_sessions >= self.max_sessions:
                self._refused(client, "busy")
                raise P.ProtocolError("busy", f"at most {self.max_sessions} client audio sessions at once")
            self._start_session(client)
        source = client.source
        step = max(1, int(PIECE_S * fmt.rate))
        for a in range(0, len(x), step):
            y = await loop.run_in_executor(self.prep, self._resample, client, x[a : a + step])
            if source.full and not client.slowed:
                client.slowed = True  # until the backlog is down to half: `resume` (see emit in _start_session)
                client.put(P.error("slow_down", f"audio arrives faster than it is processed: "
                                                f"{source.backlog_s:.0f} s are queued; pause until `resume` (or the "
                                                f"server reads more as it catches up; nothing is dropped)"))
            await source.put(y, more_s=max(0, len(x) - a - step) / fmt.rate)
            if client.source is not source:  # the session failed meanwhile
                return

    def _refused(self, client: Client, reason: str) -> None:
        """Count a session refused: once per stream the client tries (its audio messages until `audio_end`
        are one attempt), not once per message."""
        if not client.refused:
            client.refused = True
            self.metrics.refused(reason)

    @staticmethod
    def _resample(client: Client, x: np.ndarray) -> np.ndarray:  # worker thread
        if client.audio.rate == SAMPLE_RATE:
            return x
        if client.resampler is None:
            client.resampler = make_resampler(client.audio.rate)
        return client.resampler.process(x)

    def _start_session(self, client: Client) -> None:
        client.own = True
        client.source = source = PushSource(self.max_backlog_s)
        client.resampler = None
        client.session = session = self.make_session()
        session.clock = client.clock
        session.on_window = session.on_window or self.metrics.window_done
        self.metrics.sessions_started.inc()
        client.refused = False
        client.session_frames = 0
        if self.save_every_s is not None:
            from .handover import new_token

            client.saved_token, client.saved_audio_s = new_token(), 0.0
            session.on_boundary = lambda: self._save_between_windows(client, session)
        loop = asyncio.get_running_loop()

        async def emit(frames: list[Frame]) -> None:
            if client.slowed and source.backlog_s <= self.max_backlog_s / 2:
                client.slowed = False
                client.put(P.resume(source.backlog_s))  # a client that paused at slow_down may send again
            if frames:
                client.session_frames += len(frames)
                messages = await loop.run_in_executor(self.prep, client.encode, frames)
                if client.timing and session.stats.window is not None:
                    messages.append(P.timing(frames[0].index, len(frames), session.stats.window, time.monotonic()))
                await client.put_own(messages)

        async def run() -> None:
            try:
                n = await session.run(source, emit)
                if not session.handover:  # handed over: goaway instead (_hand_over)
                    client.put(P.end(n))
            except asyncio.CancelledError:
                raise
            except Exception as e:  # the model failed on this audio: tell the client, keep the server up
                client.errors(logging.ERROR, f"session failed: {type(e).__name__}: {e}", exc_info=True)
                client.note(P.error("internal", f"session failed: {type(e).__name__}: {e}"))
                if client.source is source:
                    client.source = None
                await source.close()

        def done(task: asyncio.Task) -> None:
            self._trim_later()  # its queued audio is free: give the pages back (streamer/memory.py)
            if client.slowed and client.source is not source:  # ended while the client was paused: let it go on
                client.slowed = False
                client.put(P.resume(0.0))
            if not task.cancelled():
                for m in client.after_session:
                    client.put(m)
            client.after_session.clear()
            if self.save_every_s is not None and not task.cancelled() and not session.handover:
                token = client.saved_token  # ended: its periodic save will not be resumed (else the TTL drops it)
                if token is not None and not self.closing:
                    def forget():
                        try:
                            self.store.take(token)
                        except Exception:  # (a store that is down forgets it by its TTL)
                            pass
                    loop.run_in_executor(self.prep, forget)

        client.session_task = asyncio.create_task(run(), name="ws-session")
        client.session_task.add_done_callback(done)

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

    async def _end_session(self, client: Client) -> None:
        """Flush the client's session (audio_end): it sends its last frames and `end` by itself."""
        if client.source is not None:
            source, client.source = client.source, None
            if client.resampler is not None:
                resampler, client.resampler = client.resampler, None
                tail = await asyncio.get_running_loop().run_in_executor(self.prep, resampler.flush)
                await source.put(np.asarray(tail, dtype=np.float32))
            await source.close()

    # ---- status ----------------------------------------------------------------------------------

    async def _status_loop(self) -> None:
        while True:
            await asyncio.sleep(self.status_every)
            for c in list(self.clients):
                if self.broadcast_ended and not c.own:
                    continue
                stats = c.session.stats if c.session is not None else self.broadcast_stats
                lat, rtf = (stats.latency_ms, stats.rtf) if stats is not None else (0.0, 0.0)
                extra = {"session": "own" if c.own else "broadcast"}
                if not c.own and self.source_dropped_s is not None:
                    extra["audio_dropped_s"] = round(self.source_dropped_s(), 3)
                c.note(P.status(lat, rtf, c.frames_sent, c.dropped, len(self.clients), **extra))


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host
