"""Every client reads revision 6's frame channels: messages made by `streamer.protocol` with a test channel on
(a hello that announces it, JSON and binary frames that carry it, a frame without it (sent as zeros), a binary
frame with bytes past the layout) decode to the same pose and channel values in the Python, web (protocol.js and frame-ring.js
under node), Unity (mono) and Unreal (g++) decoders."""

import importlib.util
import json
import shutil
import subprocess

import numpy as np
import pytest

from dimgestor.training.synthetic import synthetic_skeleton
from streamer import protocol as P
from streamer.frames import Channel, Frame
from helpers.clients import REPO

pytestmark = pytest.mark.timeout(180)
WAVE = Channel("test_wave", 3, "test only", ("first", "second", "seven"))
PAIR = Channel("pair", 2)


@pytest.fixture(scope="module")
def messages(tmp_path_factory):
    """A folder of recorded messages and what they carry: [(index, rotations, {name: values})] per frame."""
    folder = tmp_path_factory.mktemp("channels")
    sk = synthetic_skeleton()
    J = len(sk.names)
    chans = {WAVE.name: WAVE, PAIR.name: PAIR}
    hello = P.hello(P.SkeletonInfo.from_skeleton(sk), {}, 20, 0.25, True)
    hello["channels"] = P.channel_layout(J, chans)  # what a server with these channels on announces
    hello["binary_frame_bytes"] += 4 * (WAVE.size + PAIR.size)
    (folder / "000000.json").write_text(P.dumps(hello))
    rng = np.random.default_rng(3)
    expected = []
    for i in range(4):
        q = rng.normal(size=(J, 4))
        values = {"test_wave": np.array([0.25 * i, -1.5, 7.0]), "pair": np.array([i, 0.5])} if i != 2 else {}
        f = Frame(i, i / 20, rng.normal(size=3), (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(np.float32),
                  np.zeros(3), values)
        expected.append((i, f.rotations, {c.name: values.get(c.name, np.zeros(c.size)) for c in chans.values()}))
        if i % 2:
            data = P.frame_binary(f, chans) + (b"\0" * 8 if i == 3 else b"")  # a later revision's bytes: ignored
            (folder / f"{i + 1:06d}.bin").write_bytes(data)
        else:
            (folder / f"{i + 1:06d}.json").write_text(P.frame_json(f, chans))
    return folder, expected


def check(frames, expected, key="channels"):
    assert [f["index"] for f in frames] == [e[0] for e in expected]
    for f, (_, rotations, values) in zip(frames, expected):
        assert np.allclose(f["rotations"], rotations, atol=1e-6)
        assert f[key].keys() == values.keys()
        for name, v in values.items():
            assert np.allclose(f[key][name], v, atol=1e-6), (name, f[key][name], v)


def test_python_client_reads_the_channels(messages):
    folder, expected = messages
    spec = importlib.util.spec_from_file_location("example_client", REPO / "clients/python/client.py")
    client = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(client)
    hello, frames = None, []
    for path in sorted(folder.iterdir()):
        if path.suffix == ".bin":
            frames.append(client.decode_binary_frame(path.read_bytes(), hello))
        elif (msg := json.loads(path.read_text()))["type"] == "hello":
            hello = msg
        else:
            frames.append(msg)
    check(frames, expected)
    # without the hello a binary frame with channels is refused, not misread as more joints
    with pytest.raises(ValueError, match="28 \\+ 16\\*J"):
        client.decode_binary_frame((folder / "000002.bin").read_bytes())


def test_web_client_reads_the_channels_and_its_ring_keeps_them(messages):
    node = shutil.which("node")
    if not node:
        pytest.skip("node not installed (Debian: apt-get install nodejs)")
    folder, expected = messages
    r = subprocess.run([node, str(REPO / "clients/web/tests/channels_check.mjs"), str(folder)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    frames = [json.loads(line) for line in r.stdout.splitlines()]
    check(frames, expected)
    check(frames, expected, key="ring")  # what the page reads from the shared-memory ring


def test_unity_client_reads_the_channels(messages, tmp_path):
    mcs, mono = shutil.which("mcs"), shutil.which("mono")
    if not (mcs and mono):
        pytest.skip("mcs/mono not installed (Debian: apt-get install mono-mcs)")
    folder, expected = messages
    unity = REPO / "clients/unity"
    exe = tmp_path / "DecodeRecorded.exe"
    r = subprocess.run([mcs, "-langversion:7", "-warnaserror", f"-out:{exe}", str(unity / "DimgestorProtocol.cs"),
                        str(unity / "DimgestorJson.cs"), str(unity / "tests/DecodeRecorded.cs")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    r = subprocess.run([mono, str(exe), str(folder)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    frames = [d for d in map(json.loads, r.stdout.splitlines()) if d["type"] == "frame"]
    check(frames, expected)


def test_unreal_client_reads_the_channels(messages, tmp_path):
    gxx = shutil.which("g++")
    if not gxx:
        pytest.skip("g++ not installed (Debian: apt-get install g++)")
    folder, expected = messages
    unreal = REPO / "clients/unreal"
    exe = tmp_path / "decode_recorded"
    r = subprocess.run([gxx, "-std=c++17", "-O1", "-Wall", "-Wextra", "-Werror", "-fno-exceptions", "-o", str(exe),
                        str(unreal / "DimgestorProtocol.cpp"), str(unreal / "DimgestorJson.cpp"),
                        str(unreal / "tests/decode_recorded.cpp")], capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([str(exe), str(folder)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    frames = [d for d in map(json.loads, r.stdout.splitlines()) if d["type"] == "frame"]
    check(frames, expected)
