"""WebSocket server for protocol v1 (docs/protocol.md): broadcast frames, per-client audio sessions.

Every client has one bounded outgoing queue and one sender task; putting a frame in a full queue
drops the oldest queued frame and counts it, so broadcasting never awaits a slow client.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
from collections import deque
from http import HTTPStatus
from typing import Callable
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from streamer import protocol as P
from streamer.engine import Frame, Session
from streamer.sources import PushSource

log = logging.getLogger("streamer.ws")


class Client:
    """One connection: its encoding, its outgoing queue and counters, and its own audio session if any."""

    def __init__(self, ws: ServerConnection, max_queue: int):
        self.ws = ws
        self.encoding = "json"
        self.audio = P.AudioFormat()
        self.queue: deque[tuple[str, str | bytes]] = deque()  # (kind, message)
        self.max_queue = max_queue
        self.ready = asyncio.Event()
        self.frames_sent = 0
        self.dropped = 0
        self.own = False  # true once it sent audio: from then on it gets its own frames, not the broadcast
        self.source: PushSource | None = None
        self.session: Session | None = None
        self.session_task: asyncio.Task | None = None

    def put(self, message: str | bytes, kind: str = "ctl") -> None:
        """Queue a message; kind "frame" and "status" may be dropped (oldest first) when the queue is full."""
        if len(self.queue) >= self.max_queue:
            victim = next((i for i, (k, _) in enumerate(self.queue) if k != "ctl"), 0)
            k, _ = self.queue[victim]
            del self.queue[victim]
            self.dropped += k == "frame"
        self.queue.append((kind, message))
        self.ready.set()

    def put_frames(self, frames: list[Frame]) -> None:
        enc = P.frame_binary if self.encoding == "binary" else P.frame_json
        for f in frames:
            self.put(enc(f), "frame")

    async def send_loop(self) -> None:
        while True:
            while not self.queue:
                self.ready.clear()
                await self.ready.wait()
            kind, message = self.queue.popleft()
            await self.ws.send(message)
            self.frames_sent += kind == "frame"

    async def drained(self, timeout: float) -> None:
        """Wait (bounded) until everything queued so far has been handed to the socket."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while self.queue and loop.time() < deadline:
            await asyncio.sleep(0.01)


class WsServer:
    """Serves hello/frames/status to clients; `broadcast(frames)` is the server source's sink."""

    def __init__(self, host: str, port: int, hello: dict, make_session: Callable[[], Session] | None,
                 token: str | None = None, max_queue: int = 64, max_sessions: int = 8,
                 status_every: float = 1.0, broadcast_stats=None, source_dropped_s=None):
        self.host, self.port = host, port
        self.hello = hello
        self.make_session = make_session  # None: clients may not send audio
        self.token = token
        self.max_queue, self.max_sessions = max_queue, max_sessions
        self.status_every = status_every
        self.broadcast_stats = broadcast_stats  # Stats of the server's own source, if any
        self.source_dropped_s = source_dropped_s  # () -> seconds of live input dropped, if a live source
        self.clients: set[Client] = set()
        self.broadcast_ended = False
        self._server = None
        self._status_task: asyncio.Task | None = None

    # ---- lifecycle -------------------------------------------------------------------------------

    async def start(self) -> None:
        self._server = await serve(self._handle, self.host, self.port, process_request=self._check_token,
                                   max_size=P.HARD_MAX_BYTES, max_queue=64)
        self.port = self._server.sockets[0].getsockname()[1]  # the real port when 0 was asked
        self._status_task = asyncio.create_task(self._status_loop(), name="ws-status")

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}/"

    async def close(self, drain_s: float = 2.0) -> None:
        """Deliver what is queued (bounded wait), then close every connection and stop listening."""
        await asyncio.gather(*(c.drained(drain_s) for c in list(self.clients)))
        if self._status_task:
            self._status_task.cancel()
        if self._server is not None:
            self._server.close()  # closes connections with 1001 going away
            await self._server.wait_closed()

    def _check_token(self, connection, request):
        if self.token is None:
            return None
        given = parse_qs(urlsplit(request.path).query).get("token", [None])[0]
        if given is None or not hmac.compare_digest(given.encode(), self.token.encode()):
            log.info("refused a connection with a missing or wrong token")
            return connection.respond(HTTPStatus.UNAUTHORIZED, "missing or wrong token (use ?token=...)\n")
        return None

    # ---- broadcast (the server's own source) -----------------------------------------------------

    def broadcast(self, frames: list[Frame]) -> None:
        if not frames:
            return
        encoded: dict[str, list] = {}
        for c in self.clients:
            if c.own:
                continue
            if c.encoding not in encoded:
                enc = P.frame_binary if c.encoding == "binary" else P.frame_json
                encoded[c.encoding] = [enc(f) for f in frames]
            for m in encoded[c.encoding]:
                c.put(m, "frame")

    def broadcast_end(self, frames: int) -> None:
        self.broadcast_ended = True  # `end` is the last message its followers get
        for c in self.clients:
            if not c.own:
                c.put(P.end(frames))

    # ---- one connection --------------------------------------------------------------------------

    async def _handle(self, ws: ServerConnection) -> None:
        client = Client(ws, self.max_queue)
        self.clients.add(client)
        sender = asyncio.create_task(client.send_loop(), name="ws-sender")
        client.put(json.dumps(self.hello))
        try:
            async for message in ws:
                try:
                    if isinstance(message, bytes):
                        await self._on_audio(client, message)
                    else:
                        await self._on_text(client, message)
                except P.ProtocolError as e:
                    client.put(P.error(e.code, str(e)))
                    if e.code == "unsupported_protocol":
                        await client.drained(1.0)
                        await ws.close(1002, "unsupported protocol version")
                        break
                except (ConnectionClosed, asyncio.CancelledError):
                    raise
                except Exception as e:  # a bug or a model failure on this client's input: report, keep serving
                    log.exception("failed on a client message")
                    client.put(P.error("internal", f"{type(e).__name__}: {e}"))
        except ConnectionClosed:
            pass
        finally:
            self.clients.discard(client)
            if client.session_task is not None:
                client.session_task.cancel()
            sender.cancel()
            await asyncio.gather(sender, *(t for t in [client.session_task] if t), return_exceptions=True)

    async def _on_text(self, client: Client, text: str) -> None:
        msg = P.parse_text(text)
        if msg["type"] == "ping":
            client.put(json.dumps({**msg, "type": "pong"}))
        elif msg["type"] == "hello":
            client.encoding = msg.get("encoding", client.encoding)
            if "audio" in msg and msg["audio"] != client.audio:
                client.audio = msg["audio"]
                await self._end_session(client)  # later audio starts a session at the new rate
        elif msg["type"] == "audio_end":
            if client.source is None and (client.session_task is None or client.session_task.done()):
                client.put(P.end(0))  # no audio since the last end: an empty stream, ended
            else:
                await self._end_session(client)

    async def _on_audio(self, client: Client, data: bytes) -> None:
        if self.make_session is None:
            raise P.ProtocolError("audio_disabled", "this server does not accept client audio")
        x = P.decode_audio(data, client.audio)
        if client.source is None:
            if client.session_task is not None:  # the previous session is still finishing
                await asyncio.shield(client.session_task)
            busy = sum(1 for c in self.clients if c.source is not None)
            if busy >= self.max_sessions:
                raise P.ProtocolError("busy", f"at most {self.max_sessions} client audio sessions at once")
            self._start_session(client)
        await client.source.put(x)

    def _start_session(self, client: Client) -> None:
        client.own = True
        client.source = PushSource(client.audio.rate)
        client.session = session = self.make_session()

        async def run(source: PushSource) -> None:
            try:
                n = await session.run(source, client.put_frames)
                client.put(P.end(n))
            except asyncio.CancelledError:
                raise
            except Exception as e:  # the model failed on this audio: tell the client, keep the server up
                log.exception("client session failed")
                client.put(P.error("internal", f"session failed: {type(e).__name__}: {e}"))
                if client.source is source:
                    client.source = None

        client.session_task = asyncio.create_task(run(client.source), name="ws-session")

    async def _end_session(self, client: Client) -> None:
        """Flush the client's session (audio_end): it sends its last frames and `end` by itself."""
        if client.source is not None:
            source, client.source = client.source, None
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
                c.put(P.status(lat, rtf, c.frames_sent, c.dropped, len(self.clients), **extra), "status")
