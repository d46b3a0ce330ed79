"""Batched multi-stream denoising (dimgestor.streaming.batch): every stream gets the frames it would get alone."""
import numpy as np
import pytest
import torch

from dimgestor.model.diffusion import Diffusion
from dimgestor.model.sampler import DenoiseRunner, StepStates
from dimgestor.streaming.batch import push_many
from dimgestor.streaming.stream import GestureStream, generate_offline, sample_frames
from helpers.stream import noise_audio as _audio, random_tiny_model as _model, stream_in_pieces

TOL = 1e-5


@pytest.fixture(scope="module")
def model():
    return _model()


@pytest.mark.parametrize("n", [1, 2, 3, 7, 40])  # up to STEP_MAX frames: the written-out block; longer: modules
@pytest.mark.parametrize("sampler,eta,K", [("ddim", 0.0, 4), ("ddim", 0.6, 3), ("ddpm", 0.0, None)])
@pytest.mark.parametrize("B", [1, 3])
def test_runner_equals_the_models_own_forward(model, n, sampler, eta, K, B):
    """The fast path (modulations of all steps in one matmul, states updated in place) vs one model call per step."""
    if sampler == "ddpm":  # every one of the N steps: a short chain keeps it quick
        model = _model(n_steps=24)
    d = Diffusion(model.config)
    pairs = d.sampling_pairs(sampler, K or 1)
    runner = DenoiseRunner(model, pairs, sampler, eta)
    H = model.config.hidden
    gen = torch.Generator().manual_seed(n)
    with torch.inference_mode():
        states = StepStates.zeros(model, len(pairs), B)
        ref = [[None] * len(pairs) for _ in range(B)]
        for w, start in enumerate((0, n)):  # two windows: the second continues the carried states
            cond = torch.randn(B, n, H, generator=gen)
            seeds = [5, 6, 7 + w][:B]
            got = runner.sample(cond, [start] * B, seeds, states)
            for b in range(B):
                want, ref[b] = sample_frames(model, d, cond[b:b + 1], start, ref[b], pairs, seeds[b], sampler, eta)
                assert (got[b] - want).abs().max() < TOL
        want_states = [StepStates.from_steps(r) for r in ref]
        for b in range(B):
            for got_t, want_t in zip(StepStates(states.enc[:, b:b + 1], states.conv[:, :, b:b + 1],
                                                states.ssm[:, :, b:b + 1]), want_states[b]):
                assert (got_t - want_t).abs().max() < TOL


@pytest.mark.parametrize("n", [2, 7])  # the written-out block (held by a zero step size) and the modules
@pytest.mark.parametrize("guidance", [None, [1.0, 2.0, 1.5]])
def test_held_rows_keep_their_states_exactly(model, n, guidance):
    """`hold` (the exported graph's warm-up): held rows come out with the very states they went in with; the
    other rows' frames and states are the ones they get without it."""
    pairs = Diffusion(model.config).sampling_pairs("ddim", 3)
    runner = DenoiseRunner(model, pairs, "ddim", 0.0)
    gen = torch.Generator().manual_seed(1)
    rows = 3 if guidance is None else 5  # window 0 unguided; 1 and 2 guided, two rows each
    hold = torch.tensor([False, True, True, False, False] if guidance else [False, True, False])
    with torch.inference_mode():
        start = StepStates(*(torch.randn(t.shape, generator=gen) for t in StepStates.zeros(model, len(pairs), rows)))
        cond = torch.randn(3, n, model.config.hidden, generator=gen)
        free, held = (StepStates(*(torch.empty_like(t) for t in start)) for _ in range(2))
        want = runner.sample(cond, [4, 9, 0], [1, 2, 3], start, guidance, out=free)
        got = runner.sample(cond, [4, 9, 0], [1, 2, 3], start, guidance, out=held, hold=hold)
    for b in (0, 2):  # window 1's frames (held) mean nothing
        assert torch.equal(got[b], want[b])
    for new, old, ref, dim in zip(held, start, free, (1, 2, 2)):
        assert torch.equal(new.index_select(dim, hold.nonzero()[:, 0]), old.index_select(dim, hold.nonzero()[:, 0]))
        assert torch.equal(new.index_select(dim, (~hold).nonzero()[:, 0]), ref.index_select(dim, (~hold).nonzero()[:, 0]))


def _schedule(rng, total, low, high):
    sizes, left = [], total
    while left > 0:
        sizes.append(min(int(rng.integers(low, high)), left))
        left -= sizes[-1]
    return sizes


def test_batched_streams_equal_solo_streams(model):
    """Different seeds, audio, start times and chunk sizes; one stream leaves mid-batch, one joins late."""
    rng = np.random.default_rng(0)
    specs = [  # (seed, seconds, start tick, chunk size range)
        (11, 3.0, 0, (1600, 1601)),  # 100 ms windows
        (12, 2.5, 0, (1600, 1601)),  # same window size: shares its batch with the first
        (13, 1.2, 0, (700, 2600)),   # leaves early (finishes at tick ~10)
        (14, 2.0, 6, (1600, 1601)),  # joins at tick 6
        (15, 2.2, 2, (300, 4000)),   # ragged chunks: its own group most ticks
    ]
    plans = []
    for seed, seconds, start, (lo, hi) in specs:
        audio = _audio(seconds, seed)
        plans.append((seed, audio, start, _schedule(rng, len(audio), lo, hi)))

    solo = [stream_in_pieces(model, audio, sizes, steps=4, seed=seed, smoothing=None) for seed, audio, _, sizes in plans]

    streams = [GestureStream(model, steps=4, seed=seed, smoothing=None) for seed, *_ in plans]
    outs = [[] for _ in plans]
    pos = [0] * len(plans)
    done = [False] * len(plans)
    tick, batch_sizes = 0, []
    while not all(done):
        due = [i for i, (_, _, start, sizes) in enumerate(plans) if not done[i] and tick >= start]
        pushing = [i for i in due if tick - plans[i][2] < len(plans[i][3])]
        chunks = []
        for i in pushing:
            _, audio, start, sizes = plans[i]
            n = sizes[tick - start]
            chunks.append(audio[pos[i]:pos[i] + n])
            pos[i] += n
        for i, frames in zip(pushing, push_many([streams[i] for i in pushing], chunks)):
            outs[i].append(frames)
        batch_sizes.append(len(pushing))
        for i in set(due) - set(pushing):  # its audio ended: leave the batch
            outs[i].append(streams[i].finish())
            done[i] = True
        tick += 1
    assert max(batch_sizes) >= 4
    for i, (got, want) in enumerate(zip(outs, solo)):
        got = np.concatenate(got)
        assert got.shape == want.shape, i
        assert np.abs(got - want).max() < TOL, (i, np.abs(got - want).max())


def test_batched_streams_equal_offline_realtime_preset():
    """The realtime preset (the served one), 100 ms windows, 6 streams batched: each equals its offline run."""
    model = _model("realtime", motion_dim=12)
    audios = [_audio(2.0, seed) for seed in range(6)]
    streams = [GestureStream(model, steps=8, seed=seed, smoothing=None) for seed in range(6)]
    outs = [[] for _ in audios]
    for a in range(0, len(audios[0]), 1600):
        for o, f in zip(outs, push_many(streams, [x[a:a + 1600] for x in audios])):
            o.append(f)
    for seed, (s, o, audio) in enumerate(zip(streams, outs, audios)):
        got = np.concatenate(o + [s.finish()])
        want = generate_offline(model, audio, steps=8, seed=seed, smoothing=None)
        assert np.abs(got - want).max() < 1e-4  # the offline run scans whole chunks: float rounding differs


def test_push_many_checks_its_arguments(model):
    s = GestureStream(model, steps=2)
    with pytest.raises(ValueError, match="at most once"):
        push_many([s, s], [np.zeros(160, np.float32)] * 2)
    with pytest.raises(ValueError, match="chunks"):
        push_many([s], [])
    s.finish()
    with pytest.raises(RuntimeError, match="after finish"):
        push_many([s], [np.zeros(160, np.float32)])


def test_runner_follows_weight_changes(model):
    """A runner caches stacked adaLN weights; changing the model's weights must not serve stale ones."""
    m = _model()
    audio = _audio(1.0, 3)
    before = GestureStream(m, steps=2, smoothing=None).push(audio)
    with torch.no_grad():
        m.blocks[0].adaLN_modulation[-1].bias.add_(0.5)
    after = GestureStream(m, steps=2, smoothing=None).push(audio)
    want = generate_offline(m, audio, steps=2, smoothing=None)[: len(after)]
    assert not np.allclose(before, after)
    assert np.abs(after - want).max() < 1e-4


def test_batched_steps_only_read_their_states_and_reuse_the_batch_buffer(model, monkeypatch):
    """step_many maps the step over states: stepping the same old states again gives the same frames (the batch
    never writes into a state a caller holds), yet the same streams coming back together are not copied."""
    from dimgestor.streaming.batch import step_many

    audios = [_audio(1.5, seed) for seed in range(3)]
    streams = [GestureStream(model, steps=3, seed=seed, smoothing=None) for seed in range(3)]
    copies = []
    cat = StepStates.cat
    monkeypatch.setattr(StepStates, "cat",
                        staticmethod(lambda states, out=None: (copies.append(len(states)), cat(states, out))[1]))
    states, outs = [s.state for s in streams], [[] for _ in streams]
    for a in range(0, 8000, 1600):  # the same streams together each round: copied into one buffer once
        frames, states = step_many(streams, states, [x[a:a + 1600] for x in audios])
        for o, f in zip(outs, frames):
            o.append(f)
    assert copies == [3]
    first, _ = step_many(streams, states, [x[8000:9600] for x in audios])
    again, _ = step_many(streams, states, [x[8000:9600] for x in audios])
    assert all(len(f) > 0 and np.array_equal(f, g) for f, g in zip(first, again))
    for s, audio, o, f in zip(streams, audios, outs, first):
        solo = GestureStream(model, steps=3, seed=s.seed, smoothing=None)
        want = np.concatenate([solo.push(audio[a:a + 1600]) for a in range(0, 9600, 1600)])
        assert np.abs(np.concatenate(o + [f]) - want).max() < TOL


def test_state_buffers_are_used_again_only_once_nothing_holds_them(model):
    """`StateBuffers.take`: a buffer whose rows someone still holds (a view of a view, a numpy array) is never
    handed out again; once they are gone it is, for a batch of its size or a few rows fewer; at most `keep` free
    ones are kept."""
    from dimgestor.model.sampler import StateBuffers

    pool = StateBuffers(keep=2)
    like = StepStates.zeros(model, 3, 1)
    a = pool.take(like, 10)
    assert a.batch == 10 and a.ssm.shape[3:] == like.ssm.shape[3:] and a.conv.shape[3:] == like.conv.shape[3:]
    view = a.enc[:, 2:3].narrow(1, 0, 1)
    arr = pool.take(like, 10).ssm.numpy()
    del a
    b = pool.take(like, 10)  # the first two are held: a third
    assert pool.made == 3
    del b, view
    c, d = pool.take(like, 9), pool.take(like, 9)  # the first and the third, not the one the array holds
    assert pool.made == 3
    assert arr.__array_interface__["data"][0] not in (c.ssm.data_ptr(), d.ssm.data_ptr(), )
    assert c.ssm.data_ptr() != d.ssm.data_ptr()
    e = pool.take(like, 9)
    assert pool.made == 4
    del c, d, e, arr
    for rows in (40, 50, 60, 70):  # too big for the free ones: new ones, and at most 2 free ones are kept
        pool.take(like, rows)
    assert pool.made == 8 and len(pool) <= 3


def test_streams_in_changing_batches_reuse_the_runners_buffers(model):
    """Thirty windows of streams joining and leaving batches (their states copied together, new ones written):
    after the first rounds no new buffer is made, and every stream's frames are its solo frames."""
    audios = [_audio(1.5, seed) for seed in range(5)]
    streams = [GestureStream(model, steps=2, seed=seed, smoothing=None) for seed in range(5)]
    runner = streams[0].runner
    outs, made = [[] for _ in streams], []
    for w in range(30):
        a = w * 1600 % 24000
        pushing = [i for i in range(5) if (w + i) % 3]  # a different set each window
        for i, f in zip(pushing, push_many([streams[i] for i in pushing], [audios[i][a:a + 1600] for i in pushing])):
            outs[i].append((a, f))
        made.append(runner.buffers.made)
    assert made[-1] == made[8], made
    for i, s in enumerate(streams):
        solo = GestureStream(model, steps=2, seed=i, smoothing=None)
        want = np.concatenate([solo.push(audios[i][a:a + 1600]) for a, _ in outs[i]])
        assert np.abs(np.concatenate([f for _, f in outs[i]]) - want).max() < TOL
