"""Live `streamer serve` helpers for the client tests (Python, web, Unity, Unreal, playout): start a server on
free ports, record its messages, decode them straight from the spec and check a compiled decoder against them."""

from __future__ import annotations

import json
import os
import socket
import struct
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from helpers import warm

REPO = Path(__file__).resolve().parents[2]
CLIENT = REPO / "clients" / "python" / "client.py"
SPEECH_WAV = REPO / "dimgestor" / "assets" / "demo_en.wav"  # espeak-ng speech, 16 kHz mono PCM16
FRAME_HEADER = struct.Struct("<4sId3f")  # docs/protocol.md: magic, index, pts, root xyz; then f32[J*4]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class LiveServer:
    ws_url: str
    http_url: str | None
    proc: subprocess.Popen | warm.WarmProcess
    log: Path

    def log_tail(self, n: int = 40) -> str:
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])


@contextmanager
def live_server(tmp: Path, source: str, checkpoint: Path | None, *, http: bool = False, loop: bool = False,
                fast: bool = False, extra: tuple[str, ...] = ()):
    """`streamer serve` in a subprocess on a free port; yields once its WebSocket accepts connections. http: the
    viewer's address too (it is served on the WebSocket port)."""
    ws_port = free_port()
    args = ["serve", "--source", source, "--ws", f"127.0.0.1:{ws_port}", "--steps", "2", "--status-every", "0"]
    if checkpoint is not None:
        args += ["--checkpoint", str(checkpoint)]
    if loop:
        args.append("--loop")
    if fast:
        args.append("--fast")
    args += list(extra)
    cmd = [sys.executable, "-c", "import sys; from dimgestor_app.cli import main; sys.exit(main())", *args]
    log = tmp / f"server_{ws_port}.log"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    with open(log, "w") as out:
        proc = warm.popen(cmd, cwd=REPO, stdout=out, stderr=subprocess.STDOUT, env=env)
    server = LiveServer(f"ws://127.0.0.1:{ws_port}/", f"http://127.0.0.1:{ws_port}/" if http else None, proc, log)
    try:
        deadline = time.monotonic() + 120
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"streamer serve exited with {proc.returncode}:\n{server.log_tail()}")
            try:
                socket.create_connection(("127.0.0.1", ws_port), timeout=0.5).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"streamer serve did not listen within 120 s:\n{server.log_tail()}")
                time.sleep(0.2)
        yield server
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def run_client(*args: str, timeout: float = 90) -> subprocess.CompletedProcess:
    """clients/python/client.py as a user runs it; fails the test with its output when it fails."""
    r = subprocess.run([sys.executable, str(CLIENT), *args], capture_output=True, text=True, timeout=timeout, cwd=REPO)
    assert r.returncode == 0, f"client.py {' '.join(args)} exited {r.returncode}:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
    return r


def record(server: LiveServer, folder: Path, frames: int, binary: bool) -> list[Path]:
    """Save the first messages a client receives (hello, frames, status...) verbatim into `folder`."""
    run_client("--url", server.ws_url, "--frames", str(frames), "--save", str(folder), "--quiet",
               *(["--binary"] if binary else []))
    return sorted(folder.iterdir())


def reference_decode(path: Path) -> dict:
    """What the server sent, decoded straight from the spec (json module / struct), for comparisons."""
    if path.suffix == ".json":
        return json.loads(path.read_text())
    buf = path.read_bytes()
    magic, index, pts, *root = FRAME_HEADER.unpack_from(buf)
    assert magic == b"DGF1"
    rot = np.frombuffer(buf, "<f4", offset=FRAME_HEADER.size).astype(np.float64).reshape(-1, 4)
    return {"type": "frame", "index": index, "pts": pts, "root": root, "rotations": rot.tolist()}


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def global_rotations(parents: list[int], local: np.ndarray) -> np.ndarray:
    g = np.empty_like(local)
    for j, p in enumerate(parents):
        g[j] = local[j] if p < 0 else quat_mul(g[p], local[j])
    return g


def quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def check_decoded(records: list[Path], decoded: list[dict]) -> None:
    """A compiled decoder's output (one JSON line per recorded message) equals what the server sent."""
    by_file = {d["file"]: d for d in decoded}
    assert [p.name for p in records] == sorted(by_file), "decoder skipped or invented messages"
    hello = None
    n_frames = 0
    for path in records:
        ref, got = reference_decode(path), by_file[path.name]
        assert "error" not in got, f"{path.name}: {got.get('error')}"
        assert got["type"] == ref["type"], path.name
        if ref["type"] == "hello":
            hello = ref
            sk = ref["skeleton"]
            assert got["joints"] == len(sk["joints"]) and got["humanoid"] == len(ref["humanoid"])
            assert got["fps"] == ref["fps"] and got["audio_rate"] == ref["audio"]["rate"]
            np.testing.assert_allclose(got["offset_last"], sk["offsets"][-1], rtol=0, atol=1e-12)
        elif ref["type"] == "frame":
            n_frames += 1
            assert hello is not None, "frame before hello"
            exact = path.suffix == ".bin"  # float32 on the wire widens to double exactly
            tol = 0 if exact else 1e-12
            rot = np.asarray(ref["rotations"], np.float64)
            root = np.asarray(ref["root"], np.float64)
            assert got["index"] == ref["index"]
            np.testing.assert_allclose(got["pts"], ref["pts"], rtol=0, atol=tol)
            np.testing.assert_allclose(got["root"], root, rtol=0, atol=tol)
            np.testing.assert_allclose(got["rotations"], rot, rtol=0, atol=tol)
            assert rot.shape == (len(hello["skeleton"]["joints"]), 4)
            # Unity: mirror X. Positions in metres, quaternion (w, x, -y, -z).
            np.testing.assert_allclose(got["unity_root"], root * [-0.01, 0.01, 0.01], rtol=0, atol=1e-12)
            np.testing.assert_allclose(got["unity_rotations"], rot * [1, 1, -1, -1], rtol=0, atol=0)
            g = global_rotations(hello["skeleton"]["parents"], rot)
            np.testing.assert_allclose(got["global_rotations"], g, rtol=0, atol=1e-9)
            if "unreal_root" in got:  # (x, y, z) -> (z, -x, y) cm; quaternion (w, -z, x, -y)
                np.testing.assert_allclose(got["unreal_root"], root[[2, 0, 1]] * [1, -1, 1], rtol=0, atol=1e-9)
                np.testing.assert_allclose(got["unreal_rotations"], rot[:, [0, 3, 1, 2]] * [1, -1, 1, -1], rtol=0, atol=0)
    assert n_frames > 0


def check_axis_conversion(m: np.ndarray, rot_out: np.ndarray, rot_in: np.ndarray) -> None:
    """The converted quaternion is the same rotation seen through the change of axes m: R' = m R m^T."""
    for q_in, q_out in zip(rot_in, rot_out):
        np.testing.assert_allclose(quat_matrix(q_out), m @ quat_matrix(q_in) @ m.T, atol=1e-6)


def joint_speed(frames: list[dict], fps: float) -> np.ndarray:
    """Per frame step: mean over joints of the rotation angle between consecutive frames, in rad/s."""
    q = np.array([f["rotations"] for f in frames])  # (T, J, 4)
    dot = np.abs(np.sum(q[1:] * q[:-1], axis=-1)).clip(0, 1)
    return (2 * np.arccos(dot)).mean(axis=1) * fps


# Flow control (protocol revision 2) as the engine clients' cores see it: the server's messages as they come
# on the wire, the chunks the client offers (ID, seconds) and its audio_end; the bound on held audio is 1 s.
FLOW_SCRIPT = "\n".join([
    'chunk a 0.4',
    'message {"type": "error", "code": "slow_down", "message": "audio arrives faster than it is processed"}',
    'chunk b 0.4', 'chunk c 0.4',
    'message {"type": "future_thing", "x": [1, {"y": 2}]}',
    'message {"type": "error", "code": "slow_down", "message": "again"}',
    'message {"type": "resume", "backlog_s": 14.9}',
    'message {"type": "resume", "backlog_s": 0.0}',
    'chunk d 0.4',
    'message {"type": "error", "code": "slow_down", "message": "x"}',
    *(f'chunk e{i} 0.4' for i in range(5)),
    'end',
    'message {"type": "resume", "backlog_s": 15}',
    'end',
])


def check_flow(out: list[dict]) -> None:
    """What a client core must do with FLOW_SCRIPT: send at once until `slow_down`, hold (in order) until
    `resume`, drop the oldest beyond 1 s held (counted), send a pending audio_end after the held audio."""
    assert [o["sent"] for o in out] == [["a"], [], [], [], [], [], ["b", "c"], [], ["d"], [], [], [], [], [], [],
                                        [], ["e3", "e4"], []]
    assert [o["type"] for o in out if o["event"] == "message"] == ["error", "future_thing", "error", "resume",
                                                                  "resume", "error", "resume"]
    assert out[1]["code"] == "slow_down" and out[1]["paused"] and out[5]["paused"] and not out[6]["paused"]
    assert out[6]["backlog_s"] == 14.9 and out[3]["held_s"] == pytest.approx(0.8)
    assert out[5]["pauses"] == 1 and out[7]["resumes"] == 1 and out[-1]["pauses"] == out[-1]["resumes"] == 2
    assert out[15]["end_now"] is False and out[15]["paused"]  # audio_end waits for resume, after the held audio
    assert out[16]["end_now"] is True and out[16]["held_s"] == 0 and out[17]["end_now"] is True
    assert out[14]["held_s"] == pytest.approx(0.8) and out[-1]["dropped_chunks"] == 3
    assert out[-1]["dropped_s"] == pytest.approx(1.2)
