"""Keeping the token out of the log: a logging filter on every handler of `dimgestor serve`.

Its state (the server's own token) is class-level and lives in this module rather than in the command line's,
which runs as `__main__` under `python -m dimgestor.cli` (a second copy of its classes when imported).
"""

from __future__ import annotations

import logging
import re


class RedactTokens(logging.Filter):
    """Keeps tokens out of every log line (websockets logs request paths at debug level): any `token=` value,
    and the server's own token wherever it appears (a client may put it in the URL path, say)."""

    pattern = re.compile(r"(token=)[^&\s'\"]+", re.IGNORECASE)
    secrets: set[str] = set()  # the server's token, plain and URL-encoded (`streamer.server` adds it)

    @classmethod
    def add_secret(cls, token: str) -> None:
        from urllib.parse import quote

        cls.secrets |= {token, quote(token, safe=""), quote(token)}

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        redacted = self.pattern.sub(r"\1***", text) if "token=" in text.lower() else text
        for secret in self.secrets:
            redacted = redacted.replace(secret, "***")
        if redacted != text:
            record.msg, record.args = redacted, None
        return True
