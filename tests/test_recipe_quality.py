"""The default training recipe on a small synthetic speech-and-gesture set, trained in CI time: without any
output filter, K = 4 DDIM steps are about as smooth as the ground truth and K = 8 is not rougher than K = 2
(the paper's recipe on the same budget gets rougher with every step: benchmarks/results/recipes.json)."""

import pytest
import torch

from dimgestor.evaluation.eval import k_report, valid_clips
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.training.dataset import GestureDataset
from dimgestor.training.synthetic import make_gesture_corpus
from dimgestor.training.train import TrainConfig, train

pytestmark = [pytest.mark.timeout(900), pytest.mark.slow]

MINUTES, STEPS = 1.0, 300
# Training windows of 2.5 s (the shipped model's recipe trains on 5 s): half the compute per step. Measured here,
# K = 2 / 4 / 8 jerk ratios with 2.5 s windows: 2.13 / 1.60 / 1.45 at 300 steps (training seed 1: 2.02 / 1.70 /
# 1.55), 2.11 / 1.63 / 1.54 at 400; at 250 steps 2.13 / 1.59 / 1.52 (seed 1: 2.24 / 1.77 / 1.63) and at 200,
# 2.40 / 1.85 / 1.67: fewer steps would not do. (5 s windows at 400 steps: 2.30 / 1.78 / 1.64.)
WINDOW_S = 2.5


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("recipe")
    make_gesture_corpus(root / "train", MINUTES, clip_s=30.0, seed=3)
    make_gesture_corpus(root / "valid", 0.5, clip_s=30.0, seed=4)
    torch.set_num_threads(1)
    run = train(TrainConfig(data=str(root / "train"), out=str(root / "run"), preset="realtime", max_steps=STEPS,
                             batch_size=8, window_s=WINDOW_S, valid_fraction=0.05, ckpt_every=STEPS, valid_every=STEPS,
                             seed=0, cache_dir=str(root / "cache"), progress=False, mirror=True, speeds=(0.9, 1.1)))
    bundle = load_checkpoint(run)
    bundle.model.eval()
    valid = GestureDataset(root / "valid", split="train", valid_fraction=0.0, spec=bundle.feature_spec,
                           window_s=4.0, cache_dir=root / "cache")
    return k_report(bundle, valid_clips(valid), [2, 4, 8], seeds=1, seed=0, ae=None, log=lambda *_: None)


def test_k4_without_filter_is_within_2x_of_the_ground_truth_jerk(trained):
    ratio = trained["per_k"]["4"]["jerk_ratio"]
    assert 0.5 < ratio < 2.0, trained["per_k"]


def test_more_steps_are_not_rougher(trained):
    k = trained["per_k"]
    assert k["8"]["jerk_ratio"] <= k["2"]["jerk_ratio"] * 1.05, k
