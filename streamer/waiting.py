"""Connections that have not sent a whole request yet: bounded in number and in time.

Whatever a connection will turn out to be (a page of the viewer or a WebSocket handshake), until its
request head has arrived it costs a slot and gives nothing. At most `max_waiting` wait at once: one more
drops the one that has waited longest (so holding connections open cannot shut anyone out), and one that
has not sent its request within `timeout_s` gets a 408. websockets' own `open_timeout` still bounds the
whole handshake, answer included.
"""

from __future__ import annotations

import asyncio

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import InvalidMessage
from websockets.protocol import State

TIMEOUT_408 = (b"HTTP/1.1 408 Request Timeout\r\nContent-Type: text/plain\r\nContent-Length: 16\r\n"
               b"Connection: close\r\n\r\nrequest timeout\n")


class WaitingRoom:
    def __init__(self, max_waiting: int = 64, timeout_s: float = 10.0):
        self.max_waiting, self.timeout_s = max_waiting, timeout_s
        self.waiting: dict[ServerConnection, asyncio.TimerHandle] = {}  # oldest first

    def connection(self, *args, **kwargs) -> ServerConnection:
        """websockets' `create_connection` factory: a connection that checks in here."""
        return _Watched(self, *args, **kwargs)

    def arrived(self, connection: ServerConnection) -> None:
        if len(self.waiting) >= self.max_waiting:
            oldest = next(iter(self.waiting))  # the one that has held a slot longest without asking anything
            self.left(oldest)
            oldest.transport.abort()
        loop = asyncio.get_running_loop()
        self.waiting[connection] = loop.call_later(self.timeout_s, self._expire, connection)

    def requested(self, connection: ServerConnection) -> None:
        """Its request head arrived (websockets calls process_request): it no longer waits."""
        self.left(connection)

    def left(self, connection: ServerConnection) -> None:
        timer = self.waiting.pop(connection, None)
        if timer is not None:
            timer.cancel()

    def _expire(self, connection: ServerConnection) -> None:
        self.waiting.pop(connection, None)
        if connection.protocol.handshake_exc is None:  # (websockets answers itself what it could not parse)
            try:  # no request yet, so nothing of the handshake is under way: answer on the socket directly
                connection.transport.write(TIMEOUT_408)
            except RuntimeError:  # the socket is already shut for writing
                pass
        connection.transport.close()


BAD_REQUEST_400 = (b"HTTP/1.1 400 Bad Request\r\nContent-Type: text/plain\r\nContent-Length: 24\r\n"
                   b"Connection: close\r\n\r\nnot an HTTP/1.1 request\n")


class _Watched(ServerConnection):
    def __init__(self, room: WaitingRoom, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.room = room
        self.answered_400 = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        self.room.arrived(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.room.left(self)
        super().connection_lost(exc)

    def send_data(self) -> None:
        """A request head websockets cannot parse (HTTP/1.0, a garbled request line or version) it only
        half-closes, unanswered: answer 400 first, as an HTTP server does, so a client learns why."""
        if (self.protocol.state is State.CONNECTING and isinstance(self.protocol.handshake_exc, InvalidMessage)
                and not self.answered_400 and not self.transport.is_closing()):
            self.answered_400 = True
            self.transport.write(BAD_REQUEST_400)
        super().send_data()
