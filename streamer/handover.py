"""Sessions that outlive their worker: a client session's state saved to a store under a resume token.

A worker told to stop (SIGTERM) with a state store (`--state-store`) finishes the audio each client session
holds, saves the session (the stream's state, `dimgestor.savestate`, with the pose decoder's root and the frame
count beside it) under a fresh token, sends the client `goaway` with the token and the audio sample its state
covers, and closes with 1012. The client reconnects (through the balancer: any worker), sends `resume_session`
with the token and re-sends its audio from that sample; the frames that follow are those of an uninterrupted
run. A token resumes once and expires after `ttl_s`.

Stores: `MemoryStore` (one process: tests, a single server) and `RedisStore` (a cluster: every worker reaches
the same Redis). Both are blocking; the server calls them on a thread of their own (`streamer.store_link`).
"""
from __future__ import annotations

import secrets
import threading
import time
from typing import Protocol

__all__ = ["MemoryStore", "RedisStore", "StateStore", "new_token", "open_store"]

KEY_PREFIX = "dimgestor:session:"
DEFAULT_TTL_S = 300.0  # a client reconnects within seconds; a state nobody resumes is gone after 5 minutes


class StateStore(Protocol):
    ttl_s: float

    def put(self, token: str, data: bytes) -> None: ...

    def take(self, token: str) -> bytes | None:
        """The state saved under `token`, removed from the store (a token resumes once); None: unknown or expired."""
        ...

    def describe(self) -> str: ...


def new_token() -> str:
    """A resume token: 128 random bits, URL-safe (it names a session's state; whoever holds it may resume it)."""
    return secrets.token_urlsafe(16)


class MemoryStore:
    """States in this process's memory, each expiring `ttl_s` after it was saved."""

    def __init__(self, ttl_s: float = DEFAULT_TTL_S, now=time.monotonic):
        self.ttl_s, self.now = float(ttl_s), now
        self._items: dict[str, tuple[float, bytes]] = {}
        self._lock = threading.Lock()

    def put(self, token: str, data: bytes) -> None:
        with self._lock:
            t = self.now()
            self._items = {k: v for k, v in self._items.items() if v[0] > t}  # drop the expired
            self._items[token] = (t + self.ttl_s, bytes(data))

    def take(self, token: str) -> bytes | None:
        with self._lock:
            item = self._items.pop(token, None)
        return item[1] if item is not None and item[0] > self.now() else None

    def ping(self) -> None:
        """(Always answers: it is this process's memory.)"""

    def describe(self) -> str:
        return f"in-process (states expire after {self.ttl_s:g} s)"


class RedisStore:
    """States in Redis (`redis://HOST:PORT/DB`), set with an expiry and taken with GETDEL (atomic: two workers
    cannot both resume one token)."""

    def __init__(self, url: str, ttl_s: float = DEFAULT_TTL_S, timeout_s: float = 1.0):  # (loopback/LAN: ms)
        import redis

        self.url, self.ttl_s = url, float(ttl_s)
        self.client = redis.Redis.from_url(url, socket_timeout=timeout_s, socket_connect_timeout=timeout_s)

    def put(self, token: str, data: bytes) -> None:
        self.client.set(KEY_PREFIX + token, bytes(data), px=max(1, int(self.ttl_s * 1000)))

    def take(self, token: str) -> bytes | None:
        return self.client.getdel(KEY_PREFIX + token)

    def ping(self) -> None:
        self.client.ping()

    def describe(self) -> str:
        from urllib.parse import urlsplit

        u = urlsplit(self.url)
        return f"redis {u.hostname}:{u.port or 6379}{u.path or ''} (states expire after {self.ttl_s:g} s)"


def open_store(spec: str | None, ttl_s: float = DEFAULT_TTL_S) -> StateStore | None:
    """`--state-store`: None (sessions end with their worker), "memory" or a redis:// URL."""
    if not spec:
        return None
    if spec == "memory":
        return MemoryStore(ttl_s)
    if spec.startswith(("redis://", "rediss://", "unix://")):
        try:
            import redis  # noqa: F401
        except ImportError:
            raise SystemExit("--state-store redis://...: the redis client is not installed "
                             "(pip install 'dimgestor[cluster]')") from None
        return RedisStore(spec, ttl_s)
    raise SystemExit(f"--state-store: 'memory' or a redis://HOST:PORT/DB URL, got {spec!r}")
