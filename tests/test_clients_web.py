"""The browser viewer (clients/web/) in headless Chromium against a live `streamer serve`, in real time:
it builds the mannequin from hello and moves it with the frames, facing the camera; a generated VRM dropped on
the page follows the stream; the source audio plays through Web Audio in sync with the frames; the Talk
button sends Chromium's fake microphone (fed a speech WAV) to the server and gestures come back. Chromium is
driven over the DevTools protocol with the `websockets` package. Screenshots go to $DIMGESTOR_ARTIFACTS (or
the test's tmp folder)."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import time
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from helpers.av_sync import (PLAYED, RECORDER, RECORDING, SHOWN_NOW, assert_played_as_scheduled, late_arrivals,
                             missed16, heard_index, recorded_around, shown_minus_heard, steady,
                             timestamp_minus_current_time, voiced_at)
from helpers.browser import CHROMIUM, THREE_JS, Browser, assert_figure_drawn, read_png
from helpers.clients import REPO, SPEECH_WAV, global_rotations, live_server, quat_matrix
from helpers.vrm_model import make_vrm

pytestmark = [pytest.mark.timeout(240),
              pytest.mark.skipif(not CHROMIUM, reason="chromium not installed (Debian: apt-get install chromium; "
                                 ".ci/run installs it)"),
              pytest.mark.skipif(not THREE_JS.exists(), reason="the viewer's npm dependencies are not installed "
                                 "(make setup runs npm ci in clients/web)")]


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
    # JSON: the page connects to its own origin (the server's one port); binary: through the ?ws= override.
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
        # The received fps reads steady although frames come in bursts of one window (no 26/20 or 37/20), once
        # its 5 s window is full (before that the server may still be catching up after its first, slow windows).
        browser.wait_for(f"window.dimgestor.framesReceived >= {6 * hello['fps']}", 30, "6 s of frames")
        readings = []
        for _ in range(6):
            time.sleep(0.5)
            readings.append(browser.eval("document.getElementById('fps').textContent"))
        fps = [float(r.split("/")[0]) for r in readings]
        assert all(0.7 * hello["fps"] <= f <= 1.25 * hello["fps"] for f in fps), f"fps readout jumps: {readings}"
        assert browser.eval("window.dimgestor.errors.length") == 0, browser.eval("window.dimgestor.errors")
        time.sleep(0.5)  # let the HUD refresh before the picture
        assert_figure_drawn(browser.screenshot(tmp_path / f"web_viewer_{encoding}.png"))
    finally:
        browser.close()


@pytest.mark.parametrize("audio", ["pcm16", "float32"])
def test_web_talk_sends_the_fake_microphone_and_gestures_come_back(tmp_path, checkpoint, audio):  # noqa: F811
    # With a token: the page takes it from ?token= and connects to its own origin with it.
    with live_server(tmp_path, "ws", checkpoint, http=True, extra=("--token", "t0k3n")) as server:
        browser = Browser(tmp_path, server.http_url + f"?token=t0k3n&audio={audio}", (
            "--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
            f"--use-file-for-fake-audio-capture={SPEECH_WAV}"))
        try:
            browser.wait_for("window.dimgestor && window.dimgestor.hello && "
                             "!document.getElementById('talk').disabled", 60, "hello and an enabled Talk button")
            assert browser.eval("window.dimgestor.url") == server.ws_url + "?token=t0k3n"
            assert browser.eval("window.dimgestor.framesReceived") == 0  # --source ws: nothing until we talk
            browser.eval("document.getElementById('talk').click()", user_gesture=True)
            browser.wait_for("window.dimgestor.talking && window.dimgestor.audioChunksSent > 10", 30,
                             "microphone chunks being sent")
            browser.wait_for("window.dimgestor.framesReceived >= 10", 90, "gestures from our own audio")
            assert moving_joints(browser) > 1e-3, "the avatar did not gesture while we talked"
            rate = browser.eval("window.dimgestor.audioRate")
            assert 8000 <= rate <= 192000
            assert browser.eval("document.getElementById('message').textContent") == f"talking: {rate} Hz {audio}"
            # Never an echo: the microphone's graph ends in a zero-gain node, and no sound plays while we talk.
            assert browser.eval("window.dimgestor.micMonitorGain") == 0
            assert browser.eval("window.dimgestor.sourceAudio.chunks.length + "
                                "window.dimgestor.sourceAudio.playing.length") == 0
            assert_figure_drawn(browser.screenshot(tmp_path / f"web_talk_{audio}.png"))
            frames = browser.eval("window.dimgestor.framesReceived")
            browser.eval("document.getElementById('talk').click()", user_gesture=True)  # Stop -> audio_end
            ended = browser.wait_for("window.dimgestor.ended", 60, "end of our session")
            assert ended["frames"] >= frames
            assert browser.eval("window.dimgestor.errors.length") == 0, browser.eval("window.dimgestor.errors")
        finally:
            browser.close()


def test_web_talk_asks_for_the_speaker_its_page_names(tmp_path):
    """?speaker=NAME (revision 9): the page's hello asks for that speaker; one the server's model does not know is
    refused with the names it knows, said on the page; a known one talks and gestures without an error."""
    from helpers.checkpoint import make_tiny_checkpoint

    checkpoint = make_tiny_checkpoint(tmp_path, jitter=0.2, speakers=("alice", "bob"))
    with live_server(tmp_path, "ws", checkpoint, http=True, extra=("--face", "none")) as server:
        for speaker in ("carol", "bob"):
            (tmp_path / speaker).mkdir()
            browser = Browser(tmp_path / speaker, server.http_url + f"?speaker={speaker}", (
                "--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
                f"--use-file-for-fake-audio-capture={SPEECH_WAV}"))
            try:
                browser.wait_for("window.dimgestor && window.dimgestor.hello && "
                                 "!document.getElementById('talk').disabled", 60, "hello and an enabled Talk button")
                assert browser.eval("window.dimgestor.hello.speakers") == {"names": ["alice", "bob"], "default": None,
                                                                           "choice": True}
                if speaker == "carol":
                    browser.wait_for("window.dimgestor.errors.length > 0", 30, "the refusal of an unknown speaker")
                    [err] = browser.eval("window.dimgestor.errors")
                    assert err["code"] == "bad_message" and "this server's model knows alice, bob" in err["message"]
                    assert "knows alice, bob" in browser.eval("document.getElementById('message').textContent")
                    continue
                browser.eval("document.getElementById('talk').click()", user_gesture=True)
                browser.wait_for("window.dimgestor.framesReceived >= 10", 90, "gestures from our own audio")
                assert moving_joints(browser) > 1e-3, "the avatar did not gesture while we talked"
                assert_figure_drawn(browser.screenshot(tmp_path / "web_talk_speaker.png"))
                assert browser.eval("window.dimgestor.errors.length") == 0, browser.eval("window.dimgestor.errors")
            finally:
                browser.close()


def test_web_mic_flow_control_holds_bounded_and_sends_in_order(tmp_path):
    """clients/web/audio-flow.js under node: chunks go out at once until `slow_down`, are held (in order) until
    `resume`, and beyond the bound (here 1 s) the oldest are dropped and counted, never the newest."""
    node = shutil.which("node")
    if not node:
        pytest.skip("node not installed (Debian: apt-get install nodejs)")
    script = tmp_path / "flow.txt"
    script.write_text("\n".join(["chunk a 400", "slow_down", "chunk b 400", "chunk c 400", "slow_down", "resume",
                                 "resume", "chunk d 400", "slow_down"] + [f"chunk e{i} 400" for i in range(5)]
                                + ["resume"]))
    r = subprocess.run([node, str(REPO / "clients/web/tests/audio_flow_check.mjs"), "1000", "1", str(script)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    out = [json.loads(line) for line in r.stdout.splitlines()]
    assert [o["sent"] for o in out[:9]] == [["a"], [], [], [], [], ["b", "c"], [], ["d"], []]
    assert out[1]["paused"] and out[3]["held_s"] == 0.8 and not out[5]["paused"]
    assert out[4]["pauses"] == 1 and out[6]["resumes"] == 1  # a repeated notice is one pause
    # 5 x 0.4 s held with room for 1 s: e0, e1, e2 dropped (counted), e3 and e4 sent at resume
    assert out[-1]["sent"] == ["e3", "e4"] and out[-1]["dropped_chunks"] == 3 and out[-1]["dropped_s"] == 1.2
    assert out[-2]["held_s"] == 0.8 and out[-1]["held_s"] == 0


def test_web_frame_ring_hands_every_frame_over_in_order_and_skips_only_what_was_overwritten(tmp_path):
    """clients/web/frame-ring.js under node: the page reads from shared memory exactly the frames the socket worker
    wrote (index, pts, root, rotations, arrival, binary or not), in order, each once; a reader more than the ring
    behind loses the oldest, never a newer one; a frame of another joint count is refused (it is posted instead)."""
    node = shutil.which("node")
    if not node:
        pytest.skip("node not installed (Debian: apt-get install nodejs)")
    script = tmp_path / "ring.txt"
    script.write_text("\n".join(["take", "write 3", "take", "take", "write 1", "misfit", "write 300", "take"]))
    r = subprocess.run([node, str(REPO / "clients/web/tests/frame_ring_check.mjs"), "5", str(script)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    out = [json.loads(line) for line in r.stdout.splitlines()]
    takes = [o for o in out if o["event"] == "take"]
    assert takes[0]["frames"] == [] and takes[2]["frames"] == []
    first = takes[1]
    assert [f["index"] for f in first["frames"]] == [0, 1, 2] and first["binary"] == [False, True, False]
    assert first["at"] == [1000, 1001, 1002]
    f = first["frames"][2]
    assert f["pts"] == pytest.approx(0.1) and f["root"] == [2, -2, 0.5]
    assert f["rotations"] == [[1, j, -2, 0.25] for j in range(5)]
    assert out[3] == {"event": "misfit", "written": False}
    # 301 frames (3..303) behind a ring of 256: the newest 255 are read (the slot written next is left), in order
    last = [f["index"] for f in takes[3]["frames"]]
    assert last == list(range(304 - 255, 304))


def test_web_talk_pauses_at_slow_down_and_resumes_without_an_error(tmp_path, bundle):  # noqa: F811
    """A server slower than real time with a 1 s backlog (in process, serving the viewer itself): the page's
    microphone gets `slow_down`, holds its audio, sends it at `resume` (protocol revision 2), shows no error,
    and ends its session with `end` after Stop."""
    from streamer.sessions import Session

    from helpers.ws import SlowExecutor, make_server, running

    executor = SlowExecutor(1, delay_s=2.0)  # at most 1 s of audio per call: about half real time
    ws = make_server(bundle, max_backlog_s=1.0)
    ws.make_session = lambda **kw: Session.from_bundle(bundle, steps=2, window_ms=100, scheduler=executor, **kw)
    with running(ws):
        browser = Browser(tmp_path, ws.viewer_urls[0], (
            "--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
            f"--use-file-for-fake-audio-capture={SPEECH_WAV}"))
        try:
            browser.wait_for("window.dimgestor && window.dimgestor.hello && "
                             "!document.getElementById('talk').disabled", 60, "hello and an enabled Talk button")
            browser.eval("document.getElementById('talk').click()", user_gesture=True)
            browser.wait_for("window.dimgestor.audioFlow && window.dimgestor.audioFlow.resumes >= 1", 90,
                             "slow_down then resume")
            browser.wait_for("window.dimgestor.framesReceived >= 10", 60, "gestures from our own audio")
            flow = browser.eval("({pauses: dimgestor.audioFlow.pauses, resumes: dimgestor.audioFlow.resumes, "
                                "dropped: dimgestor.audioFlow.droppedChunks, sent: dimgestor.audioChunksSent, "
                                "notices: dimgestor.notices.map((m) => m.type === 'error' ? m.code : m.type)})")
            assert flow["pauses"] >= 1 and flow["dropped"] == 0 and flow["sent"] > 10, flow
            assert set(flow["notices"]) == {"slow_down", "resume"}, flow
            assert "server error" not in browser.eval("document.getElementById('message').textContent")
            frames = browser.eval("window.dimgestor.framesReceived")
            browser.eval("document.getElementById('talk').click()", user_gesture=True)  # Stop -> audio_end
            ended = browser.wait_for("window.dimgestor.ended", 120, "end of our session")
            assert ended["frames"] >= frames
            assert browser.eval("window.dimgestor.errors.length") == 0, browser.eval("window.dimgestor.errors")
            assert browser.eval("window.dimgestor.audioFlow.paused") is False
        finally:
            browser.close()
    executor.shutdown()


# ---------------------------------------------------------------- the real skeleton: mannequin, sound, VRM

@pytest.fixture(scope="module")
def default_model_server(tmp_path_factory):
    """The embedded default model (the ZEGGS skeleton, fingers and feet) on the speech clip, looped; the source
    starts when the first page connects, so that page hears the clip from its first sample."""
    with live_server(tmp_path_factory.mktemp("web_default"), str(SPEECH_WAV), None, http=True, loop=True,
                     extra=("--wait-client",)) as s:
        yield s


def humanoid_positions(browser: Browser) -> dict[str, np.ndarray]:
    """World positions (m) of the streamed skeleton's humanoid joints, by HumanBodyBones name."""
    hello = browser.eval("window.dimgestor.hello")
    names = hello["skeleton"]["joints"]
    pos = browser.positions()
    return {bone: pos[names.index(joint)] for bone, joint in hello["humanoid"].items()}


def facing_cosine(browser: Browser) -> float:
    """cos of the angle between where the body faces (from its joints) and where the camera is, on the floor."""
    p = humanoid_positions(browser)
    left, up = p["LeftUpperLeg"] - p["RightUpperLeg"], p["Head"] - p["Hips"]
    forward = np.cross(left, up) * [1, 0, 1]
    to_camera = (np.asarray(browser.eval("window.dimgestor.cameraPosition()")) - p["Hips"]) * [1, 0, 1]
    return float(forward @ to_camera / np.linalg.norm(forward) / np.linalg.norm(to_camera))


def test_late_arrivals_counts_each_stall_once():
    steady = [(10 + 0.05 * i + 0.3, 10 + 0.05 * i) for i in range(200)]  # 0.3 s transit, every frame
    assert late_arrivals(steady, 0.1) == 0
    stalled = steady[:100] + [(a + 0.8, p) for a, p in steady[100:110]] + steady[110:]  # 0.8 s late for 0.5 s
    assert late_arrivals(stalled, 0.1) == 1
    assert late_arrivals(stalled, 1.0) == 0  # within the margin: nothing a clock with it would notice


def test_web_mannequin_faces_the_camera_moves_and_plays_the_source_audio_in_sync(tmp_path, default_model_server):
    from scipy.signal import resample_poly

    from dimgestor.audio import load_wav

    server = default_model_server
    browser = Browser(tmp_path, server.http_url)
    try:
        browser.wait_for("!!window.dimgestor", 60, "the page")
        rate = browser.eval(RECORDER)  # before any sound: the page schedules it once frames come
        browser.wait_for("!!window.dimgestor.shownFrame", 60, "a frame on screen")
        assert browser.eval("window.dimgestor.avatar") == "mannequin"
        time.sleep(1.5)  # the view is framed on the first frames, then keeps in front of the avatar as it turns
        cosines = []
        for _ in range(3):
            cosines.append(facing_cosine(browser))
            time.sleep(0.3)
        assert min(cosines) > 0.7, f"the avatar does not face the camera at start (cos {np.round(cosines, 2)})"

        # The audio clock advances, and the frame drawn is the one whose pts is heard when the page picked it: read
        # in an animation frame callback after the page's own (which picks the pose and draws it), with the audio
        # clock then and how long ago the pick was. (Read at an arbitrary moment, a software-rendered page on a
        # loaded machine may be several frames behind.)
        samples = []
        for _ in range(20):
            time.sleep(0.4)
            samples.append(browser.eval(SHOWN_NOW))
        t = np.array([s["t"] for s in samples])
        assert np.all(np.diff(t) > 0.1), f"the page's audio clock does not advance: {t}"
        clock = browser.eval("(({underruns, soundHolds, catchUps, marginS, baseMarginS, offset}) => ({underruns, "
                             "soundHolds, catchUps, marginS, baseMarginS, offset}))(window.dimgestor.clock)")
        arrivals = browser.eval("window.dimgestor.arrivalLog")
        rec = browser.eval(RECORDING)
        pieces = browser.eval(PLAYED)
        png_a = browser.screenshot(tmp_path / "web_mannequin_a.png")
        time.sleep(0.7)
        png_b = browser.screenshot(tmp_path / "web_mannequin_b.png")
        browser.eval("window.dimgestor.setAvatar('skeleton')")
        time.sleep(0.3)
        png_skeleton = browser.screenshot(tmp_path / "web_skeleton.png")
        errors = browser.eval("window.dimgestor.errors")
    finally:
        browser.close()
    assert not errors, errors

    # What the page played (its output, recorded sample by sample), brought to 16 kHz.
    played = np.frombuffer(base64.b64decode(rec["pcm"]), "<i2").astype(np.float32) / 32767
    played16 = resample_poly(played, 16000, rate).astype(np.float32) if rate != 16000 else played
    source = load_wav(SPEECH_WAV).astype(np.float32)

    # Sync: when the page picked a frame, the output played what the recording has at the context time the
    # browser's output timestamp gives for that moment (helpers/av_sync.py SHOWN_NOW). Which moment of the source that is, is found from the sound itself (a 100 ms stretch matched against the clip, which loops),
    # so a pause in the sound (the page waiting for late frames) cannot fool the check; silent moments are left
    # out. The frame picked then must be the one with that pts.
    # A starved page (a software-rendered Chromium on two busy cores draws about once a second) holds where the
    # sound it had scheduled ran out (av-clock.js soundStopped), and nothing plays then: the moments checked are
    # the steady reads, and where the clip speaks at the pts on screen, the sound must be heard at most of them.
    # (Reads across a stretch the recorder missed are left out: the audio context skipped render quanta there.)
    missed = missed16(rec, rate)
    sync = shown_minus_heard(samples, played16, rec["start"] / rate, source, missed)
    heard_at = [heard_index(s, rec["start"] / rate) for s in steady(samples)]
    speaking = sum(voiced_at(source, s["pts"]) and recorded_around(missed, i) for s, i in zip(steady(samples), heard_at))
    print(f"frame pts - heard pts (s): {np.round(sync, 3)}; {speaking} steady reads where the clip speaks; "
          f"drawing (s): {np.round([s['drawing'] for s in samples], 3)}; clock {clock}; "
          f"recorder missed (s): {[(round(a / 16000, 2), round(b / 16000, 2)) for a, b in missed]}")
    assert len(sync) >= max(4, 2 * speaking // 3), (
        f"too few moments with sound to check sync ({len(sync)} of {len(samples)} reads; the clip speaks at "
        f"{speaking} steady ones); clock {clock}")
    # One read may be off, as in test_clients_web_local (there 0.64 and 0.91 s, here -0.639 s among 15 reads at 0.000
    # with a clean clock and the recorder missing 10 ms, once in a fresh clone's run: not understood, and the reads
    # printed above say more next time); two may not, and the rest must agree.
    off = np.abs(np.array(sync)) >= 0.1
    assert off.sum() <= 1 and np.median(np.abs(sync)) < 0.03, \
        f"frames and sound out of sync (s): {np.round(sync, 3)}; clock {clock}"
    # and that timestamp is the output's clock: the context's own current time puts those moments within 50 ms of it
    stamp = timestamp_minus_current_time(samples)
    assert not stamp or np.median(np.abs(stamp)) < 0.05, f"output timestamp - current time (s): {np.round(stamp, 3)}"
    # The clock may lose itself only at a stall: frames came later than anything in the 10 s before by more than
    # its margin (the server or the page stalled: CI's other work on its two cores), or the page came back later
    # than the sound it had scheduled lasted (counted by the page: soundHolds); each may cost a hold and the
    # catch-ups that give the buffer back. On a quiet machine there are none, and at most 2 in all.
    stalls = late_arrivals(arrivals, clock["baseMarginS"]) + clock["soundHolds"]
    assert clock["catchUps"] + clock["underruns"] <= 2 + 3 * stalls, \
        f"the page kept losing its clock: {clock}, {stalls} stalls in the frames' arrival and the page's sound"

    # It played the clip from its first sample on: the page scheduled it from the clip's start (all it skipped of
    # that for coming late, which a loaded machine makes it, it says: `late`), and the recording holds what it
    # scheduled: the clip's sound at each piece's pts at the piece's time and silence between (holds, catch-ups
    # and lateness included), where the recorder got every block.
    assert np.abs(played16).max() > 0.1, f"nothing was played ({len(played16)} samples recorded)"
    first = pieces[0]
    print(f"the first pieces (at, pts, dur, late, stop): "
          f"{[tuple(round(v, 3) if v is not None else None for v in p.values()) for p in pieces[:4]]}")
    assert (first["pts"] - first["late"]) % (len(source) / 16000) < 0.015, f"not played from its start: {first}"
    start_s = rec["start"] / rate
    assert_played_as_scheduled(played16, start_s, pieces, source, first["at"] - 0.1, 1.0, missed, wrap=True)
    assert_played_as_scheduled(played16, start_s, pieces, source, start_s, len(played16) / 16000, missed, wrap=True)

    # Two moments differ on screen (it moves), and the skeleton toggle draws something else.
    a, b, sk = read_png(png_a), read_png(png_b), read_png(png_skeleton)
    assert_figure_drawn(png_a)
    assert np.abs(a[:, 300:] - b[:, 300:]).max(axis=2).__gt__(0.1).sum() > 200, "the avatar did not move between two moments"
    assert np.abs(b[:, 300:] - sk[:, 300:]).max(axis=2).__gt__(0.1).sum() > 2000, "the skeleton toggle changed nothing"


@pytest.mark.parametrize("version, arms_down", [("1.0", 0.0), ("0.0", 0.0), ("1.0", 45.0)])
def test_web_a_dropped_vrm_follows_the_stream(tmp_path, default_model_server, version, arms_down):
    """A VRM (1.0, 0.x, and one whose rest pose is an A-pose) dropped on the viewer: each limb points where the
    streamed skeleton's does."""
    vrm = make_vrm(version, arms_down=arms_down)
    server = default_model_server
    browser = Browser(tmp_path, server.http_url + "?sound=off")
    try:
        browser.wait_for("!!(window.dimgestor && window.dimgestor.shownFrame)", 60, "a frame on screen")
        # The drop code path: a file dropped on the page.
        browser.eval(f"""(() => {{
          const bytes = Uint8Array.from(atob('{base64.b64encode(vrm).decode()}'), (c) => c.charCodeAt(0));
          const dt = new DataTransfer();
          dt.items.add(new File([bytes], 'test-{version}.vrm'));
          document.body.dispatchEvent(new DragEvent('drop', {{dataTransfer: dt, bubbles: true, cancelable: true}}));
        }})()""")
        browser.wait_for("!!window.dimgestor.vrm && window.dimgestor.avatar === 'vrm'", 30, "the VRM to load")
        assert browser.eval("window.dimgestor.vrm.metaVersion") == version[0]
        time.sleep(0.5)

        def pose():
            both = browser.eval("({vrm: window.dimgestor.vrm.boneWorldPositions(), src: window.dimgestor.jointWorldPositions()})")
            return {k: np.asarray(v) for k, v in both["vrm"].items()}, both["src"]

        hello = browser.eval("window.dimgestor.hello")
        names = hello["skeleton"]["joints"]
        first, _ = pose()
        time.sleep(1.0)
        second, src = pose()
        moved = max(np.linalg.norm(first[b] - second[b]) for b in ("leftHand", "rightHand", "leftLowerArm", "rightLowerArm"))
        assert moved > 0.01, f"the VRM's arms did not move with the stream ({moved * 100:.1f} cm)"
        # Retargeted, not just moving: each limb points where the streamed skeleton's limb points.
        src = np.asarray(src)
        for a, b, ja, jb in [("leftUpperArm", "leftLowerArm", "LeftUpperArm", "LeftLowerArm"),
                             ("rightLowerArm", "rightHand", "RightLowerArm", "RightHand"),
                             ("leftUpperLeg", "leftLowerLeg", "LeftUpperLeg", "LeftLowerLeg"),
                             ("spine", "chest", "Spine", "Chest")]:
            d_vrm = second[b] - second[a]
            d_src = src[names.index(hello["humanoid"][jb])] - src[names.index(hello["humanoid"][ja])]
            cos = d_vrm @ d_src / np.linalg.norm(d_vrm) / np.linalg.norm(d_src)
            assert cos > np.cos(np.radians(5)), f"VRM {version} {a}->{b} points {np.degrees(np.arccos(min(cos, 1))):.1f} degrees off the skeleton's"
        time.sleep(0.3)
        png = browser.screenshot(tmp_path / f"web_vrm_{version}{'_apose' if arms_down else ''}.png")
        assert browser.eval("window.dimgestor.errors.length") == 0, browser.eval("window.dimgestor.errors")
    finally:
        browser.close()
    img = read_png(png)[:, 300:]
    skin = (img[..., 0] > 0.45) & (img[..., 0] > img[..., 2] + 0.15)  # the test avatar's boxes are skin-coloured
    assert skin.sum() > 100, f"{png}: the VRM is not visible ({skin.sum()} pixels)"


def worker_streams(port: int) -> float:
    """A worker's live streams, from its own /metrics (behind nginx: which worker holds our session)."""
    import re

    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
    return float(re.search(r"^dimgestor_streams (\S+)$", text, re.M).group(1))


@contextmanager
def talking_through_a_cluster(tmp_path, checkpoint, *cluster_args: str):
    """deploy/local-cluster (2 workers on the tiny checkpoint, `cluster_args` before `--`) and the viewer loaded
    through its nginx, talking with Chromium's fake microphone until 30 frames came back -> (cluster, browser)."""
    from helpers.cluster import Cluster

    cluster = Cluster(*cluster_args, "--", "--checkpoint", str(checkpoint), "--steps", "2", "--window-ms", "100",
                      "--status-every", "0")
    browser = None
    try:
        cluster.wait_for(r"^ready: ")
        browser = Browser(tmp_path, cluster.http + "/?audio=pcm16", (
            "--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
            f"--use-file-for-fake-audio-capture={SPEECH_WAV}"))
        browser.wait_for("window.dimgestor && window.dimgestor.hello && "
                         "!document.getElementById('talk').disabled", 60, "hello and an enabled Talk button")
        browser.eval("document.getElementById('talk').click()", user_gesture=True)
        browser.wait_for("window.dimgestor.framesReceived >= 30", 90, "gestures from our own audio")
        yield cluster, browser
    finally:
        if browser is not None:
            browser.close()
        cluster.stop()


@pytest.mark.skipif(not (shutil.which("redis-server") and shutil.which("nginx") or os.path.exists("/usr/sbin/nginx")),
                    reason="nginx and redis-server are needed (.ci/run installs both): the cluster's balancer and store")
def test_web_talk_moves_to_another_worker_when_its_worker_stops(tmp_path, checkpoint):  # noqa: F811
    """Issue 22: the viewer, talking through nginx (deploy/local-cluster, 2 workers + Redis), gets `goaway` when
    its worker is stopped (SIGTERM), resumes its session on the other one and goes on: no frame index skipped,
    no error, the microphone held meanwhile and re-sent from the sample the saved state covers."""
    import signal

    with talking_through_a_cluster(tmp_path, checkpoint) as (cluster, browser):
        workers = cluster.workers()
        (port, pid), = [w for w in workers.values() if worker_streams(w[0]) >= 1]  # ours
        os.kill(pid, signal.SIGTERM)
        browser.wait_for("window.dimgestor.resumed === 1", 30, "our session resumed on the other worker")
        before = browser.eval("window.dimgestor.framesReceived")
        browser.wait_for(f"window.dimgestor.framesReceived >= {before + 40}", 60, "gestures going on after the move")
        other = next(p for p, _ in workers.values() if p != port)
        assert worker_streams(other) >= 1  # the session lives there now
        api = browser.eval("({handovers: dimgestor.handovers, gaps: dimgestor.gaps, errors: dimgestor.errors, "
                           "dropped: dimgestor.audioChunksDropped, state: dimgestor.state})")
        assert api == {"handovers": 1, "gaps": 0, "errors": [], "dropped": 0, "state": "open"}, api
        assert moving_joints(browser) > 1e-3
        assert_figure_drawn(browser.screenshot(tmp_path / "web_talk_moved.png"))


@pytest.mark.skipif(not (shutil.which("nginx") or os.path.exists("/usr/sbin/nginx")),
                    reason="nginx is needed (.ci/run installs it): the cluster's balancer")
def test_web_talk_goes_on_in_a_fresh_session_when_its_worker_is_killed(tmp_path, checkpoint):  # noqa: F811
    """Issue 22 item 4: the viewer talking through nginx (two workers) loses its worker to SIGKILL (no goaway):
    it reconnects within 2 s and talks on in a fresh session on the other worker, the microphone never stopped."""
    import signal

    with talking_through_a_cluster(tmp_path, checkpoint, "--no-state-store") as (cluster, browser):
        (port, pid), = [w for w in cluster.workers().values() if worker_streams(w[0]) >= 1]  # ours
        before = browser.eval("window.dimgestor.framesReceived")
        os.kill(pid, signal.SIGKILL)
        killed = time.monotonic()
        browser.wait_for(f"window.dimgestor.reconnects === 1 && window.dimgestor.framesReceived > {before + 2}", 30,
                         "frames again, from a fresh session")
        noticed = time.monotonic() - killed
        t0 = time.monotonic()
        browser.eval("0")  # one round trip of this check's polling, as the page answers now (a loaded machine: s)
        polling = 0.2 + 2 * (time.monotonic() - t0)  # its interval, and the last poll's round trip with slack
        assert noticed < 2.0 + max(1.0, polling), (noticed, polling)  # within 2 s, plus this check's own polling
        browser.wait_for(f"window.dimgestor.framesReceived >= {before + 40}", 60, "gestures going on")
        api = browser.eval("({talking: dimgestor.talking, errors: dimgestor.errors, state: dimgestor.state})")
        assert api == {"talking": True, "errors": [], "state": "open"}, api


def test_web_viewer_on_a_software_renderer_draws_at_half_density_and_at_most_20_fps(tmp_path):
    """Where WebGL runs on the CPU (headless Chromium here: SwiftShader) the page draws its canvas at half the pixel
    density and at most 20 times a second (the page asks for the next drawing 8 ms early: >= 42 ms apart). Measured
    on the page alone (no server: nothing else wants the CPU), where it could draw every ~18 ms without the cap; a
    GPU page: full density, no cap."""
    import threading

    from streamer.web import make_server

    httpd = make_server("127.0.0.1", 0, tmp_path)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    browser = Browser(tmp_path, f"http://127.0.0.1:{httpd.server_address[1]}/?sound=off")
    try:
        browser.wait_for("!!window.dimgestor && window.dimgestor.frameMs !== null", 60, "the page drawing")
        time.sleep(3)  # frameMs: a moving average over ~10 drawings
        drawing = browser.eval("({...window.dimgestor.drawing, dpr: devicePixelRatio, "
                               "frameMs: window.dimgestor.frameMs})")
    finally:
        browser.close()
        httpd.shutdown()
    if drawing["softwareGl"]:
        assert drawing["pixelRatio"] == 0.5 * drawing["dpr"] and drawing["maxFps"] == 20, drawing
        assert drawing["frameMs"] > 40, drawing
    else:
        assert drawing["pixelRatio"] == drawing["dpr"] and drawing["maxFps"] is None, drawing


def test_chromium_keeps_its_temporary_files_in_a_folder_removed_at_close(tmp_path):
    """The tests' Chromium writes its singleton socket's folder into a short folder of ours, not the machine's
    temporary folder (where a stopped Chromium left one per start), and that folder goes at close."""
    browser = Browser(tmp_path, "about:blank")
    try:
        browser.wait_page()
        ours = Path(browser.tmpdir)
        assert [p.name.startswith("org.chromium.Chromium.") for p in ours.iterdir()] == [True], list(ours.iterdir())
    finally:
        browser.close()
    assert not ours.exists()
