"""Sessions that outlive their worker: a client session's state saved to a store under a resume token.

A worker told to stop (SIGTERM) with a state store (`--state-store`) finishes the audio each client session
holds, saves the session (the stream's state, `dimgestor.streaming.savestate`, with the pose decoder's root and the frame
count beside it) under a fresh token, sends the client `goaway` with the token and the audio sample its state
covers, and closes with 1012. The client reconnects (through the balancer: any worker), sends `resume_session`
with the token and re-sends its audio from that sample; the frames that follow are those of an uninterrupted
run. A token resumes once and expires after `ttl_s`.

A token is a capability: whoever holds it may take the state, so the store never shows one. Keys are a hash of
the token (listing them reveals none); a take consumes the token for good (a tombstone, `spent`, refuses any
later put under it: the owner's next periodic save cannot make it resumable again); and while the session is
live on a connection its worker holds a lease on its token (`touch` every `TOUCH_EVERY_S`, `release` when the
connection goes), so a periodic-save token resumes only after a lost connection: a take while the lease holds is
refused with `SessionLive`. After a crash nobody releases: the state becomes resumable when the lease runs out
(`lease_s`). A hand-over's token is fresh and has no lease.

Stores: `MemoryStore` (one process: tests, a single server) and `RedisStore` (a cluster: every worker reaches
the same Redis). Both are blocking, with the same semantics; the server calls them on a thread of their own
(`streamer.store_link`). A state larger than `max_bytes` is refused (`StateRefused`), so one session cannot fill
the store.
"""
from __future__ import annotations

import hashlib
import secrets
import threading
import time
from typing import Iterable, Protocol

__all__ = ["MemoryStore", "RedisStore", "SessionLive", "StateRefused", "StateStore", "StoreAnswer", "new_token",
           "open_store", "token_hash"]

KEY_PREFIX = "dimgestor:"  # + "state:", "live:" or "spent:" + the token's hash
DEFAULT_TTL_S = 300.0  # a client reconnects within seconds; a state nobody resumes is gone after 5 minutes
LEASE_S = 3.0  # a live session's lease: its worker renews it every TOUCH_EVERY_S; after a crash, this late
TOUCH_EVERY_S = 1.0
# One saved state is ~1.2 MB with the default model (docs/deploy.md); 4x that leaves room for larger presets.
DEFAULT_MAX_BYTES = 5 * 2**20


class StoreAnswer(Exception):
    """The store answered, with a no: not a failure of the store (the link passes it on as it is)."""


class StateRefused(StoreAnswer):
    """A put the store refuses: `reason` "too_large" (over `max_bytes`) or "spent" (the token was taken)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


class SessionLive(StoreAnswer):
    """A take refused: the token's session is live on a connection (its lease runs `retry_after_s` more)."""

    def __init__(self, retry_after_s: float):
        super().__init__(f"the session is live on a connection (its lease runs {retry_after_s:.1f} s more)")
        self.retry_after_s = retry_after_s


class StateStore(Protocol):
    ttl_s: float
    max_bytes: int

    def put(self, token: str, data: bytes, live: bool = False) -> None:
        """Save `data` under `token` (overwriting); live: its session is live here (the lease is renewed too).
        Raises StateRefused."""
        ...

    def take(self, token: str) -> bytes | None:
        """The state saved under `token`, removed and the token consumed (a token resumes once); None: unknown,
        expired or already taken. Raises SessionLive while the token's lease holds."""
        ...

    def touch(self, tokens: list[str]) -> None:
        """Renew the leases of these live sessions' tokens (for `lease_s` from now)."""
        ...

    def release(self, token: str) -> None:
        """The token's connection is gone: its state (if any) may be taken now."""
        ...

    def forget(self, token: str) -> None:
        """The token's session ended: its state and lease go and the token is consumed."""
        ...

    def describe(self) -> str: ...


def new_token() -> str:
    """A resume token: 128 random bits, URL-safe (it names a session's state; whoever holds it may resume it)."""
    return secrets.token_urlsafe(16)


def token_hash(token: str) -> str:
    """What the store keys a token by: its SHA-256 (128 random bits need no salt)."""
    return hashlib.sha256(token.encode()).hexdigest()


def _check_size(data: bytes, max_bytes: int) -> None:
    if len(data) > max_bytes:
        raise StateRefused("too_large", f"a state of {len(data)} bytes is over the store's cap of {max_bytes} "
                                        "(--state-max-bytes)")


def _spent() -> StateRefused:
    return StateRefused("spent", "the token was taken or its session ended: it saves nothing more")


class MemoryStore:
    """States in this process's memory, each expiring `ttl_s` after it was saved."""

    def __init__(self, ttl_s: float = DEFAULT_TTL_S, now=time.monotonic, lease_s: float = LEASE_S,
                 max_bytes: int = DEFAULT_MAX_BYTES):
        self.ttl_s, self.now, self.lease_s, self.max_bytes = float(ttl_s), now, float(lease_s), int(max_bytes)
        self._states: dict[str, tuple[float, bytes]] = {}  # hash -> (expires, state)
        self._leases: dict[str, float] = {}  # hash -> until
        self._spent: dict[str, float] = {}  # hash -> expires
        self._lock = threading.Lock()

    def _drop_expired(self, t: float) -> None:
        self._states = {k: v for k, v in self._states.items() if v[0] > t}
        self._leases = {k: v for k, v in self._leases.items() if v > t}
        self._spent = {k: v for k, v in self._spent.items() if v > t}

    def put(self, token: str, data: bytes, live: bool = False) -> None:
        _check_size(data, self.max_bytes)
        h = token_hash(token)
        with self._lock:
            t = self.now()
            self._drop_expired(t)
            if h in self._spent:
                raise _spent()
            self._states[h] = (t + self.ttl_s, bytes(data))
            if live:
                self._leases[h] = t + self.lease_s

    def take(self, token: str) -> bytes | None:
        h = token_hash(token)
        with self._lock:
            t = self.now()
            if self._spent.get(h, t) > t:
                return None
            if (until := self._leases.get(h, t)) > t:
                raise SessionLive(until - t)
            item = self._states.pop(h, None)
            if item is None or item[0] <= t:
                return None
            self._leases.pop(h, None)
            self._spent[h] = t + self.ttl_s
            return item[1]

    def touch(self, tokens: Iterable[str]) -> None:
        with self._lock:
            until = self.now() + self.lease_s
            self._leases.update((token_hash(token), until) for token in tokens)

    def release(self, token: str) -> None:
        with self._lock:
            self._leases.pop(token_hash(token), None)

    def forget(self, token: str) -> None:
        h = token_hash(token)
        with self._lock:
            self._states.pop(h, None)
            self._leases.pop(h, None)
            self._spent[h] = self.now() + self.ttl_s

    def keys(self) -> list[str]:
        """What the store holds, as Redis would list it (tests: no token shows)."""
        with self._lock:
            return [KEY_PREFIX + kind + ":" + h for kind, d in (("state", self._states), ("live", self._leases),
                                                               ("spent", self._spent)) for h in d]

    def ping(self) -> None:
        """(Always answers: it is this process's memory.)"""

    def describe(self) -> str:
        return f"in-process (states expire after {self.ttl_s:g} s)"


# Redis: one Lua script per operation, so each is atomic (two workers cannot both take a token; a put cannot
# land between a take's check and its tombstone). KEYS = state, live, spent. A lease's value is the Redis clock
# (ms) it holds until, and its key expires with the state's TTL, not the lease's: under `maxmemory-policy
# volatile-ttl` the keys nearest expiry go first, and a short-lived lease key would go before any state, making a
# live session's token resumable.
_NOW = "local t = redis.call('TIME') local now = t[1] * 1000 + math.floor(t[2] / 1000) "
_PUT = _NOW + """
if redis.call('EXISTS', KEYS[3]) == 1 then return 0 end
redis.call('SET', KEYS[1], ARGV[1], 'PX', ARGV[2])
if ARGV[3] == '1' then redis.call('SET', KEYS[2], now + ARGV[4], 'PX', ARGV[2]) end
return 1
"""
_TAKE = _NOW + """
if redis.call('EXISTS', KEYS[3]) == 1 then return {0} end
local live = tonumber(redis.call('GET', KEYS[2]) or '0')
if live > now then return {1, live - now} end
local data = redis.call('GET', KEYS[1])
if not data then return {0} end
redis.call('DEL', KEYS[1], KEYS[2])
redis.call('SET', KEYS[3], '1', 'PX', ARGV[1])
return {2, data}
"""
_TOUCH = _NOW + """
for i = 1, #KEYS do redis.call('SET', KEYS[i], now + ARGV[1], 'PX', ARGV[2]) end
return #KEYS
"""
_FORGET = """
redis.call('DEL', KEYS[1], KEYS[2])
redis.call('SET', KEYS[3], '1', 'PX', ARGV[1])
return 1
"""


class RedisStore:
    """States in Redis (`redis://[USER:PASSWORD@]HOST:PORT/DB`, `rediss://` for TLS), set with an expiry."""

    def __init__(self, url: str, ttl_s: float = DEFAULT_TTL_S, timeout_s: float = 1.0, lease_s: float = LEASE_S,
                 max_bytes: int = DEFAULT_MAX_BYTES):  # (timeout: loopback/LAN answers in ms)
        import redis

        self.url, self.ttl_s, self.lease_s, self.max_bytes = url, float(ttl_s), float(lease_s), int(max_bytes)
        self.client = redis.Redis.from_url(url, socket_timeout=timeout_s, socket_connect_timeout=timeout_s)
        self._put, self._take, self._touch, self._forget = (self.client.register_script(s)
                                                            for s in (_PUT, _TAKE, _TOUCH, _FORGET))

    def _ms(self, seconds: float) -> int:
        return max(1, int(seconds * 1000))

    @staticmethod
    def _keys(token: str) -> list[str]:
        h = token_hash(token)
        return [f"{KEY_PREFIX}state:{h}", f"{KEY_PREFIX}live:{h}", f"{KEY_PREFIX}spent:{h}"]

    def put(self, token: str, data: bytes, live: bool = False) -> None:
        _check_size(data, self.max_bytes)
        if not self._put(self._keys(token), [bytes(data), self._ms(self.ttl_s), int(live), self._ms(self.lease_s)]):
            raise _spent()

    def take(self, token: str) -> bytes | None:
        got = self._take(self._keys(token), [self._ms(self.ttl_s)])
        if got[0] == 1:
            raise SessionLive(int(got[1]) / 1000)
        return got[1] if got[0] == 2 else None

    def touch(self, tokens: Iterable[str]) -> None:
        keys = [f"{KEY_PREFIX}live:{token_hash(t)}" for t in tokens]
        if keys:
            self._touch(keys, [self._ms(self.lease_s), self._ms(self.ttl_s)])

    def release(self, token: str) -> None:
        self.client.delete(self._keys(token)[1])

    def forget(self, token: str) -> None:
        self._forget(self._keys(token), [self._ms(self.ttl_s)])

    def ping(self) -> None:
        self.client.ping()

    def describe(self) -> str:
        """Where (never the password)."""
        from urllib.parse import urlsplit

        u = urlsplit(self.url)
        who = f"{u.username}@" if u.username else ""
        tls = " TLS" if u.scheme == "rediss" else ""
        return (f"redis{tls} {who}{u.hostname}:{u.port or 6379}{u.path or ''} (states expire after "
                f"{self.ttl_s:g} s)")


def open_store(spec: str | None, ttl_s: float = DEFAULT_TTL_S, max_bytes: int = DEFAULT_MAX_BYTES) -> StateStore | None:
    """`--state-store`: None (sessions end with their worker), "memory" or a redis:// URL."""
    if not spec:
        return None
    if spec == "memory":
        return MemoryStore(ttl_s, max_bytes=max_bytes)
    if spec.startswith(("redis://", "rediss://", "unix://")):
        try:
            import redis  # noqa: F401
        except ImportError:
            raise SystemExit("--state-store redis://...: the redis client is not installed "
                             "(pip install 'dimgestor[cluster]')") from None
        _keep_password_out_of_logs(spec)
        return RedisStore(spec, ttl_s, max_bytes=max_bytes)
    raise SystemExit(f"--state-store: 'memory' or a redis://HOST:PORT/DB URL, got {spec!r}")


def _keep_password_out_of_logs(url: str) -> None:
    """The URL's password (and the URL itself) is masked in every log line (`streamer.redact`)."""
    from urllib.parse import unquote, urlsplit

    from streamer.redact import RedactTokens

    password = urlsplit(url).password
    if password:
        RedactTokens.add_secret(unquote(password))
        RedactTokens.add_secret(password)
