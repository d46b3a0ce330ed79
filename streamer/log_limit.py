"""One log line at most every so often, whatever floods it: what each client's errors, refused handshakes,
departures and failed viewer requests are logged through, so no client can grow the log faster than that."""

from __future__ import annotations

import logging
import time

log = logging.getLogger("streamer.ws")


class ErrorLog:
    """Logs at most once per `every_s` (one line, prefixed with `who`), with how many were not logged in between."""

    def __init__(self, who: str, every_s: float = 10.0, what: str = "errors", logger: logging.Logger = log):
        self.who, self.every_s, self.what, self.log = who, every_s, what, logger
        self.last = -float("inf")
        self.unlogged = 0

    def __call__(self, level: int, text: str, exc_info: bool = False) -> None:
        now = time.monotonic()
        if now - self.last < self.every_s:
            self.unlogged += 1
            return
        more = f" (and {self.unlogged} more {self.what} in the last {now - self.last:.0f} s)" if self.unlogged else ""
        self.log.log(level, "%s: %s%s", self.who, text, more, exc_info=exc_info)
        self.last, self.unlogged = now, 0
