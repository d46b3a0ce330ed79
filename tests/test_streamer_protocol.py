"""Protocol v1 messages (docs/protocol.md) without sockets: encodings, validation, audio decoding."""

import json

import numpy as np
import pytest

from dimgestor.training.synthetic import synthetic_skeleton
from streamer import protocol as P
from streamer.frames import Frame


def frame(J=13, index=7):
    rng = np.random.default_rng(index)
    q = rng.normal(size=(J, 4))
    return Frame(index, index / 20, rng.normal(size=3) * 50, q / np.linalg.norm(q, axis=-1, keepdims=True), np.zeros(5))


def test_hello_carries_the_skeleton_and_the_contract_fields():
    sk = synthetic_skeleton()
    h = P.hello(P.SkeletonInfo.from_skeleton(sk), {"Hips": sk.names[0]}, 20, 0.25, True, window_ms=200)
    h = json.loads(json.dumps(h))  # JSON-safe
    assert h["type"] == "hello" and h["protocol"] == 1 and h["fps"] == 20 and h["encoding"] == "json"
    s = h["skeleton"]
    assert s["joints"] == sk.names and s["parents"] == sk.parents and s["parents"][0] == -1
    assert np.allclose(s["offsets"], sk.offsets) and len(s["rest_rotations"]) == len(sk.names)
    assert (s["units"], s["handedness"], s["up"]) == ("cm", "right", "y")
    assert h["audio"] == {"accepts": True, "rate": 16000, "formats": ["pcm16", "float32"]}
    assert h["lookahead_s"] == 0.25 and h["window_ms"] == 200
    assert h["binary_frame_bytes"] == 28 + 16 * len(sk.names)


def test_frame_json_and_binary_round_trip():
    f = frame()
    j = json.loads(P.frame_json(f))
    assert j["type"] == "frame" and j["index"] == 7 and j["pts"] == pytest.approx(0.35)
    assert np.allclose(j["root"], f.root_pos, atol=1e-5) and np.allclose(j["rotations"], f.rotations, atol=1e-6)
    b = P.frame_binary(f)
    assert b[:4] == b"DGF1" and len(b) == 28 + 16 * 13
    d = P.parse_frame_binary(b)
    assert d["index"] == 7 and d["pts"] == f.pts
    assert np.allclose(d["root"], f.root_pos, atol=1e-4) and np.allclose(d["rotations"], f.rotations, atol=1e-6)


@pytest.mark.parametrize("text, code", [
    ("not json", "bad_message"), ("[1, 2]", "bad_message"), ('{"no_type": 1}', "bad_message"),
    ('{"type": "dance"}', "bad_message"), ('{"type": "hello", "protocol": 2}', "unsupported_protocol"),
    ('{"type": "hello", "encoding": "xml"}', "bad_message"),
    ('{"type": "hello", "audio": {"rate": 1000}}', "bad_audio"),
    ('{"type": "hello", "audio": {"format": "mp3"}}', "bad_audio"),
    ('{"type": "hello", "audio": {"channels": 6}}', "bad_audio"),
    ('{"type": "ping", "pad": "' + "x" * 70000 + '"}', "too_large"),
])
def test_bad_client_messages_get_the_documented_code(text, code):
    with pytest.raises(P.ProtocolError) as e:
        P.parse_text(text)
    assert e.value.code == code and str(e.value)


def test_client_hello_is_parsed_into_a_format():
    m = P.parse_text('{"type": "hello", "protocol": 1, "encoding": "binary", '
                     '"audio": {"rate": 48000, "format": "float32", "channels": 2}}')
    assert m["encoding"] == "binary" and m["audio"] == P.AudioFormat(48000, "float32", 2)
    assert P.parse_text('{"type": "ping", "t": 3}') == {"type": "ping", "t": 3}


def test_audio_decoding():
    x = np.array([0.5, -0.25, 0.0, 1.0], np.float32)
    pcm = (x * 32767).astype("<i2").tobytes()
    assert np.allclose(P.decode_audio(pcm, P.AudioFormat()), x, atol=1e-4)
    stereo = np.stack([x, -x], 1).astype("<f4").tobytes()
    assert np.allclose(P.decode_audio(stereo, P.AudioFormat(48000, "float32", 2)), 0)
    for data, fmt, code in [(pcm[:-1], P.AudioFormat(), "bad_audio"),
                            (np.array([np.nan], "<f4").tobytes(), P.AudioFormat(format="float32"), "bad_audio"),
                            (bytes(P.MAX_BINARY_BYTES + 2), P.AudioFormat(), "too_large")]:
        with pytest.raises(P.ProtocolError) as e:
            P.decode_audio(data, fmt)
        assert e.value.code == code


def test_source_audio_messages_round_trip_and_the_hello_field_is_checked():
    x = np.array([0.5, -0.25, 0.0, 1.0, -1.0, 2.0], np.float32)  # 2.0 clips
    buf = P.source_audio_binary(12.345, x)
    assert buf[:4] == P.AUDIO_MAGIC and len(buf) == P.AUDIO_HEADER.size + 2 * len(x) == 16 + 12
    d = P.parse_source_audio_binary(buf)
    assert d["rate"] == P.AUDIO_RATE and d["pts"] == 12.345
    np.testing.assert_allclose(d["samples"], np.clip(x, -1, 1), atol=1 / 32767)
    for bad in (buf[:-1], b"DGF1" + buf[4:]):
        with pytest.raises(ValueError):
            P.parse_source_audio_binary(bad)
    assert P.parse_text('{"type": "hello", "source_audio": true}')["source_audio"] is True
    with pytest.raises(P.ProtocolError) as e:
        P.parse_text('{"type": "hello", "source_audio": "yes"}')
    assert e.value.code == "bad_message"


def test_the_face_in_the_hello_a_json_frame_and_a_binary_frame():
    """Revision 7: hello.face names the server's set and the known ones; a JSON frame carries the face channel as
    weight by name (4 decimals, every name of the set), a binary frame its floats at the layout's offset."""
    from dimgestor.face import FACE_LABELS, convert
    from dimgestor.face.names import ARKIT
    from streamer.face import face_channel

    sk = synthetic_skeleton()
    h = P.hello(P.SkeletonInfo.from_skeleton(sk), {}, 20, 0.25, True, face=P.face_hello("vrm1"))
    assert h["revision"] == P.REVISION and h["channels"] == []  # binary frames carry no face until a client asks
    assert h["face"] == {"names": "vrm1", "sets": ["vrm0", "vrm1", "arkit", "oculus"],
                         "labels": ["aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft", "blinkRight", "happy"]}
    with pytest.raises(ValueError, match="known sets are vrm0, vrm1, arkit, oculus"):
        P.face_hello("vrm2")

    J = len(sk.names)
    canonical = np.linspace(0.0, 1.0, len(FACE_LABELS)) ** 2 / 3 + 1e-5  # (weights that need rounding)
    f = Frame(3, 0.15, np.zeros(3), frame(J).rotations, np.zeros(5), {"face": canonical})
    arkit = {"face": face_channel("arkit")}
    j = json.loads(P.encode_frames([f], "json", arkit)[0])
    assert list(j["face"]) == list(ARKIT) and "channels" not in j
    assert list(j["face"].values()) == np.round(convert(canonical, "arkit"), 4).tolist()
    layout = P.channel_layout(J, arkit)
    assert layout == [{"name": "face", "size": 52, "offset": 28 + 16 * J, "labels": list(ARKIT),
                       "description": "face blendshape weights 0..1, arkit names"}]
    b = P.encode_frames([f], "binary", arkit)[0]
    assert len(b) == 28 + 16 * J + 4 * 52
    assert np.allclose(P.parse_frame_binary(b, J, layout)["channels"]["face"], convert(canonical, "arkit"), atol=1e-7)
    assert json.loads(P.channels_message(layout)) == {"type": "channels", "channels": layout}
    # no map: WS_CHANNELS (empty), the frames of revision 5
    assert "face" not in json.loads(P.encode_frames([f], "json")[0]) and len(P.encode_frames([f], "binary")[0]) \
        == 28 + 16 * J


@pytest.mark.parametrize("hello, says", [
    ({"face": "vrm2"}, "known sets are vrm0, vrm1, arkit, oculus"), ({"face": 3}, "known sets"),
    ({"face": ["arkit"]}, "known sets"), ({"smile": 2}, "smile must be a number from 0 to 1"),
    ({"smile": "yes"}, "smile"), ({"smile": False}, "smile"),
])
def test_a_client_hello_with_a_bad_face_or_smile_is_a_bad_message(hello, says):
    with pytest.raises(P.ProtocolError, match=says) as e:
        P.parse_text(json.dumps({"type": "hello", **hello}))
    assert e.value.code == "bad_message"


def test_a_client_hello_asks_for_a_face_set_none_or_a_smile():
    assert P.parse_text('{"type": "hello", "face": "oculus", "smile": 1}') == {"type": "hello", "face": "oculus",
                                                                               "smile": 1.0}
    assert P.parse_text('{"type": "hello", "face": "none", "smile": 0.25}')["face"] == "none"
