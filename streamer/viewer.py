"""The web viewer's files (clients/web/), served by the WebSocket server on its own port.

`WsServer` hands every request that is not a WebSocket upgrade to `ViewerFiles.answer`, from websockets'
`process_request` hook, so the page, its assets and the WebSocket share one origin (the page connects to
the host and port it was loaded from). websockets has already read the request head within its own limits
on line length and header count; what is left here: GET and HEAD only, only regular files inside the
mounted folders (no directory listings, no dot files, symlinks followed only within a mount), at most
MAX_FILE_BYTES, a content type by suffix, and never a raise (whatever the target holds, the answer is a
status; the checks of paths are `streamer.request_checks`).
"""

from __future__ import annotations

import email.utils
import mimetypes
from dataclasses import dataclass
from http import HTTPStatus
from pathlib import Path

from websockets.datastructures import Headers
from websockets.http11 import Response

import streamer
from streamer import request_checks as RC

WEB_DIR = Path(streamer.__file__).resolve().parents[1] / "clients" / "web"
MAX_FILE_BYTES = 64 * 1024 * 1024
TYPES = {".js": "text/javascript", ".mjs": "text/javascript", ".json": "application/json",
         ".html": "text/html; charset=utf-8", ".css": "text/css", ".wasm": "application/wasm"}
TEXT = "text/plain; charset=utf-8"
# Cross-origin isolation: the page may share memory with its workers (the socket worker's frame ring,
# clients/web/socket-worker.js; onnxruntime-web's threads in local mode). Every file it loads is our own.
ISOLATION = (("Cross-Origin-Opener-Policy", "same-origin"), ("Cross-Origin-Embedder-Policy", "require-corp"))


@dataclass(frozen=True)
class Answer:
    status: int
    body: bytes
    content_type: str = TEXT
    head_only: bool = False  # HEAD: the headers of the GET answer, no body

    def response(self) -> Response:
        """As a websockets `Response` (sent instead of the upgrade; the connection closes after it)."""
        headers = Headers([("Date", email.utils.formatdate(usegmt=True)), ("Connection", "close"),
                           ("Content-Length", str(len(self.body))), ("Content-Type", self.content_type),
                           ("X-Content-Type-Options", "nosniff"), ("Cache-Control", "no-cache"), *ISOLATION])
        if self.status == HTTPStatus.METHOD_NOT_ALLOWED:
            headers["Allow"] = "GET, HEAD"
        return Response(self.status, HTTPStatus(self.status).phrase, headers, b"" if self.head_only else self.body)


class ViewerFiles:
    """Serves `mounts` ({URL path prefix ending in "/": folder, or exact URL path: file}); by default the web
    viewer's folder at "/"."""

    def __init__(self, mounts: dict[str, Path] | None = None):
        self.mounts = {k: Path(v).resolve() for k, v in (mounts or {"/": WEB_DIR}).items()}

    def answer(self, method: str, target: str) -> Answer:
        """A request's method and target -> the answer (a file, or a 4xx saying why not)."""
        head_only = method == "HEAD"
        if method not in ("GET", "HEAD"):
            return Answer(HTTPStatus.METHOD_NOT_ALLOWED, b"only GET and HEAD\n")
        if len(target) > RC.MAX_TARGET_CHARS:
            return Answer(HTTPStatus.REQUEST_URI_TOO_LONG, b"request target too long\n", head_only=head_only)
        if RC.split_target(target) is None:
            return Answer(HTTPStatus.BAD_REQUEST, b"bad request\n", head_only=head_only)
        path = RC.url_path(target)
        file = self.file(path) if path is not None else None
        try:
            body = file.read_bytes() if file is not None else None
        except OSError:
            body = None
        if body is None:
            return Answer(HTTPStatus.NOT_FOUND, b"not found\n", head_only=head_only)
        ctype = TYPES.get(file.suffix) or mimetypes.guess_type(file.name)[0] or "application/octet-stream"
        return Answer(HTTPStatus.OK, body, ctype, head_only)

    def file(self, path: str) -> Path | None:
        """The regular file a decoded URL path names inside a mount, or None (never outside a mount)."""
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


def is_upgrade(upgrade_headers: list[str]) -> bool:
    """Whether a request asks for a WebSocket (an `Upgrade` header naming websocket), not for a file."""
    return any(token.strip().lower() == "websocket" for value in upgrade_headers for token in value.split(","))
