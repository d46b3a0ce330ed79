"""Static HTTP server for the web viewer (clients/web/) plus GET /config.json pointing it at the WebSocket.

A deliberately small server on its own thread and event loop, so nothing it does can slow the
streaming: GET and HEAD only, one request per connection, a deadline on reading a request and on
sending a response, a bounded number of connections, and only regular files inside explicitly
mounted folders (no directory listings, no dot files, symlinks followed only within a mount).
"""

from __future__ import annotations

import asyncio
import json
import mimetypes
import socket
import threading
from pathlib import Path
from urllib.parse import unquote, urlsplit

import streamer

WEB_DIR = Path(streamer.__file__).resolve().parents[1] / "clients" / "web"
MAX_HEAD_BYTES = 8192
MAX_FILE_BYTES = 64 * 1024 * 1024
TYPES = {".js": "text/javascript", ".mjs": "text/javascript", ".json": "application/json",
         ".html": "text/html; charset=utf-8", ".css": "text/css", ".wasm": "application/wasm"}
REASONS = {200: "OK", 400: "Bad Request", 404: "Not Found", 405: "Method Not Allowed",
           408: "Request Timeout", 431: "Request Header Fields Too Large", 503: "Service Unavailable"}


class ViewerServer:
    """Serves `mounts` ({URL path prefix ending in "/": folder, or exact URL path: file}) from a daemon
    thread; `url` is where to point a browser. The default mount is the web viewer folder at "/"."""

    def __init__(self, host: str, port: int, ws_port: int | None, token_required: bool, web_dir: Path = WEB_DIR,
                 mounts: dict[str, Path] | None = None, max_connections: int = 64, timeout_s: float = 10.0):
        self.mounts = {k: Path(v).resolve() for k, v in (mounts or {"/": web_dir}).items()}
        self.ws_port, self.token_required = ws_port or 0, token_required
        self.max_connections, self.timeout_s = max_connections, timeout_s
        self.connections = 0
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
        server.close()

    # ---- one connection --------------------------------------------------------------------------

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.connections >= self.max_connections:
            writer.transport.abort()  # over the limit: refuse at once rather than queue
            return
        self.connections += 1
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
            status, body, ctype, method = self._route(head)
            await self._respond(writer, status, body, ctype, head_only=method == "HEAD")
        finally:
            self.connections -= 1
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
            return 405, b"only GET and HEAD\n", "text/plain", method
        path = unquote(urlsplit(target).path)
        if path == "/config.json":
            return 200, self._config(head), "application/json", method
        file = self._file(path)
        if file is None:
            return 404, b"not found\n", "text/plain", method
        ctype = TYPES.get(file.suffix) or mimetypes.guess_type(file.name)[0] or "application/octet-stream"
        try:
            return 200, file.read_bytes(), ctype, method
        except OSError:
            return 404, b"not found\n", "text/plain", method

    def _file(self, path: str) -> Path | None:
        """The regular file a URL path names inside a mount, or None (never outside a mount)."""
        if "\0" in path or "\\" in path or not path.startswith("/"):
            return None
        if any(part.startswith(".") for part in path.split("/")):
            return None  # dot files and `..`
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

    def _config(self, head: bytes) -> bytes:
        # The browser reaches the WebSocket on the host it loaded this page from.
        host = "127.0.0.1"
        for line in head.split(b"\r\n")[1:]:
            name, _, value = line.partition(b":")
            if name.strip().lower() == b"host":
                host = urlsplit("//" + value.strip().decode("latin-1")).hostname or host
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
