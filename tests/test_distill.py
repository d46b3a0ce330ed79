"""`dimgestor distill` (issue 50): a guided K-step teacher distilled into a 1- or 2-pass student, or a K-pass one
with its guidance folded in, or an unguided one distilled progressively into half its steps, on the synthetic
fixture: the held-out distillation loss falls, the student's checkpoint samples in its passes without guidance, it
streams exactly (any chunking equals the whole recording) and its batched streams equal each stream alone."""
import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from pydantic import ValidationError

from dimgestor.streaming.batch import push_many
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.streaming.stream import GestureStream, generate_offline
from dimgestor.audio import save_wav
from dimgestor.model.diffusion import Diffusion
from dimgestor.training.distill import (GAIN_RANGE, DistillConfig, SpeechBank, calibration, distill, student_pairs,
                                        teacher_spans, teacher_steps)
from dimgestor.training.synthetic import make_synthetic_pair, synthetic_speech
from dimgestor.training.train import TrainConfig, train
from helpers.stream import noise_audio, stream_in_pieces


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("distilldata")
    make_synthetic_pair(root, "a", seconds=24.0, seed=0)
    return root


@pytest.fixture(scope="module")
def teacher(data, tmp_path_factory):
    """A tiny model trained briefly with condition dropout, sampled with 4 steps and guidance 1.5."""
    out = tmp_path_factory.mktemp("teacher")
    return train(TrainConfig(data=str(data), out=str(out / "run"), preset="tiny", max_steps=60, batch_size=4, lr=3e-3,
                             warmup=10, window_s=2.0, ckpt_every=60, valid_every=0, ema=0.9, seed=0, device="cpu",
                             cache_dir=str(out / "cache"), progress=False, valid_fraction=0.2, cond_drop=0.2,
                             overrides={"guidance": 1.5, "sample_steps": 4}))


# (steps, the teacher's guidance): 4 is the teacher's own steps, its guidance folded in; 2 of the teacher unguided
# learns progressively, each step two of the teacher's
@pytest.fixture(scope="module", params=[(1, None), (2, None), (4, None), (2, 1.0)],
                ids=["1", "2", "4", "2-progressive"])
def student(request, data, teacher, tmp_path_factory):
    steps, guidance = request.param
    out = tmp_path_factory.mktemp(f"student{steps}")
    last = distill(DistillConfig(checkpoint=str(teacher), out=str(out / "run"), steps=steps, guidance=guidance,
                                 data=str(data), max_steps=80, batch_size=4, lr=2e-3, warmup=5, aug_copies=1,
                                 valid_every=40, ckpt_every=80, cache_dir=str(out / "cache")), progress=False)
    return steps, out / "run", last, guidance


def test_the_held_out_distillation_loss_falls_and_the_student_samples_in_its_passes(student, teacher):
    steps, run, last, guidance = student
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [0, 40, 80]
    assert log[-1]["valid_loss"] < 0.7 * log[0]["valid_loss"], log
    b, t = load_checkpoint(last), load_checkpoint(teacher)
    assert (b.config.sample_steps, b.config.guidance) == (steps, 1.0)
    assert (t.config.sample_steps, t.config.guidance) == (4, 1.5)
    assert b.info["distilled_from"] == str(teacher)
    assert b.info["teacher"] == {"sample_steps": 4, "guidance": guidance or 1.5, "step": t.info["step"],  # (its run's)
                                 "history": t.info["history"], "train_wall_s": t.info["train_wall_s"]}
    method = {1: "chain", 2: "chain" if guidance is None else "progressive", 4: "fold"}[steps]
    assert b.info["method"] == method
    t_pairs = t.stream().pairs
    assert b.stream().pairs == {"chain": Diffusion(b.config).sampling_pairs("ddim", steps), "fold": t_pairs,
                                "progressive": [(t_pairs[0][0], t_pairs[1][1]), (t_pairs[2][0], -1)]}[method]
    assert b.config.ddim_timesteps == (None if method == "chain" else tuple(t for t, _ in b.stream().pairs))
    stream = b.stream()
    assert len(stream.pairs) == steps and stream.guidance == 1.0
    assert stream.state.denoiser.batch == 1  # one row: no unconditional branch
    own = ("sample_steps", "guidance", "ddim_timesteps")
    assert {k: v for k, v in b.config.model_dump().items() if k not in own} == \
        {k: v for k, v in t.config.model_dump().items() if k not in own}
    assert "calibration" not in b.info and not hasattr(b.model, "out_gain")  # (--calibrate: not by default)


def test_the_student_streams_exactly_and_its_batch_equals_each_stream_alone(student):
    _, _, last, _ = student
    model = load_checkpoint(last).model
    audio = noise_audio(2.0 + 77 / 16000, seed=4)
    offline = generate_offline(model, audio, seed=5, smoothing=None)
    assert np.abs(offline).max() > 0.05
    rng = np.random.default_rng(1)
    for _ in range(3):
        sizes = list(rng.integers(1, 5000, 40))
        sizes = [s for s in np.diff([0, *np.cumsum(sizes)[np.cumsum(sizes) < len(audio)], len(audio)])]
        assert np.abs(stream_in_pieces(model, audio, sizes, seed=5, smoothing=None) - offline).max() < 1e-4  # (test_stream)
    others = [noise_audio(1.5, seed=s) for s in (7, 8)]
    alone = [generate_offline(model, a, seed=s, smoothing=None) for s, a in zip((11, 12), others)]
    streams = [GestureStream(model, seed=s, smoothing=None) for s in (11, 12)]
    got = [[], []]
    for a in range(0, len(others[0]), 1600):
        for i, frames in enumerate(push_many(streams, [x[a:a + 1600] for x in others])):
            got[i].append(frames)
    for i, s in enumerate(streams):
        got[i].append(s.finish())
        assert np.abs(np.concatenate(got[i]) - alone[i]).max() < 1e-5, i


def test_the_calibration_gives_a_student_that_moves_less_its_teachers_spread_and_mean():
    """Per feature: the ratio of the frame-to-frame changes' spreads (inside each window, not across two), the
    teacher's mean after it; 1 where the teacher's feature stands still; within GAIN_RANGE."""
    g = torch.Generator().manual_seed(0)
    teacher = [torch.randn(3, 50, 4, generator=g).cumsum(1), torch.randn(2, 30, 4, generator=g).cumsum(1)]
    for x in teacher:
        x[..., 2] = 0.7  # a feature that does not move
    student = [torch.stack([0.8 * x[..., 0] + 0.3, 0.5 * x[..., 1], x[..., 2] + 0.1, 0.01 * x[..., 3]], -1)
               for x in teacher]
    student[1] = student[1] + 5.0  # (a jump between windows is no change: only changes inside windows count)
    gain, shift = calibration(teacher, student)
    assert gain[:3].tolist() == pytest.approx([1.25, 2.0, 1.0], rel=1e-5) and gain[3] == GAIN_RANGE[1]
    mean = lambda xs: torch.cat([x.flatten(0, 1) for x in xs]).mean(0)  # noqa: E731
    fixed = [x * gain + shift for x in student]
    assert mean(fixed)[:3].tolist() == pytest.approx(mean(teacher)[:3].tolist(), abs=1e-4)
    assert all(torch.allclose(f[..., 0], t[..., 0] + (f[..., 0] - t[..., 0]).mean(), atol=1e-4)
               for f, t in zip(fixed, teacher))


def test_a_calibrated_students_motion_is_scaled_wherever_it_is_sampled(teacher, data, tmp_path):
    """--calibrate: the checkpoint holds its calibration (measured at the save, recorded in its info); offline and
    streamed motion are the student's own motion scaled and shifted by it."""
    last = distill(DistillConfig(checkpoint=str(teacher), out=str(tmp_path / "run"), steps=2, data=str(data),
                                 calibrate=True, calibration_windows=12, max_steps=20, batch_size=4, lr=2e-3, warmup=5,
                                 aug_copies=1, valid_every=0, ckpt_every=20, cache_dir=str(tmp_path / "cache")),
                   progress=False)
    b = load_checkpoint(last)
    assert b.config.calibrated and b.info["distill"]["calibrate"]
    gain, shift = b.model.out_gain, b.model.out_shift
    info = b.info["calibration"]
    assert info["windows"] == 12 and info["gain_min"] == pytest.approx(gain.min().item())
    assert (gain - 1).abs().max() > 1e-3 and GAIN_RANGE[0] <= gain.min() <= gain.max() <= GAIN_RANGE[1]
    audio = noise_audio(1.5, seed=3)
    got = generate_offline(b.model, audio, seed=2, smoothing=None)
    streamed = stream_in_pieces(b.model, audio, [1234] * 19 + [len(audio) - 1234 * 19], seed=2, smoothing=None)
    b.model.out_gain, b.model.out_shift = torch.ones_like(gain), torch.zeros_like(shift)
    plain = generate_offline(b.model, audio, seed=2, smoothing=None)
    assert np.abs(got - (plain * gain.numpy() + shift.numpy())).max() < 1e-5
    assert np.abs(streamed - got).max() < 1e-4


def test_a_run_goes_on_from_an_earlier_student(student, teacher, data, tmp_path):
    """--init: the student starts from an earlier run's checkpoint (its held-out loss where that run ended), and one
    of another number of passes is refused."""
    steps, run, last, guidance = student
    before = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()][-1]["valid_loss"]
    common = dict(checkpoint=str(teacher), guidance=guidance, data=str(data), max_steps=2, batch_size=4, lr=2e-3,
                  warmup=1, aug_copies=1, valid_every=2, ckpt_every=2, cache_dir=str(tmp_path / "cache"))
    distill(DistillConfig(out=str(tmp_path / "on"), init=str(last), steps=steps, **common), progress=False)
    log = [json.loads(line) for line in (tmp_path / "on" / "log.jsonl").read_text().splitlines()]
    assert log[0]["step"] == 0 and log[0]["valid_loss"] == pytest.approx(before, rel=1e-5)
    with pytest.raises(ValueError, match="not of --steps"):
        distill(DistillConfig(out=str(tmp_path / "other"), init=str(last), steps={1: 2, 2: 1, 4: 2}[steps], **common),
                progress=False)


def test_a_student_of_a_student_keeps_its_lineage(teacher, data, tmp_path):
    """A 2-step student of a folded student (the shipped recipe's chain) records its teacher's own teacher, so the
    first guided model's scale and training stay in its info."""
    common = dict(data=str(data), max_steps=2, batch_size=4, lr=2e-3, warmup=1, aug_copies=1, valid_every=2,
                  ckpt_every=2, cache_dir=str(tmp_path / "cache"))
    folded = distill(DistillConfig(checkpoint=str(teacher), out=str(tmp_path / "fold"), steps=4, **common),
                     progress=False)
    halved = distill(DistillConfig(checkpoint=str(folded), out=str(tmp_path / "half"), steps=2, **common),
                     progress=False)
    f, h = load_checkpoint(folded), load_checkpoint(halved)
    assert (f.info["method"], h.info["method"]) == ("fold", "progressive")
    assert h.info["teacher"]["teacher"] == f.info["teacher"] and f.info["teacher"]["guidance"] == 1.5
    assert (h.info["teacher"]["sample_steps"], h.info["teacher"]["guidance"]) == (4, 1.0)


def test_a_student_of_the_teachers_own_steps_learns_each_steps_guided_output(student, teacher, data):
    """--steps K of a K-step teacher: each step of the student's chain, on the teacher's noisy motion of that step,
    gives nearer the guided output of the teacher's two rows than the teacher's conditional row alone does (where
    the student started)."""
    steps, _, last, _ = student
    if steps != 4:
        pytest.skip("a student of fewer steps learns the whole chain, or its teacher's steps two at a time")
    b, t = load_checkpoint(last), load_checkpoint(teacher)
    diffusion = Diffusion(t.config)
    pairs = diffusion.sampling_pairs("ddim", 4)
    assert b.stream().pairs == t.stream().pairs == pairs
    fe = t.model.frontend
    feats = fe(torch.from_numpy(noise_audio(2.5, seed=9))[None], fe.init_state(1, "cpu"))[0]
    with torch.no_grad():
        cond_t, _ = t.model.condition(feats)
        x = diffusion.noise_like(torch.zeros(2, cond_t.shape[1], t.config.motion_dim), torch.Generator().manual_seed(3))
        xs, ts, target = teacher_steps(t.model, diffusion, pairs, cond_t.expand(2, -1, -1), x, 1.5)
        assert ts.tolist() == [p[0] for p in pairs for _ in range(2)]
        before = t.model(xs, ts, cond_t.expand(8, -1, -1))[0]
        after = b.model(xs, ts, b.model.condition(feats)[0].expand(8, -1, -1))[0]
    for k in range(4):
        rows = slice(2 * k, 2 * k + 2)
        assert F.mse_loss(after[rows], target[rows]) < 0.7 * F.mse_loss(before[rows], target[rows]), k


def test_a_student_of_more_steps_than_its_teacher_or_of_its_steps_without_guidance_is_refused(teacher, data, tmp_path):
    common = dict(checkpoint=str(teacher), data=str(data), max_steps=1, batch_size=2, valid_every=0,
                  cache_dir=str(tmp_path / "cache"))
    cases = [(dict(steps=5), "--steps 5: more than the teacher's own 4 steps"),
             (dict(steps=4, guidance=1.0), "--steps 4: the teacher already samples in 4 passes of one row"),
             (dict(steps=4, spread_weight=1.0), "--spread-weight: for a student that learns its teacher's whole"),
             (dict(steps=2, guidance=1.0, spread_weight=1.0), "not a progressive one")]
    for k, (args, words) in enumerate(cases):
        with pytest.raises(ValueError, match=words):
            distill(DistillConfig(out=str(tmp_path / f"o{k}"), **args, **common), progress=False)
        assert not (tmp_path / f"o{k}").exists()


def test_a_progressive_students_step_lands_nearer_where_its_teachers_two_steps_land(student, teacher):
    """An unguided teacher's --steps 2: each student step, from the teacher's noisy motion where a span of two of
    the teacher's steps starts, lands (one DDIM step) nearer where those two land than the teacher's one step from
    there does (where the student started)."""
    steps, _, last, guidance = student
    if guidance is None:
        pytest.skip("a guided teacher's student folds its guidance in or learns the whole chain")
    b, t = load_checkpoint(last), load_checkpoint(teacher)
    diffusion = Diffusion(t.config)
    pairs, mine = diffusion.sampling_pairs("ddim", 4), b.stream().pairs

    def land(x, x0, t0, t1):  # one DDIM step (eta 0) with this x0
        eps = (x - diffusion.a(t0) ** 0.5 * x0) / (1 - diffusion.a(t0)) ** 0.5
        return diffusion.ddim_step(x, eps, t0, t1, x0=x0)[0]

    fe = t.model.frontend
    feats = fe(torch.from_numpy(noise_audio(2.5, seed=9))[None], fe.init_state(1, "cpu"))[0]
    with torch.no_grad():
        cond_t, _ = t.model.condition(feats)
        x = diffusion.noise_like(torch.zeros(2, cond_t.shape[1], t.config.motion_dim), torch.Generator().manual_seed(3))
        xs, ts, target = teacher_spans(t.model, diffusion, pairs, 2, cond_t.expand(2, -1, -1), x)
        assert ts.tolist() == [t0 for t0, _ in mine for _ in range(2)]
        for k, (t0, t1) in enumerate(mine):
            rows = slice(2 * k, 2 * k + 2)
            lands = land(xs[rows], target[rows], t0, t1)  # (where the teacher's two land)
            got = {}
            for name, m in (("before", t.model), ("after", b.model)):
                x0 = diffusion.split(m(xs[rows], t0, m.condition(feats)[0].expand(2, -1, -1))[0], xs[rows], t0)[1]
                got[name] = F.mse_loss(land(xs[rows], x0, t0, t1), lands)
            assert got["after"] < 0.7 * got["before"], (k, got)


def test_a_students_way_of_learning_and_its_steps_follow_its_teachers():
    """fold: the teacher's own steps, guided; progressive: a one-row teacher's steps r at a time (every r-th of its
    timesteps); chain: anything else, on ddim_pairs."""
    from dimgestor.model.diffusion import ddim_pairs

    four = ddim_pairs(4, 8, "linspace")
    assert four == [(7, 5), (5, 2), (2, 0), (0, -1)]
    assert student_pairs(four, 4, 1.25, 8, "linspace") == ("fold", four)
    assert student_pairs(four, 2, 1.0, 8, "linspace") == ("progressive", [(7, 2), (2, -1)])
    assert student_pairs(four, 1, 1.0, 8, "linspace") == ("progressive", [(7, -1)])
    assert student_pairs(four, 2, 1.25, 8, "linspace") == ("chain", [(7, 0), (0, -1)])
    assert student_pairs(four, 3, 1.0, 8, "linspace") == ("chain", ddim_pairs(3, 8, "linspace"))
    with pytest.raises(ValueError, match="more than the teacher's own 4"):
        student_pairs(four, 5, 1.25, 8, "linspace")
    with pytest.raises(ValueError, match="already samples in 4 passes"):
        student_pairs(four, 4, 1.0, 8, "linspace")


@pytest.fixture(scope="module")
def speech(tmp_path_factory):
    """Speech without motion: two synthetic voices of 7 and 3.3 s in a folder (one in a sub-folder), as 22.05 kHz
    files (resampled as they are read)."""
    root = tmp_path_factory.mktemp("speech")
    (root / "more").mkdir()
    save_wav(root / "a.wav", synthetic_speech(7.0, 22050, 21), 22050)
    save_wav(root / "more" / "b.wav", synthetic_speech(3.3, 22050, 22), 22050)
    return root


def test_speech_without_motion_is_cut_into_windows_each_heard_as_a_stream_hears_its_file(teacher, speech):
    model = load_checkpoint(teacher).model
    c = model.config
    frames = 40  # 2 s windows every 1 s: 7 s gives 6 windows, 3.3 s gives 2
    bank = SpeechBank([speech], model, frames, "cpu", copies=2, seed=3)
    assert [f.name for f in bank.files] == ["a.wav", "b.wav"] and len(bank) == 8
    n = frames * c.feats_per_frame + c.lookahead_feats
    assert all(f.shape[:2] == (3, n) for f in bank.feats)
    clean, versions = bank.feats[2][0], bank.feats[2][1:]
    assert all((v - clean).abs().max() > 1e-3 for v in versions) and (versions[0] - versions[1]).abs().max() > 1e-3
    # window 2 starts 2 s into a.wav: the front end streamed over the file in pieces gives the same features there
    from dimgestor.audio import load_wav
    audio = load_wav(speech / "a.wav", c.sample_rate)
    fe, state, got = model.frontend, model.frontend.init_state(1, "cpu"), []
    for a in range(0, len(audio), 3001):
        f, state = fe(torch.from_numpy(audio[a:a + 3001])[None], state)
        got.append(f[0])
    whole = torch.cat(got)
    a = 2 * c.fps * c.feats_per_frame
    assert (whole[a:a + frames * c.feats_per_frame] - clean[: frames * c.feats_per_frame]).abs().max() < 1e-4
    assert bank.batch([0, 7, 3], torch.Generator().manual_seed(0)).shape == (3, n, clean.shape[1])


def test_a_student_learns_from_speech_without_motion_too(teacher, data, speech, tmp_path):
    last = distill(DistillConfig(checkpoint=str(teacher), out=str(tmp_path / "run"), steps=2, data=str(data),
                                 audio=(str(speech),), audio_share=0.5, max_steps=60, batch_size=4, lr=2e-3, warmup=5,
                                 aug_copies=1, valid_every=60, ckpt_every=60, cache_dir=str(tmp_path / "cache")),
                   progress=False)
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert log[-1]["valid_loss"] < 0.7 * log[0]["valid_loss"], log
    info = load_checkpoint(last).info["distill"]
    assert info["audio"] == [str(speech)] and info["audio_share"] == 0.5


def test_a_student_with_the_spread_loss_learns_and_records_its_weight(teacher, data, tmp_path):
    """--spread-weight: half of each batch repeats the other half's windows with other noise, and the difference
    between the two motions is learnt as well."""
    last = distill(DistillConfig(checkpoint=str(teacher), out=str(tmp_path / "run"), steps=2, data=str(data),
                                 spread_weight=2.0, max_steps=60, batch_size=4, lr=2e-3, warmup=5, aug_copies=1,
                                 valid_every=60, ckpt_every=60, cache_dir=str(tmp_path / "cache")), progress=False)
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert log[-1]["valid_loss"] < 0.7 * log[0]["valid_loss"], log
    assert load_checkpoint(last).info["distill"]["spread_weight"] == 2.0


def test_speech_that_cannot_be_read_is_refused_by_name(teacher, data, tmp_path):
    common = dict(checkpoint=str(teacher), data=str(data), max_steps=1, batch_size=2, valid_every=0,
                  cache_dir=str(tmp_path / "cache"))
    (tmp_path / "empty").mkdir()
    (tmp_path / "bad.wav").write_bytes(b"RIFF not a wave")
    save_wav(tmp_path / "short.wav", synthetic_speech(0.5, 16000, 1), 16000)
    cases = [(tmp_path / "missing", FileNotFoundError, "missing: no such file"),
             (tmp_path / "empty", ValueError, "empty: no .wav files"),
             (tmp_path / "bad.wav", ValueError, "bad.wav: not a readable WAV"),
             (tmp_path / "short.wav", ValueError, "no file is as long as one window")]
    for k, (path, error, words) in enumerate(cases):
        with pytest.raises(error, match=words):
            distill(DistillConfig(out=str(tmp_path / f"o{k}"), audio=(str(path),), **common), progress=False)
        assert not (tmp_path / f"o{k}").exists()


def test_the_teachers_guidance_may_be_set_and_is_recorded(teacher, data, tmp_path):
    """--guidance S: the teacher's chain runs at scale S instead of its config's (1.5 here): the targets, so the
    held-out distillation loss before the first step, differ."""
    first = {}
    for scale in (None, 2.5):
        run = tmp_path / f"run_{scale}"
        last = distill(DistillConfig(checkpoint=str(teacher), out=str(run), steps=2, data=str(data), guidance=scale,
                                     max_steps=1, batch_size=2, valid_every=1, ckpt_every=1, aug_copies=0,
                                     cache_dir=str(tmp_path / "cache")), progress=False)
        first[scale] = json.loads((run / "log.jsonl").read_text().splitlines()[0])["valid_loss"]
        b = load_checkpoint(last)
        assert (b.info["teacher"]["sample_steps"], b.info["teacher"]["guidance"]) == (4, scale or 1.5)
        assert b.config.guidance == 1.0
    assert abs(first[2.5] - first[None]) > 1e-3 * first[None], first
    with pytest.raises(ValidationError, match="greater than 0"):
        DistillConfig(out="x", guidance=0)
