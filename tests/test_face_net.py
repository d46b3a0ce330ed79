"""The face's own listener (dimgestor.face.net): a stream in any pieces hears exactly what the whole recording
hears, the numpy stream is the torch network, and the weights in the package load and hear speech."""

import numpy as np
import pytest
import torch

from dimgestor.audio import SAMPLE_RATE, load_wav
from dimgestor.face import net
from dimgestor.face.visemes import V
from helpers.clients import SPEECH_WAV

SPEECH = load_wav(SPEECH_WAV)[: 4 * SAMPLE_RATE]  # espeak-ng English


@pytest.fixture(scope="module")
def random_weights(tmp_path_factory):
    """A network with random weights (large enough that every layer matters)."""
    torch.manual_seed(3)
    model = net.torch_listener()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.05)
        model.prior[:] = torch.linspace(-8, -2, net.N_MELS, dtype=torch.float64)
    path = tmp_path_factory.mktemp("listener") / "w.safetensors"
    net.save_weights(model, path, {"test": True})
    return model, str(path)


def heard_in_pieces(audio, sizes, weights, fps=20):
    listener, at, k = net.NetListener(fps, weights=weights), 0, 0
    while at < len(audio):
        n = sizes[k % len(sizes)]
        listener.push(audio[at:at + n])
        at, k = at + n, k + 1
    listener.finish(int(np.ceil(len(audio) / SAMPLE_RATE * fps - 1e-9)))
    return listener.ready


@pytest.mark.parametrize("weights", ["random", "shipped"])
def test_a_stream_in_any_pieces_hears_what_the_whole_recording_hears(random_weights, weights):
    path = random_weights[1] if weights == "random" else None
    whole = net.NetListener.offline(SPEECH, 20, weights=path)
    assert len(whole) == 80
    for sizes in ([1, 159, 161, 3333], [7, 5000], [800], [len(SPEECH)]):
        got = heard_in_pieces(SPEECH, sizes, path)
        assert [i for i, _ in got] == list(range(80))
        for (_, a), b in zip(got, whole):
            np.testing.assert_array_equal(a.visemes, b.visemes, err_msg=f"chunk sizes {sizes}")
            assert a.opening == b.opening


def test_the_numpy_stream_is_the_torch_network(random_weights):
    """Every 10 ms output of the stream against the torch network run over the whole recording at once."""
    model, path = random_weights
    mel = net.log_mel(SPEECH)
    x, _ = net.normalise(mel, None, model.prior.numpy())
    with torch.no_grad():
        want = model(torch.from_numpy(x)[None])[0].numpy()
    listener = net.NetListener(20, weights=path)
    listener._trim = lambda: None  # keep every output to compare
    listener.push(SPEECH)
    got = listener.out
    assert len(got) > 300 and np.abs(want).max() > 1.0
    np.testing.assert_allclose(got, want[:len(got)], atol=1e-4, rtol=0)


def test_each_frame_is_heard_within_the_lookahead():
    """Frame i is ready once the audio up to i / fps + LOOKAHEAD_S is in, and not before."""
    listener = net.NetListener(20)
    upto = int(round((1.0 + net.LOOKAHEAD_S) * SAMPLE_RATE))
    listener.push(SPEECH[:upto - 1])
    assert listener.next_frame == 20
    listener.push(SPEECH[upto - 1:upto])
    assert listener.next_frame == 21
    assert net.LOOKAHEAD_S <= 0.15  # inside the live model's lookahead


def test_a_resumed_stream_starts_from_the_stream_clock():
    """A session resumed at sample s (its frame index carried on) hears from there: frames from its first, the
    same whatever the pieces."""
    start, frame = 2 * SAMPLE_RATE, 40
    a = net.NetListener(20, start_sample=start, start_frame=frame)
    a.push(SPEECH[start:])
    a.finish(80)
    b = net.NetListener(20, start_sample=start, start_frame=frame)
    for at in range(start, len(SPEECH), 999):
        b.push(SPEECH[at:at + 999])
    b.finish(80)
    assert [i for i, _ in a.ready] == list(range(40, 80)) == [i for i, _ in b.ready]
    for (_, x), (_, y) in zip(a.ready, b.ready):
        np.testing.assert_array_equal(x.visemes, y.visemes)


def test_the_shipped_listener_hears_speech_and_silence():
    """The package's weights: the training record is in the file; speech opens the jaw, silence is heard as
    silence."""
    meta = net.weights_meta()
    assert meta["steps"] > 0 and meta["data_minutes"] > 60
    audio = np.concatenate([np.zeros(SAMPLE_RATE, np.float32), SPEECH, np.zeros(SAMPLE_RATE, np.float32)])
    heard = net.NetListener.offline(audio, 20)
    opening = np.array([h.opening for h in heard])
    sil = np.array([h.visemes[V["sil"]] for h in heard])
    assert np.all(sil[2:18] > 0.5) and np.all(sil[-15:] > 0.5), np.round(sil, 2)
    assert opening[25:95].max() > 0.6 and np.mean(opening[25:95] > 0.3) > 0.3


def test_other_frame_rates_hear_the_same_speech():
    """30 fps (BEAT2's) reads the same 10 ms outputs at its own times: 20.0 (a checkpoint's float) is 20."""
    at20 = net.NetListener.offline(SPEECH, 20)
    at20f = net.NetListener.offline(SPEECH, 20.0)
    at30 = net.NetListener.offline(SPEECH, 30)
    assert len(at30) == 120 and all(np.array_equal(a.visemes, b.visemes) for a, b in zip(at20, at20f))
    for i in range(0, 120, 3):  # frames at the same times (every 0.1 s)
        np.testing.assert_allclose(at30[i].visemes, at20[i * 2 // 3].visemes, atol=1e-5)  # (other step sizes)


@pytest.mark.parametrize("group", [2, 4])
def test_steps_of_several_frames_are_the_same_for_any_pieces(random_weights, group):
    """A longer lookahead lets a step make several frames (`frames_per_step`): still the same whatever the
    pieces, and within float rounding of single steps."""
    path = random_weights[1]
    whole = net.NetListener.offline(SPEECH, 20, weights=path, frames_per_step=group)
    single = net.NetListener.offline(SPEECH, 20, weights=path)
    listener = net.NetListener(20, weights=path, frames_per_step=group)
    for at in range(0, len(SPEECH), 1234):
        listener.push(SPEECH[at:at + 1234])
    listener.finish(80)
    assert len(whole) == len(listener.ready) == 80
    for (_, a), b, c in zip(listener.ready, whole, single):
        np.testing.assert_array_equal(a.visemes, b.visemes)
        np.testing.assert_allclose(b.visemes, c.visemes, atol=1e-5)
    assert net.NetListener.frames_per_step(20, 0.3) == 4 and net.NetListener.frames_per_step(20, 0.15) == 1


def test_a_shorter_lookahead_than_the_networks_shows_the_mouth_late_by_the_difference():
    """A model that looks 0.08 s ahead still gets a face: frame i shows what frame i - 6 (10 ms each) showed."""
    from dimgestor.face import FaceStream

    assert net.NetListener.late_frames(0.08) == 6 and net.NetListener.late_frames(0.15) == 0
    on_time = net.NetListener.offline(SPEECH, 100)
    late = net.NetListener(100, late=6)
    late.push(SPEECH)
    late.finish(400)
    for (i, h) in late.ready[6:]:
        np.testing.assert_allclose(h.visemes, on_time[i - 6].visemes, atol=1e-5)
    face = FaceStream(20, 0.08)
    face.push(SPEECH[:SAMPLE_RATE])
    assert face.frames_ready == int(round((1.0 - 0.08) * 20)) + 1


def test_streams_stepped_together_hear_what_each_hears_alone(random_weights):
    """`NetListener.run_many` (a server's batch of windows: the streams' steps through each layer as one matrix
    product) gives each stream what it hears alone: streams at other points of their audio, one resumed
    mid-recording, one stepping several frames at a time, pushed in other pieces. Equal here; within float
    rounding where a matrix product's row depends on the rows beside it."""
    path = random_weights[1]
    specs = [dict(offset=0), dict(offset=777), dict(offset=0, group=4), dict(offset=0, start=SAMPLE_RATE)]

    def make(spec):
        start = spec.get("start", 0)
        return net.NetListener(20, weights=path, frames_per_step=spec.get("group", 1), start_sample=start,
                               start_frame=start * 20 // SAMPLE_RATE)

    together = [make(s) for s in specs]
    ends = [len(SPEECH)] * len(specs)
    for at in range(0, len(SPEECH), 1600):
        live = []
        for x, spec, end in zip(together, specs, ends):
            lo = max(at - spec["offset"], spec.get("start", 0))
            hi = min(at + 1600 - spec["offset"], end)
            if hi > lo:
                x.push(SPEECH[lo:hi], run=False)
                live.append(x)
        net.NetListener.run_many(live)
    assert max(len(x.ready) for x in together) > 0
    for x, spec in zip(together, specs):
        got_upto = len(x.ready)
        alone = make(spec)
        alone.push(SPEECH[spec.get("start", 0):])
        assert got_upto > 40 and [i for i, _ in x.ready] == [i for i, _ in alone.ready[:got_upto]]
        for (_, a), (_, b) in zip(x.ready, alone.ready):
            np.testing.assert_allclose(a.visemes, b.visemes, atol=1e-6, rtol=0, err_msg=str(spec))
            assert abs(a.opening - b.opening) <= 1e-6
