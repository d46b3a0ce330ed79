"""A random tiny model, test audio and a chunked `GestureStream` run, for the streaming = offline tests."""

import numpy as np
import torch

from dimgestor.audio import SAMPLE_RATE
from dimgestor.config import get_preset
from dimgestor.model import DiMGestor
from dimgestor.stream import GestureStream


def random_tiny_model(**overrides):
    """A `tiny` model with its zero init broken, so the frames depend on every parameter."""
    model = DiMGestor(get_preset("tiny", **overrides))
    torch.manual_seed(1)
    with torch.no_grad():  # break the zero init so the frames depend on everything
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    return model


def noise_audio(seconds, seed=0):
    """Noise with a slow loudness envelope, at the model's rate."""
    rng = np.random.default_rng(seed)
    n = int(seconds * SAMPLE_RATE)
    env = 0.5 + 0.5 * np.sin(np.arange(n) / 1600)
    return (rng.standard_normal(n) * 0.1 * env).astype(np.float32)


def stream_in_pieces(model, audio, sizes, **kw):
    """`GestureStream` fed `audio` in pieces of `sizes` samples, then finished: all its frames."""
    s = GestureStream(model, **kw)
    out, i = [], 0
    for n in sizes:
        out.append(s.push(audio[i:i + n]))
        i += n
    assert i == len(audio)
    out.append(s.finish())
    frames = np.concatenate(out)
    assert s.frames_out == len(frames)
    return frames
