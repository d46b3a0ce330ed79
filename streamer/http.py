"""Static HTTP server for the web viewer (clients/web/) plus GET /config.json pointing it at the WebSocket.

A deliberately small server on its own thread and event loop, so nothing it does can slow the
streaming: GET and HEAD only, one request per connection, a deadline on reading a request and on
sending a response, a bounded number of connections (when all are taken, the one that has waited
longest for its request is dropped for a new one: holding connections open cannot shut others out),
and only regular files inside explicitly mounted folders (no directory listings, no dot files, symlinks
followed only within a mount). No request raises: whatever it holds, the answer is a status line (the
checks of paths and headers are `streamer.request_checks`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import mimetypes
import socket
import threading
from pathlib import Path

import streamer
from streamer import request_checks as RC
from streamer.log_limit import ErrorLog

WEB_DIR = Path(streamer.__file__).resolve().parents[1] / "clients" / "web"
MAX_HEAD_BYTES = 8192
MAX_FILE_BYTES = 64 * 1024 * 1024
TYPES = {".js": "text/javascript", ".mjs": "text/javascript", ".json": "application/json",
         ".html": "text/html; charset=utf-8", ".css": "text/css", ".wasm": "application/wasm"}
REASONS = {200: "OK", 400: "Bad Request", 404: "Not Found", 405: "Method Not Allowed", 408: "Request Timeout",
           414: "URI Too Long", 431: "Request Header Fields Too Large", 500: "Internal Server Error",
           503: "Service Unavailable"}
log = logging.getLogger("streamer.http")


class ViewerServer:
    """Serves `mounts` ({URL path prefix ending in "/": folder, or exact URL path: file}) from a daemon
    thread; `url` is where to point a browser. The default mount is the web viewer folder at "/"."""

    def __init__(self, host: str, port: int, ws_port: int | None, token_required: bool, web_dir: Path = WEB_DIR,
                 mounts: dict[str, Path] | None = None, max_connections: int = 64, timeout_s: float = 10.0,
                 ws_hosts: set[str] | None = None):
        self.mounts = {k: Path(v).resolve() for k, v in (mounts or {"/": web_dir}).items()}
        self.ws_port, self.token_required = ws_port or 0, token_required
        self.ws_hosts = ws_hosts  # the Host names config.json may point the viewer to (None: any well-formed one)
        self.max_connections, self.timeout_s = max_connections, timeout_s
        self.waiting: dict[asyncio.StreamWriter, None] = {}  # connections still reading their request, oldest first
        self.busy = 0  # connections past their request (being answered)
        self.failures = ErrorLog("viewer", what="failed requests", logger=log)
        self.web_dir = web_dir
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.create_server((host, port), family=family, backlog=128)
        self.host, self.port = host, self.sock.getsockname()[1]
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self._run, name="http", daemon=True)
        self._stopped: asyncio.Event | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def start(self) -> None:
        self.thread.start()

    def close(self) -> None:
        if self.thread.is_alive() and self._stopped is not None:
            self.loop.call_soon_threadsafe(self._stopped.set)
            self.thread.join(2.0)
        else:
            self.sock.close()

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_until_complete(self._main())

    async def _main(self) -> None:
        self._stopped = asyncio.Event()
        server = await asyncio.start_server(self._serve, sock=self.sock, limit=MAX_HEAD_BYTES)
        async with server:
            await self._stopped.wait()
            for writer in list(self.waiting):  # connections still sending a request: not worth waiting for
                writer.transport.abort()
        server.close()

    # ---- one connection --------------------------------------------------------------------------

    @property
    def connections(self) -> int:
        return len(self.waiting) + self.busy

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.connections >= self.max_connections:
            if not self.waiting:
                writer.transport.abort()  # every connection is being answered: refuse at once rather than queue
                return
            oldest = next(iter(self.waiting))  # the one that has held a slot longest without asking anything
            del self.waiting[oldest]
            oldest.transport.abort()
        self.waiting[writer] = None
        answering = False
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), self.timeout_s)
            except asyncio.TimeoutError:
                await self._respond(writer, 408, b"request timeout\n")
                return
            except asyncio.LimitOverrunError:
                await self._respond(writer, 431, b"request head too large\n")
                return
            except (asyncio.IncompleteReadError, ConnectionError):
                return
            if self.waiting.pop(writer, 0) is not None:  # evicted meanwhile (for a newer connection)
                return
            self.busy += 1
            answering = True
            try:
                status, body, ctype, method = self._route(head)
            except Exception as e:  # a bug: one line (rate-limited), no traceback, and an answer all the same
                self.failures(logging.ERROR, f"failed on a request: {type(e).__name__}: {e}")
                status, body, ctype, method = 500, b"internal error\n", "text/plain", ""
            await self._respond(writer, status, body, ctype, head_only=method == "HEAD")
        finally:
            self.waiting.pop(writer, None)
            self.busy -= answering
            if writer.transport.get_write_buffer_size():
                writer.transport.abort()  # a client that does not read what it asked for
            else:
                writer.close()

    def _route(self, head: bytes) -> tuple[int, bytes, str, str]:
        """A request head -> (status, body, content type, method)."""
        try:
            method, target, version = head.split(b"\r\n", 1)[0].decode("ascii").split(" ")
        except (UnicodeDecodeError, ValueError):
            return 400, b"bad request\n", "text/plain", ""
        if method not in ("GET", "HEAD"):
            return 405, b"only GET and HEAD\n", "text/plain", ""
        if len(target) > RC.MAX_TARGET_CHARS:
            return 414, b"request target too long\n", "text/plain", method
        if RC.split_target(target) is None or not version.startswith("HTTP/1."):
            return 400, b"bad request\n", "text/plain", method
        path = RC.url_path(target)
        if path == "/config.json":
            config = self._config(head)
            if config is None:
                return 400, b"bad Host header\n", "text/plain", method
            return 200, config, "application/json", method
        file = self._file(path) if path is not None else None
        if file is None:
            return 404, b"not found\n", "text/plain", method
        ctype = TYPES.get(file.suffix) or mimetypes.guess_type(file.name)[0] or "application/octet-stream"
        try:
            return 200, file.read_bytes(), ctype, method
        except OSError:
            return 404, b"not found\n", "text/plain", method

    def _file(self, path: str) -> Path | None:
        """The regular file a URL path names inside a mount, or None (never outside a mount)."""
        if RC.file_path(path) is None:  # (dot files, `..`, NUL, over-long segments...)
            return None
        try:
            return self._mounted(path)
        except (OSError, ValueError, RuntimeError):  # the file system's own refusals (a name too long, a loop)
            return None

    def _mounted(self, path: str) -> Path | None:
        for prefix in sorted(self.mounts, key=len, reverse=True):
            root = self.mounts[prefix]
            if path == prefix or (prefix.endswith("/") and path.startswith(prefix)):
                rel = path[len(prefix):] if prefix.endswith("/") else ""
                target = (root / rel) if rel else root
                if target.is_dir():
                    target = target / "index.html"
                try:
                    real = target.resolve(strict=True)
                except (OSError, RuntimeError):
                    return None
                base = root if root.is_dir() else root.parent
                inside = real == root or real.is_relative_to(base)
                if inside and real.is_file() and real.stat().st_size <= MAX_FILE_BYTES:
                    return real
                return None
        return None

    def _config(self, head: bytes) -> bytes | None:
        """config.json: the WebSocket on the host the browser loaded this page from, if it is one of this
        server's names (a Host header is the client's to choose: an arbitrary one is never echoed back);
        None for a malformed or repeated Host header."""
        values = [value.strip().decode("latin-1") for name, _, value in
                  (line.partition(b":") for line in head.split(b"\r\n")[1:]) if name.strip().lower() == b"host"]
        given = RC.single(values)
        if given is RC.REPEATED:
            return None
        host = RC.host_name(given) if given is not None else None
        if given is not None and host is None:
            return None
        if host is None or (self.ws_hosts is not None and host not in self.ws_hosts):
            host = self.host if self.host not in ("0.0.0.0", "::", "") else "127.0.0.1"
        host = f"[{host}]" if ":" in host else host  # IPv6 literal
        return json.dumps({"ws_url": f"ws://{host}:{self.ws_port}/", "token_required": self.token_required}).encode()

    async def _respond(self, writer: asyncio.StreamWriter, status: int, body: bytes, ctype: str = "text/plain",
                       head_only: bool = False) -> None:
        headers = [f"HTTP/1.1 {status} {REASONS[status]}", f"Content-Type: {ctype}", f"Content-Length: {len(body)}",
                   "Connection: close", "X-Content-Type-Options: nosniff", "Cache-Control: no-cache"]
        if status == 405:
            headers.append("Allow: GET, HEAD")
        writer.write(("\r\n".join(headers) + "\r\n\r\n").encode() + (b"" if head_only else body))
        try:
            await asyncio.wait_for(writer.drain(), self.timeout_s)
        except (asyncio.TimeoutError, ConnectionError):
            pass
