"""A random tiny model, test audio and a chunked `GestureStream` run, for the streaming = offline tests."""

import numpy as np
import torch

from dimgestor.audio import SAMPLE_RATE
from dimgestor.config import get_preset
from dimgestor.model.network import DiMGestor
from dimgestor.streaming.stream import GestureStream


def random_tiny_model(preset="tiny", seed=3, **overrides):
    """A model (the `tiny` preset unless told) with its zero init broken, so the frames depend on every parameter;
    the same weights for the same arguments."""
    torch.manual_seed(seed)
    model = DiMGestor(get_preset(preset, **overrides))
    with torch.no_grad():  # break the zero init so the frames depend on everything
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    return model.eval()


def noise_audio(seconds, seed=0):
    """Noise with a slow loudness envelope, at the model's rate."""
    rng = np.random.default_rng(seed)
    n = int(seconds * SAMPLE_RATE)
    env = 0.5 + 0.5 * np.sin(np.arange(n) / 1600)
    return (rng.standard_normal(n) * 0.1 * env).astype(np.float32)


def push_in_pieces(stream, audio, sizes):
    """`stream` fed `audio` in pieces of `sizes` samples, then finished: all its frames."""
    out, i = [], 0
    for n in sizes:
        out.append(stream.push(audio[i:i + n]))
        i += n
    assert i == len(audio)
    out.append(stream.finish())
    frames = np.concatenate(out)
    assert stream.frames_out == len(frames)
    return frames


def stream_in_pieces(model, audio, sizes, **kw):
    """A new `GestureStream(model, **kw)` fed `audio` in pieces of `sizes` samples, then finished: all its frames."""
    return push_in_pieces(GestureStream(model, **kw), audio, sizes)
