"""The Unreal client's engine-independent decoder (clients/unreal/DimgestorProtocol.cpp) compiled with g++
(C++17, no exceptions, like an Unreal module), run on messages recorded from a live `streamer serve`
(JSON and binary), gives back what the server sent, in BVH, Unity and Unreal axes."""

import json
import shutil
import subprocess

import numpy as np
import pytest

from test_clients_python import (REPO, SPEECH_WAV, check_axis_conversion, check_decoded, checkpoint,  # noqa: F401
                                 live_server, record)

UNREAL = REPO / "clients" / "unreal"
GXX = shutil.which("g++")
pytestmark = [pytest.mark.timeout(180),
              pytest.mark.skipif(not GXX, reason="g++ not installed (Debian: apt-get install g++)")]


@pytest.fixture(scope="module")
def decoder(tmp_path_factory):
    exe = tmp_path_factory.mktemp("unreal") / "decode_recorded"
    cmd = [GXX, "-std=c++17", "-O1", "-Wall", "-Wextra", "-Werror", "-fno-exceptions", "-o", str(exe),
           str(UNREAL / "DimgestorProtocol.cpp"), str(UNREAL / "DimgestorJson.cpp"),
           str(UNREAL / "tests" / "decode_recorded.cpp")]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, f"g++ failed:\n{r.stderr}"
    return exe


def decode(exe, folder):
    r = subprocess.run([str(exe), str(folder)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return [json.loads(line) for line in r.stdout.splitlines()]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, checkpoint):  # noqa: F811
    tmp = tmp_path_factory.mktemp("unreal_rec")
    with live_server(tmp, str(SPEECH_WAV), checkpoint, loop=True) as server:
        return {"json": record(server, tmp / "json", 12, binary=False),
                "binary": record(server, tmp / "binary", 12, binary=True)}


@pytest.mark.parametrize("encoding", ["json", "binary"])
def test_unreal_decoder_gives_back_what_the_server_sent(decoder, recordings, encoding):
    files = recordings[encoding]
    out = decode(decoder, files[0].parent)
    assert all("unreal_rotations" in d for d in out if d["type"] == "frame")
    check_decoded(files, out)


def test_unreal_conversion_is_the_same_rotation_in_unreal_axes(decoder, recordings):
    out = [d for d in decode(decoder, recordings["json"][0].parent) if d["type"] == "frame"]
    # BVH (x left, y up, z forward; right-handed) -> Unreal (X forward, Y right, Z up; left-handed).
    to_unreal = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.linalg.det(to_unreal) < 0
    for d in out[:3]:
        check_axis_conversion(to_unreal, np.asarray(d["unreal_rotations"]), np.asarray(d["rotations"]))
        np.testing.assert_allclose(d["unreal_root"], to_unreal @ np.asarray(d["root"]), atol=1e-9)


def test_unreal_decoder_names_what_is_wrong_with_bad_input(decoder, tmp_path):
    (tmp_path / "000000.json").write_text('{"type": "frame", "index": 1,\n "root": [1, 2, }')
    (tmp_path / "000001.bin").write_bytes(b"DGF1" + bytes(30))
    (tmp_path / "000002.json").write_text('{"type": "hello", "protocol": 2}')
    (tmp_path / "000003.json").write_text('{"type": "future_thing", "x": [1, {"y": "\\u00e9\\ud83d\\ude00"}]}')
    out = decode(decoder, tmp_path)
    assert "JSON line 2 column 17: expected a value, found '}'" in out[0]["error"]
    assert "34 bytes is not 28 + 16*J" in out[1]["error"]
    assert "server speaks protocol 2, this client 1" in out[2]["error"]
    assert out[3] == {"file": "000003.json", "type": "future_thing"}


def test_unreal_component_compiles_against_engine_stubs():
    """The component type-checks against stand-ins of the engine types it uses (tests/stubs), with
    shadowing as an error like Unreal's own builds; a real engine build is still the final word."""
    cmd = [GXX, "-std=c++17", "-fsyntax-only", "-Wall", "-Werror", "-Wshadow", "-fno-exceptions",
           f"-I{UNREAL / 'tests' / 'stubs'}", f"-I{UNREAL}", str(UNREAL / "DimgestorComponent.cpp")]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, f"g++ failed:\n{r.stderr}"
    component = (UNREAL / "DimgestorComponent.cpp").read_text()
    for api in ("FWebSocketsModule::Get().CreateWebSocket", "OnBinaryMessage", "FJsonSerializer::Serialize",
                "SetBoneTransformByName", "EBoneSpaces::ComponentSpace"):
        assert api in component
