"""Audio -> the condition of the frames it completes, for one stream or a group in one call (a window's few frames
cost each call's fixed ops, not arithmetic); every op computes its rows alone, so a row's condition is its own."""
from __future__ import annotations

from typing import Any, NamedTuple, Sequence

import numpy as np
import torch

from .mamba2 import Mamba2State
from .network import DiMGestor, ExtractorState

__all__ = ["Conditioned", "condition", "condition_group", "group_key"]


class Conditioned(NamedTuple):
    """Samples' condition and the conditioning states after them."""

    cond: torch.Tensor  # (1, n, H): the condition of the n frames the samples complete
    frontend: Any  # the audio front end's state (`AudioFrontEnd.init_state`)
    extractor: ExtractorState


def condition(model: DiMGestor, frontend, extractor: ExtractorState, samples: np.ndarray,
              speaker: int | None = None) -> Conditioned:
    """One stream's mono float32 samples after its front end's and extractor's states -> their condition.
    speaker: its index in the model's config.speakers, -1 for none (None: the model's own, `use_speaker`)."""
    dev = next(model.parameters()).device
    with torch.inference_mode():
        x = torch.from_numpy(np.ascontiguousarray(samples)).to(dev)[None]
        feats, fe = model.frontend(x, frontend)
        cond, ex = model.condition(feats, extractor, _speakers(model, [speaker], dev))
    return Conditioned(cond, fe, ex)


def condition_group(model: DiMGestor, frontends: Sequence, extractors: Sequence[ExtractorState],
                    samples: Sequence[np.ndarray], speakers: Sequence[int | None] | None = None) -> list[Conditioned]:
    """`condition` of a group of streams (states alike in `group_key`, samples of one length) in one call each;
    speakers: each stream's (as `condition`'s; None: the model's own for all)."""
    speakers = [None] * len(samples) if speakers is None else list(speakers)
    if len(samples) == 1:
        return [condition(model, frontends[0], extractors[0], samples[0], speakers[0])]
    with torch.inference_mode():
        dev = extractors[0].buf.device
        x = torch.from_numpy(np.stack(samples)).to(dev)  # (B, N)
        feats, fe = model.frontend(x, _stack(frontends))
        cond, ex = model.condition(feats, _stack(extractors), _speakers(model, speakers, dev))
    return [Conditioned(c, f, e) for c, f, e in zip(cond.split(1), _rows(fe, frontends), _rows(ex, extractors))]


def _speakers(model: DiMGestor, speakers: Sequence[int | None], device) -> torch.Tensor | None:
    """Each row's speaker index (B,) for `DiMGestor.condition`, None (the model's own) for a model without a speaker
    condition or when no row names one."""
    if getattr(model, "speaker_embed", None) is None or all(s is None for s in speakers):
        return None
    own = int(model.speaker_index)
    return torch.tensor([own if s is None else s for s in speakers], dtype=torch.long, device=device)


def group_key(frontend, extractor: ExtractorState) -> tuple:
    """States with equal keys stack into one call. Their buffers grow and shrink with what a stream has received,
    so a stream in warm-up or fed another chunk size lands in a group of its own."""
    return _shapes(frontend), _shapes(extractor)


def _shapes(state) -> tuple:
    """The shape, dtype and device of every tensor in a state: states alike in these stack into one batch."""
    if torch.is_tensor(state):
        return (tuple(state.shape), state.dtype, state.device)
    if isinstance(state, Mamba2State):
        return (_shapes(state.conv), _shapes(state.ssm))
    if isinstance(state, tuple):
        return tuple(_shapes(part) for part in state)
    return ()  # a count (`consumed`): any value stacks


def _stack(parts: Sequence):
    """States of one type and shape, one stream (row) each -> one state of their rows in turn."""
    first = parts[0]
    if torch.is_tensor(first):
        return torch.cat(list(parts))
    if isinstance(first, Mamba2State):
        return Mamba2State(_stack([p.conv for p in parts]), _stack([p.ssm for p in parts]))
    if isinstance(first, tuple):
        return type(first)(*(_stack([p[f] for p in parts]) for f in range(len(first))))
    if isinstance(first, int):
        return 0  # a count the forward only adds to: each row's own is added back by `_row`
    raise TypeError(f"cannot stack a state part of type {type(first).__name__}")


def _rows(state, befores: Sequence) -> list:
    """Each row of a stacked state after the call, as its own state; befores: each stream's own state before it
    (for the counts). A tensor's rows come from one split, not a slice a row."""
    if torch.is_tensor(state):
        return list(state.split(1))
    if isinstance(state, Mamba2State):
        return [Mamba2State(c, s) for c, s in zip(state.conv.split(1), state.ssm.split(1))]
    if isinstance(state, tuple):
        parts = [_rows(part, [b[f] for b in befores]) for f, part in enumerate(state)]
        return [type(state)(*row) for row in zip(*parts)]
    return [before + state for before in befores]  # the stream's count + what the batch added
