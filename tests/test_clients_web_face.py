"""The browser viewer shows the face (protocol revision 7): it asks for VRM 1.0 names in its hello, reads the face
from JSON frames and, after the server's `channels` message, from binary frames (through the shared-memory ring),
plays it with the pose (the face shown is the shown frame's), opens the mannequin's jaw on speech and closes it in
silence, closes its eyelids on a blink, and sets a VRM's expressions. Checked under node (the parsing, the ring, the
playout) and in headless Chromium against a server that speaks revision 7's face from the protocol's text
(helpers/face_server.py), and end to end against `dimgestor serve`. Screenshots go to $DIMGESTOR_ARTIFACTS (or the
test's tmp folder)."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import time

import numpy as np
import pytest

from helpers.browser import CHROMIUM, THREE_JS, Browser, read_png
from helpers.clients import REPO
from helpers.face_server import FPS, FaceServer, face_track, speech_then_silence
from helpers.vrm_model import EXPRESSIONS, make_vrm

pytestmark = pytest.mark.timeout(240)
needs_browser = pytest.mark.skipif(
    not (CHROMIUM and THREE_JS.exists()), reason="chromium (Debian: apt-get install chromium) and the viewer's npm "
    "dependencies (make setup runs npm ci in clients/web) are needed")
SPEECH_S, SILENCE_S = 3.0, 2.0  # the fake server's clip: the demo's first 3 s of speech, then 2 s of silence
VOWELS = ("aa", "ih", "ou", "ee", "oh")


@pytest.fixture(scope="module")
def track():
    """The canonical face of the clip, FPS frames a second (looped by the server)."""
    return face_track(speech_then_silence(SPEECH_S, SILENCE_S))


def expected_jaw(face: dict) -> float:
    """The mannequin's jaw from a vrm1 face: the vowels' weights summed (each is its height), at most 1."""
    return min(1.0, sum(face[v] for v in VOWELS))


def silent(index: int, track: np.ndarray) -> bool:
    """Frame `index` (looped) is in the clip's silence, 0.3 s after the speech stopped and before it starts again."""
    return int(SPEECH_S * FPS) + 6 <= index % len(track) <= len(track) - 2


# ---------------------------------------------------------------- under node: parsing, ring, playout

def test_web_reads_the_face_from_json_and_binary_frames_and_plays_it_with_the_pose(tmp_path, track):
    node = shutil.which("node")
    if not node:
        pytest.skip("node not installed (Debian: apt-get install nodejs)")
    server = FaceServer(track)
    msgs = [json.dumps(server.hello),
            server.frame_json(0, "vrm0"), server.frame_json(1, "vrm0"),              # before asking: the server's set
            json.dumps({"type": "channels", "channels": server.layout("vrm1")}),    # after `face: "vrm1"`
            server.frame_binary(2, "vrm1"), server.frame_binary(3, "vrm1"),
            server.frame_json(4, "vrm1"), server.frame_json(5, "vrm1"), server.frame_binary(6, "vrm1"),
            json.dumps({"type": "channels", "channels": []}),                       # after `face: "none"`
            server.frame_binary(7, None), server.frame_json(8, None)]
    for i, m in enumerate(msgs):
        binary = isinstance(m, bytes)
        (tmp_path / f"{i:06d}.{'bin' if binary else 'json'}").write_bytes(m if binary else m.encode())
    r = subprocess.run([node, str(REPO / "clients/web/tests/face_check.mjs"), str(tmp_path)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    out = [json.loads(line) for line in r.stdout.splitlines()]
    frames = [o for o in out if o["event"] == "frame"]
    assert [f["index"] for f in frames] == list(range(9))
    for f in frames:
        i, name_set = f["index"], "vrm0" if f["index"] < 2 else "vrm1" if f["index"] < 7 else None
        if name_set is None:
            assert f["face"] is None and f["ring"] is None and f["mouth"]["jaw"] == 0
            continue
        want = dict(zip(server.labels(name_set), server.weights(i, name_set)))
        assert list(f["face"]) == list(want) and list(f["ring"]) == list(want), (i, f["face"])
        for name, w in want.items():  # JSON: 4 decimals; binary: float32
            assert f["face"][name] == pytest.approx(w, abs=6e-5) and f["ring"][name] == pytest.approx(w, abs=6e-5)
        vowels = ("A", "I", "U", "E", "O") if name_set == "vrm0" else VOWELS
        assert f["mouth"]["jaw"] == pytest.approx(min(1, sum(want[v] for v in vowels)), abs=3e-4)
        blink = want["Blink" if name_set == "vrm0" else "blink"]
        assert f["mouth"]["blinkLeft"] == pytest.approx(blink + want["Blink_L" if name_set == "vrm0" else "blinkLeft"],
                                                        abs=2e-4)
        # a VRM gets VRM 1.0 preset names whichever set came (three-vrm maps 0.x presets onto them)
        assert list(f["vrm"]) == list(EXPRESSIONS)
        assert f["vrm"]["aa"] == pytest.approx(want["A" if name_set == "vrm0" else "aa"], abs=6e-5)
    # Played out with the pose: at a frame's pts its own face, halfway between two frames the mean of theirs.
    by_index = {f["index"]: f["ring"] for f in frames}
    halfway = 0
    for s in (o for o in out if o["event"] == "sample"):
        a, b = by_index[s["index"]], by_index.get(s["index"] + 1)
        if abs(s["pts"] - s["index"] / FPS) < 1e-9:
            assert s["face"] == a, s
        elif a and b and a.keys() == b.keys():
            halfway += 1
            for name, w in a.items():
                assert s["face"][name] == pytest.approx((w + b[name]) / 2, abs=1e-9), (s, name)
    assert halfway == 5  # 0-1 (vrm0), 2-3, 3-4, 4-5, 5-6 (vrm1)


# ---------------------------------------------------------------- in Chromium

def read_shown(browser: Browser) -> dict:
    return browser.eval("(() => { const d = window.dimgestor, f = d.shownFrame; return {index: f.index, pts: f.pts, "
                        "face: f.face, shown: d.face, mouth: d.mouth, expressions: d.vrm ? d.vrm.expressions : null, "
                        "paused: d.paused}; })()")


def track_at(track: np.ndarray, pts: float, name_set: str = "vrm1") -> dict:
    """The face the page should show at `pts`: the two frames around it, linearly (as playout.js)."""
    from dimgestor.face import convert, names_of

    i = int(np.floor(pts * FPS + 1e-9))
    u = pts * FPS - i
    a, b = convert(track[i % len(track)], name_set), convert(track[(i + 1) % len(track)], name_set)
    return dict(zip(names_of(name_set), a + (b - a) * u))


def wait_and_pause(browser: Browser, condition: str, what: str, timeout: float = 30) -> dict:
    """Pause the page (picture held) at the first draw where `condition` (on `d` = window.dimgestor) holds."""
    browser.eval(f"""window.__pauseWhen = () => {{ const d = window.dimgestor;
      if (!d.paused && d.shownFrame && ({condition})) d.setPaused(true);
      else if (!d.paused) requestAnimationFrame(window.__pauseWhen); }}; requestAnimationFrame(window.__pauseWhen)""")
    browser.wait_for("window.dimgestor.paused", timeout, what)
    time.sleep(0.6)  # a few draws of the held picture (a software-rendered page draws slowly)
    return read_shown(browser)


def face_box(browser: Browser, part: str) -> tuple[int, int, int, int]:
    """Pixel box (x0, y0, x1, y1) around the mannequin's 'mouth' or 'eyes' on screen now, a few pixels wider."""
    x0, y0, x1, y1 = browser.eval(f"window.dimgestor.faceBox('{part}')")
    return max(0, x0 - 3), max(0, y0 - 3), x1 + 3, y1 + 3


def dark_in(png, box) -> int:
    """Pixels in `box` darker than the lips and the skin: the inside of an open mouth."""
    x0, y0, x1, y1 = box
    return int((read_png(png)[y0:y1, x0:x1].max(axis=2) < 0.3).sum())


def paused_close_up(browser: Browser, condition: str, what: str, png) -> tuple[dict, tuple]:
    """Held at the first draw where `condition` holds, the face framed close up: (what is shown, the mouth's box)."""
    shown = wait_and_pause(browser, condition, what)
    browser.eval("window.dimgestor.frameFace()")
    time.sleep(0.5)
    browser.screenshot(png)
    return shown, face_box(browser, "mouth")


@needs_browser
def test_web_mannequin_binary_opens_its_mouth_on_speech_and_closes_it_in_silence(tmp_path, track):
    with FaceServer(track) as server:
        browser = Browser(tmp_path, server.url + "?encoding=binary&sound=off")
        try:
            browser.wait_for("window.dimgestor && window.dimgestor.shownFrame && window.dimgestor.shownFrame.face",
                             60, "a frame with a face on screen")
            assert server.hellos[-1]["face"] == "vrm1" and server.hellos[-1]["encoding"] == "binary"
            assert browser.eval("window.dimgestor.channelNames()") == ["face"]
            assert browser.eval("window.dimgestor.binaryFramesReceived") > 0
            browser.eval("window.dimgestor.frameFace()")
            # The face shown is the shown frame's, interpolated as its pose; the mannequin shows what it says.
            reads = []
            for _ in range(16):
                reads.append(read_shown(browser))
                time.sleep(0.15)
            for r in reads:
                assert list(r["face"]) == server.labels("vrm1") and r["shown"] == r["face"]
                want = track_at(track, r["pts"])
                assert max(abs(r["face"][n] - w) for n, w in want.items()) < 1e-4, (r, want)
                assert r["mouth"]["jaw"] == pytest.approx(expected_jaw(r["face"]), abs=1e-6)
                assert r["mouth"]["blinkLeft"] == pytest.approx(min(1, r["face"]["blink"] + r["face"]["blinkLeft"]))

            # On a vowel: the mouth open; in the silence: closed. Each held (paused) for its screenshot.
            vowel = wait_and_pause(browser, "d.mouth.jaw > 0.6", "an open vowel on screen")
            assert vowel["mouth"]["jaw"] > 0.6
            png_open = browser.screenshot(tmp_path / "web_face_open.png")
            box = face_box(browser, "mouth")
            browser.eval("window.dimgestor.setPaused(false)")
            n = len(track)
            quiet = wait_and_pause(browser, f"d.shownFrame.index % {n} >= {int(SPEECH_S * FPS) + 8} && "
                                   f"d.shownFrame.index % {n} <= {n - 3}", "the silence on screen")
            assert silent(quiet["index"], track)
            assert quiet["mouth"]["jaw"] < 0.02 and quiet["mouth"]["blinkLeft"] < 0.02, quiet
            png_closed = browser.screenshot(tmp_path / "web_face_closed.png")
            browser.eval("window.dimgestor.setPaused(false)")
            blink = wait_and_pause(browser, "d.mouth.blinkLeft > 0.7 && d.mouth.blinkRight > 0.7", "a blink on screen")
            png_blink = browser.screenshot(tmp_path / "web_face_blink.png")
            eyes = face_box(browser, "eyes")
            assert browser.eval("window.dimgestor.errors") == []
        finally:
            browser.close()
    assert blink["mouth"]["blinkLeft"] > 0.7
    a, b, c = read_png(png_open), read_png(png_closed), read_png(png_blink)
    # Same pose, same camera: the open mouth changes the mouth's pixels and little else (right of the HUD, whose
    # counters change); the blink the eyes'.
    diff = np.abs(a - b).max(axis=2) > 0.1
    diff[:, :300] = False
    x0, y0, x1, y1 = box
    inside = diff[y0:y1, x0:x1].sum()
    assert inside > 60, f"the open mouth changed {inside} pixels around the mouth {box}"
    assert diff.sum() - inside < 0.25 * inside, f"the open mouth changed {diff.sum() - inside} pixels elsewhere"
    assert dark_in(png_open, box) > dark_in(png_closed, box) + 30, \
        f"no dark opening: {dark_in(png_open, box)} vs {dark_in(png_closed, box)} dark pixels in {box}"
    blink_diff = np.abs(c - b).max(axis=2) > 0.1
    ex0, ey0, ex1, ey1 = eyes
    assert blink_diff[ey0:ey1, ex0:ex1].sum() > 40, f"the blink changed nothing around the eyes {eyes}"


def load_vrm(browser: Browser, version: str) -> None:
    vrm = make_vrm(version, expressions=True)
    browser.eval(f"""(() => {{
      const bytes = Uint8Array.from(atob('{base64.b64encode(vrm).decode()}'), (c) => c.charCodeAt(0));
      window.dimgestor.loadAvatarFile(new File([bytes], 'face-{version}.vrm'));
    }})()""")
    browser.wait_for(f"!!window.dimgestor.vrm && window.dimgestor.vrm.metaVersion === '{version[0]}' && "
                     "window.dimgestor.avatar === 'vrm'", 30, f"the VRM {version} to load")


@needs_browser
def test_web_vrm_expressions_follow_the_face(tmp_path, track):
    influences = """(() => { const v = window.dimgestor.vrm, out = {};
      v.vrm.scene.traverse((o) => {
        if (o.morphTargetInfluences && !out.w) out.w = Array.from(o.morphTargetInfluences); });
      return {w: out.w, expressions: v.expressions, face: window.dimgestor.face}; })()"""
    with FaceServer(track) as server:
        browser = Browser(tmp_path, server.url + "?sound=off")  # JSON frames
        try:
            browser.wait_for("window.dimgestor && window.dimgestor.shownFrame && window.dimgestor.shownFrame.face",
                             60, "a frame with a face on screen")
            assert server.hellos[-1]["face"] == "vrm1" and server.hellos[-1].get("encoding") == "json"
            for version in ("1.0", "0.0"):
                load_vrm(browser, version)
                spoken = wait_and_pause(browser, "d.vrm.expressions && d.vrm.expressions.aa > 0.4", "an open A")
                assert spoken["expressions"] == {n: spoken["face"][n] for n in EXPRESSIONS}, spoken
                # three-vrm applied them: each preset drives its own morph target (helpers/vrm_model.py)
                w = browser.eval(influences)
                for k, name in enumerate(EXPRESSIONS):
                    assert w["w"][k] == pytest.approx(w["expressions"][name], abs=1e-6), (version, name, w)
                browser.eval("window.dimgestor.frameFace()")
                time.sleep(0.4)
                png = browser.screenshot(tmp_path / f"web_face_vrm_{version}.png")
                browser.eval("window.dimgestor.setPaused(false)")
                n = len(track)
                quiet = wait_and_pause(browser, f"d.shownFrame.index % {n} >= {int(SPEECH_S * FPS) + 8} && "
                                       f"d.shownFrame.index % {n} <= {n - 3}", "the silence")
                assert all(quiet["expressions"][v] < 0.02 for v in VOWELS), quiet
                w = browser.eval(influences)
                assert max(w["w"][:5]) < 0.02, w
                browser.eval("window.dimgestor.setPaused(false)")
            assert browser.eval("window.dimgestor.errors") == []
        finally:
            browser.close()
    assert png.exists()


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The fake server's clip as a WAV for `dimgestor serve`: SPEECH_S of speech, then SILENCE_S of silence."""
    from dimgestor.audio import save_wav

    path = tmp_path_factory.mktemp("face_clip") / "speech_then_silence.wav"
    save_wav(path, speech_then_silence(SPEECH_S, SILENCE_S), 16000)
    return path


@needs_browser
def test_web_face_from_dimgestor_serve_end_to_end(tmp_path, checkpoint, clip):
    """`dimgestor serve` (its default face, VRM 0 names) on speech then silence, looped, the page asking for binary
    frames: the page's hello asks for vrm1, the server's `channels` message lays the face out after the rotations,
    and the mannequin's jaw opens in the speech and rests in the silence."""
    from helpers.clients import live_server

    with live_server(tmp_path, str(clip), checkpoint, http=True, loop=True, extra=("--wait-client",)) as server:
        browser = Browser(tmp_path, server.http_url + "?encoding=binary&sound=off")
        try:
            browser.wait_for("window.dimgestor && window.dimgestor.shownFrame && window.dimgestor.shownFrame.face",
                             60, "a frame with a face on screen")
            hello = browser.eval("window.dimgestor.hello")
            assert hello["revision"] >= 7 and hello["face"]["names"] == "vrm0" and hello["channels"] == []
            layout = browser.eval("window.dimgestor.channels")
            assert [c["name"] for c in layout] == ["face"] and layout[0]["labels"] == FaceServer.labels("vrm1")
            assert layout[0]["offset"] == 28 + 16 * len(hello["skeleton"]["joints"])
            browser.eval("window.dimgestor.frameFace()")
            reads = []
            for _ in range(30):  # 6 s: a whole loop of the clip
                reads.append(read_shown(browser))
                time.sleep(0.2)
            # Screenshots: on a vowel the mouth open, in the silence closed (the body moves: each framed as held)
            vowel, box_open = paused_close_up(browser, "d.mouth.jaw > 0.5", "an open vowel on screen",
                                              tmp_path / "web_face_serve_vowel.png")
            browser.eval("window.dimgestor.setPaused(false)")
            quiet, box_closed = paused_close_up(
                browser, f"d.shownFrame.pts % {SPEECH_S + SILENCE_S} > {SPEECH_S + 0.5}", "the silence on screen",
                tmp_path / "web_face_serve_silence.png")
            errors = browser.eval("window.dimgestor.errors")
            binary = browser.eval("window.dimgestor.binaryFramesReceived")
            arrived = browser.eval("window.dimgestor.arrivalLog.map(([, pts]) => pts)")
        finally:
            browser.close()
    assert errors == [] and binary > 0
    # (the face of a frame in the clip's digital silence is 0 in every vowel; a shown face between two frames
    # is interpolated as the pose: the frames received around the one held say whether a gap was bridged)
    near = [round(p, 3) for p in arrived if abs(p - quiet["pts"]) < 0.3]
    assert vowel["mouth"]["jaw"] > 0.5 and quiet["mouth"]["jaw"] < 0.05, \
        f"vowel {vowel}; quiet {quiet}; frames received within 0.3 s of the quiet one: {near}"
    dark_open, dark_closed = (dark_in(tmp_path / "web_face_serve_vowel.png", box_open),
                              dark_in(tmp_path / "web_face_serve_silence.png", box_closed))
    assert dark_open > dark_closed + 30, f"no dark opening: {dark_open} vs {dark_closed} dark pixels"
    clip_s = SPEECH_S + SILENCE_S
    for r in reads:
        assert list(r["face"]) == FaceServer.labels("vrm1") and all(0 <= w <= 1 for w in r["face"].values()), r
        assert r["mouth"]["jaw"] == pytest.approx(expected_jaw(r["face"]), abs=1e-6)
    speech = [r["mouth"]["jaw"] for r in reads if 0.3 <= r["pts"] % clip_s <= SPEECH_S - 0.2]
    silence = [r["mouth"]["jaw"] for r in reads if SPEECH_S + 0.5 <= r["pts"] % clip_s <= clip_s - 0.1]
    print(f"jaw in speech {np.round(speech, 2)}; in silence {np.round(silence, 2)}")
    assert len(speech) >= 5 and len(silence) >= 3, (len(speech), len(silence))
    assert max(speech) > 0.3 and np.mean(speech) > 0.1, f"the mouth hardly opened in the speech: {np.round(speech, 2)}"
    assert max(silence) < 0.05, f"the mouth did not rest in the silence: {np.round(silence, 2)}"
