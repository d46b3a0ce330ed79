"""Training past one process (issue 22, item 5): `torchrun` with 2 CPU processes (gloo) takes the same steps as one
process with the same global batch: every rank draws the whole batch (windows, versions, diffusion steps, noise,
dropout) from the same generator and trains on its half, and DDP averages the gradients. Resume works, and only
rank 0 writes."""
import json
import os
import shutil
import subprocess
import sys

import pytest
import torch

from dimgestor.checkpoint import load_checkpoint
from dimgestor.synthetic import make_synthetic_pair
from dimgestor.train import TrainConfig, train

pytestmark = pytest.mark.timeout(300)
TORCHRUN = shutil.which("torchrun", path=os.path.dirname(sys.executable)) or shutil.which("torchrun")
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


@pytest.mark.skipif(TORCHRUN is None, reason="torchrun (installed with torch) not found")
def test_two_processes_take_the_same_steps_as_one_with_the_same_global_batch_and_resume(tmp_path):
    data, cache = tmp_path / "data", tmp_path / "cache"
    make_synthetic_pair(data, "a", seconds=24.0, seed=0)

    def cli(out: str, max_steps: int, *extra: str, launcher: tuple[str, ...] = (sys.executable,)) -> None:
        cmd = [*launcher, "-m", "dimgestor.cli", "train", "--data", str(data), "--out", str(tmp_path / out),
               "--max-steps", str(max_steps), "--cache-dir", str(cache), "--no-progress", "--threads", "1",
               "--device", "cpu", *_flags(COMMON), *extra]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=240,
                           env={**os.environ, "OMP_NUM_THREADS": "1"})
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
        assert f"world {2 if len(launcher) > 1 else 1}," in r.stdout

    def torchrun(max_steps: int, *extra: str) -> None:
        cli("two", max_steps, *extra, launcher=(TORCHRUN, "--standalone", "--nproc_per_node", "2"))

    cli("one", 6)  # one process, 6 steps of 4 windows
    torchrun(4)  # two processes (2 windows each), interrupted at step 4 ...
    torchrun(6, "--resume")  # ... and resumed by two processes again
    a, b = _log(tmp_path / "one"), _log(tmp_path / "two")
    assert [r["step"] for r in a] == [r["step"] for r in b] == [0, 2, 4, 6]
    for x, y in zip(a, b):  # the same trajectory: only the order of float sums differs (gloo's all-reduce)
        assert y["valid_loss"] == pytest.approx(x["valid_loss"], rel=1e-5)
        if y["step"] <= 4:  # (the logged train loss is smoothed, and its smoothing starts again on --resume)
            assert y.get("train_loss", 0) == pytest.approx(x.get("train_loss", 0), rel=1e-5)
    wa = load_checkpoint(tmp_path / "one").model.state_dict()
    wb = load_checkpoint(tmp_path / "two").model.state_dict()
    for k in wa:
        assert torch.allclose(wa[k], wb[k], rtol=1e-4, atol=1e-6), k
    # one writer: rank 0's checkpoints and log, nothing else in the run folder
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == [
        "ckpt_0000002", "ckpt_0000004", "ckpt_0000006", "log.jsonl"]


def test_a_global_batch_that_does_not_split_over_the_processes_is_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "3")
    make_synthetic_pair(tmp_path / "data", "a", seconds=8.0, seed=0)
    with pytest.raises(ValueError, match="--batch-size 4 does not split evenly over 3 processes"):
        train(TrainConfig(data=str(tmp_path / "data"), out=str(tmp_path / "run"), max_steps=2, device="cpu",
                          progress=False, **{**COMMON, "batch_size": 4}))
