"""Many streams stepped at once: `GestureStream.step` mapped over their states, conditioned and denoised in groups."""
from __future__ import annotations

from collections import defaultdict
from typing import Sequence

import torch

from ..model.conditioning import condition, condition_group, group_key
from ..model.sampler import DenoiseRunner, StepStates, Window, denoise
from .stream import GestureStream, StreamState

__all__ = ["push_many", "step_many", "begin_many"]


def push_many(streams: Sequence[GestureStream], chunks: Sequence, return_exceptions: bool = False) -> list:
    """Push chunks[i] into streams[i] (distinct streams) -> each one's new frames, as `push` would:
    `step_many` on the streams' states, each stream then holding its new state (a failed one keeps its own)."""
    outs, states = step_many(streams, [s.state for s in streams], chunks, return_exceptions)
    for s, out, state in zip(streams, outs, states):
        s.state = state
    return outs


def step_many(streams: Sequence[GestureStream], states: Sequence[StreamState], chunks: Sequence,
              return_exceptions: bool = False) -> tuple[list, list[StreamState]]:
    """`GestureStream.step` of many streams: states[i] (only read) and chunks[i] -> (each one's frames, each one's
    new state), the frames those it gets alone. return_exceptions: a stream whose step fails gets its exception in
    its place and keeps its state while the others go on; otherwise the first one is raised."""
    if len({id(s) for s in streams}) != len(streams):
        raise ValueError("push_many: each stream at most once per call")
    if not len(chunks) == len(states) == len(streams):
        raise ValueError(f"push_many: {len(streams)} streams but {len(states)} states and {len(chunks)} chunks")
    out: list = [None] * len(streams)
    conds, new, begin_failed = begin_many(streams, states, chunks, return_exceptions)
    for i, e in begin_failed.items():
        out[i] = e
    windows = {i: streams[i].window(new[i], c) for i, c in enumerate(conds) if c is not None and c.shape[1]}
    for i, c in enumerate(conds):
        if c is not None and not c.shape[1]:
            out[i], new[i] = streams[i].end_step(new[i], None, new[i].denoiser)
    frames, denoisers, failed = _denoise_rounds({i: streams[i].runner for i in windows}, windows, return_exceptions)
    for i in windows:
        if i in failed:
            out[i], new[i] = failed[i], states[i]
        else:
            out[i], new[i] = streams[i].end_step(new[i], frames[i], denoisers[i])
    return out, new


def begin_many(streams: Sequence[GestureStream], states: Sequence[StreamState], chunks: Sequence,
               return_exceptions: bool = False) -> tuple[list, list[StreamState], dict[int, Exception]]:
    """`GestureStream.begin_step` of many streams, conditioned in groups -> (each one's condition (1, n, H), each
    one's state after it, {index: exception} of the failed ones). return_exceptions: as `step_many`; a group whose
    call fails runs stream by stream, so only the stream at fault fails."""
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
        groups[(id(s.model), len(samples[i]), group_key(state.frontend, state.extractor))].append(i)
    for idx in groups.values():
        try:
            done = condition_group(streams[idx[0]].model, [states[i].frontend for i in idx],
                                   [states[i].extractor for i in idx], [samples[i] for i in idx],
                                   [streams[i].speaker_index for i in idx])
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
                c = done[k] if done is not None else condition(streams[i].model, states[i].frontend,
                                                               states[i].extractor, samples[i],
                                                               streams[i].speaker_index)
            except Exception as e:
                if not return_exceptions:
                    raise
                failed[i] = e
                continue
            conds[i], new[i] = c.cond, states[i].conditioned(c, len(samples[i]))
    return conds, new, failed


def _denoise_rounds(runners: dict[int, DenoiseRunner], windows: dict[int, Window], return_exceptions: bool
                    ) -> tuple[dict[int, torch.Tensor], dict[int, StepStates], dict[int, Exception]]:
    """Windows (keyed by stream) -> (frames, new denoiser states, exceptions), cut into pieces of the most common
    length so that a stream that fell behind still shares the others' batches (streaming = offline for any cut)."""
    lengths = [w.cond.shape[1] for w in windows.values()]
    piece = max(set(lengths), key=lambda n: (lengths.count(n), n)) if windows else 1
    done = {i: 0 for i in windows}
    pieces: dict[int, list] = {i: [] for i in windows}
    states = {i: w.state for i, w in windows.items()}
    failed: dict[int, Exception] = {}
    while todo := [i for i, w in windows.items() if i not in failed and done[i] < w.cond.shape[1]]:
        take = {i: piece if len(todo) > 1 else windows[i].cond.shape[1] - done[i] for i in todo}
        cut = {i: windows[i]._replace(cond=windows[i].cond[:, done[i]:done[i] + take[i]], state=states[i],
                                      frame_start=windows[i].frame_start + done[i]) for i in todo}
        groups: dict[tuple, list[int]] = defaultdict(list)
        for i in todo:
            groups[(id(runners[i]), cut[i].cond.shape[1], cut[i].cond.device, cut[i].cond.dtype)].append(i)
        for idx in groups.values():
            try:
                xs, news = denoise(runners[idx[0]], [cut[i] for i in idx])
            except Exception as e:
                if not return_exceptions:
                    raise
                failed.update({i: e for i in idx})
                continue
            for i, x, d in zip(idx, xs, news):
                pieces[i].append(x)
                states[i] = d
        for i in todo:
            done[i] += take[i]
    frames = {i: torch.cat(p) if len(p) > 1 else p[0] for i, p in pieces.items() if i not in failed}
    return frames, states, failed
