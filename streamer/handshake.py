"""The HTTP side of the WebSocket port: `/healthz`, `/readyz`, `/metrics` and the viewer's files are answered,
and a WebSocket handshake is checked (origin, then token) before it reaches the server."""

from __future__ import annotations

import hmac
import logging
import socket
from http import HTTPStatus

from streamer import health
from streamer import request_checks as RC
from streamer.log_limit import ErrorLog
from streamer.viewer import Answer, ViewerFiles, is_upgrade

REFUSED = {HTTPStatus.FORBIDDEN: "origin not allowed (see dimgestor serve --allow-origin)\n",
           HTTPStatus.UNAUTHORIZED: "missing or wrong token (use ?token=...)\n"}


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


def refusal(target: str, origins: list[str], version: str, allowed: set[str],
            token: str | None) -> tuple[HTTPStatus | None, str]:
    """(None, "") to accept a handshake for request target `target` with these Origin headers, else
    (status, why): 400 for a malformed target or Origin (or two of them) or an HTTP version other than
    1.1 (the WebSocket handshake's own; the library would answer 505), 403 for an origin not `allowed`
    ("*": any), 401 for a missing or wrong token."""
    if RC.split_target(target) is None or version != "HTTP/1.1":
        return HTTPStatus.BAD_REQUEST, "a malformed request target or HTTP version"
    given = RC.single(origins)
    if given is RC.REPEATED:
        return HTTPStatus.BAD_REQUEST, f"{len(origins)} Origin headers"
    if given is not None and "*" not in allowed:
        origin = RC.origin(given)
        if origin is None:
            return HTTPStatus.BAD_REQUEST, "a malformed Origin header"
        if origin not in allowed:
            return HTTPStatus.FORBIDDEN, f"origin {origin[:100]!r} (not in the allow-list; see --allow-origin)"
    if token is None:
        return None, ""
    given_token = RC.query_value(target, "token")
    if given_token is None or not hmac.compare_digest(given_token.encode("utf-8", "surrogatepass"), token.encode()):
        return HTTPStatus.UNAUTHORIZED, "a missing or wrong token"
    return None, ""


class Front:
    """Answers what is not a WebSocket upgrade and checks what is; never raises (a raise would be a 500 and a
    traceback in the log). `refusal(target, origins, version) -> (status or None, why)` is the server's
    handshake check (its allow-list as it is now: the server's own origins are known once it listens)."""

    def __init__(self, waiting_room, metrics, serve_metrics: bool, files: ViewerFiles | None, refusal):
        self.waiting_room, self.metrics, self.serve_metrics, self.files = waiting_room, metrics, serve_metrics, files
        self.refusal = refusal
        self.refusals = ErrorLog("refused handshakes", what="refusals")  # one line per 10 s, whatever the flood
        self.file_failures = ErrorLog("viewer", what="failed requests")

    def process_request(self, connection, request):
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
        return connection.respond(status, REFUSED.get(status, "bad request\n"))
