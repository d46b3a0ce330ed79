"""Classifier-free guidance: condition dropout in training, a guidance scale at sampling.

Scale 1 is today's sampler exactly; a guided stream equals its offline run for any chunking, and alone or
batched with other streams (guided or not); the unconditional branch is the network with the condition zeroed.
"""
import json

import numpy as np
import pytest
import torch

from dimgestor.config import get_preset
from dimgestor.model.diffusion import Diffusion, motion_noise
from dimgestor.model.sampler import DenoiseRunner, StepStates
from dimgestor.streaming.batch import push_many
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.streaming.stream import GestureStream, generate_offline, sample_frames
from dimgestor.training.synthetic import make_synthetic_pair
from dimgestor.training.train import TrainConfig, resolve_cond_drop, train
from dimgestor_app.cli import main
from helpers.stream import noise_audio as _audio, push_in_pieces, random_tiny_model as _model, stream_in_pieces

TOL = 1e-5  # batched vs alone, runner vs the model's own forward (as tests/test_batch.py)


def _sizes(total, pattern):
    sizes, i = [], 0
    while sum(sizes) < total:
        sizes.append(pattern[i % len(pattern)])
        i += 1
    sizes[-1] -= sum(sizes) - total
    return sizes


@pytest.fixture(scope="module")
def model():
    return _model()


def _unguided_sampler(model, diffusion, cond, pairs, seed):
    """Today's DDIM loop (eta 0) written out, without any guidance: what scale 1 must reproduce bit for bit."""
    n, D, L = cond.shape[1], model.config.motion_dim, model.config.noise_taps
    x = motion_noise(seed, 0, n, 0, D, L)[None]
    for t, t_prev in pairs:
        out, _ = model(x, t, cond, None)
        eps, x0 = diffusion.split(out, x, t)
        x, _ = diffusion.ddim_step(x, eps, t, t_prev, 0.0, None, x0=x0)
    return x[0]


# ---------------- scale 1 is today's sampler ----------------
def test_scale_one_is_the_unguided_sampler_offline():
    model = _model(guidance=2.0)  # the config asks for guidance; an explicit 1 must switch it off entirely
    d = Diffusion(model.config)
    pairs = d.sampling_pairs("ddim", 4)
    cond = torch.randn(1, 23, model.config.hidden, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        want = _unguided_sampler(model, d, cond, pairs, seed=4)
        got, states = sample_frames(model, d, cond, 0, [None] * 4, pairs, 4, "ddim", 0.0, guidance=1.0)
        guided, _ = sample_frames(model, d, cond, 0, [None] * 4, pairs, 4, "ddim", 0.0, guidance=2.0)
    assert torch.equal(got, want)
    assert all(s.enc.shape[0] == 1 for s in states)  # no unconditional row was run
    assert not torch.allclose(guided, want, atol=1e-3)
    audio = _audio(1.3, 0)
    unguided = _model()  # the same weights with the config's default scale 1
    assert np.array_equal(generate_offline(model, audio, steps=4, guidance=1.0), generate_offline(unguided, audio, steps=4))
    assert np.array_equal(generate_offline(model, audio, steps=4), generate_offline(unguided, audio, steps=4, guidance=2.0))


def test_scale_one_is_the_unguided_sampler_streaming_and_batched(model):
    """Streams at scale 1 carry one state row and run exactly the unguided ops, alone and batched (states of
    one row a window: an unconditional row would not fit them)."""
    d = Diffusion(model.config)
    pairs = d.sampling_pairs("ddim", 3)
    runner = DenoiseRunner(model, pairs)
    cond = torch.randn(3, 5, model.config.hidden, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        a, b = StepStates.zeros(model, 3, 3), StepStates.zeros(model, 3, 3)
        for start in (0, 5):
            got = runner.sample(cond, [start] * 3, [1, 2, 3], a, guidance=[1.0, 1.0, 1.0])
            want = runner.sample(cond, [start] * 3, [1, 2, 3], b)
            assert torch.equal(got, want)
        assert all(torch.equal(x, y) for x, y in zip(a, b))

    audios = [_audio(1.5, s) for s in range(3)]
    plain = [GestureStream(model, steps=4, seed=s, smoothing=None) for s in range(3)]
    ones = [GestureStream(model, steps=4, seed=s, smoothing=None, guidance=1.0) for s in range(3)]
    assert all(s.state.denoiser.batch == 1 for s in ones)
    for i in range(0, len(audios[0]), 1600):
        for x, y in zip(push_many(plain, [a[i:i + 1600] for a in audios]), push_many(ones, [a[i:i + 1600] for a in audios])):
            assert np.array_equal(x, y)
    assert all(np.array_equal(x.finish(), y.finish()) for x, y in zip(plain, ones))


# ---------------- the fast path equals the model's own forward ----------------
@pytest.mark.parametrize("n", [1, 3, 40])  # up to STEP_MAX frames: the written-out block; 40: the modules
@pytest.mark.parametrize("sampler,eta", [("ddim", 0.0), ("ddim", 0.6)])
def test_guided_runner_equals_the_models_own_forward(model, n, sampler, eta):
    """Three windows at scales 2, 1 and 0 in one batch (five network rows) vs the reference, one window at a time."""
    d = Diffusion(model.config)
    pairs = d.sampling_pairs(sampler, 3)
    runner = DenoiseRunner(model, pairs, sampler, eta)
    scales, seeds = [2.0, 1.0, 0.0], [5, 6, 7]
    gen = torch.Generator().manual_seed(n)
    with torch.inference_mode():
        states = StepStates.zeros(model, len(pairs), 5)  # rows: c0 u0 | c1 | c2 u2
        ref = [[None] * len(pairs) for _ in scales]
        for start in (0, n):  # two windows: the second continues the carried states
            cond = torch.randn(3, n, model.config.hidden, generator=gen)
            got = runner.sample(cond, [start] * 3, seeds, states, guidance=scales)
            for b, s in enumerate(scales):
                want, ref[b] = sample_frames(model, d, cond[b:b + 1], start, ref[b], pairs, seeds[b], sampler, eta, s)
                assert (got[b] - want).abs().max() < TOL
        want_states = StepStates.cat([StepStates.from_steps(r) for r in ref])
        for got_t, want_t in zip(states, want_states):
            assert got_t.shape == want_t.shape and (got_t - want_t).abs().max() < TOL
        with pytest.raises(ValueError, match="rows"):
            runner.sample(cond, [0] * 3, seeds, StepStates.zeros(model, len(pairs), 3), guidance=scales)


# ---------------- streaming = offline, batched = alone ----------------
@pytest.mark.parametrize("guidance,eta", [(2.5, 0.0), (0.0, 0.0), (1.7, 0.7)])
def test_guided_streaming_equals_offline_for_awkward_chunks(model, guidance, eta):
    audio = _audio(2.0 + 123 / 16000, 4)
    offline = generate_offline(model, audio, steps=5, seed=9, eta=eta, guidance=guidance, smoothing=None)
    assert offline.shape == (40, 12)
    assert not np.allclose(offline, generate_offline(model, audio, steps=5, seed=9, eta=eta, smoothing=None), atol=1e-3)
    for pattern in ([1, 2, 799, 801, 1601], [800], [3333]):  # 1 sample, odd lengths, one frame, not frame multiples
        s = GestureStream(model, steps=5, seed=9, eta=eta, smoothing=None, guidance=guidance)
        assert s.state.denoiser.batch == 2
        assert np.abs(push_in_pieces(s, audio, _sizes(len(audio), pattern)) - offline).max() < 1e-4


def test_guided_streams_batched_equal_guided_streams_alone(model, monkeypatch):
    """Scales 2, 1, 3, 0 and 2 with their own seeds, audio and chunking; one joins late, one leaves early."""
    rng = np.random.default_rng(0)
    specs = [  # (seed, guidance, seconds, start tick, chunk sizes)
        (11, 2.0, 2.4, 0, [1600]),
        (12, 1.0, 2.2, 0, [1600]),  # unguided, in the same batch as the guided ones
        (13, 3.0, 1.1, 0, [700, 2500, 1333]),  # leaves early
        (14, 0.0, 1.8, 5, [1600]),  # joins late
        (15, 2.0, 2.0, 1, [int(n) for n in rng.integers(300, 4000, 12)]),  # ragged
    ]
    plans = [(seed, g, _audio(sec, seed), start, _sizes(int(sec * 16000), sizes)) for seed, g, sec, start, sizes in specs]
    solo = [stream_in_pieces(model, audio, sizes, steps=4, seed=seed, smoothing=None, guidance=g)
            for seed, g, audio, _, sizes in plans]

    streams = [GestureStream(model, steps=4, seed=seed, smoothing=None, guidance=g) for seed, g, *_ in plans]
    runner, rows = streams[0].runner, []
    assert all(s.runner is runner for s in streams)
    sample = runner.sample
    monkeypatch.setattr(runner, "sample", lambda cond, starts, seeds, states, *a, **k: (
        rows.append(states.batch), sample(cond, starts, seeds, states, *a, **k))[1])  # the network rows of each batch
    outs, pos, done = [[] for _ in plans], [0] * len(plans), [False] * len(plans)
    tick = 0
    while not all(done):
        due = [i for i, p in enumerate(plans) if not done[i] and tick >= p[3]]
        pushing = [i for i in due if tick - plans[i][3] < len(plans[i][4])]
        chunks = []
        for i in pushing:
            n = plans[i][4][tick - plans[i][3]]
            chunks.append(plans[i][2][pos[i]:pos[i] + n])
            pos[i] += n
        for i, frames in zip(pushing, push_many([streams[i] for i in pushing], chunks)):
            outs[i].append(frames)
        for i in set(due) - set(pushing):
            outs[i].append(streams[i].finish())
            done[i] = True
        tick += 1
    assert max(rows) >= 6  # guided streams shared a batch: two rows each
    for i, (got, want) in enumerate(zip(outs, solo)):
        got = np.concatenate(got)
        assert got.shape == want.shape and np.abs(got - want).max() < TOL, (i, np.abs(got - want).max())


def test_guidance_is_validated(model):
    for bad in (-0.5, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="guidance"):
            GestureStream(model, guidance=bad)
        with pytest.raises(ValueError, match="guidance"):
            generate_offline(model, _audio(0.5, 0), guidance=bad)
    with pytest.raises(ValueError):
        get_preset("tiny", guidance=-1.0)


# ---------------- condition dropout in training ----------------
def test_dropped_condition_is_the_zero_condition():
    """A window whose condition is dropped trains the network fed zeros; kept windows are untouched."""
    model = _model()
    d = Diffusion(model.config)
    g = torch.Generator().manual_seed(0)
    x0, noise = torch.randn(3, 6, 12, generator=g), torch.randn(3, 6, 12, generator=g)
    feats = torch.randn(3, 6 * 5 + model.config.lookahead_feats, 20, generator=g)
    t = torch.tensor([5, 300, 900])
    with torch.no_grad():
        x_t = d.q_sample(x0, t, noise)
        out_null, _ = model(x_t, t, torch.zeros(3, 6, model.config.hidden))
        want = torch.nn.functional.mse_loss(out_null, d.target(x0, t, noise))
        assert torch.equal(d.training_loss(model, x0, feats, t, noise, drop=torch.ones(3, dtype=torch.bool)), want)
        plain = d.training_loss(model, x0, feats, t, noise)
        assert torch.equal(d.training_loss(model, x0, feats, t, noise, drop=torch.zeros(3, dtype=torch.bool)), plain)
        assert not torch.isclose(plain, want)
        # per window: dropping window 1 only changes window 1's share of the loss
        cond, _ = model.condition(feats)
        out_c, _ = model(x_t, t, cond[:, :6])
        mixed = torch.cat([out_c[:1], out_null[1:2], out_c[2:]])
        want = torch.nn.functional.mse_loss(mixed, d.target(x0, t, noise))
        got = d.training_loss(model, x0, feats, t, noise, drop=torch.tensor([False, True, False]))
        assert torch.allclose(got, want, rtol=1e-6)


STEPS = 30  # of the `runs` below: resuming is exact and dropout changes the weights at any length


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny model trained with condition dropout 0.5: whole, and interrupted halfway then resumed."""
    root = tmp_path_factory.mktemp("cfg")
    make_synthetic_pair(root / "data", "a", seconds=24.0, seed=0)

    def opts(out, **kw):
        base = dict(data=str(root / "data"), out=str(root / out), preset="tiny", max_steps=STEPS, batch_size=4,
                    lr=3e-3, warmup=10, window_s=2.0, ckpt_every=STEPS // 2, valid_every=STEPS // 2, ema=0.9, seed=0,
                    device="cpu", cache_dir=str(root / "cache"), progress=False, valid_fraction=0.2, cond_drop=0.5)
        return TrainConfig(**{**base, **kw})

    whole = train(opts("whole"))
    train(opts("part", max_steps=STEPS // 2))
    resumed = train(opts("part", resume=True))
    no_drop = train(opts("no_drop", max_steps=STEPS // 2, cond_drop=0.0))
    return {"root": root, "whole": whole, "resumed": resumed, "part_half": root / "part" / f"ckpt_{STEPS // 2:07d}",
            "no_drop_half": no_drop}


def test_resume_is_exact_with_condition_dropout(runs):
    a, b = load_checkpoint(runs["whole"]).model.state_dict(), load_checkpoint(runs["resumed"]).model.state_dict()
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-6), k
    # and the dropout did change the training (same seed, batches, t and noise otherwise)
    p = load_checkpoint(runs["part_half"]).model.state_dict()
    q = load_checkpoint(runs["no_drop_half"]).model.state_dict()
    assert any(not torch.allclose(p[k], q[k], atol=1e-4) for k in p)


def test_guidance_extrapolates_from_the_unconditional_towards_the_conditional(runs):
    """On the model trained with dropout: scale 0 is the unconditional model (blind to the audio), and with one
    sampler step (x0 linear in the network output) scale s lands at out_u + s (out_c - out_u) exactly."""
    model = load_checkpoint(runs["whole"]).model
    a, b = _audio(2.0, 1), _audio(2.0, 2) * 3
    g0, g1 = generate_offline(model, a, steps=1, seed=3, guidance=0.0), generate_offline(model, a, steps=1, seed=3)
    assert np.array_equal(g0, generate_offline(model, b, steps=1, seed=3, guidance=0.0))  # the audio is not seen
    assert np.abs(g1 - generate_offline(model, b, steps=1, seed=3)).max() > 1e-3  # the conditional model hears it
    for s in (0.5, 2.0, 3.5):
        gs = generate_offline(model, a, steps=1, seed=3, guidance=s)
        assert np.abs(gs - (g0 + s * (g1 - g0))).max() < 1e-4 * max(1.0, s)
    g4 = generate_offline(model, a, steps=4, seed=3, guidance=2.0)
    assert np.isfinite(g4).all() and np.abs(g4 - generate_offline(model, a, steps=4, seed=3)).max() > 1e-3


def test_recipes_and_options_set_the_dropout():
    assert resolve_cond_drop(TrainConfig(data="", out="")) == 0.0  # the streaming recipe: none until measured
    assert resolve_cond_drop(TrainConfig(data="", out="", cond_drop=0.2)) == 0.2
    assert resolve_cond_drop(TrainConfig(data="", out="", recipe=None)) == 0.0
    with pytest.raises(ValueError, match="cond_drop"):
        resolve_cond_drop(TrainConfig(data="", out="", cond_drop=1.5))


# ---------------- the command line ----------------
def test_cli_generate_export_and_train_options(runs, tmp_path, monkeypatch, capsys):
    from dimgestor.audio import save_wav
    from dimgestor.bvh import read_bvh

    save_wav(tmp_path / "speech.wav", _audio(1.0, 5), 16000)
    common = ["generate", "--checkpoint", str(runs["whole"]), "--audio", str(tmp_path / "speech.wav"), "--steps", "2"]
    assert main(common + ["--out", str(tmp_path / "plain.bvh")]) == 0
    assert main(common + ["--out", str(tmp_path / "g2.bvh"), "--guidance", "2"]) == 0
    plain, g2 = read_bvh(tmp_path / "plain.bvh").values, read_bvh(tmp_path / "g2.bvh").values
    assert plain.shape == g2.shape and not np.allclose(plain, g2)

    exported = tmp_path / "exported"  # export sets the default that generate then uses when not told
    assert main(["export", "--checkpoint", str(runs["whole"]), "--out", str(exported), "--guidance", "2"]) == 0
    assert json.loads((exported / "config.json").read_text())["model"]["guidance"] == 2.0
    assert load_checkpoint(exported).config.guidance == 2.0
    assert main(["generate", "--checkpoint", str(exported), "--audio", str(tmp_path / "speech.wav"), "--steps", "2",
                 "--out", str(tmp_path / "default.bvh")]) == 0
    assert np.allclose(read_bvh(tmp_path / "default.bvh").values, g2)
    capsys.readouterr()
    assert main(common + ["--out", str(tmp_path / "bad.bvh"), "--guidance", "-1"]) == 2
    assert "guidance" in capsys.readouterr().err
    assert main(["export", "--checkpoint", str(runs["whole"]), "--out", str(tmp_path / "e2"), "--guidance", "nan"]) == 2

    import dimgestor.training.train as train_module
    seen = {}
    monkeypatch.setattr(train_module, "train", lambda opts: seen.setdefault("opts", opts) and tmp_path)
    base = ["train", "--data", str(runs["root"] / "data"), "--out", str(tmp_path / "r"),
            "--cache-dir", str(runs["root"] / "cache")]
    assert main(base + ["--cond-drop", "0.1"]) == 0 and seen["opts"].cond_drop == 0.1
    seen.clear()
    assert main(base) == 0 and seen["opts"].cond_drop is None
    assert main(base + ["--cond-drop", "2"]) == 2
