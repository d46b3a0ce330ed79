"""A stored state is untrusted input (issue 40, item 5): every field is checked before anything is built from it;
what is refused is refused with a StateError naming the field, never another exception, and every state a real
stream passes through is accepted."""
import copy
import json

import numpy as np
import pytest
import torch

from dimgestor.streaming import savestate
from dimgestor.streaming.stream import GestureStream
from streamer.sessions import Session
from helpers.stream import noise_audio as _audio, random_tiny_model as _model

SAVE_AT = 9001  # samples before the save: odd, so the front end holds a partial frame


# The checks stand behind the seal: they are what a state re-sealed by someone without the workers' secret meets,
# so these tests change a state's header or bytes and seal it again (as anyone can without the secret).
_header = savestate.split


def _pack(header, raw: bytes, text: str | None = None) -> bytes:
    return savestate.pack(header if text is None else text, raw)


def _same(a, b) -> bool:
    """Two states (or parts) hold the same values, NaN where the other has NaN."""
    if hasattr(a, "numpy") or isinstance(a, np.ndarray):
        return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(np.asarray(a), np.asarray(b),
                                                                             equal_nan=True)
    if isinstance(a, tuple) or hasattr(a, "__dataclass_fields__"):
        fa = a if isinstance(a, tuple) else [getattr(a, f) for f in a.__dataclass_fields__]
        fb = b if isinstance(b, tuple) else [getattr(b, f) for f in b.__dataclass_fields__]
        return type(a) is type(b) and len(fa) == len(fb) and all(_same(x, y) for x, y in zip(fa, fb))
    return type(a) is type(b) and a == b


def _pretrained_model(folder):
    """A tiny random wav2vec2 front end (as tests/test_stream.py builds it)."""
    transformers = pytest.importorskip("transformers", reason="optional extra `pretrained` not installed")
    torch.manual_seed(0)
    w2v = transformers.Wav2Vec2Config(hidden_size=16, num_hidden_layers=1, num_attention_heads=2, intermediate_size=32,
                                      conv_dim=(8,) * 7, num_conv_pos_embeddings=16, num_conv_pos_embedding_groups=2)
    transformers.Wav2Vec2Model(w2v).save_pretrained(folder)
    return _model(frontend="pretrained", pretrained_path=str(folder), pretrained_block_ms=200,
                  pretrained_left_ms=200, pretrained_right_ms=100)


@pytest.mark.parametrize("frontend,smoothing,guidance", [("logmel", None, 1.0), ("logmel", (3.0, 0.5), 2.0),
                                                         ("speech", None, 1.0), ("pretrained", None, 1.0)])
def test_every_state_a_stream_passes_through_is_accepted(frontend, smoothing, guidance, tmp_path):
    model = _pretrained_model(tmp_path) if frontend == "pretrained" else _model(frontend=frontend)
    s = GestureStream(model, steps=2, seed=5, smoothing=smoothing, guidance=guidance)
    audio, rng, at = _audio(3.0), np.random.default_rng(1), 0
    sizes = [0, 1, 159, 160, 161, 1600, 3] + list(rng.integers(0, 4000, 12))
    for n in sizes:
        s.push(audio[at:at + n])
        at += n
        state, _ = savestate.loads(GestureStream(model, steps=2, seed=5, smoothing=smoothing, guidance=guidance),
                                   savestate.dumps(s))
        assert _same(state, s.state)
    assert s.frames_out > 0


@pytest.fixture(scope="module")
def model():
    return _model()


@pytest.fixture(scope="module")
def saved(model):
    s = GestureStream(model, steps=2, seed=5)
    s.push(_audio(1.0)[:SAVE_AT])
    return savestate.dumps(s)


def _refused(model, data, match):
    with pytest.raises(savestate.StateError, match=match):
        savestate.loads(GestureStream(model, steps=2, seed=5), data)


def test_a_leaf_offset_that_is_not_a_number_is_refused(model, saved):
    header, raw = _header(saved)
    header["state"]["f"]["denoiser"]["f"]["ssm"]["at"] = "x"
    _refused(model, _pack(header, raw), r"state\.denoiser\.ssm at byte 'x'")


def test_a_header_nested_100000_deep_is_refused(model, saved):
    header, raw = _header(saved)
    header["meta"] = "DEEP"
    text = json.dumps(header).replace('"DEEP"', "[" * 100_000 + "]" * 100_000)
    _refused(model, _pack(None, raw, text), "nested too deep")


@pytest.mark.parametrize("depth", [1, 900, 990, 3000])
def test_values_nested_at_any_depth_anywhere_are_refused_with_a_state_error(bundle, session_saved, depth):
    """Below the depth where the JSON parser gives up, a nested value reaches the checks (and their messages):
    a StateError all the same, never a RecursionError."""
    places = [("model",), ("settings", "seed"), ("meta", "frames"), ("meta", "decoder", "x"), ("meta", "decoder", "drift"),
              ("meta", "encoding"), ("state", "f", "samples_in", "v"), ("state", "f", "extractor"),
              ("state", "f", "frontend", "f", "tail", "shape"), ("state", "f", "denoiser", "f", "ssm", "at")]
    for *up, key in places:
        header, raw = _header(session_saved)
        parent = header
        for k in up:
            parent = parent[k]
        parent[key] = "NESTED"
        text = json.dumps(header).replace('"NESTED"', "[" * depth + "1" + "]" * depth)
        with pytest.raises(savestate.StateError):
            _session(bundle).restore(_pack(None, raw, text))


def test_a_shape_of_2_to_the_40_is_refused_without_allocating(model, saved):
    header, raw = _header(saved)
    leaf = header["state"]["f"]["frontend"]["f"]["tail"]  # (1, m): its length may vary, its size may not
    leaf["shape"] = [1, 2 ** 40]
    _refused(model, _pack(header, raw), r"state\.frontend\.tail of float32 \[1, 1099511627776\] in \d+ bytes")
    leaf["n"] = 2 ** 42
    _refused(model, _pack(header, raw), r"cut short at state\.frontend\.tail")


def test_a_negative_or_inconsistent_sample_count_is_refused(model, saved):
    header, raw = _header(saved)
    for value, match in ((-10 ** 12, r"state\.samples_in is -1000000000000"), (SAVE_AT + 1, "samples_in 9002"),
                         (9001.0, r"state\.samples_in is float"), (True, r"state\.samples_in is bool")):
        h = copy.deepcopy(header)
        h["state"]["f"]["samples_in"]["v"] = value
        _refused(model, _pack(h, raw), match)


def test_counters_past_what_a_frame_index_holds_are_refused_though_they_agree(model, saved):
    """samples_in, the front end's frames and frames_out all moved on by 2^32 frames' worth, consistently: refused by
    name (they once resumed and ended the session with `internal`, an index too big for the binary frame)."""
    header, raw = _header(saved)
    ex, fe = model.extractor, model.frontend
    for frames in (2**32, 10**200):
        h = copy.deepcopy(header)
        f = h["state"]["f"]
        f["frames_out"]["v"] += frames
        f["frontend"]["f"]["consumed"]["v"] += frames * ex.stride
        f["samples_in"]["v"] += frames * ex.stride * fe.hop
        _refused(model, _pack(h, raw), r"state\.frames_out is \d+, over 2147483647")


def test_nan_or_infinity_in_a_state_is_refused(model, saved):
    header, raw = _header(saved)
    ssm = header["state"]["f"]["denoiser"]["f"]["ssm"]
    for bad in (np.nan, np.inf):
        b = bytearray(raw)
        b[ssm["at"] + 40:ssm["at"] + 44] = np.float32(bad).tobytes()
        _refused(model, _pack(header, bytes(b)), r"state\.denoiser\.ssm holds 1 values that are NaN or infinite")
    header["meta"] = {"gain": "NUMBER"}
    for bad in ("NaN", "-Infinity", "1e999"):
        _refused(model, _pack(None, raw, json.dumps(header).replace('"NUMBER"', bad)), f"header holds {bad}")


def _leaf_bytes(header, raw, path: str):
    """(the node, a writable float view of the bytes) of the leaf at `path` ("state.denoiser.ssm")."""
    node = header["state"]
    for part in path.split(".")[1:]:
        node = node["f"][part]
    dtype = np.float64 if node["dtype"] == "float64" else np.float32
    b = bytearray(raw)
    return node, b, np.frombuffer(memoryview(b)[node["at"]:node["at"] + node["n"]], dtype)


def test_every_float_of_1e30_or_a_leaf_beyond_the_models_own_states_is_refused(model, saved):
    """Finite values a stream of this model never holds (issue 52, item 3): they once resumed and streamed every frame
    NaN. Each leaf's bound is what the probes made (`state_bounds`) times the margin: just inside it resumes, just
    beyond it is refused by name."""
    from dimgestor.streaming import state_bounds

    header, raw = _header(saved)
    stream = GestureStream(model, steps=2, seed=5)
    limits = state_bounds.bounds(stream)
    assert set(limits) >= {"state.frontend.tail", "state.extractor.buf", "state.denoiser.enc", "state.denoiser.ssm"}
    every = bytearray(raw)
    for path in limits:
        _, every, view = _leaf_bytes(header, bytes(every), path)
        view[:] = 1e30
    _refused(model, _pack(header, bytes(every)), r"state\.\S+ holds \d+ values beyond [\d.e+]+ \(e\.g\. 1e\+30\)")
    for path in ("state.denoiser.ssm", "state.denoiser.enc", "state.extractor.style.conv"):
        node, b, view = _leaf_bytes(header, raw, path)
        view[3] = limits[path] * 0.99
        state, _ = savestate.loads(stream, _pack(header, bytes(b)))  # inside: resumed, that value as it was written
        assert np.isclose(float(dict(state_bounds.leaves(state))[path].reshape(-1)[3]),
                          limits[path] * 0.99)
        view[3] = -limits[path] * 1.01
        _refused(model, _pack(header, bytes(b)), rf"{path.replace('.', '[.]')} holds 1 values beyond")


def test_a_speech_front_ends_frame_counts_past_the_frames_it_consumed_are_refused():
    model = _model(frontend="speech")
    s = GestureStream(model, steps=2, seed=5)
    s.push(_audio(0.5))
    header, raw = _header(savestate.dumps(s))
    consumed = s.state.frontend.consumed
    for name, bad in (("count", consumed + 1), ("voiced", -1.0), ("quiet", 1e30)):
        _, b, view = _leaf_bytes(header, raw, f"state.frontend.{name}")
        view[0] = bad
        with pytest.raises(savestate.StateError, match=rf"state\.frontend\.{name} holds .*only {consumed} frames"):
            savestate.loads(GestureStream(model, steps=2, seed=5), _pack(header, bytes(b)))


def test_a_speech_front_ends_noise_floor_may_be_nan_only_before_its_first_frame():
    model = _model(frontend="speech")
    s = GestureStream(model, steps=2, seed=5)
    s.push(_audio(0.005))  # less than a frame: its floor is still NaN, as in a fresh state
    assert s.state.frontend.floor.isnan().all()
    savestate.loads(GestureStream(model, steps=2, seed=5), savestate.dumps(s))
    s.push(_audio(0.5))
    header, raw = _header(savestate.dumps(s))
    floor = header["state"]["f"]["frontend"]["f"]["floor"]
    b = bytearray(raw)
    b[floor["at"]:floor["at"] + 8] = np.float64(np.nan).tobytes()
    with pytest.raises(savestate.StateError, match=r"state\.frontend\.floor holds 1 values"):
        savestate.loads(GestureStream(model, steps=2, seed=5), _pack(header, bytes(b)))


def test_a_finished_stream_and_bytes_beyond_the_state_are_refused(model, saved):
    header, raw = _header(saved)
    _refused(model, _pack(header, raw + b"\0" * 4), "4 bytes beyond its last leaf")
    header["state"]["f"]["finished"]["v"] = True
    _refused(model, _pack(header, raw), "a finished stream cannot go on")


# ---- a session's state: the stream's and the meta beside it (Session.restore) ----

def _session(bundle) -> Session:
    return Session.from_bundle(bundle, steps=2, seed=3, window_ms=100)


@pytest.fixture(scope="module")
def session_saved(bundle):
    s = _session(bundle)
    frames = s.infer(_audio(1.0)[:SAVE_AT])
    return s.snapshot(len(frames), rate=16000, encoding="json")


@pytest.mark.parametrize("change,match", [
    (lambda m: m.pop("decoder"), r"meta\.decoder is not an object"),
    (lambda m: m.update(frames=m["frames"] + 1), r"meta\.frames is \d+, the state made"),
    (lambda m: m["decoder"].update(x="1.5"), r"meta\.decoder x, z and heading are finite"),
    (lambda m: m["decoder"].update(heading=None), r"meta\.decoder x, z and heading are finite"),
    (lambda m: m["decoder"].update(frames=-1), r"meta\.decoder\.frames is -1"),
    (lambda m: m["decoder"].update(drift=[0.0, 0.0]), r"meta\.decoder\.drift is 3 finite numbers"),
    (lambda m: m["decoder"].update(x=1e38), r"meta\.decoder\.x is 1e\+38: \d+ frames move it [\d.e+]+ at most"),
    (lambda m: m["decoder"].update(heading=-1e9), r"meta\.decoder\.heading is -1000000000\.0: \d+ frames"),
    (lambda m: m["decoder"].update(drift=[0.0, 1e12, 0.0]), r"meta\.decoder\.drift is .*beyond a frame's largest"),
    (lambda m: m.update(rate=10 ** 9), r"meta\.rate is 1000000000"),
    (lambda m: m.update(encoding=["json"]), r"meta\.encoding is json or binary"),
    (lambda m: m.update(resampler={"up": 1}), r"meta\.resampler does not fit"),
])
def test_a_session_state_with_bad_meta_is_refused_and_the_session_is_unchanged(bundle, session_saved, change, match):
    header, raw = _header(session_saved)
    change(header["meta"])
    s = _session(bundle)
    with pytest.raises(savestate.StateError, match=match):
        s.restore(_pack(header, raw))
    assert s.stream.samples_in == 0 and s.stream.frames_out == 0


def test_a_session_state_with_its_resampler_resumes_and_a_bad_resampler_is_refused(bundle, session_saved):
    from streamer.sources import make_resampler

    r = make_resampler(48000)
    r.process(np.zeros(SAVE_AT * 3 + 30, np.float32))  # 48 kHz in, exactly SAVE_AT out (30: the filter's delay)
    assert r.outputs == SAVE_AT
    header, raw = _header(session_saved)
    header["meta"].update(rate=48000, resampler=r.get_state())
    assert _session(bundle).restore(_pack(header, raw))["resampler"]["n_in"] == SAVE_AT * 3 + 30
    for field, value, match in (("n_in", SAVE_AT * 3 + 37, "gave"), ("buf", "zz" * 8, "hex digits"),
                                ("buf_start", -1, ">= 0"), ("m_out", 2 ** 70, "gave")):
        h = copy.deepcopy(header)
        h["meta"]["resampler"][field] = value
        if field == "buf":
            h["meta"]["resampler"]["buf"] = value + h["meta"]["resampler"]["buf"][16:]
        with pytest.raises(savestate.StateError, match=rf"meta\.resampler .*{match}"):
            _session(bundle).restore(_pack(h, raw))
    h = copy.deepcopy(header)
    h["meta"]["resampler"]["buf"] = np.full(len(h["meta"]["resampler"]["buf"]) // 16, np.nan).tobytes().hex()
    with pytest.raises(savestate.StateError, match=r"meta\.resampler .*NaN"):
        _session(bundle).restore(_pack(h, raw))
