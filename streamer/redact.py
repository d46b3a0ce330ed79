"""Keeping tokens (and the state store's password) out of the log: a logging filter on every handler of
`dimgestor serve`.

Its state (the server's own token) is class-level and lives in this module rather than in the command line's,
which runs as `__main__` under `python -m dimgestor_app.cli` (a second copy of its classes when imported).
"""

from __future__ import annotations

import logging
import re


class RedactTokens(logging.Filter):
    """Keeps tokens out of every log line, whatever its shape: a URL's `token=` value (websockets logs request
    paths at debug level), a message's `"token": ...` or `"resume_token": ...` as JSON or as a Python repr (-v logs
    every message: resume_session, session_saved, goaway), and the secrets added here wherever they appear (the
    server's token: a client may put it in the URL path, say; the state store's password)."""

    pattern = re.compile(r"(token(?:\\?[\"'])?\s*[=:]\s*(?:\\?[\"'])?)[^&\s'\"\\]+", re.IGNORECASE)
    secrets: set[str] = set()  # plain and URL-encoded (`streamer.server` adds the server's token)

    @classmethod
    def add_secret(cls, token: str) -> None:
        from urllib.parse import quote

        cls.secrets |= {token, quote(token, safe=""), quote(token)}

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        redacted = self.pattern.sub(r"\1***", text) if "token" in text.lower() else text
        for secret in self.secrets:
            redacted = redacted.replace(secret, "***")
        if redacted != text:
            record.msg, record.args = redacted, None
        return True
