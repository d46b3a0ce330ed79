"""deploy/local-cluster run as a user runs it, for the tests that need workers behind a real nginx and for
benchmarks/cluster_load.py."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from helpers.clients import free_port

REPO = Path(__file__).resolve().parents[2]
LOCAL_CLUSTER = REPO / "deploy" / "local-cluster"
NGINX = shutil.which("nginx") or next((p for p in ("/usr/sbin/nginx", "/usr/local/sbin/nginx") if os.access(p, os.X_OK)),
                                      None)


class Cluster:
    """deploy/local-cluster as a user runs it, its output (stdout and stderr) read line by line in a thread.
    `threads`: each worker's torch threads (OMP_NUM_THREADS; None: torch's own choice, as a user's cluster)."""

    def __init__(self, *args: str, workers: int = 2, threads: int | None = 1):
        self.port = free_port()
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        if threads is not None:
            env["OMP_NUM_THREADS"] = str(threads)
        self.proc = subprocess.Popen([sys.executable, str(LOCAL_CLUSTER), "--workers", str(workers), "--port",
                                      str(self.port), *args], cwd=REPO, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.reader = threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True)
        self.reader.start()
        self.url, self.http = f"ws://127.0.0.1:{self.port}/", f"http://127.0.0.1:{self.port}"

    @property
    def output(self) -> str:
        return "".join(self.lines)

    def wait_for(self, pattern: str, timeout: float = 90.0) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if m := re.search(pattern, self.output, re.M):
                return m
            if self.proc.poll() is not None and not self.reader.is_alive():
                break
            time.sleep(0.05)
        raise AssertionError(f"{pattern!r} never printed; local-cluster's output:\n{self.output}")

    def pids(self) -> dict[str, list[int]]:
        """"workers" and "redis" -> the pids local-cluster printed (every worker that ran, restarted ones too)."""
        return {"workers": [int(p) for p in re.findall(r"^worker \d+(?: restarted)?: http://\S+ \(pid (\d+)\)$",
                                                        self.output, re.M)],
                "redis": [int(p) for p in re.findall(r"^state store: \S+ \(pid (\d+)\)$", self.output, re.M)]}

    def workers(self) -> dict[int, tuple[int, int]]:
        """worker number -> (its own port, its pid), from the lines local-cluster prints before `ready`."""
        return {int(n): (int(port), int(pid)) for n, port, pid in
                re.findall(r"^worker (\d+): http://127\.0\.0\.1:(\d+)/ \(pid (\d+)\)$", self.output, re.M)}

    def stop(self, timeout: float = 30.0) -> int:
        """SIGTERM, as a service manager or Ctrl-C would; -> its exit status (a bound, not a measured time)."""
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self.reader.join(5)
