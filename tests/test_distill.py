"""`dimgestor distill` (issue 50): a guided K-step teacher distilled into a 1- or 2-pass student on the synthetic
fixture: the held-out distillation loss falls, the student's checkpoint samples in its passes without guidance, it
streams exactly (any chunking equals the whole recording) and its batched streams equal each stream alone."""
import json

import numpy as np
import pytest

from dimgestor.streaming.batch import push_many
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.streaming.stream import GestureStream, generate_offline
from dimgestor.training.distill import DistillConfig, distill
from dimgestor.training.synthetic import make_synthetic_pair
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


@pytest.fixture(scope="module", params=[1, 2])
def student(request, data, teacher, tmp_path_factory):
    out = tmp_path_factory.mktemp(f"student{request.param}")
    last = distill(DistillConfig(checkpoint=str(teacher), out=str(out / "run"), steps=request.param, data=str(data),
                                 max_steps=80, batch_size=4, lr=2e-3, warmup=5, aug_copies=1, valid_every=40,
                                 ckpt_every=80, cache_dir=str(out / "cache")), progress=False)
    return request.param, out / "run", last


def test_the_held_out_distillation_loss_falls_and_the_student_samples_in_its_passes(student, teacher):
    steps, run, last = student
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [0, 40, 80]
    assert log[-1]["valid_loss"] < 0.7 * log[0]["valid_loss"], log
    b, t = load_checkpoint(last), load_checkpoint(teacher)
    assert (b.config.sample_steps, b.config.guidance) == (steps, 1.0)
    assert (t.config.sample_steps, t.config.guidance) == (4, 1.5)
    assert b.info["distilled_from"] == str(teacher) and b.info["teacher"] == {"sample_steps": 4, "guidance": 1.5}
    stream = b.stream()
    assert len(stream.pairs) == steps and stream.guidance == 1.0
    assert stream.state.denoiser.batch == 1  # one row: no unconditional branch
    assert {k: v for k, v in b.config.model_dump().items() if k not in ("sample_steps", "guidance")} == \
        {k: v for k, v in t.config.model_dump().items() if k not in ("sample_steps", "guidance")}


def test_the_student_streams_exactly_and_its_batch_equals_each_stream_alone(student):
    _, _, last = student
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


def test_a_run_goes_on_from_an_earlier_student(student, teacher, data, tmp_path):
    """--init: the student starts from an earlier run's checkpoint (its held-out loss where that run ended), and one
    of another number of passes is refused."""
    steps, run, last = student
    before = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()][-1]["valid_loss"]
    common = dict(checkpoint=str(teacher), data=str(data), max_steps=2, batch_size=4, lr=2e-3, warmup=1,
                  aug_copies=1, valid_every=2, ckpt_every=2, cache_dir=str(tmp_path / "cache"))
    distill(DistillConfig(out=str(tmp_path / "on"), init=str(last), steps=steps, **common), progress=False)
    log = [json.loads(line) for line in (tmp_path / "on" / "log.jsonl").read_text().splitlines()]
    assert log[0]["step"] == 0 and log[0]["valid_loss"] == pytest.approx(before, rel=1e-5)
    with pytest.raises(ValueError, match="not of --steps"):
        distill(DistillConfig(out=str(tmp_path / "other"), init=str(last), steps=3 - steps, **common), progress=False)
