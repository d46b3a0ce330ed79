"""The viewer's local mode (`streamer web`, `?local=model/`): the model runs in the browser with onnxruntime-web
(WebAssembly, in a Web Worker), no inference server. In real headless Chromium: a known WAV gives the frames
Python's `FrameStepStream` on ONNX Runtime gives for the same audio, seed, K and M (normalized features within
1e-4, decoded rotations within 1e-4 and root within 1e-3 cm); a dropped WAV is heard from its first sample, in
sync with its gestures, and a second drop replaces it; the fake microphone gives moving frames at the stream's
rate in real time with the page saying it runs locally, showing its real-time factor and a measured speech ->
motion delay. The pose
decoding (pose-decoder.js) and the output filter are also checked under node against Python's numbers.
The page runs the embedded default model (K = 2 here, to export quickly); the node checks a tiny checkpoint."""

from __future__ import annotations

import base64
import json
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from helpers.av_sync import (PLAYED, RECORDER, RECORDING, SHOWN_NOW, assert_played_as_scheduled, late_arrivals, missed16,
                             heard_index, recorded_around, shown_minus_heard, steady, streams,
                             timestamp_minus_current_time, voiced_at)
from helpers.browser import CHROMIUM, Browser, assert_figure_drawn
from helpers.clients import REPO, SPEECH_WAV, free_port

ORT_WEB = REPO / "clients" / "web" / "node_modules" / "onnxruntime-web" / "dist" / "ort.wasm.min.mjs"
NODE = shutil.which("node")
pytest.importorskip("onnxruntime", reason="the `onnx` extra is not installed")
needs_chromium = pytest.mark.skipif(not CHROMIUM, reason="chromium not installed (Debian: apt-get install chromium)")
needs_ort_web = pytest.mark.skipif(not ORT_WEB.exists(), reason="onnxruntime-web is not installed (make setup runs "
                                   "npm ci in clients/web)")
STEPS, FRAMES, SEED = 2, 2, 0  # the page's seed is 0 unless ?seed= says otherwise
FEATURE_TOL, ROTATION_TOL, ROOT_TOL_CM = 1e-4, 1e-4, 1e-3


SILENCE_S = 2.0  # the known WAV: this much digital silence, then the speech WAV


@pytest.fixture(scope="module")
def web_model(tmp_path_factory):
    """The embedded default model exported for the page (graph, manifest, web.json; ~30 s, once a run for every
    test process: helpers/web_export.py) in a folder of this module's, and the known WAV."""
    from dimgestor.audio import SAMPLE_RATE, load_wav, save_wav
    from helpers.web_export import own_copy, web_export

    folder = own_copy(web_export(tmp_path_factory, STEPS, FRAMES), tmp_path_factory.mktemp("web_model"))
    speech = load_wav(SPEECH_WAV)
    save_wav(folder / "known.wav", np.concatenate([np.zeros(int(SILENCE_S * SAMPLE_RATE)), speech]), SAMPLE_RATE)
    return folder


@pytest.fixture(scope="module")
def web_server(web_model, tmp_path_factory):
    """`streamer web` on a free port serving the page and the model folder; yields its base URL."""
    port = free_port()
    log = tmp_path_factory.mktemp("web_server") / "server.log"
    cmd = [sys.executable, "-c", "import sys; from dimgestor_app.cli import main; sys.exit(main())", "web",
           "--model", str(web_model), "--port", str(port)]
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while True:
            assert proc.poll() is None, f"streamer web exited:\n{log.read_text()}"
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                assert time.monotonic() < deadline, f"streamer web did not listen:\n{log.read_text()}"
                time.sleep(0.2)
        yield f"http://127.0.0.1:{port}/"
    finally:
        proc.terminate()
        proc.wait(10)


def python_frames(folder: Path, audio: np.ndarray) -> np.ndarray:
    """The reference: Python's FrameStepStream on ONNX Runtime, the whole audio pushed, then finish."""
    from dimgestor.export.onnx_stream import ort_stream

    stream = ort_stream(folder, seed=SEED)
    return np.concatenate([stream.push(audio), stream.finish()])


def python_poses(folder: Path, frames: np.ndarray):
    from dimgestor.features import PoseDecoder
    from dimgestor.streaming.checkpoint import load_checkpoint

    web = json.loads((folder / "web.json").read_text())
    bundle = load_checkpoint(json.loads((folder / "manifest.json").read_text())["checkpoint"]["path"])
    decoder = PoseDecoder(bundle.skeleton, bundle.feature_spec, root=web["root"], tether_s=web["tether_s"])
    return decoder.decode(bundle.denormalize(frames))


def open_local(tmp_path: Path, url: str, extra: tuple[str, ...] = ()) -> Browser:
    browser = Browser(tmp_path, url + "?local=model/", extra)
    try:
        browser.wait_page()  # the page may have no execution context yet just after Chromium starts
        browser.wait_for("window.dimgestorLocal && window.dimgestorLocal.info", 120, "the local model to load")
    except BaseException:
        browser.close()
        raise
    return browser


def test_streamer_web_serves_the_page_and_the_model_as_static_files(web_model, web_server):
    """The page, the model folder and onnxruntime-web's WASM with the types Chromium needs, cross-origin isolated;
    web.json's hello is the one `streamer serve` sends for this checkpoint (skeleton, humanoid map)."""
    import urllib.error
    import urllib.request

    def get(path):
        with urllib.request.urlopen(web_server + path, timeout=30) as r:
            return r.headers, r.read()

    headers, body = get("node_modules/onnxruntime-web/dist/ort-wasm-simd-threaded.wasm")
    assert headers["Content-Type"] == "application/wasm" and body[:4] == b"\0asm"
    assert headers["Cross-Origin-Opener-Policy"] == "same-origin"
    assert headers["Cross-Origin-Embedder-Policy"] == "require-corp"
    assert get("local-worker.js")[0]["Content-Type"] == "text/javascript"
    manifest = json.loads(get("model/manifest.json")[1])
    assert manifest["sampler"]["steps"] == STEPS and manifest["call"]["frames_per_call"] == FRAMES
    assert get("model/frame_step.onnx")[1] == (web_model / "frame_step.onnx").read_bytes()
    web = json.loads(get("model/web.json")[1])
    hello = web["hello"]
    assert hello["type"] == "hello" and hello["source"] == "local" and hello["audio"]["accepts"]
    assert len(hello["skeleton"]["joints"]) == web["features"]["numJoints"] and hello["humanoid"]["Hips"]
    assert 6 + 3 * len(web["features"]["joints"]) == len(manifest["checkpoint"]["mean"]) == web["features"]["dim"]
    with pytest.raises(urllib.error.HTTPError, match="404"):
        get("model/../../pyproject.toml")


@pytest.mark.skipif(not NODE, reason="node not installed (Debian: apt-get install nodejs)")
@pytest.mark.parametrize("heading", ["velocity", "facing"])
@pytest.mark.parametrize("root", ["free", "tether", "lock"])
def test_pose_decoder_in_javascript_equals_python(tmp_path, checkpoint, root, heading):
    from dimgestor.features import PoseDecoder
    from dimgestor.smoothing import OneEuroFilter
    from dimgestor.streaming.checkpoint import load_checkpoint

    bundle = load_checkpoint(checkpoint)
    sk, spec = bundle.skeleton, bundle.feature_spec.resolve(bundle.skeleton).model_copy(update={"heading": heading})
    rows = np.random.default_rng(3).normal(size=(41, spec.dim)).astype(np.float32) * 2  # turns of a radian and more
    feeds = {"spec": {"mean": bundle.mean.tolist(), "std": bundle.std.tolist(), "joints": spec.joint_indices(sk),
                      "numJoints": sk.num_joints, "heading": heading, "fps": spec.fps},
             "root": root, "tether_s": 0.5, "rows": rows.tolist(), "filter": {"fps": 20, "hz": 3.0, "beta": 0.7}}
    (tmp_path / "in.json").write_text(json.dumps(feeds))
    r = subprocess.run([NODE, str(REPO / "clients/web/tests/pose_decoder_check.mjs"), str(tmp_path / "in.json")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    features = bundle.denormalize(rows)
    np.testing.assert_array_equal(np.float32(got["features"]), features)  # f * std + mean, float32: exactly
    pose = PoseDecoder(sk, spec, root=root, tether_s=0.5).decode(features)
    np.testing.assert_allclose(got["root"], pose.root_pos, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got["rotations"], pose.rotations, rtol=0, atol=1e-12)
    if root != "lock":  # (the root did travel: the integration was exercised)
        assert np.abs(pose.root_pos[:, [0, 2]]).max() > 1.0
    want = OneEuroFilter(20, 3.0, 0.7).step(None, rows.astype(np.float64))[0]  # split in two calls there, whole here
    np.testing.assert_allclose(got["filtered"], want, rtol=0, atol=1e-12)


@pytest.mark.timeout(300)
@needs_chromium
@needs_ort_web
def test_local_frames_for_a_wav_equal_python_onnx_runtime(tmp_path, web_model, web_server):
    from dimgestor.audio import load_wav
    from dimgestor.face import net
    from dimgestor.face.visemes import V
    from helpers.clients import joint_speed

    browser = open_local(tmp_path, web_server)
    try:
        info = browser.eval("window.dimgestorLocal.info")
        assert info["sampler"]["steps"] == STEPS and info["call"]["frames_per_call"] == FRAMES
        got = browser.eval("window.dimgestorLocal.runWav('/model/known.wav')")
        errors = browser.eval("window.dimgestor.errors")
    finally:
        browser.close()
    assert errors == []
    audio = load_wav(web_model / "known.wav")
    want = python_frames(web_model, audio)
    assert len(want) == len(audio) * 20 // 16000 and len(got["normalized"]) == len(want)
    np.testing.assert_allclose(got["normalized"], want, rtol=0, atol=FEATURE_TOL)
    pose = python_poses(web_model, want)
    np.testing.assert_allclose(got["rotations"], pose.rotations, rtol=0, atol=ROTATION_TOL)
    np.testing.assert_allclose(got["root"], pose.root_pos, rtol=0, atol=ROOT_TOL_CM)
    assert 0 < got["rtf"] and got["samples"] == len(audio)
    # The face: the listener's graph (face_step.onnx) beside the body's, each frame's mouth as the server's
    # listener hears it (`mouth` of face-step-stream.js from dimgestor.face.net's stream), open on the speech's
    # vowels and shut in the silence before it.
    assert info["face"] is True and all(f is not None for f in got["face"])
    jaw = np.array([f["jawOpen"] for f in got["face"]])
    heard = net.NetListener.offline(audio, 20)
    want_jaw = np.array([h.opening * (1 - h.visemes[V["PP"]]) * (0.2 if np.argmax(h.visemes) == V["PP"] else 1)
                         for h in heard])[:len(jaw)]
    np.testing.assert_allclose(jaw, want_jaw, rtol=0, atol=1e-4)
    assert jaw[:int(SILENCE_S * 20) - 4].max() < 0.1 and jaw[int(SILENCE_S * 20):].max() > 0.5
    vowels = np.array([[f[k] for k in ("aa", "ih", "ou", "ee", "oh")] for f in got["face"]])
    assert len(set(np.argmax(vowels[vowels.max(1) > 0.3], 1))) >= 3  # several vowel shapes, not one
    # The gestures follow the speech: joints turn faster while it speaks than in the silence before it.
    speed = joint_speed([{"rotations": r} for r in got["rotations"]], 20)
    silent, speaking = speed[5:int(SILENCE_S * 20) - 8].mean(), speed[int(SILENCE_S * 20) + 5:].mean()
    assert speaking > 1.5 * silent, (silent, speaking)


@pytest.mark.timeout(300)
@needs_chromium
@needs_ort_web
def test_local_fake_microphone_moves_the_avatar_in_real_time(tmp_path, web_server):
    browser = open_local(tmp_path, web_server, (
        "--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
        f"--use-file-for-fake-audio-capture={SPEECH_WAV}"))
    try:
        browser.eval("window.dimgestor.talk()", user_gesture=True)
        browser.wait_for("window.dimgestorLocal.framesMade >= 20", 60, "20 frames from the microphone")
        read = ("({t: performance.now() / 1000, frames: window.dimgestorLocal.framesMade, "
                "audio: window.dimgestorLocal.audioS, captured: window.dimgestorLocal.capturedS, "
                "backlog: window.dimgestorLocal.backlogS, dropped: window.dimgestorLocal.droppedS, "
                "busy: window.dimgestorLocal.runMs / 1000, "
                "shown: window.dimgestor.shownFrame && window.dimgestor.shownFrame.index})")
        a = browser.eval(read)
        poses, backlogs = [], [a["backlog"]]
        for _ in range(8):
            time.sleep(0.5)
            r = browser.eval("({p: window.dimgestor.jointWorldPositions(), backlog: window.dimgestorLocal.backlogS})")
            poses.append(r["p"])
            backlogs.append(r["backlog"])
        b = browser.eval(read)
        backlogs.append(b["backlog"])
        hud = browser.eval("({state: document.getElementById('state').textContent, "
                           "url: document.getElementById('url').textContent, "
                           "rtf: document.getElementById('rtf').textContent})")
        browser.screenshot(tmp_path / "web_local_mic.png")
        png = tmp_path / "web_local_mic.png"
        errors = browser.eval("window.dimgestor.errors")
        browser.eval("window.dimgestor.stopTalk()")
    finally:
        browser.close()
    assert errors == []
    wall, audio = b["t"] - a["t"], b["audio"] - a["audio"]
    # The fake microphone delivers audio in real time; every sample of it is answered by the model, waiting for
    # it (backlog, bounded at 2 s) or dropped and counted; every 50 ms answered makes one frame.
    assert b["captured"] - a["captured"] == pytest.approx(wall, rel=0.25), (a, b)
    for r in (a, b):
        assert r["audio"] + r["backlog"] + r["dropped"] == pytest.approx(r["captured"], abs=1e-6), r
    # Keeping up: unless the shared machine starved the page, the backlog did not grow and nothing was dropped.
    # Starved is what this test measures itself: the worker busy for 70% of the time or more (its calls' time
    # includes any time the CPU was taken away), or the page's main thread (which answers the worker) so late
    # that our 8 reads of half a second between sleeps took over 30% longer than the sleeps. A starved page falls
    # behind by design (bounded, counted): then only the bookkeeping above is checked.
    # One read is a snapshot: the worker's answers reach the page on its main thread, which also draws, so a read
    # taken while answers queue behind a slow draw sees them as backlog (CI saw 0.5 s at the last read with the
    # worker busy 10% of the time). Falling behind is a backlog that stays: the smallest of the last four reads.
    busy, stalled = b["busy"] - a["busy"], wall - 8 * 0.5
    if busy < 0.7 * wall and stalled < 0.3 * wall:
        assert min(backlogs[-4:]) < a["backlog"] + 0.5 and b["dropped"] == a["dropped"], (busy, backlogs, a, b)
    else:
        print(f"starved: the worker busy {busy:.1f} s, reads {stalled:.1f} s late, of {wall:.1f} s: keeping up "
              "not checked")
    made = b["frames"] - a["frames"]
    assert made == pytest.approx(audio * 20, abs=2 * FRAMES + 1), (a, b)
    assert b["shown"] is not None and b["shown"] > a["frames"] - 40, "the picture does not follow the frames made"
    moves = np.abs(np.diff(np.asarray(poses), axis=0)).max(axis=(1, 2))
    assert (moves > 1e-4).sum() >= 5, f"the avatar hardly moves: {moves}"
    assert hud["state"] == "local" and "no server inference" in hud["url"]
    assert 0 < float(hud["rtf"]) < 10, hud
    assert_figure_drawn(png)


DROP = """(async (url, name) => {
  const bytes = await (await fetch(url)).arrayBuffer();
  const dt = new DataTransfer();
  dt.items.add(new File([bytes], name, {type: 'audio/wav'}));
  const c = window.dimgestor.sourceAudio.context();
  const at = {t: c.currentTime, page: performance.now() / 1000};
  document.body.dispatchEvent(new DragEvent('drop', {dataTransfer: dt, bubbles: true, cancelable: true}));
  return at;
})"""


@pytest.mark.timeout(300)
@needs_chromium
@needs_ort_web
def test_local_dropped_wav_is_heard_in_sync_with_its_gestures_and_a_second_drop_replaces_it(
        tmp_path, web_model, web_server):
    from scipy.signal import resample_poly

    from dimgestor.audio import load_wav

    shutil.copy(SPEECH_WAV, web_model / "speech.wav")  # speech from its first 15 ms: a cut start would show
    browser = open_local(tmp_path, web_server)
    try:
        rate = browser.eval(RECORDER)  # records what the page plays, sample by sample, from before any sound
        browser.eval(f"({DROP})('/model/speech.wav', 'speech.wav')")
        browser.wait_for("!!window.dimgestor.shownFrame && window.dimgestor.shownFrame.pts > 0.3", 60,
                         "the dropped WAV's frames on screen")
        first = []
        for _ in range(6):
            time.sleep(0.4)
            first.append(browser.eval(SHOWN_NOW))
        second_at = browser.eval(f"({DROP})('/model/speech.wav', 'again.wav')")
        browser.wait_for(f"window.dimgestor.arrivalLog.some(([a, p]) => a > {second_at['page']} && p < 0.2)", 60,
                         "the second drop's frames")
        began = browser.eval("window.dimgestorLocal.streamAt") / 1000  # (page s) when the second stream replaced the first
        time.sleep(0.5)
        readout = browser.eval("({delay: window.dimgestor.delayMs, measured: window.dimgestor.delayMeasured, "
                               "sound: document.getElementById('sound').textContent})")
        samples = []
        for _ in range(24):  # ~11 s of the 13.8 s file
            time.sleep(0.4)
            samples.append(browser.eval(SHOWN_NOW))
        clock = browser.eval("(({underruns, soundHolds, catchUps, marginS, baseMarginS, offset}) => ({underruns, "
                             "soundHolds, catchUps, marginS, baseMarginS, offset}))(window.dimgestor.clock)")
        arrivals = browser.eval("window.dimgestor.arrivalLog")
        rec = browser.eval(RECORDING)
        pieces = browser.eval(PLAYED)
        errors = browser.eval("window.dimgestor.errors")
    finally:
        browser.close()
    assert errors == []
    played = np.frombuffer(base64.b64decode(rec["pcm"]), "<i2").astype(np.float32) / 32767
    played16 = resample_poly(played, 16000, rate).astype(np.float32) if rate != 16000 else played
    source = load_wav(SPEECH_WAV).astype(np.float32)
    start_s = rec["start"] / rate
    assert np.abs(played16).max() > 0.1, f"nothing was played ({len(played16)} samples recorded)"

    # Heard from the file's first sample, each time: the page schedules each drop from pts 0 (all it skipped of
    # that for coming late, which a loaded machine makes it, it says: `late`), and what the recording holds is
    # what it scheduled, the file's sound at each piece's pts at the piece's time and silence between (holds,
    # catch-ups and lateness included), from before the sound starts until a second of it has been compared.
    missed = missed16(rec, rate)  # (stretches the recorder missed: the audio context skipped render quanta there)
    drops = streams(pieces)
    assert len(drops) == 2, [(round(d[0]["pts"], 3), len(d)) for d in drops]
    for drop in drops:
        print(f"a drop's first pieces (at, pts, dur, late, stop): "
              f"{[tuple(round(v, 3) if v is not None else None for v in p.values()) for p in drop[:4]]}")
        assert drop[0]["pts"] - drop[0]["late"] < 0.015, f"the page did not play the file from its start: {drop[0]}"
        assert_played_as_scheduled(played16, start_s, pieces, source, drop[0]["at"] - 0.1, 1.0, missed)
    # The second drop: the first file's sound stops when the second stream begins (within 0.1 s: the output's
    # latency), and the second is played as scheduled to the end of the recording.
    # (The page's and the audio context's clocks, read together at the drop, tick alike.)
    began_at = second_at["t"] + began - second_at["page"]
    ended = max(p["at"] + p["dur"] if p["stop"] is None else min(p["stop"], p["at"] + p["dur"]) for p in drops[0])
    assert ended <= began_at + 0.1, f"the first file played on {ended - began_at:.2f} s after the second began"
    assert_played_as_scheduled(played16, start_s, pieces, source, drops[1][0]["at"], len(played16) / 16000, missed)
    print(f"the first file's sound stopped {began - second_at['page']:.2f} s after the second drop; the second's "
          f"sound began {drops[1][0]['at'] - began_at:.2f} s after that")

    # In sync over the file: the frame on screen is the one whose pts is heard (as the server mode's test, within
    # 0.1 s), read in both streams; the second read ~11 s of its file.
    # (Reads across a stretch the recorder missed are left out: the audio context skipped render quanta there.)
    sync_first = shown_minus_heard(first, played16, start_s, source, missed)
    sync = shown_minus_heard(samples, played16, start_s, source, missed)
    print(f"frame pts - heard pts (s): first {np.round(sync_first, 3)}, second {np.round(sync, 3)}; clock {clock}; "
          f"recorder missed (s): {[(round(a / 16000, 2), round(b / 16000, 2)) for a, b in missed]}; reads (pts, held, "
          f"jumps, drawing): {[(round(r['pts'], 2), r['held'], r['jumps'], round(r['drawing'], 3)) for r in samples]}")
    # (as the server mode's test: a starved page holds where its sound ran out, so the moments checked are the
    # steady reads, and where the file speaks at the pts on screen the sound must be heard at most of them)
    heard_at = [heard_index(s, start_s) for s in steady(samples)]
    speaking = sum(voiced_at(source, s["pts"]) and recorded_around(missed, i) for s, i in zip(steady(samples), heard_at))
    assert len(sync) >= max(4, 2 * speaking // 3), (
        f"too few moments with sound to check sync ({len(sync)} of {len(samples)} reads; the file speaks at "
        f"{speaking} steady ones)")
    # One read may be off (seen twice in CI among ~20 within 10 ms, 0.64 and 0.91 s, once with a clean clock and
    # once after underruns, not understood: the reads printed above say more next time); two may not. (The reads
    # go by the output timestamp: a third CI run's reads went by the context's current time, which a loaded
    # machine's late audio thread holds back, and read 0.06-0.13 s off all one way.)
    off = np.abs(np.array(sync_first + sync)) >= 0.1
    assert off.sum() <= 1 and np.median(np.abs(sync_first + sync)) < 0.03, \
        f"frames and sound out of sync (s) at {off.sum()} reads; clock {clock}"
    # and that timestamp is the output's clock: the context's own current time puts those moments within 50 ms of it
    stamp = timestamp_minus_current_time(first + samples)
    assert not stamp or np.median(np.abs(stamp)) < 0.05, f"output timestamp - current time (s): {np.round(stamp, 3)}"
    # The clock may lose itself only where frames came later than anything before by more than its margin (the
    # worker or the page starved on this shared machine: measured in the second stream's arrivals), as watching.
    stalls = late_arrivals([(a, p) for a, p in arrivals if a > began], clock["baseMarginS"]) + clock["soundHolds"]
    assert clock["catchUps"] + clock["underruns"] <= 2 + 3 * stalls, \
        f"the page kept losing its clock: {clock}, {stalls} stalls in the frames' arrival"
    # The HUD's speech -> motion is measured from when each piece of the file was heard, and the Sound button is on.
    # It is at most 5 s, or on a machine that starved the page's inference more than that, what this run measured
    # from the second drop to its first sound, plus 1 s (beside a busy loop: 5.7 s, the page waited 7.2 s).
    waited_s = (began - second_at["page"]) + (drops[1][0]["at"] - began_at)
    assert readout["measured"] and 0 < readout["delay"] < 1000 * max(5.0, waited_s + 1.0), (readout, waited_s)
    assert readout["sound"] == "Sound on", readout
