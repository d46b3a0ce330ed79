"""Training past one process (issue 22, item 5): `torchrun` with 2 CPU processes (gloo) takes the same steps as one
process with the same global batch: every rank draws the whole batch (windows, versions, diffusion steps, noise,
dropout) from the same generator and trains on its half, and DDP averages the gradients. Resume works, and only
rank 0 writes.

What the order of float sums cannot change is compared exactly: the steps, every rank's draws (its generator's
state) and a resumed run against one that was never interrupted (the same processes, the same sums). The weights
and losses of one process and of two differ by rounding alone (a batch gradient summed in one matmul, or as two
halves added by gloo), by an amount that depends on the machine's kernels. So the bound is measured on the machine
running the test: a second one-process run with the same draws whose only difference is the order of its sums
(ATen's scalar kernels, ATEN_CPU_CAPABILITY=default, instead of its vector ones) shows how far rounding alone moves
this training here; two processes must stay within SPREAD times that. A process that trained on the wrong half,
or drew a different batch, moves the weights by about a learning-rate step (1e-3 of them), far outside."""
import json
import os
import shutil
import subprocess
import sys

import pytest
import torch

from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.training.synthetic import make_synthetic_pair
from dimgestor.training.train import TrainConfig, train

pytestmark = pytest.mark.timeout(300)
TORCHRUN = shutil.which("torchrun", path=os.path.dirname(sys.executable)) or shutil.which("torchrun")
SPREAD = 10  # how many times the measured rounding spread two processes may differ from one (0.3x measured here)
EPS32 = float(torch.finfo(torch.float32).eps)  # (the spread is at least float32's resolution of what is compared)
COMMON = dict(preset="tiny", batch_size=4, lr=3e-3, warmup=2, window_s=2.0, valid_fraction=0.2, valid_every=2,
              ckpt_every=2, seed=0, augment=True, aug_copies=1, cond_drop=0.1)


def _flags(options: dict) -> list[str]:
    flags = []
    for k, v in options.items():
        flag = "--" + k.replace("_", "-")
        flags += [flag] if v is True else [f"--no-{k.replace('_', '-')}"] if v is False else [flag, str(v)]
    return flags


def _log(run):
    return [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]


def _state(run, step=6):
    return torch.load(run / f"ckpt_{step:07d}" / "train_state.pt", map_location="cpu", weights_only=False)


def _distance(a: dict, b: dict) -> float:
    """The Euclidean distance between two models' weights (all tensors as one vector)."""
    return sum(float(((a[k].double() - b[k].double()) ** 2).sum()) for k in a) ** 0.5


@pytest.mark.skipif(TORCHRUN is None, reason="torchrun (installed with torch) not found")
def test_two_processes_take_the_same_steps_as_one_with_the_same_global_batch_and_resume(tmp_path):
    data, cache = tmp_path / "data", tmp_path / "cache"
    make_synthetic_pair(data, "a", seconds=24.0, seed=0)

    def cli(out: str, max_steps: int, *extra: str, launcher: tuple[str, ...] = (sys.executable,), **env) -> None:
        cmd = [*launcher, "-m", "dimgestor_app.cli", "train", "--data", str(data), "--out", str(tmp_path / out),
               "--max-steps", str(max_steps), "--cache-dir", str(cache), "--no-progress", "--threads", "1",
               "--device", "cpu", *_flags(COMMON), *extra]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=240,
                           env={**os.environ, "OMP_NUM_THREADS": "1", **env})
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
        assert f"world {2 if len(launcher) > 1 else 1}," in r.stdout

    def torchrun(max_steps: int, *extra: str) -> None:
        cli("two", max_steps, *extra, launcher=(TORCHRUN, "--standalone", "--nproc_per_node", "2"))

    cli("one", 6)  # one process, 6 steps of 4 windows
    cli("scalar", 6, ATEN_CPU_CAPABILITY="default")  # the same, its sums in another order: rounding's spread here
    cli("straight", 6, launcher=(TORCHRUN, "--standalone", "--nproc_per_node", "2"))  # two processes (2 windows each)
    # ... and the same run as if stopped at step 4 (what a run with --max-steps 4 leaves: the lr schedule does not
    # depend on --max-steps), resumed by two new processes
    shutil.copytree(tmp_path / "straight", tmp_path / "two", ignore=shutil.ignore_patterns("ckpt_0000006"))
    (tmp_path / "two" / "log.jsonl").write_text("".join(
        json.dumps(r) + "\n" for r in _log(tmp_path / "straight") if r["step"] <= 4))
    torchrun(6, "--resume")

    # (1) exactly: the same steps, and every rank drew the same global batches as the one process did
    one, two = _state(tmp_path / "one"), _state(tmp_path / "two")
    assert [r["step"] for r in _log(tmp_path / "one")] == [r["step"] for r in _log(tmp_path / "two")] == [0, 2, 4, 6]
    assert len(two["generators"]) == 2
    assert all(torch.equal(g, one["generators"][0]) for g in two["generators"])
    assert torch.equal(two["torch_rng"], one["torch_rng"])
    # (2) exactly: resuming two processes continues as if never interrupted (the same processes add in one order)
    straight = _state(tmp_path / "straight")
    assert _distance(two["model"], straight["model"]) == 0 and _distance(two["ema"], straight["ema"]) == 0
    assert _log(tmp_path / "two")[-1]["valid_loss"] == _log(tmp_path / "straight")[-1]["valid_loss"]
    assert torch.equal(two["optimizer"]["state"][0]["exp_avg_sq"], straight["optimizer"]["state"][0]["exp_avg_sq"])

    # (3) within rounding: the weights (the EMA that is saved, and the trained ones) and the losses
    wa, ws, wb = (load_checkpoint(tmp_path / n).model.state_dict() for n in ("one", "scalar", "two"))
    for x, y, s in [(wa, wb, ws), (one["model"], two["model"], _state(tmp_path / "scalar")["model"])]:
        spread = max(_distance(x, s), EPS32 * _distance(x, {k: 0 * v for k, v in x.items()}))
        d = _distance(x, y)
        print(f"weights: two processes {d:.2e} from one; rounding alone {spread:.2e}")
        assert d <= SPREAD * spread, f"two processes' weights {d:.2e} from one process's; rounding moves {spread:.2e}"
    a, s, b = (_log(tmp_path / n) for n in ("one", "scalar", "two"))
    for key, steps in [("valid_loss", (0, 2, 4, 6)), ("train_loss", (2, 4))]:  # (train: smoothed, anew on --resume)
        x, y, z = ([r[key] for r in log if r["step"] in steps] for log in (a, b, s))
        spread = max(max(abs(p - q) for p, q in zip(x, z)), EPS32 * max(x))
        assert max(abs(p - q) for p, q in zip(x, y)) <= SPREAD * spread, (key, x, y, z)
    # one writer: rank 0's checkpoints and log, nothing else in the run folder
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == [
        "ckpt_0000002", "ckpt_0000004", "ckpt_0000006", "log.jsonl"]


def test_a_global_batch_that_does_not_split_over_the_processes_is_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "3")
    make_synthetic_pair(tmp_path / "data", "a", seconds=8.0, seed=0)
    with pytest.raises(ValueError, match="--batch-size 4 does not split evenly over 3 processes"):
        train(TrainConfig(data=str(tmp_path / "data"), out=str(tmp_path / "run"), max_steps=2, device="cpu",
                          progress=False, **{**COMMON, "batch_size": 4}))
