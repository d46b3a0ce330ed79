"""Headless Chromium driven over the DevTools protocol (with the `websockets` package), for the tests of the
browser clients (clients/web/) and the benchmarks that measure them. Screenshots also go to $DIMGESTOR_ARTIFACTS."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from contextlib import ExitStack
from pathlib import Path

import numpy as np
from websockets.sync.client import connect

from helpers.clients import REPO

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
THREE_JS = REPO / "clients" / "web" / "node_modules" / "three" / "build" / "three.module.js"


class Browser:
    """Headless Chromium with one page, driven over the DevTools protocol."""

    def __init__(self, tmp: Path, url: str, extra_flags: tuple[str, ...] = ()):
        profile = tmp / "chromium-profile"
        profile.mkdir()
        self.log = tmp / "chromium.log"
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--no-first-run",
                 "--disable-component-update", "--disable-sync", f"--user-data-dir={profile}",
                 "--remote-debugging-port=0", "--window-size=960,640",
                 # WebGL on the CPU: without a GPU, Chromium only draws WebGL through SwiftShader when asked.
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--autoplay-policy=no-user-gesture-required",
                 *extra_flags]
        with open(self.log, "w") as log:
            # (TMPDIR: its singleton socket's folder goes into a folder of ours, removed at close, not into the
            # machine's, where a stopped Chromium leaves it; a short path: the socket's may not pass 107 bytes)
            self.tmpdir = tempfile.mkdtemp(prefix="dimgestor-chromium-")
            self.proc = subprocess.Popen([CHROMIUM, *flags, url], stdout=log, stderr=subprocess.STDOUT,
                                         env={**os.environ, "TMPDIR": self.tmpdir})
        port_file = profile / "DevToolsActivePort"  # Chromium writes the port it picked here
        deadline = time.monotonic() + 30
        while not (port_file.exists() and len(port_file.read_text().split()) >= 2):
            if time.monotonic() > deadline or self.proc.poll() is not None:
                self.proc.kill()
                self.proc.wait()
                shutil.rmtree(self.tmpdir, ignore_errors=True)
                raise RuntimeError(f"chromium did not start:\n{self.log.read_text()[-3000:]}")
            time.sleep(0.1)
        port = port_file.read_text().split()[0]
        targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10))
        page = next(t for t in targets if t["type"] == "page")
        self.stack = ExitStack()
        self.ws = self.stack.enter_context(connect(page["webSocketDebuggerUrl"], max_size=64 * 2**20))
        self.next_id = 0

    def call(self, method: str, **params) -> dict:
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg["result"]

    def eval(self, expression: str, user_gesture: bool = False):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True,
                      userGesture=user_gesture)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def wait_page(self, timeout: float = 30.0) -> None:
        """Until the page has an execution context (just after Chromium starts, Runtime.evaluate fails)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                self.eval("document.readyState")
                return
            except RuntimeError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    def wait_for(self, expression: str, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        while True:
            try:
                value = self.eval(expression)
            except RuntimeError as e:  # no execution context for a moment: the page is (re)loading; a cross-origin
                if "execution context" not in str(e) or time.monotonic() > deadline:  # isolated page (the viewer)
                    raise                                                             # swaps its process then
                value = None
            if value:
                return value
            if time.monotonic() > deadline:
                page = self.eval("JSON.stringify({state: window.dimgestor && window.dimgestor.state, "
                                 "frames: window.dimgestor && window.dimgestor.framesReceived, "
                                 "errors: window.dimgestor && window.dimgestor.errors, "
                                 "message: document.getElementById('message').textContent})")
                raise AssertionError(f"timed out waiting for {what}; page: {page}")
            time.sleep(0.2)

    def positions(self) -> np.ndarray:
        return np.asarray(self.eval("window.dimgestor.jointWorldPositions()"), dtype=np.float64)

    def screenshot(self, path: Path) -> Path:
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))
        artifacts = os.environ.get("DIMGESTOR_ARTIFACTS")
        if artifacts:
            Path(artifacts).mkdir(parents=True, exist_ok=True)
            shutil.copy(path, Path(artifacts) / path.name)
        print(f"screenshot: {path}")
        return path

    def close(self):
        try:
            self.stack.close()
        finally:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            shutil.rmtree(self.tmpdir, ignore_errors=True)


def read_png(png: Path) -> np.ndarray:
    import matplotlib.image

    return matplotlib.image.imread(str(png))[..., :3]


def assert_figure_drawn(png: Path) -> None:
    """The screenshot shows the mannequin: enough light, nearly grey pixels (its body) right of the HUD."""
    img = read_png(png)[:, 300:]
    light = (img.min(axis=2) > 0.55) & (img.max(axis=2) - img.min(axis=2) < 0.15)  # the background is dark
    assert light.sum() > 1500, f"{png}: the avatar is not visible ({light.sum()} body-coloured pixels)"
