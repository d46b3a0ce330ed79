"""The browser viewer (clients/web/) in headless Chromium against a live `streamer serve --http`: it builds
the skeleton from hello and moves it with the frames; the Talk button sends Chromium's fake microphone
(fed a speech WAV) to the server and gestures come back. Chromium is driven over the DevTools protocol
with the `websockets` package. Screenshots go to $DIMGESTOR_ARTIFACTS (or the test's tmp folder)."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import time
import urllib.request
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
from websockets.sync.client import connect

from test_clients_python import SPEECH_WAV, checkpoint, global_rotations, live_server, quat_matrix  # noqa: F401

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = [pytest.mark.timeout(240),
              pytest.mark.skipif(not CHROMIUM, reason="chromium not installed (Debian: apt-get install chromium; "
                                 ".ci/run installs it)")]


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
            self.proc = subprocess.Popen([CHROMIUM, *flags, url], stdout=log, stderr=subprocess.STDOUT)
        port_file = profile / "DevToolsActivePort"  # Chromium writes the port it picked here
        deadline = time.monotonic() + 30
        while not (port_file.exists() and len(port_file.read_text().split()) >= 2):
            if time.monotonic() > deadline or self.proc.poll() is not None:
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

    def wait_for(self, expression: str, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        while True:
            value = self.eval(expression)
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


def assert_figure_drawn(png: Path) -> None:
    """The screenshot shows the figure: enough pixels in the bone colour (#d9b38c, shaded)."""
    import matplotlib.image

    img = matplotlib.image.imread(str(png))[..., :3]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    bone = (r > 0.45) & (r > g + 0.05) & (g > b + 0.05)  # warm, light: only the capsules look like this
    assert bone.sum() > 300, f"{png}: the figure is not visible ({bone.sum()} bone-coloured pixels)"


def forward_kinematics(skeleton: dict, frame: dict) -> np.ndarray:
    """Joint positions as docs/protocol.md defines them: parent global * translate(offset) * rotate(rotation)."""
    g = global_rotations(skeleton["parents"], np.asarray(frame["rotations"], np.float64))
    pos = np.zeros((len(g), 3))
    for j, p in enumerate(skeleton["parents"]):
        pos[j] = frame["root"] if p < 0 else pos[p] + quat_matrix(g[p]) @ np.asarray(skeleton["offsets"][j])
    return pos


def moving_joints(browser: Browser, seconds: float = 1.0) -> float:
    a = browser.positions()
    time.sleep(seconds)
    b = browser.positions()
    assert a.shape == b.shape and a.shape[1] == 3 and np.isfinite(a).all() and np.isfinite(b).all()
    return float(np.abs(a - b).max())


@pytest.fixture(scope="module")
def broadcast_server(tmp_path_factory, checkpoint):  # noqa: F811
    with live_server(tmp_path_factory.mktemp("web_server"), str(SPEECH_WAV), checkpoint, http=True, loop=True) as s:
        yield s


@pytest.mark.parametrize("encoding", ["json", "binary"])
def test_web_viewer_animates_the_skeleton_from_a_live_server(tmp_path, broadcast_server, encoding):
    server = broadcast_server
    # JSON: the page finds the WebSocket through /config.json; binary: through the ?ws= override.
    url = server.http_url if encoding == "json" else f"{server.http_url}?ws={server.ws_url}&encoding=binary"
    browser = Browser(tmp_path, url)
    try:
        browser.wait_for("window.dimgestor && window.dimgestor.framesReceived >= 10", 90, "10 frames")
        hello = browser.eval("window.dimgestor.hello")
        assert hello["protocol"] == 1 and browser.eval("window.dimgestor.url").startswith(server.ws_url)
        n_joints = len(hello["skeleton"]["joints"])
        assert browser.eval("window.dimgestor.jointNames().length") == n_joints
        assert moving_joints(browser) > 1e-3, "joints did not move between two moments"
        # The figure is where the protocol puts it: forward kinematics of the frame it shows, in metres.
        shown = browser.eval("({frame: window.dimgestor.shownFrame, pos: window.dimgestor.jointWorldPositions()})")
        np.testing.assert_allclose(shown["pos"], forward_kinematics(hello["skeleton"], shown["frame"]) * 0.01,
                                   atol=1e-5)
        binary = browser.eval("window.dimgestor.binaryFramesReceived")
        assert (binary > 0) if encoding == "binary" else (binary == 0)
        browser.wait_for("window.dimgestor.status !== null", 10, "a status message")
        hud = browser.eval("({state: document.getElementById('state').textContent, "
                           "fps: document.getElementById('fps').textContent, "
                           "latency: document.getElementById('latency').textContent})")
        assert hud["state"] == "open" and hud["fps"].endswith(f"/ {hello['fps']}") and hud["latency"].endswith("ms")
        assert browser.eval("window.dimgestor.errors.length") == 0, browser.eval("window.dimgestor.errors")
        time.sleep(0.5)  # let the HUD refresh before the picture
        assert_figure_drawn(browser.screenshot(tmp_path / f"web_viewer_{encoding}.png"))
    finally:
        browser.close()


@pytest.mark.parametrize("audio", ["pcm16", "float32"])
def test_web_talk_sends_the_fake_microphone_and_gestures_come_back(tmp_path, checkpoint, audio):  # noqa: F811
    # With a token: the page learns from /config.json that one is needed and takes it from ?token=.
    with live_server(tmp_path, "ws", checkpoint, http=True, extra=("--token", "t0k3n")) as server:
        config = json.load(urllib.request.urlopen(server.http_url + "config.json", timeout=10))
        assert config["ws_url"] == server.ws_url and config["token_required"] is True
        browser = Browser(tmp_path, server.http_url + f"?token=t0k3n&audio={audio}", (
            "--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
            f"--use-file-for-fake-audio-capture={SPEECH_WAV}"))
        try:
            browser.wait_for("window.dimgestor && window.dimgestor.hello && "
                             "!document.getElementById('talk').disabled", 60, "hello and an enabled Talk button")
            assert browser.eval("window.dimgestor.framesReceived") == 0  # --source ws: nothing until we talk
            browser.eval("document.getElementById('talk').click()", user_gesture=True)
            browser.wait_for("window.dimgestor.talking && window.dimgestor.audioChunksSent > 10", 30,
                             "microphone chunks being sent")
            browser.wait_for("window.dimgestor.framesReceived >= 10", 90, "gestures from our own audio")
            assert moving_joints(browser) > 1e-3, "the avatar did not gesture while we talked"
            rate = browser.eval("window.dimgestor.audioRate")
            assert 8000 <= rate <= 192000
            assert browser.eval("document.getElementById('message').textContent") == f"talking: {rate} Hz {audio}"
            assert_figure_drawn(browser.screenshot(tmp_path / f"web_talk_{audio}.png"))
            frames = browser.eval("window.dimgestor.framesReceived")
            browser.eval("document.getElementById('talk').click()", user_gesture=True)  # Stop -> audio_end
            ended = browser.wait_for("window.dimgestor.ended", 60, "end of our session")
            assert ended["frames"] >= frames
            assert browser.eval("window.dimgestor.errors.length") == 0, browser.eval("window.dimgestor.errors")
        finally:
            browser.close()
