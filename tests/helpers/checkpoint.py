"""The tiny checkpoint the tests serve and load, built one way: a `tiny` model on the synthetic skeleton with random
weights, saved the way training saves one (fast, and the same files for the same arguments)."""

from pathlib import Path

import numpy as np
import torch

from dimgestor.config import get_preset
from dimgestor.features import FeatureSpec
from dimgestor.model.network import DiMGestor
from dimgestor.streaming.checkpoint import save_checkpoint
from dimgestor.training.synthetic import synthetic_skeleton


def make_tiny_checkpoint(folder: Path, seed: int = 0, jitter: float = 0.0, **config) -> Path:
    """`folder`/tiny; jitter: noise on every weight after the init (breaks the zero init so the frames depend on
    every parameter); config: fields of the `tiny` preset changed. Random weights still give motion that follows
    the audio and the noise."""
    skeleton = synthetic_skeleton()
    spec = FeatureSpec.for_skeleton(skeleton)
    torch.manual_seed(seed)
    model = DiMGestor(get_preset("tiny", **{"motion_dim": spec.dim, **config})).eval()
    if jitter:
        with torch.no_grad():
            for p in model.parameters():
                p.add_(torch.randn_like(p) * jitter)
    rng = np.random.default_rng(seed)
    mean, std = rng.normal(size=spec.dim) * 0.1, rng.uniform(0.2, 0.6, size=spec.dim)
    return save_checkpoint(Path(folder) / "tiny", model, spec, skeleton, mean, std, info={"test": True})
