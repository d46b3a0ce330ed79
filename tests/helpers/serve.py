"""`dimgestor serve` as a subprocess that tests talk to: the addresses it prints, and a client that follows it."""

import asyncio
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

from websockets.asyncio.client import connect

from helpers import warm

REPO = Path(__file__).resolve().parents[2]
WAV_SECONDS = 3.0  # the length of the `wav` fixture (tests/conftest.py)


class Serve:
    """A running `dimgestor serve` (or another `command`); reads its stderr in a thread to find the addresses it
    prints."""

    def __init__(self, *args: str, env: dict | None = None, command: tuple[str, ...] = ("-m", "dimgestor_app.cli", "serve")):
        env = {**(env or os.environ), "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
        self.proc = warm.popen([sys.executable, *command, *args], cwd=REPO, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        for line in self.proc.stdout:
            self.lines.append(line)

    def wait_for(self, pattern: str, timeout: float = 60.0) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in list(self.lines):
                if m := re.search(pattern, line):
                    return m
            if self.proc.poll() is not None and not self.thread.is_alive():
                break
            time.sleep(0.02)
        raise AssertionError(f"{pattern!r} never printed; output:\n{self.output}")

    @property
    def output(self) -> str:
        return "".join(self.lines)

    def finish(self, timeout: float = 60.0) -> int:
        try:
            return self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self.thread.join(5)


def serve(checkpoint, *args):
    return Serve("--checkpoint", str(checkpoint), "--ws", "127.0.0.1:0", "--steps", "2", "--status-every", "0.5", *args)


async def follow(url: str, hello_extra: dict | None = None):
    """Connect, read hello then everything until `end` and the server's close."""
    msgs = []
    async with connect(url) as c:
        hello = json.loads(await asyncio.wait_for(c.recv(), 30))
        if hello_extra:
            await c.send(json.dumps({"type": "hello", "protocol": 1, **hello_extra}))
        async for m in c:
            msgs.append(m if isinstance(m, bytes) else json.loads(m))
    return hello, msgs
