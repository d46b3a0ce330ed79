"""A VRM Animation (.vrma) played on a VRM avatar by @pixiv/three-vrm-animation in real headless Chromium
(tests/web/vrma.html), the way a web application plays one: where each humanoid bone ends up at chosen times, and
a screenshot of each (also copied to $DIMGESTOR_ARTIFACTS, as helpers/browser.py does)."""

from __future__ import annotations

import functools
import json
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Sequence

import numpy as np
import pytest

from helpers.browser import CHROMIUM, Browser
from helpers.clients import REPO

PAGE = REPO / "tests" / "web"
NODE_MODULES = REPO / "clients" / "web" / "node_modules"
ANIMATION_JS = NODE_MODULES / "@pixiv" / "three-vrm-animation" / "lib" / "three-vrm-animation.module.js"
SKIP_REASON = ("chromium not installed (Debian: apt-get install chromium)" if not CHROMIUM else
               None if ANIMATION_JS.exists() else
               "the viewer's npm dependencies (three, three-vrm, three-vrm-animation) are not installed: run "
               "`make setup` (npm ci in clients/web)")
needs_vrma_browser = pytest.mark.skipif(SKIP_REASON is not None, reason=SKIP_REASON or "")


@dataclass
class VrmaPlayback:
    meta_version: str  # the avatar's VRM version as three-vrm read it: "1" or "0"
    duration: float  # the clip's, seconds
    tracks: list[str]  # the clip's tracks (normalized bone node names .quaternion / .position)
    rest_hips: np.ndarray  # (3,) the VRMA's rest hips position in its own world, metres
    times: np.ndarray  # (T,) the requested times, seconds
    bones: list[str]  # the avatar's humanoid bones (VRM 1.0 names)
    positions: np.ndarray  # (T, B, 3) raw bone nodes in world space: metres, Y up, the avatar facing +Z
    screenshots: list[Path]  # one PNG per time
    warnings: list[str]  # console.warn lines (three-vrm-animation says there what it ignores)
    expressions: dict[str, np.ndarray] = None  # the avatar's expressions' weights (T,) as the clip set them

    def position(self, bone: str) -> np.ndarray:
        """(T, 3) one bone's world positions."""
        return self.positions[:, self.bones.index(bone)]


class _QuietHandler(SimpleHTTPRequestHandler):
    extensions_map = {**SimpleHTTPRequestHandler.extensions_map, ".js": "text/javascript",
                      ".mjs": "text/javascript"}  # module scripts must have a JavaScript type

    def log_message(self, *args):
        pass


@dataclass
class GltfPlayback:
    duration: float  # the first animation's, seconds
    bones: list[str]  # the skeleton's bones (three.js Bone objects) by name
    positions: np.ndarray  # (T, B, 3) their world positions, the file's units (metres), Y up
    screenshots: list[Path]


@contextmanager
def _page(tmp: Path, name: str, files: dict[str, bytes]):
    """The test page in headless Chromium, served with the viewer's node_modules and `files` beside it; yields
    the browser once the page's modules loaded, and raises if the page reported errors by the end."""
    if SKIP_REASON:
        pytest.skip(SKIP_REASON)
    work = Path(tempfile.mkdtemp(prefix=f"{name}-", dir=tmp))
    site = work / "site"  # what the server shows: the page, the viewer's node_modules and the files
    site.mkdir()
    for f in ("vrma.html", "vrma.js"):
        (site / f).symlink_to(PAGE / f)
    (site / "node_modules").symlink_to(NODE_MODULES)
    for f, data in files.items():
        (site / f).write_bytes(data)
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_QuietHandler, directory=str(site)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    browser = None
    try:
        browser = Browser(work, f"http://127.0.0.1:{server.server_address[1]}/vrma.html")
        browser.wait_page()
        browser.wait_for("!!window.vrmaCheck", 30, "the page's modules to load")
        yield browser
        errors = browser.eval("vrmaCheck.errors")
        if errors:
            raise RuntimeError(f"the page reported errors: {json.dumps(errors)}")
    finally:
        if browser is not None:
            browser.close()
        server.shutdown()
        server.server_close()


def _poses(browser, call: str, tmp: Path, name: str, times: Sequence[float]) -> tuple[list, list[Path]]:
    """`call`(t) evaluated at each of `times`, with a screenshot after each (tmp/NAME_k.png)."""
    poses, shots = [], []
    for k, t in enumerate(times):
        poses.append(browser.eval(f"vrmaCheck.{call}({float(t)!r})"))
        shots.append(browser.screenshot(tmp / f"{name}_{k:02d}.png"))
    return poses, shots


def play_gltf(tmp: Path, glb: Path, times: Sequence[float], name: str = "gltf") -> GltfPlayback:
    """A .glb loaded by three.js's GLTFLoader and its first animation played by an AnimationMixer in Chromium, as
    a web application does: its bones' world positions at each of `times`, a screenshot of each."""
    with _page(tmp, name, {"motion.glb": Path(glb).read_bytes()}) as browser:
        info = browser.eval("vrmaCheck.loadGltf('motion.glb')")
        poses, shots = _poses(browser, "gltfPose", tmp, name, times)
    bones = list(poses[0])
    return GltfPlayback(info["duration"], bones, np.array([[p[b] for b in bones] for p in poses], np.float64), shots)


def play_vrma(tmp: Path, vrm: bytes | Path, vrma: Path, times: Sequence[float], name: str = "vrma") -> VrmaPlayback:
    """Load `vrm` (bytes or a file) and `vrma` in the page and pose the avatar at each of `times` (seconds; the
    clip plays once and holds its last key after its end). VRM 0.x avatars are turned to face +Z
    (VRMUtils.rotateVRM0) as viewers do, so positions compare across versions. Screenshots: tmp/NAME_k.png."""
    files = {"avatar.vrm": vrm if isinstance(vrm, bytes) else Path(vrm).read_bytes(),
             "clip.vrma": Path(vrma).read_bytes()}
    with _page(tmp, name, files) as browser:
        info = browser.eval("vrmaCheck.load('avatar.vrm', 'clip.vrma')")
        poses, shots = _poses(browser, "pose", tmp, name, times)
        warnings = browser.eval("vrmaCheck.warnings")
    bones = list(poses[0]["bones"])
    names = list(poses[0]["expressions"])
    return VrmaPlayback(
        meta_version=info["metaVersion"], duration=info["duration"], tracks=info["tracks"],
        rest_hips=np.asarray(info["restHipsPosition"]), times=np.asarray(times, np.float64), bones=bones,
        positions=np.array([[p["bones"][b] for b in bones] for p in poses], np.float64), screenshots=shots,
        warnings=warnings, expressions={n: np.array([p["expressions"][n] for p in poses]) for n in names})
