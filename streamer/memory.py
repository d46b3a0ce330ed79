"""Give memory freed after a burst back to the system.

A flood of fast senders fills the server with megabytes of queued audio per client; once they have drained,
CPython and numpy free it, but glibc's allocator keeps most of the pages for reuse: measured, 8 clients took
the process from 319 to 403 MB and it stayed there; `malloc_trim(0)` brought it to 332 MB (31 clients: 319 ->
650-800 MB kept). `Trimmer` calls it after sessions end, at most once per `every_s`, on a worker thread
(ctypes releases the GIL for the call), a second after one ends so that its buffers are gone. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import time
from typing import Callable


def _malloc_trim() -> Callable[[], object] | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):  # not glibc (musl, macOS, Windows)
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return lambda: trim(0)


class Trimmer:
    """When to trim: `wait_s()` until the next trim may run (at most one per `every_s`); `trim()` runs it (any
    thread) and counts it."""

    def __init__(self, every_s: float = 30.0, now: Callable[[], float] = time.monotonic,
                 release: Callable[[], object] | None = None):
        self.every_s, self.now = every_s, now
        self.release = release if release is not None else _malloc_trim()
        self.last: float | None = None
        self.count = 0

    @property
    def available(self) -> bool:
        return self.release is not None

    def wait_s(self) -> float:
        return 0.0 if self.last is None else max(0.0, self.every_s - (self.now() - self.last))

    def trim(self) -> None:
        self.last = self.now()
        self.count += 1
        self.release()
