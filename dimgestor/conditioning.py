"""The condition side of many streams at once: the audio front end and the feature extractor as one call a group.

A profile of 32 batched streams put 1.3 s of 7.4 s in conditioning each stream's window alone (issue 23): a
window is a few feature frames, so each call's cost is its ops' fixed cost (and, for the speech front end,
its running statistics' Python loop over the frames), not arithmetic. `begin_many` does `GestureStream.
begin_step` for many streams, one front-end call and one extractor call per group of streams whose

- model is the same,
- chunks have the same length, and
- carried states have the same shapes: the front end's tail and the extractor's downsampler buffer grow and
  shrink with what a stream has received, so a stream in warm-up (its buffer still filling before its first
  frame) or one fed another chunk size lands in a group of its own, or alone.

Every real-time window has the same length, so on a busy server the streams past warm-up share one group. The
states are stacked in (one row per stream) and split out (each stream's row, a view), and every op of the front
ends and the extractor computes its rows independently, so a stream's condition is the one it gets alone to
float rounding (the Mamba-2 style extractor picks its scan by batch size as well as length). A front end's
state is a NamedTuple of tensors with the stream on dim 0 and a `consumed` count its forward only adds to:
stacked it starts at 0 and each row gets its own count plus the batch's.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import replace
from typing import Sequence

import numpy as np
import torch

from .mamba2 import Mamba2State

__all__ = ["begin_many"]


def begin_many(streams: Sequence, states: Sequence, chunks: Sequence, return_exceptions: bool = False
               ) -> tuple[list, list, dict[int, Exception]]:
    """`GestureStream.begin_step` of many streams -> (each one's condition (1, n, H), each one's state after the
    step's first half, {index: exception} of the failed ones (their condition None, their state the one given)).

    The states given are only read. return_exceptions: a stream whose step fails (a finished stream, bad audio)
    gets its exception and the others go on; otherwise the first one is raised. A group whose batched call
    fails runs stream by stream, so only the stream at fault fails.
    """
    conds, new, failed = [None] * len(streams), list(states), {}
    samples: list = [None] * len(streams)
    groups: dict[tuple, list[int]] = defaultdict(list)
    for i, (s, state, chunk) in enumerate(zip(streams, states, chunks)):
        try:
            samples[i] = s.check_step(state, chunk)
        except Exception as e:
            if not return_exceptions:
                raise
            failed[i] = e
            continue
        groups[(id(s.model), len(samples[i]), _shapes(state.frontend), _shapes(state.extractor))].append(i)
    for idx in groups.values():
        try:
            done = _condition([streams[i] for i in idx], [states[i] for i in idx], [samples[i] for i in idx])
        except Exception as e:
            if len(idx) > 1:
                done = None  # stream by stream below: the one at fault fails alone
            elif not return_exceptions:
                raise
            else:
                failed[idx[0]] = e
                continue
        for k, i in enumerate(idx):
            try:
                cond, state = done[k] if done is not None else streams[i]._condition(states[i], samples[i])
            except Exception as e:
                if not return_exceptions:
                    raise
                failed[i] = e
                continue
            conds[i], new[i] = cond, replace(state, samples_in=state.samples_in + len(samples[i]))
    return conds, new, failed


def _condition(streams: Sequence, states: Sequence, samples: Sequence[np.ndarray]) -> list[tuple[torch.Tensor, object]]:
    """One group: the streams' states and equal-length samples -> each one's (condition (1, n, H), state with the
    front end's and the extractor's moved on), from one front-end and one extractor call."""
    if len(streams) == 1:
        return [streams[0]._condition(states[0], samples[0])]
    model = streams[0].model
    with torch.inference_mode():
        x = torch.from_numpy(np.stack(samples)).to(states[0].extractor.buf.device)  # (B, N)
        feats, fe = model.frontend(x, _stack([s.frontend for s in states]))
        cond, ex = model.condition(feats, _stack([s.extractor for s in states]))
    return [(cond[r:r + 1], replace(s, frontend=_row(fe, r, s.frontend), extractor=_row(ex, r, s.extractor)))
            for r, s in enumerate(states)]


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


def _row(state, r: int, before):
    """Row r of a stacked state after the call; `before`: that stream's own state before it (for the counts)."""
    if torch.is_tensor(state):
        return state[r:r + 1]
    if isinstance(state, Mamba2State):
        return Mamba2State(_row(state.conv, r, None), _row(state.ssm, r, None))
    if isinstance(state, tuple):
        return type(state)(*(_row(part, r, b) for part, b in zip(state, before)))
    return before + state  # the stream's count + what the batch added
