"""No request raises (issue 25): the viewer's HTTP requests and the WebSocket handshake, fuzzed.

Both are answered on the WebSocket port. Malformed paths, hosts, origins, targets and header sets get a 4xx
(or, a request that is not HTTP at all is closed without an answer, as the websockets library does), never a
5xx, never a traceback in the log, and at most a rate-limited line. Hypothesis drives the pure checks and the routing;
a raw-socket loop sends a few hundred requests to live servers.
"""

import asyncio
import logging
import random
import socket

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from streamer import request_checks as RC
from streamer.redact import RedactTokens
from streamer.viewer import ViewerFiles
from helpers.ws import make_server, running, server

pytestmark = pytest.mark.timeout(180)
FUZZ = settings(max_examples=300, deadline=None,  # the fixtures used under @given hold no per-example state
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

# Pieces that broke or nearly broke something once, mixed into the generated text.
NASTY = ["[::1", "[", "]", "//", "/..", "%", "%00", "%2e%2e", "%ff", "\\", ":", "::", "@", "?", "#", "token=",
         "a" * 300, "é", "\x00", "\t", " ", "*", "http://", "https://app.example.com//", "[::1]:99999", "localhost."]
nasty_text = st.lists(st.one_of(st.sampled_from(NASTY), st.text(max_size=20)), max_size=6).map("".join)
targets = st.one_of(nasty_text, nasty_text.map(lambda t: "/" + t), st.just("/config.json"),
                    st.sampled_from(["/", "/index.html", "/config.json?x=[", "//[::1", "/" + "b" * 256,
                                     "/" + "c/" * 600, "/?token=" + "%" * 3]))
methods = st.one_of(st.sampled_from(["GET", "HEAD", "POST", "get", ""]), st.text(max_size=8))


def head(method: str, target: str, hdrs: list[tuple[str, str]], version: str = "HTTP/1.1") -> bytes:
    lines = [f"{method} {target} {version}", *(f"{k}: {v}" for k, v in hdrs)]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("utf-8", "surrogatepass")


# ---- the pure checks -----------------------------------------------------------------------------

@FUZZ
@given(nasty_text)
def test_the_request_checks_never_raise_and_keep_their_promises(text):
    host = RC.host_name(text)
    assert host is None or (host and "/" not in host and "[" not in host)
    origin = RC.origin(text)
    assert origin is None or origin == "null" or ("://" in origin and "/" not in origin.split("://", 1)[1])
    path = RC.url_path(text)
    assert path is None or (path.startswith("/") and ".." not in path.split("/") and "\0" not in path)
    assert path is None or all(len(seg.encode("utf-8", "surrogatepass")) <= 255 for seg in path.split("/"))
    RC.query_value(text, "token")
    RC.allowed_origin(text)


def test_origins_are_exact_and_hosts_well_formed():
    assert RC.origin("https://app.example.com") == "https://app.example.com"
    for bad in ("https://app.example.com//", "https://app.example.com/", "https://a.example.com/x",
                "https://u@a.example.com", "a.example.com", "https://a.example.com:99999"):
        assert RC.origin(bad) is None, bad
    assert RC.allowed_origin("http://myapp.example:3000/") == "http://myapp.example:3000"  # a config's slash: forgiven
    assert RC.host_name("[::1]:8080") == "::1" and RC.host_name("LocalHost:80") == "localhost"
    assert RC.host_name("[::1") is None and RC.host_name("evil.example/x") is None
    assert RC.single([]) is None and RC.single(["a"]) == "a" and RC.single(["a", "b"]) is RC.REPEATED


# ---- the viewer ----------------------------------------------------------------------------------

@pytest.fixture
def files(tmp_path):
    (tmp_path / "index.html").write_text("<html>viewer</html>")
    return ViewerFiles({"/": tmp_path})


@pytest.fixture
def viewer(files):
    """The WebSocket server (no model: it takes no client audio) serving `files`, on its own event loop."""
    with running(server({"type": "hello"}, None, files=files, request_timeout_s=1.0,
                          max_waiting=8)) as ws:
        yield ws


@FUZZ
@given(methods, targets)
def test_the_viewer_answers_every_request_with_a_status_below_500(files, method, target):
    # (websockets has parsed the head and its headers by then; the viewer reads only the method and target)
    answer = files.answer(method, target)
    assert answer.status in (200, 400, 404, 405, 414), (answer.status, answer.body)


def test_the_viewer_refuses_overlong_names_and_targets(files):
    assert files.answer("GET", "/" + "x" * 300).status == 404  # ENAMETOOLONG is a "not found"
    assert files.answer("GET", "/" + "x" * 3000).status == 414


def raw(port: int, request: bytes, timeout: float = 5.0) -> bytes:
    """Send a request on a fresh connection; what came back up to the end of the response head or the
    server's close (b"" for nothing)."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        try:
            s.sendall(request)
            out = b""
            while b"\r\n\r\n" not in out and (chunk := s.recv(65536)):
                out += chunk
            return out
        except (ConnectionResetError, BrokenPipeError, socket.timeout):
            return b""


def fuzz_requests(n: int, seed: int, websocket: bool) -> list[bytes]:
    """n request heads: random mixes of nasty methods, targets and headers (a valid handshake's headers
    first on the WebSocket port, so that the checks behind them are reached)."""
    rng = random.Random(seed)
    pick = lambda: rng.choice(NASTY) + rng.choice(["", "x", "/", rng.choice(NASTY)])  # noqa: E731
    base = [("Upgrade", "websocket"), ("Connection", "Upgrade"), ("Sec-WebSocket-Key", "dGhlIHNhbXBsZSBub25jZQ=="),
            ("Sec-WebSocket-Version", "13")] if websocket else []
    out = []
    for i in range(n):
        hdrs = [("Host", rng.choice(["127.0.0.1", "[::1", "localhost:1", pick()]))] + base
        for _ in range(rng.randrange(3)):
            hdrs.append((rng.choice(["Origin", "Host", "Origin", "X-" + pick()]), rng.choice([
                "http://127.0.0.1:8080", "https://app.example.com//", "null", pick()])))
        rng.shuffle(hdrs)
        target = rng.choice(["/", "/?token=s3cret", "/config.json", "/index.html", "/" + pick(), pick() + pick(),
                             "/" + "d" * rng.choice([254, 255, 256, 1000, 2100])])
        method = rng.choice(["GET", "GET", "GET", "HEAD", "POST", pick()])
        out.append(head(method, target, hdrs, rng.choice(["HTTP/1.1", "HTTP/1.1", "HTTP/1.0", pick()])))
    return out


def status_of(response: bytes) -> int | None:
    if not response:
        return None
    line = response.split(b"\r\n", 1)[0].split(b" ")
    return int(line[1]) if len(line) > 1 and line[1].isdigit() else -1


class Records(logging.Handler):
    def __init__(self):
        super().__init__(logging.INFO)
        self.records: list[logging.LogRecord] = []

    def emit(self, record):
        self.records.append(record)


@pytest.fixture
def records():
    handler = Records()
    root = logging.getLogger()
    old = root.level
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    yield handler.records
    root.removeHandler(handler)
    root.setLevel(old)


def test_a_flood_of_malformed_viewer_requests_gets_4xx_and_no_log(viewer, records):
    statuses = [status_of(raw(viewer.port, r)) for r in fuzz_requests(400, seed=1, websocket=False)]
    # (what websockets cannot parse as HTTP/1.1 gets our 400: streamer/waiting.py)
    assert all(s is not None and s < 500 for s in statuses), sorted(set(map(str, statuses)))
    assert {200, 400, 404, 414} <= set(statuses), sorted(set(map(str, statuses)))  # (the mix reached the checks)
    ours = [r for r in records if r.name.startswith("streamer")]
    theirs = [r for r in records if not r.name.startswith("streamer") and r.levelno >= logging.WARNING]
    assert not [r for r in records if r.exc_info], [r.getMessage() for r in records if r.exc_info][:3]
    assert len(ours) <= 2 and not theirs, [r.getMessage() for r in ours + theirs][:5]


def test_a_flood_of_malformed_handshakes_gets_4xx_and_at_most_a_rate_limited_line(bundle, records):
    async def run():
        ws = make_server(bundle, token="s3cret", origins=["http://127.0.0.1:8080"])
        await ws.open()
        loop = asyncio.get_running_loop()
        try:
            return [status_of(await loop.run_in_executor(None, raw, ws.port, r))
                    for r in fuzz_requests(400, seed=2, websocket=True)]
        finally:
            await ws.close()

    statuses = asyncio.run(run())
    assert all(s is not None and 100 <= s < 500 for s in statuses), sorted(set(map(str, statuses)))
    assert {400, 401, 403} <= set(statuses), sorted(set(map(str, statuses)))
    ours = [r for r in records if r.name.startswith("streamer")]
    theirs = [r for r in records if not r.name.startswith("streamer") and r.levelno >= logging.WARNING]
    assert not [r for r in records if r.exc_info], [r.getMessage() for r in records if r.exc_info][:3]
    assert len(ours) <= 2 and not theirs, [r.getMessage() for r in ours + theirs][:5]


@FUZZ
@given(targets, st.lists(nasty_text, max_size=3))
def test_the_handshake_check_never_raises(bundle, target, origins):
    ws = make_server(bundle, token="s3cret", origins=["http://127.0.0.1:8080"])
    status, why = ws.refusal(target, origins)
    assert status in (None, 400, 401, 403), (status, why)
    if status is None:
        assert RC.query_value(target, "token") == "s3cret"


def test_origins_with_a_path_or_given_twice_are_refused(bundle):
    ws = make_server(bundle, origins=["https://app.example.com"])
    assert ws.refusal("/", ["https://app.example.com"])[0] is None
    assert ws.refusal("/", [])[0] is None  # native clients send none
    assert ws.refusal("/", ["https://app.example.com//"])[0] == 400
    assert ws.refusal("/", ["https://evil.example"])[0] == 403
    assert ws.refusal("/", ["https://app.example.com", "https://app.example.com"])[0] == 400
    assert ws.refusal("//[::1", [])[0] is None and make_server(bundle, token="t").refusal("//[::1", [])[0] == 401


def test_the_token_is_masked_wherever_it_appears_in_a_log_line():
    RedactTokens.add_secret("pa th/s3cret")
    try:
        record = logging.LogRecord("websockets.server", logging.DEBUG, __file__, 1, "< GET %s HTTP/1.1",
                                   ("/pa%20th%2Fs3cret/x?a=1&token=other",), None)
        RedactTokens().filter(record)
        assert record.getMessage() == "< GET /***/x?a=1&token=*** HTTP/1.1"
    finally:
        RedactTokens.secrets.clear()


def test_connections_held_open_cannot_shut_real_requests_out(viewer):
    """One client re-opening slow connections (never sending a whole request) beside real requests: the
    real ones are all served (the server drops the connection that has waited longest without a request)."""
    held, served = [], 0
    try:
        for i in range(30):
            for _ in range(3):  # the abuser keeps re-opening, 3 per real request, past the limit of 8
                s = socket.create_connection(("127.0.0.1", viewer.port))
                s.sendall(b"GET / HTTP/1.1\r\n")  # and never finishes its request
                held.append(s)
            served += raw(viewer.port, b"GET / HTTP/1.1\r\nHost: localhost\r\n\r\n").startswith(b"HTTP/1.1 200")
    finally:
        for s in held:
            s.close()
    assert served == 30 and len(viewer.waiting_room.waiting) <= viewer.waiting_room.max_waiting


@pytest.mark.parametrize("request_head", [b"GET /\r\n\r\n", b"hello there\r\n\r\n",
                                          b"GET /config.json HTTP/9\r\n\r\n"])
def test_a_request_websockets_cannot_parse_gets_400_not_a_silent_close(viewer, request_head):
    response = raw(viewer.port, request_head)
    assert status_of(response) == 400, response
