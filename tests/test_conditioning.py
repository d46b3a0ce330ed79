"""Many streams' front end and feature extractor as one call a group (dimgestor.model.conditioning): each stream gets the
condition and the state it gets alone."""
import numpy as np
import pytest
import torch

from dimgestor.model.mamba2 import Mamba2State
from dimgestor.streaming.batch import begin_many, push_many, step_many
from dimgestor.streaming.stream import GestureStream
from helpers.stream import noise_audio, random_tiny_model

TOL = 1e-5


@pytest.fixture(scope="module", params=["logmel", "speech"])
def model(request):
    return random_tiny_model(frontend=request.param).eval()


def _leaves(state):
    """Every tensor and count of a state, in order."""
    if torch.is_tensor(state) or isinstance(state, int):
        return [state]
    if isinstance(state, Mamba2State):
        return [state.conv, state.ssm]
    return [leaf for part in state for leaf in _leaves(part)]


def _assert_same_state(got, want):
    for g, w in zip(_leaves(got.frontend) + _leaves(got.extractor), _leaves(want.frontend) + _leaves(want.extractor)):
        if isinstance(w, int):
            assert g == w
        else:
            assert g.shape == w.shape
            assert torch.allclose(g.double(), w.double(), atol=TOL, rtol=0, equal_nan=True)
    assert got.samples_in == want.samples_in


def _calls(monkeypatch, model):
    """The batch size of every front-end call."""
    sizes = []
    forward = type(model.frontend).forward

    def counted(self, samples, state):
        sizes.append(samples.shape[0])
        return forward(self, samples, state)

    monkeypatch.setattr(type(model.frontend), "forward", counted)
    return sizes


def test_groups_of_equal_chunks_and_state_shapes_equal_each_stream_alone(model, monkeypatch):
    """Streams in warm-up beside streams past it, a stream fed other chunk sizes, streams joining late: round by
    round each stream's condition and state equal its solo run's, and the equal ones shared one call."""
    sizes = _calls(monkeypatch, model)
    plans = [  # (start round, chunk sizes): 100 ms windows, one fed ragged chunks
        (0, [1600] * 8), (0, [1600] * 8), (2, [1600] * 6), (3, [1600] * 5), (1, [800, 2400, 700, 1600, 333, 1600, 1600])]
    audios = [noise_audio(sum(c) / 16000, seed) for seed, (_, c) in enumerate(plans)]
    streams = [GestureStream(model, steps=2, seed=seed) for seed in range(len(plans))]
    solo = [GestureStream(model, steps=2, seed=seed) for seed in range(len(plans))]
    states, solo_states, pos = [s.state for s in streams], [s.state for s in solo], [0] * len(plans)
    grouped = []
    for rnd in range(8):
        due = [i for i, (start, chunks) in enumerate(plans) if 0 <= rnd - start < len(chunks)]
        chunks = []
        for i in due:
            n = plans[i][1][rnd - plans[i][0]]
            chunks.append(audios[i][pos[i]:pos[i] + n])
            pos[i] += n
        del sizes[:]
        conds, new, failed = begin_many([streams[i] for i in due], [states[i] for i in due], chunks)
        grouped.append(sorted(sizes))
        assert failed == {}
        for k, i in enumerate(due):
            want_cond, solo_states[i] = solo[i].begin_step(solo_states[i], chunks[k])
            assert conds[k].shape == want_cond.shape
            assert want_cond.numel() == 0 or (conds[k] - want_cond).abs().max() <= TOL
            _assert_same_state(new[k], solo_states[i])
            states[i] = new[k]
    assert max(max(g) for g in grouped) >= 3  # the streams past warm-up shared a call
    assert any(len(g) > 1 for g in grouped)  # ... beside another group (warm-up, ragged chunks)
    assert sum(sum(g) for g in grouped) == sum(len(c) for _, c in plans)  # every window conditioned once


def test_step_many_frames_equal_solo_with_guidance_and_mixed_lengths(model):
    """Through the whole step (guided rows, the denoiser batch after the conditioning groups): frames as alone."""
    audios = [noise_audio(1.6, seed) for seed in range(4)]
    chunk = [1600, 1600, 1600, 1000]
    streams = [GestureStream(model, steps=3, seed=seed, guidance=1.5, smoothing=None) for seed in range(4)]
    solo = [GestureStream(model, steps=3, seed=seed, guidance=1.5, smoothing=None) for seed in range(4)]
    for a in range(0, 16000, 1600):
        pushing = [i for i in range(4) if a >= 1600 * i // 2]  # later streams join in warm-up
        chunks = [audios[i][a * chunk[i] // 1600:(a + 1600) * chunk[i] // 1600] for i in pushing]
        got = push_many([streams[i] for i in pushing], chunks)
        for i, c, g in zip(pushing, chunks, got):
            want = solo[i].push(c)
            assert g.shape == want.shape and (g.size == 0 or np.abs(g - want).max() < TOL)


def test_a_failing_stream_among_others_fails_alone(model):
    """return_exceptions: bad audio and a finished stream get their errors and keep their states; the others
    (one group) get the frames they get alone."""
    audios = [noise_audio(1.0, seed) for seed in range(4)]
    streams = [GestureStream(model, steps=2, seed=seed, smoothing=None) for seed in range(5)]
    streams[4].finish()
    solo = [GestureStream(model, steps=2, seed=seed, smoothing=None) for seed in range(3)]
    for a in range(0, 16000, 1600):
        before = [s.state for s in streams]
        chunks = [x[a:a + 1600] for x in audios[:3]] + [(audios[3][a:a + 1600] * 1000).astype(np.int16),
                                                         audios[3][a:a + 1600]]
        outs = push_many(streams, chunks, return_exceptions=True)
        assert isinstance(outs[3], ValueError) and "float" in str(outs[3])
        assert isinstance(outs[4], RuntimeError) and "after finish" in str(outs[4])
        assert streams[3].state is before[3] and streams[4].state is before[4]
        for i in range(3):
            want = solo[i].push(audios[i][a:a + 1600])
            assert outs[i].shape == want.shape and (want.size == 0 or np.abs(outs[i] - want).max() < TOL)
    with pytest.raises(ValueError, match="float"):
        push_many(streams[:4], chunks[:4])


def test_a_group_whose_batched_call_fails_runs_stream_by_stream(model, monkeypatch):
    """A front end that fails on one stream's audio only: the batched call fails, then each stream runs alone and
    only that one fails (its state kept); without return_exceptions its error is raised."""
    forward = type(model.frontend).forward

    def picky(self, samples, state):
        if bool((samples == 0.25).all(dim=1).any()):
            raise ValueError("this front end refuses a constant 0.25")
        return forward(self, samples, state)

    monkeypatch.setattr(type(model.frontend), "forward", picky)
    streams = [GestureStream(model, steps=2, seed=seed) for seed in range(3)]
    chunks = [noise_audio(0.1, 0), np.full(1600, 0.25, np.float32), noise_audio(0.1, 2)]
    conds, new, failed = begin_many(streams, [s.state for s in streams], chunks, return_exceptions=True)
    assert list(failed) == [1] and "0.25" in str(failed[1])
    assert conds[1] is None and new[1] is streams[1].state
    for i in (0, 2):
        want_cond, want_state = streams[i].begin_step(streams[i].state, chunks[i])
        assert conds[i].shape == want_cond.shape
        _assert_same_state(new[i], want_state)
    with pytest.raises(ValueError, match="0.25"):
        step_many(streams, [s.state for s in streams], chunks)
