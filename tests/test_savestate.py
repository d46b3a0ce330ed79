"""A stream's state saved as bytes and resumed by another stream (another process, another machine) goes on
exactly; states that cannot be resumed exactly are refused with the reason (issue 22, item 3)."""
import copy
import json
import struct

import numpy as np
import pytest
import torch

from dimgestor.streaming import savestate
from dimgestor.streaming.stream import GestureStream, generate_offline
from helpers.stream import noise_audio as _audio, random_tiny_model as _model


@pytest.fixture(scope="module")
def model():
    return _model()


@pytest.mark.parametrize("guidance,smoothing,frontend", [(1.0, None, "logmel"), (2.0, (3.0, 0.5), "logmel"),
                                                        (1.25, None, "speech")])
def test_a_resumed_stream_goes_on_exactly(model, guidance, smoothing, frontend):
    if frontend != model.config.frontend:
        model = _model(frontend=frontend)
    audio = _audio(2.4)
    whole = GestureStream(model, steps=4, seed=7, smoothing=smoothing, guidance=guidance)
    before = whole.push(audio[:13001])
    data = savestate.dumps(whole, meta={"session": "a", "sample": 13001})
    after = np.concatenate([whole.push(audio[13001:30000]), whole.push(audio[30000:]), whole.finish()])

    twin = copy.deepcopy(model)  # the same weights in another object, as another worker loads them
    resumed = GestureStream(twin, steps=4, seed=7, smoothing=smoothing, guidance=guidance)
    state, meta = savestate.loads(resumed, data)
    assert meta == {"session": "a", "sample": 13001}
    assert (state.samples_in, state.frames_out) == (13001, len(before))
    resumed.state = state
    again = np.concatenate([resumed.push(audio[13001:30000]), resumed.push(audio[30000:]), resumed.finish()])
    assert len(again) == len(after) > 10 and np.array_equal(again, after)  # bit for bit, not within a tolerance
    offline = generate_offline(model, audio, steps=4, seed=7, smoothing=smoothing, guidance=guidance)
    assert np.abs(np.concatenate([before, again]) - offline).max() < 1e-4


def test_the_fresh_state_round_trips_and_the_size_is_the_state(model):
    s = GestureStream(model, steps=8, seed=1)
    data = savestate.dumps(s)
    state, meta = savestate.loads(GestureStream(model, steps=8, seed=1), data)
    assert meta == {} and state.samples_in == 0 and state.smoother is None
    nbytes = sum(t.numel() * t.element_size() for t in state.denoiser)
    assert nbytes < len(data) < nbytes + 64 * 1024  # the tensors plus a small header


def test_a_state_of_another_version_is_refused_not_misread(model):
    data = bytearray(savestate.dumps(GestureStream(model, steps=4)))
    struct.pack_into("<H", data, 7, savestate.STATE_VERSION + 1)
    with pytest.raises(savestate.StateError, match=f"version {savestate.STATE_VERSION + 1}.*another release"):
        savestate.loads(GestureStream(model, steps=4), bytes(data))
    header, raw = savestate.split(data)  # version 1: no seal, the header right after the prefix
    text = json.dumps(header).encode()
    v1 = struct.pack("<7sHI", b"DGSTATE", 1, len(text)) + text + raw
    with pytest.raises(savestate.StateError, match="version 1, this engine reads version 2 only: .*another release"):
        savestate.loads(GestureStream(model, steps=4), v1)


def test_a_state_resumes_with_the_secret_it_was_sealed_with_and_no_other(model):
    """The workers' shared secret (serve --state-secret-file) seals a state with HMAC-SHA256: a state sealed with
    another secret, or with none (plain SHA-256, as anyone can), is refused before its header is read."""
    s = GestureStream(model, steps=4, seed=3)
    s.push(_audio(0.5))
    secret = b"the cluster's secret"
    sealed = savestate.dumps(s, meta={"a": 1}, key=secret)
    state, meta = savestate.loads(GestureStream(model, steps=4, seed=3), sealed, key=secret)
    assert meta == {"a": 1} and state.samples_in == s.samples_in
    header, raw = savestate.split(sealed)
    header["meta"]["a"] = 2
    for data, key in ((sealed, b"another secret"), (sealed, None), (savestate.dumps(s), secret),
                      (savestate.pack(header, raw), secret), (savestate.pack(header, raw, b"guessed"), secret)):
        with pytest.raises(savestate.StateError, match=r"seal does not match: .* another state secret "
                                                       r"\(--state-secret-file\), or without one"):
            savestate.loads(GestureStream(model, steps=4, seed=3), data, key=key)
    assert savestate.loads(GestureStream(model, steps=4, seed=3), savestate.pack(header, raw, secret),
                           key=secret)[1] == {"a": 2}  # (pack: split's inverse)


def test_one_changed_bit_anywhere_is_refused(model):
    """Every byte but the magic and the version (each refused with its own reason) is under the seal: the header's
    length, the seal, the header and each leaf's bytes."""
    data = savestate.dumps(GestureStream(model, steps=4))
    header, raw = savestate.split(data)
    body = len(data) - len(raw)
    for at in (*range(9, 13), 13, 44, 45, body - 1, body, body + len(raw) // 2, len(data) - 1):
        for bit in (0, 7):
            b = bytearray(data)
            b[at] ^= 1 << bit
            with pytest.raises(savestate.StateError, match="seal does not match"):
                savestate.loads(GestureStream(model, steps=4), bytes(b))


def test_a_state_of_another_model_or_other_settings_is_refused(model):
    s = GestureStream(model, steps=4, seed=3)
    s.push(_audio(0.5))
    data = savestate.dumps(s)
    other = copy.deepcopy(model)
    with torch.no_grad():
        next(other.parameters())[0].add_(1e-3)  # one weight moved
    with pytest.raises(savestate.StateError, match="another model"):
        savestate.loads(GestureStream(other, steps=4, seed=3), data)
    with pytest.raises(savestate.StateError, match=r"other sampling settings \(pairs\)"):
        savestate.loads(GestureStream(model, steps=8, seed=3), data)
    with pytest.raises(savestate.StateError, match=r"\(seed\)"):
        savestate.loads(GestureStream(model, steps=4, seed=4), data)
    with pytest.raises(savestate.StateError, match=r"guidance"):
        savestate.loads(GestureStream(model, steps=4, seed=3, guidance=2.0), data)


def test_broken_bytes_are_refused_with_the_reason(model):
    s = GestureStream(model, steps=4)
    s.push(_audio(0.5))
    data = savestate.dumps(s)
    header, raw = savestate.split(data)
    body = len(data) - len(raw)
    load = lambda d: savestate.loads(GestureStream(model, steps=4), d)  # noqa: E731
    with pytest.raises(savestate.StateError, match="no DGSTATE header"):
        load(b"hello")
    for cut in (data[:-10], data[:body - 5], data[:20]):  # the seal finds it first ...
        with pytest.raises(savestate.StateError, match="seal does not match: corrupted or cut short"):
            load(cut)
    # ... and re-sealed (as anyone without the workers' secret can), the checks behind it
    with pytest.raises(savestate.StateError, match="cut short"):
        load(savestate.reseal(data[:-10]))
    with pytest.raises(savestate.StateError, match="cut short"):
        load(savestate.reseal(data[:body - 5]))
    with pytest.raises(savestate.StateError, match="does not parse"):
        load(savestate.pack(b"{" * (body - 45), raw))

    def patched(change):
        h = copy.deepcopy(header)
        change(h)
        return savestate.pack(h, raw)
    with pytest.raises(savestate.StateError, match="state.extractor is a 'Popen'"):
        load(patched(lambda h: h["state"]["f"]["extractor"].update(t="Popen")))
    with pytest.raises(savestate.StateError, match="has fields"):
        load(patched(lambda h: h["state"]["f"].pop("frontend")))
    with pytest.raises(savestate.StateError, match=r"state.denoiser.enc of shape \[1, "):
        load(patched(lambda h: h["state"]["f"]["denoiser"]["f"]["enc"].update(
            shape=[1] + h["state"]["f"]["denoiser"]["f"]["enc"]["shape"][1:],
            n=h["state"]["f"]["denoiser"]["f"]["enc"]["n"] // h["state"]["f"]["denoiser"]["f"]["enc"]["shape"][0])))


def test_two_loads_of_one_checkpoint_share_a_fingerprint_and_a_changed_weight_does_not():
    from dimgestor.streaming.checkpoint import load_checkpoint

    a, b = load_checkpoint(None).model, load_checkpoint(None).model  # the embedded default, as two workers load it
    assert savestate.model_fingerprint(a) == savestate.model_fingerprint(b)
    with torch.no_grad():
        next(b.parameters()).view(-1)[0] += 1.0  # in place: the cached fingerprint must not survive it
    assert savestate.model_fingerprint(a) != savestate.model_fingerprint(b)
