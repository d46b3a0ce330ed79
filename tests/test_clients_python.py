"""clients/python/client.py against a live `streamer serve` (helpers in tests/helpers/clients.py)."""

import contextlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from streamer.sessions import Session
from helpers import warm
from helpers.clients import CLIENT, REPO, SPEECH_WAV, joint_speed, live_server, record, reference_decode, run_client
from helpers.ws import SlowExecutor, make_server, running

pytestmark = pytest.mark.timeout(180)


def test_python_client_sends_a_wav_and_receives_its_own_session(tmp_path, checkpoint):
    with live_server(tmp_path, "ws", checkpoint) as server:
        saved, bvh = tmp_path / "own", tmp_path / "own.bvh"
        r = run_client("--url", server.ws_url, "--wav", str(SPEECH_WAV), "--fast", "--binary", "--save", str(saved),
                       "--bvh", str(bvh))
    msgs = [reference_decode(p) for p in sorted(saved.iterdir())]
    assert msgs[0]["type"] == "hello"
    frames = [m for m in msgs if m["type"] == "frame"]
    end = [m for m in msgs if m["type"] == "end"]
    assert end and end[0]["frames"] == len(frames), "own session must end with every frame it produced"
    assert [f["index"] for f in frames] == list(range(len(frames)))
    import wave

    with wave.open(str(SPEECH_WAV)) as w:
        seconds = w.getnframes() / w.getframerate()
    assert abs(len(frames) - seconds * msgs[0]["fps"]) <= 2
    assert all(p.suffix == ".bin" for p in sorted(saved.iterdir()) if reference_decode(p)["type"] == "frame")
    assert f"received {len(frames)} frames" in r.stderr
    assert "frame" in r.stdout and "end:" in r.stdout

    # --bvh OUT: the same motion as `dimgestor generate` on the same audio, checkpoint, steps, seed and root mode
    # (serve's defaults: seed 0, root tethered), every joint within 1e-3 cm (FK of the two files)
    from dimgestor.bvh import forward_kinematics, read_bvh

    assert f"wrote {len(frames)} frames to {bvh}" in r.stderr
    offline = tmp_path / "offline.bvh"
    g = warm.run([sys.executable, "-m", "dimgestor_app.cli", "generate", "--checkpoint", str(checkpoint), "--audio",
                  str(SPEECH_WAV), "--out", str(offline), "--steps", "2", "--seed", "0", "--root", "tether"],
                 cwd=REPO, capture_output=True, text=True, timeout=120)
    assert g.returncode == 0, g.stderr
    got, want = read_bvh(bvh), read_bvh(offline)
    assert got.skeleton.names == want.skeleton.names and got.num_frames == want.num_frames == len(frames)
    assert np.allclose(got.skeleton.offsets, want.skeleton.offsets, atol=1e-5)
    assert got.frame_time == pytest.approx(want.frame_time)
    assert np.abs(forward_kinematics(got) - forward_kinematics(want)).max() < 1e-3


def write_wav(path, seconds: float, rate: int = 16000) -> None:
    import wave

    from dimgestor.training.synthetic import synthetic_speech

    with wave.open(str(path), "wb") as w:
        w.setnchannels(1), w.setsampwidth(2), w.setframerate(rate)
        w.writeframes((synthetic_speech(seconds, rate=rate, seed=2) * 20000).astype("<i2").tobytes())


def check_own_session(saved, seconds: float) -> list[dict]:
    """Every frame of `seconds` of audio, in order, then `end` with their count."""
    msgs = [reference_decode(p) for p in sorted(saved.iterdir())]
    frames = [m for m in msgs if m["type"] == "frame"]
    assert [f["index"] for f in frames] == list(range(len(frames)))
    assert abs(len(frames) - seconds * msgs[0]["fps"]) <= 2, (len(frames), seconds)
    assert msgs[-1] == {"type": "end", "frames": len(frames)}
    return msgs


def _send_wav_to_slow_server(tmp_path, bundle, seconds, rate, executor, max_backlog_s):
    """`client.py --wav --fast` against a WsServer whose sessions infer on `executor` and hold `max_backlog_s` of
    backlog -> (the client's CompletedProcess, the messages of its own session, checked whole)."""
    talk = tmp_path / "talk.wav"
    write_wav(talk, seconds, rate=rate)
    ws = make_server(bundle, max_backlog_s=max_backlog_s, files=None)
    ws.make_session = lambda **kw: Session.from_bundle(bundle, steps=2, window_ms=100, scheduler=executor, **kw)
    saved = tmp_path / "own"
    with running(ws):
        r = run_client("--url", ws.url, "--wav", str(talk), "--fast", "--binary", "--save", str(saved), "--quiet",
                       timeout=170)
    executor.shutdown()
    return r, check_own_session(saved, seconds)


def test_python_client_pauses_at_slow_down_and_goes_on_at_resume(tmp_path, bundle):
    """A server whose backlog holds 1 s of audio and whose inference runs only a few times real time: the
    client's 10 s of self-clocked lead overflows it, so it gets `slow_down`, stops sending until `resume`
    (revision 2) and still ends with every frame of the file, printing no error."""
    # >= 50 ms per inference call: the server cannot keep up with a burst
    r, msgs = _send_wav_to_slow_server(tmp_path, bundle, 20.0, 16000, SlowExecutor(1), max_backlog_s=1.0)
    kinds = [m["type"] if m["type"] != "error" else m["code"] for m in msgs]
    assert kinds.count("slow_down") >= 1 and kinds.count("slow_down") == kinds.count("resume"), kinds
    assert set(kinds) <= {"hello", "frame", "status", "slow_down", "resume", "end"}, set(kinds)
    out = r.stdout.splitlines()
    pauses = [i for i, line in enumerate(out) if line.startswith("slow_down: pausing")]
    resumes = [i for i, line in enumerate(out) if line.startswith("resume: ")]
    assert len(pauses) == len(resumes) == kinds.count("slow_down") and all(a < b for a, b in zip(pauses, resumes))
    assert not [line for line in out if line.startswith("error:")], r.stdout
    assert f"paused {len(pauses)} times at slow_down" in r.stderr, r.stderr


def test_python_client_sends_a_file_self_clocked_and_is_never_slowed_down(tmp_path, bundle):
    """Against a server that runs a few times real time and holds 12 s of backlog, a file sent --fast but kept
    within 10 s (plus one 1 s message) of the frames that came back never fills the backlog: no `slow_down`
    (so the server never holds its socket, pings included), and every frame. Sent as fast as the server
    reads, the same file would overflow it."""
    # calls take up to 1 s of audio: about 3x real time at most
    r, msgs = _send_wav_to_slow_server(tmp_path, bundle, 30.0, 22050, SlowExecutor(1, delay_s=0.3), max_backlog_s=12.0)
    assert not [m for m in msgs if m["type"] in ("error", "resume")], [m for m in msgs if m["type"] != "frame"]
    assert "slow_down" not in r.stdout and "error:" not in r.stdout, r.stdout


def load_client():
    import importlib.util

    spec = importlib.util.spec_from_file_location("dimgestor_example_client", CLIENT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_python_client_mic_hold_is_bounded_and_counts_what_it_drops():
    """While paused, the microphone's chunks wait in MicHold: in order, at most hold_s seconds of them; beyond,
    the oldest go and are counted (never the newest)."""
    client = load_client()
    hold = client.MicHold(rate=1000, hold_s=1.0)
    chunks = [np.full(400, k, "<f4").tobytes() for k in range(6)]  # 0.4 s each
    for c in chunks:
        hold.add(c)
    assert list(hold.chunks) == chunks[4:] and hold.samples == 800  # a third 0.4 s chunk would exceed 1 s
    assert hold.dropped_samples == 1600 and hold.dropped_s == 1.6
    assert hold.take() == chunks[4] and hold.samples == 400


def test_python_client_flow_pauses_and_clocks_itself_on_the_server_messages():
    """AudioFlow: paused from `slow_down` to `resume`; a file at most ahead_s beyond the last frame of its own
    session (frames of a broadcast still queued before ours, which start at index 0, do not count)."""
    client = load_client()
    flow = client.AudioFlow(ahead_s=10.0)
    assert flow.may_send()
    flow.sent_s = 10.0
    assert not flow.may_send()  # 10 s ahead of nothing yet
    flow.on_message({"type": "frame", "index": 500, "pts": 25.0}, 20.0)  # the broadcast's, before ours
    assert not flow.may_send() and flow.heard_s == 0.0
    flow.on_message({"type": "frame", "index": 0, "pts": 0.0}, 20.0)
    flow.on_message({"type": "frame", "index": 1, "pts": 0.05}, 20.0)
    assert flow.heard_s == 0.1 and flow.may_send()
    flow.on_message({"type": "error", "code": "slow_down", "message": "x"}, 20.0)
    assert flow.paused and not flow.may_send() and flow.pauses == 1
    flow.on_message({"type": "future_thing"}, 20.0)
    assert not flow.may_send()
    flow.on_message({"type": "resume", "backlog_s": 14.9}, 20.0)
    assert flow.may_send() and not flow.paused
    flow.on_message({"type": "error", "code": "busy", "message": "x"}, 20.0)
    assert flow.refused == "busy" and flow.may_send()  # (the sender stops and sends audio_end)


def test_python_client_watches_the_broadcast_as_json(tmp_path, checkpoint):
    with live_server(tmp_path, str(SPEECH_WAV), checkpoint, loop=True) as server:
        folder = tmp_path / "rec"
        record(server, folder, 10, binary=False)
    msgs = [reference_decode(p) for p in sorted(folder.iterdir())]
    frames = [m for m in msgs if m["type"] == "frame"]
    assert len(frames) == 10 and all(p.suffix == ".json" for p in folder.iterdir())
    idx = [f["index"] for f in frames]
    assert idx == list(range(idx[0], idx[0] + 10))


def test_python_client_reports_a_refused_token(tmp_path, checkpoint):
    with live_server(tmp_path, "ws", checkpoint, extra=("--token", "s3cret")) as server:
        r = subprocess.run([sys.executable, str(CLIENT), "--url", server.ws_url, "--frames", "1"],
                           capture_output=True, text=True, timeout=60)
        ok = run_client("--url", server.ws_url, "--token", "s3cret", "--seconds", "1")
    assert r.returncode == 1 and "HTTP 401" in r.stderr and "--token" in r.stderr
    assert ok.stdout.startswith("hello: dimgestor/")


@pytest.fixture(scope="module")
def vmic(tmp_path_factory):
    from helpers.virtual_mic import virtual_mic

    with virtual_mic(tmp_path_factory.mktemp("vmic")) as mic:
        yield mic


@contextlib.contextmanager
def mic_client(vmic, url: str, *args: str):
    """The Python client on `--mic` (the virtual sound card's 44.1 kHz device); afterwards the card's players
    are stopped and the client killed if it is still running."""
    proc = subprocess.Popen([sys.executable, "-u", str(CLIENT), "--url", url, "--mic", "--device", "vmic44", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=vmic.env, cwd=REPO)
    try:
        yield proc
    finally:
        vmic.stop_players()
        if proc.poll() is None:
            proc.kill()


def ctrl_c(proc: subprocess.Popen) -> tuple[str, str]:
    """The first Ctrl-C, then what the client writes until it exits: (stdout, stderr). Read through the same
    buffered pipes (communicate() would skip what readline buffered)."""
    proc.send_signal(signal.SIGINT)
    out, err = proc.stdout.read(), proc.stderr.read()
    proc.wait(60)
    return out, err


def test_python_client_mic_streams_until_ctrl_c_then_ends_cleanly(tmp_path, vmic):
    """`--mic` through real PortAudio at the device's 44.1 kHz: speech played into a virtual sound card comes
    back as gestures (the embedded default model) that move faster than in the silence played after it;
    the first Ctrl-C sends audio_end and waits for the session's last frames."""
    from helpers.virtual_mic import speech_then_silence

    talk = speech_then_silence(tmp_path / "talk.wav", 4.0, 4.0)
    saved = tmp_path / "saved"
    arrival: dict[int, float] = {}
    with live_server(tmp_path, "ws", None) as server:
        with mic_client(vmic, server.ws_url, "--save", str(saved)) as proc:
            t_play = None
            while t_play is None or time.monotonic() < t_play + 8.5:  # gestures come back while we talk
                line = proc.stdout.readline()
                assert line, f"client ended early: {proc.stderr.read()}"
                if line.startswith("frame"):
                    arrival[int(line.split()[1])] = time.monotonic()
                    if t_play is None:
                        vmic.play(talk, "mic44")
                        t_play = time.monotonic()
            out, err = ctrl_c(proc)  # audio_end, then wait for the last frames
    assert proc.returncode == 0, err
    assert "microphone: 44100 Hz" in err and "end:" in out
    total = len(arrival) + sum(line.startswith("frame") for line in out.splitlines())
    assert f"received {total} frames" in err

    msgs = [reference_decode(p) for p in sorted(saved.iterdir())]
    frames = [m for m in msgs if m["type"] == "frame" and m["index"] in arrival]
    speed = joint_speed(frames, msgs[0]["fps"])
    t = np.array([arrival[m["index"]] for m in frames[1:]]) - t_play
    talking, resting = speed[(t > 1.0) & (t < 4.0)], speed[(t > 6.0) & (t < 8.0)]
    assert len(talking) > 40 and len(resting) > 25, (len(talking), len(resting))
    assert np.median(talking) > 2 * np.median(resting), (np.median(talking), np.median(resting))


def test_python_client_mic_holds_its_audio_at_slow_down_and_sends_it_at_resume(tmp_path, vmic, bundle):
    """`--mic` (real PortAudio, a virtual sound card) talking to a server at a third of real time whose backlog
    holds 0.5 s (in process): it gets `slow_down`, holds the microphone (under its 10 s bound: nothing dropped)
    and sends it at `resume`; Ctrl-C then ends the session with `end`, no error, and says how often it paused."""
    from helpers.virtual_mic import speech_then_silence

    talk = speech_then_silence(tmp_path / "talk.wav", 3.0, 1.0)
    executor = SlowExecutor(1, delay_s=3.0)
    ws = make_server(bundle, max_backlog_s=0.5, files=None)
    ws.make_session = lambda **kw: Session.from_bundle(bundle, steps=2, window_ms=100, scheduler=executor, **kw)
    with running(ws):
        with mic_client(vmic, ws.url, "--quiet") as proc:
            lines = []
            while not any(line.startswith("resume: ") for line in lines):
                line = proc.stdout.readline()
                assert line, f"client ended early: {''.join(lines)}{proc.stderr.read()}"
                lines.append(line)
                if line.startswith("hello:"):
                    vmic.play(talk, "mic44")
            out, err = ctrl_c(proc)  # held audio, audio_end, the last frames
    executor.shutdown()
    out = "".join(lines) + out
    assert proc.returncode == 0, err
    assert "end:" in out and "error:" not in out, out
    assert any(line.startswith("slow_down: pausing") for line in out.splitlines()), out
    assert "paused" in err and "times at slow_down" in err and "dropped" not in err, err


@pytest.mark.parametrize("args, says", [
    (["--device", "vspeaker"], "no input device 'vspeaker'"),
    (["--device", "vmic44", "--rate", "1000000"], "input device 'vmic44' cannot capture at 1000000 Hz"),
])
def test_python_client_names_an_unusable_mic_before_connecting(vmic, args, says):
    r = subprocess.run([sys.executable, str(CLIENT), "--url", "ws://127.0.0.1:9/", "--mic", *args],
                       capture_output=True, text=True, timeout=60, env=vmic.env)
    assert r.returncode == 1 and r.stderr.strip().splitlines() == [r.stderr.strip()] and says in r.stderr, r.stderr


def test_python_client_names_a_bad_wav_before_connecting(tmp_path):
    bad = tmp_path / "notes.wav"
    bad.write_text("not audio")
    for path, says in [(bad, "not a PCM WAV file"), (tmp_path / "missing.wav", "no such file")]:
        r = subprocess.run([sys.executable, str(CLIENT), "--url", "ws://127.0.0.1:9/", "--wav", str(path)],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 1 and str(path) in r.stderr and says in r.stderr, r.stderr


def test_python_client_reads_the_face_of_json_and_binary_frames_and_writes_it_as_csv(tmp_path):
    """Revision 7 without a server: a binary frame's face read through a `channels` message's layout comes out as
    the JSON frame's `face` (weight by name); --face-csv's rows are `time` (index / fps) then one column per name."""
    import json

    from dimgestor.face.names import ARKIT, convert
    from dimgestor.training.synthetic import synthetic_skeleton
    from streamer import protocol as P
    from streamer.face import face_channel
    from streamer.frames import Frame

    client = load_client()
    sk = synthetic_skeleton()
    J = len(sk.names)
    hello = P.hello(P.SkeletonInfo.from_skeleton(sk), {}, 20, 0.25, True, face=P.face_hello("vrm0"))
    chans = {"face": face_channel("arkit")}
    layout = P.channels_message(P.channel_layout(J, chans))
    canonical = np.linspace(0.0, 1.0, 20)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (J, 1))
    frames = [Frame(i, i / 20, np.zeros(3), q, np.zeros(3), {"face": canonical * (i + 1) / 3}) for i in range(3)]
    args = client.parse_args(["--quiet", "--face-csv", str(tmp_path / "face.csv")])
    assert args.face == "vrm0"  # --face-csv asks for a set: VRM 0's unless --face names another
    printer, csv = client.Printer(args), client.FaceCsv(args.face_csv)
    got = [printer.handle(json.dumps(hello)), printer.handle(layout)]
    got += [printer.handle(m) for m in (P.encode_frames(frames[:2], "binary", chans)
                                        + P.encode_frames(frames[2:], "json", chans))]
    for m in got[2:]:
        csv.add(m)
    assert [list(m["face"]) for m in got[2:]] == [list(ARKIT)] * 3 and "channels" not in got[2]
    for m, f in zip(got[2:], frames):  # float32 (binary) and 4 decimals (JSON) of the same weights
        assert np.allclose(list(m["face"].values()), convert(f.channels["face"], "arkit"), rtol=0, atol=5e-5)
    assert max(got[4]["face"].values()) > 0.5
    assert csv.write() == 3
    rows = (tmp_path / "face.csv").read_text().splitlines()
    assert rows[0] == ",".join(["time", *ARKIT]) and len(rows) == 4
    assert [r.split(",")[0] for r in rows[1:]] == ["0.0000", "0.0500", "0.1000"]
    table = np.array([r.split(",")[1:] for r in rows[1:]], dtype=float)
    assert np.allclose(table, [list(m["face"].values()) for m in got[2:]], atol=5e-5)
    with pytest.raises(SystemExit):
        client.parse_args(["--face", "none", "--face-csv", "x.csv"])


def test_python_client_writes_the_face_csv_of_its_own_session_in_json_and_binary(tmp_path, checkpoint):
    """Against a live server (its default --face vrm0): --face-csv from JSON frames (nothing asked: the server's
    set) and from binary frames (asked: vrm0) hold the same face, one row per frame of the session."""
    from dimgestor.face.names import names_of

    with live_server(tmp_path, "ws", checkpoint) as server:
        as_json, as_binary = tmp_path / "json.csv", tmp_path / "binary.csv"
        r = run_client("--url", server.ws_url, "--wav", str(SPEECH_WAV), "--fast", "--quiet", "--face-csv",
                       str(as_json))
        b = run_client("--url", server.ws_url, "--wav", str(SPEECH_WAV), "--fast", "--binary", "--face", "vrm0",
                       "--save", str(tmp_path / "saved"), "--face-csv", str(as_binary))
    frames = int(r.stderr.split("received ")[1].split()[0])
    assert f"wrote the face of {frames} frames to {as_json}" in r.stderr, r.stderr
    assert f"wrote the face of {frames} frames to {as_binary}" in b.stderr, b.stderr
    assert "channels: face (9 values at byte" in b.stdout and " face A " in b.stdout
    tables = []
    for path in (as_json, as_binary):
        rows = path.read_text().splitlines()
        assert rows[0] == "time," + ",".join(names_of("vrm0")) and len(rows) == frames + 1
        table = np.array([row.split(",") for row in rows[1:]], dtype=float)
        assert np.allclose(table[:, 0], np.arange(frames) / 20, atol=5e-5)
        tables.append(table[:, 1:])
    # (each CSV has 4 decimals, of JSON's rounded values and of binary float32 ones: a weight at a rounding boundary
    # can differ by one unit of the last digit)
    assert np.abs(tables[0] - tables[1]).max() <= 1e-4 + 1e-9 and tables[0][:, :5].max() > 0.3  # the mouth speaks
