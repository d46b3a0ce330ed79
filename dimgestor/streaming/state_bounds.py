"""The magnitudes a stream's state can hold, learnt from the model's own states: what a restored state must stay in.

A saved state passes its seal, its tree, its counters and a finiteness check (`savestate_checks`) and may still
hold values no stream of this model ever makes (every float 1e30), which the model turns into NaN frames. So the
largest magnitude of each float leaf is learnt by running the stream itself, with the same weights and settings,
over probe signals that push it to its extremes (silence, quiet and full-scale noise, a full-scale square wave, a
chirp, clicks, voiced bursts and the packaged demo speech); a restored leaf may reach `MARGIN` times that (at least
`FLOOR`), never more. Audio is in [-1, 1] and every state is made from it and from the sampler's Gaussian noise, so
the bounds are the model's, not one recording's. Learnt once per model and settings (about a second on a laptop's
CPU), on the first resume, or before it (`prime`).

The speech front end's counters (frames seen, voiced frames, frames since speech) grow with the stream: they are
bounded by the frames the front end consumed instead.
"""
from __future__ import annotations

import threading
import weakref
from importlib import resources
from typing import Any, Iterator

import numpy as np
import torch

from ..audio import read_wav, resample
from .savestate_checks import StateError, floats

__all__ = ["MARGIN", "FLOOR", "PROBE_S", "bounds", "check_bounds", "learn", "leaves", "prime", "probes"]

MARGIN = 32.0  # a restored leaf may hold up to MARGIN x the largest magnitude the probes made (see `learn`)
FLOOR = 1.0  # ... and at least this (a leaf the probes left near 0)
PROBE_S = 3.0  # seconds of each probe signal
# leaves that count frames: bounded by the front end's consumed frames, not by a magnitude
COUNTERS = ("count", "voiced", "quiet")


def leaves(v: Any, path: str = "state") -> Iterator[tuple[str, Any]]:
    """(path, leaf) of every tensor and array in a state (or a part of it), as `savestate` names them."""
    if isinstance(v, (torch.Tensor, np.ndarray)):
        yield path, v
    elif isinstance(v, tuple):
        names = getattr(v, "_fields", None)
        for i, x in enumerate(v):
            yield from leaves(x, f"{path}.{names[i]}" if names else f"{path}[{i}]")
    elif hasattr(v, "__dataclass_fields__"):
        for name in v.__dataclass_fields__:
            yield from leaves(getattr(v, name), f"{path}.{name}")


def _peak(a: np.ndarray) -> float:
    """The largest finite magnitude in `a` (0 for none: a fresh speech front end holds NaN before its first frame)."""
    a = np.abs(a[np.isfinite(a)]) if a.size else a
    return float(a.max()) if a.size else 0.0


def probes(rate: int, seconds: float = PROBE_S) -> list[np.ndarray]:
    """The probe signals at `rate`: each `seconds` long, in [-1, 1], the same on every machine."""
    n = int(rate * seconds)
    t = np.arange(n) / rate
    rng = np.random.default_rng(0)
    noise = rng.standard_normal(n)
    chirp = np.sin(2 * np.pi * (50 * t + (rate / 2.2 - 50) / (2 * seconds) * t ** 2))
    square = np.sign(np.sin(2 * np.pi * 110 * t))
    clicks = np.zeros(n)
    clicks[:: rate // 7] = 1.0
    voiced = sum(np.sin(2 * np.pi * 120 * k * t) / k for k in range(1, 30)) * (np.sin(2 * np.pi * 3 * t) > 0)
    bursts = np.clip(noise, -1, 1) * (np.sin(2 * np.pi * 0.7 * t) > 0.3)  # loud, then silent: the floor swings
    out = [np.zeros(n), 0.001 * noise, np.clip(noise, -1, 1), square, chirp, clicks, voiced / np.abs(voiced).max(),
           bursts]
    try:
        with resources.as_file(resources.files("dimgestor.assets") / "demo_en.wav") as p:
            audio, sr = read_wav(p)
        speech = resample(audio.mean(axis=1), sr, rate)[:n]
        out.append(np.pad(speech, (0, n - len(speech))) / max(np.abs(speech).max(), 1e-9))  # at full scale
    except Exception:  # (a trimmed install without the demo: the synthetic probes alone)
        pass
    return [np.clip(x, -1, 1).astype(np.float32) for x in out]


def learn(stream, seconds: float = PROBE_S) -> dict[str, float]:
    """path -> the largest magnitude each float leaf of `stream`'s state held over the probes (a stream of the same
    model and settings runs them; `stream` itself is left as it is)."""
    from .batch import push_many
    from .stream import GestureStream
    s = stream
    signals = probes(s.model.config.sample_rate, seconds)
    runs = [GestureStream(s.model, seed=s.seed, sampler=s.sampler, eta=s.eta, smoothing=None, guidance=s.guidance,
                          speaker=s.speaker) for _ in signals]
    for r in runs:  # (the same schedule and output filter, however they were given)
        r.pairs, r.runner, r.smoother = s.pairs, s.runner, s.smoother
        r.state = r.initial_state()
    peaks: dict[str, float] = {}
    chunk = s.model.config.sample_rate // 5
    for at in range(0, len(signals[0]), chunk):
        push_many(runs, [x[at:at + chunk] for x in signals])
        for r in runs:
            for path, v in leaves(r.state):
                a = floats(v)
                if a is not None and path.rsplit(".", 1)[-1] not in COUNTERS:
                    peaks[path] = max(peaks.get(path, 0.0), _peak(a))
    return peaks


_LEARNT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> {settings: peaks}
_LOCK = threading.Lock()


def bounds(stream) -> dict[str, float]:
    """path -> the largest magnitude a restored leaf of `stream`'s state may hold; learnt once per model and
    settings (`learn`), then remembered with the model."""
    f = stream.smoother
    key = repr((stream.seed, stream.sampler, stream.eta, stream.guidance, [tuple(p) for p in stream.pairs],
                None if f is None else (f.fps, f.min_cutoff_hz, f.beta, f.d_cutoff_hz),
                stream.speaker))  # (savestate's settings)
    with _LOCK:
        known = _LEARNT.setdefault(stream.model, {})
        if key not in known:
            known[key] = {p: MARGIN * max(v, FLOOR) for p, v in learn(stream).items()}
        return known[key]


def prime(stream) -> None:
    """Learn `stream`'s bounds now (a server does it before it takes its first resume)."""
    bounds(stream)


def check_bounds(stream, state) -> None:
    """StateError naming the first leaf of `state` beyond what `stream`'s own states hold (`bounds`), or a counter
    beyond the frames its front end consumed."""
    limit = bounds(stream)
    for path, v in leaves(state):
        a = floats(v)
        if a is None:
            continue
        name = path.rsplit(".", 1)
        if name[-1] in COUNTERS:
            owner = state
            for part in name[0].split(".")[1:]:
                owner = getattr(owner, part)
            most = owner.consumed
            bad = (a < 0) | (a > most)
            if bad.any():
                raise StateError(f"saved stream state: {path} holds {_show(a[bad])}, a count of frames, but only "
                                 f"{most} frames were consumed")
            continue
        most = limit.get(path)
        if most is None:  # (a leaf the probes never saw: none in the states this engine makes)
            raise StateError(f"saved stream state: {path} has no learnt bound")
        bad = np.abs(a) > most  # (NaN compares False: finiteness is `savestate_checks`' to say)
        if bad.any():
            raise StateError(f"saved stream state: {path} holds {int(bad.sum())} values beyond {most:.4g} (e.g. "
                             f"{_show(a[bad])}), the most this model's own states reach, with a margin")


def _show(a: np.ndarray) -> str:
    return f"{float(a.flat[0]):.4g}"
