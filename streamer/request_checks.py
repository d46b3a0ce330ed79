"""Pure checks of the parts of an HTTP request that the viewer and the WebSocket handshake read.

Every function takes untrusted text and returns a value or None ("malformed"); none of them raises, so a
caller answers a malformed request with a 4xx instead of a traceback. They are shared by the viewer's
files (`streamer.viewer`) and the WebSocket handshake (`streamer.ws`), served on one port, and hold no state.
"""

from __future__ import annotations

import ipaddress
import re
from urllib.parse import parse_qs, unquote

MAX_TARGET_CHARS = 2048  # a request target longer than this is refused (414)
MAX_SEGMENT_BYTES = 255  # NAME_MAX: a longer path segment cannot name a file (the OS raises on it)
MAX_PATH_BYTES = 1024

_HOST_NAME = re.compile(r"[a-z0-9](?:[a-z0-9-]{0,61}[a-z0-9])?(?:\.[a-z0-9](?:[a-z0-9-]{0,61}[a-z0-9])?)*\.?")
_PORT = re.compile(r"[0-9]{1,5}")
_SCHEME = re.compile(r"[a-z][a-z0-9+.-]{0,31}")


def split_target(target: str) -> tuple[str, str] | None:
    """An origin-form request target ("/path?query") -> (raw path, raw query), or None.

    Only the origin form is accepted ("/..."): absolute URLs and "*" are refused, and a target that starts
    with "//" is read as a path (urllib would read a host there, and raise on "//[::1").
    """
    if not isinstance(target, str) or not target.startswith("/") or len(target) > MAX_TARGET_CHARS:
        return None
    if any(c in target for c in " \t\r\n\0#"):
        return None
    path, _, query = target.partition("?")
    return path, query


def url_path(target: str) -> str | None:
    """The decoded path of a request target if it may name a file (`file_path`), else None."""
    parts = split_target(target)
    if parts is None:
        return None
    try:
        path = unquote(parts[0], errors="strict")
    except UnicodeDecodeError:
        return None
    return file_path(path)


def file_path(path: str) -> str | None:
    """`path` (decoded) if it may name a file: absolute, no NUL, no backslash, no dot segment (".", "..", dot
    files), no segment over 255 bytes (the OS raises on one), at most 1024 bytes; else None."""
    if not isinstance(path, str) or "\0" in path or "\\" in path or not path.startswith("/"):
        return None
    if len(path.encode("utf-8", "surrogatepass")) > MAX_PATH_BYTES:
        return None
    for segment in path.split("/"):
        if segment.startswith(".") or len(segment.encode("utf-8", "surrogatepass")) > MAX_SEGMENT_BYTES:
            return None
    return path


def query_value(target: str, name: str) -> str | None:
    """The first value of query parameter `name` in a request target, or None (absent or malformed)."""
    parts = split_target(target)
    if parts is None:
        return None
    try:
        values = parse_qs(parts[1], keep_blank_values=True, max_num_fields=64).get(name)
    except ValueError:  # more than max_num_fields
        return None
    return values[0] if values else None


def host_name(value: str) -> str | None:
    """A Host header value ("name[:port]", "1.2.3.4[:port]", "[v6][:port]") -> the lowercase host name (an IPv6
    literal without brackets), or None when it is malformed."""
    if not isinstance(value, str) or not value or len(value) > 300:
        return None
    value = value.strip().lower()
    if value.startswith("["):
        end = value.find("]")
        if end < 0:
            return None
        host, rest = value[1:end], value[end + 1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            return None
    else:
        host, _, port = value.partition(":")
        rest = f":{port}" if _ else ""
        if not _HOST_NAME.fullmatch(host):
            return None
    if rest and not (rest.startswith(":") and _PORT.fullmatch(rest[1:]) and int(rest[1:]) <= 65535):
        return None
    return host if ":" in host else host.rstrip(".")


def origin(value: str) -> str | None:
    """An Origin header value -> its lowercase serialized form ("scheme://host[:port]", or "null"), or None
    when it is not one: a path, even a lone "/" (browsers never send one), userinfo, a query or spaces."""
    if not isinstance(value, str) or len(value) > 300:
        return None
    value = value.lower()
    if value == "null":
        return value
    scheme, sep, authority = value.partition("://")
    if not sep or not _SCHEME.fullmatch(scheme) or host_name(authority) is None or any(c in authority for c in "/?#@"):
        return None
    return value


def allowed_origin(entry: str) -> str | None:
    """An --allow-origin entry -> the origin it allows (one trailing "/" forgiven), "*" or None if malformed."""
    entry = entry.strip()
    if entry == "*":
        return entry
    return origin(entry[:-1] if entry.endswith("/") and not entry.endswith("//") else entry)


REPEATED = "\0repeated"  # not a header value any client can send (NUL is refused in headers)


def single(values: list[str]) -> str | None:
    """The value of a header that may appear at most once: None when absent, REPEATED when it appears more
    than once (ambiguous: which one would the browser have meant? callers refuse it with a 400)."""
    if not values:
        return None
    return values[0] if len(values) == 1 else REPEATED
