"""What a stored stream state must satisfy before it is trusted (`dimgestor.streaming.savestate.loads`).

A state comes from a store other processes write to: untrusted input. Its header is compared, node by node,
with the header of this stream's own fresh state: the same tree of types, the same dtypes, the same shapes
except the one dimension a stream moves on (the front end's and the extractor's unconsumed tails), the leaves
laid one after the other in exactly the bytes there are (so a shape of 2^40 is refused before anything is
allocated). Then the built state's counters must agree with each other and its numbers be finite. Each failure
is a `StateError` naming the field: the state is resumed exactly or not at all.
"""
from __future__ import annotations

import math
import reprlib
from typing import Any

import numpy as np
import torch

__all__ = ["StateError", "check_tree", "check_state", "is_int", "finite_number", "floats", "show", "MAX_FRAMES"]

# The most frames a stream may have made: a frame's index as every output carries it (OSC's int32 is the narrowest;
# the binary frame's is a uint32), 3.4 years at 20 fps. A saved state past it is refused, not streamed into an error.
MAX_FRAMES = 2**31 - 1

# leaves whose last dimension a running stream moves on: samples and features not yet consumed
VARYING = {"state.frontend.tail": 1, "state.frontend.speech.tail": 1, "state.extractor.buf": 2}
_KEYS = {"value": {"t", "v"}, "tuple": {"t", "items"}, "tensor": {"t", "dtype", "shape", "at", "n"},
         "ndarray": {"t", "dtype", "shape", "at", "n"}}


class StateError(ValueError):
    """A saved state that cannot be resumed here; the message says why."""


def is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def finite_number(v: Any) -> bool:
    """An int or a float that is a finite float (an int of 400 digits is not)."""
    return (isinstance(v, float) and math.isfinite(v)) or (is_int(v) and abs(v) < 1e300)


_SHOW = reprlib.Repr()
_SHOW.maxlevel, _SHOW.maxstring, _SHOW.maxother, _SHOW.maxlong = 2, 40, 40, 40


def show(v: Any) -> str:
    """An untrusted value, abridged for an error message (never deep nor long)."""
    return _SHOW.repr(v)


def _kind(v: Any) -> str:
    return "null" if v is None else "bool" if isinstance(v, bool) else type(v).__name__


class _Layout:
    """Where the next leaf's bytes must begin, and how many bytes there are."""

    def __init__(self, size: int):
        self.offset, self.size = 0, size


def check_tree(saved: Any, ref: Any, size: int, alternatives: dict[str, Any]) -> None:
    """`saved` (a header's state tree) against `ref` (the fresh state's, from `describe`), over `size` bytes of
    leaves; `alternatives`: path -> the node a path may hold instead (the output filter's state once it ran)."""
    layout = _Layout(size)
    _node(saved, ref, "state", layout, alternatives)
    if layout.offset != size:
        raise StateError(f"saved stream state: {size - layout.offset} bytes beyond its last leaf")


def _node(nd: Any, ref: dict, path: str, layout: _Layout, alternatives: dict[str, Any]) -> None:
    if not isinstance(nd, dict) or not isinstance(nd.get("t"), str):
        raise StateError(f"saved stream state: malformed node at {path}")
    if nd["t"] != ref["t"] and path in alternatives:
        ref = alternatives[path]
    if nd["t"] != ref["t"]:
        raise StateError(f"saved stream state: {path} is a {show(nd['t'])}, expected a {ref['t']!r}")
    if set(nd) != _KEYS.get(ref["t"], {"t", "f"}):
        raise StateError(f"saved stream state: {path} has keys {sorted(nd)}, expected "
                         f"{sorted(_KEYS.get(ref['t'], {'t', 'f'}))}")
    kind = ref["t"]
    if kind == "value":
        got, want = _kind(nd["v"]), _kind(ref["v"])
        if got != want and not (want == "float" and got == "int"):
            raise StateError(f"saved stream state: {path} is {got} {show(nd['v'])}, expected {want}")
        if got == "float" and not math.isfinite(nd["v"]):
            raise StateError(f"saved stream state: {path} is {nd['v']}")
    elif kind in ("tensor", "ndarray"):
        _leaf(nd, ref, path, layout)
    elif kind == "tuple":
        items = nd["items"]
        if not isinstance(items, list) or len(items) != len(ref["items"]):
            raise StateError(f"saved stream state: {path} is not a tuple of {len(ref['items'])}")
        for i, (x, r) in enumerate(zip(items, ref["items"])):
            _node(x, r, f"{path}[{i}]", layout, alternatives)
    else:
        fields = nd["f"]
        if not isinstance(fields, dict) or set(fields) != set(ref["f"]):
            raise StateError(f"saved stream state: {kind} at {path} has fields "
                             f"{show(sorted(fields) if isinstance(fields, dict) else fields)}, expected "
                             f"{sorted(ref['f'])}")
        for name, r in ref["f"].items():
            _node(fields[name], r, f"{path}.{name}", layout, alternatives)


def _leaf(nd: dict, ref: dict, path: str, layout: _Layout) -> None:
    if nd["dtype"] != ref["dtype"]:
        raise StateError(f"saved stream state: {path} of dtype {show(nd['dtype'])}, expected {ref['dtype']}")
    shape, want, vary = nd["shape"], ref["shape"], VARYING.get(path)
    if (not isinstance(shape, list) or len(shape) != len(want) or not all(is_int(d) and d >= 0 for d in shape)
            or any(d != w for i, (d, w) in enumerate(zip(shape, want)) if i != vary)):
        raise StateError(f"saved stream state: {path} of shape {show(shape)}, expected {want}"
                         + (f" (dimension {vary} may differ)" if vary is not None else ""))
    itemsize = np.dtype(ref["dtype"]).itemsize if ref["t"] == "ndarray" else _torch_dtype(ref["dtype"]).itemsize
    n, at = nd["n"], nd["at"]
    if not is_int(n) or n != math.prod(shape) * itemsize:
        raise StateError(f"saved stream state: {path} of {ref['dtype']} {shape} in {show(n)} bytes")
    if not is_int(at) or at != layout.offset:
        raise StateError(f"saved stream state: {path} at byte {show(at)}, expected {layout.offset} (the leaves "
                         "lie one after the other)")
    if at + n > layout.size:
        raise StateError(f"saved stream state cut short at {path}: needs bytes {at}-{at + n}, "
                         f"{layout.size} present")
    layout.offset += n


def _torch_dtype(name: str) -> torch.dtype:
    return getattr(torch, name)


def check_state(stream, state, fresh) -> None:
    """The built `state`'s counters agree with each other and with its tails, and its numbers are finite;
    `fresh`: the stream's initial state."""
    fe, ex = stream.model.frontend, stream.model.extractor
    consumed = state.frontend.consumed
    for name, v in (("samples_in", state.samples_in), ("frames_out", state.frames_out),
                    ("frontend.consumed", consumed)):
        if v < 0:
            raise StateError(f"saved stream state: state.{name} is {v}")
    if state.frames_out > MAX_FRAMES:  # (the other counters agree with it, checked below, so they are bounded too)
        raise StateError(f"saved stream state: state.frames_out is {state.frames_out}, over {MAX_FRAMES}, the most a "
                         "frame's index can be")
    if state.finished:
        raise StateError("saved stream state: state.finished: a finished stream cannot go on")
    # the front end holds the samples it has not consumed: frames (log-mel, speech) or blocks (pretrained)
    step = getattr(fe, "block", None) or fe.hop
    held = state.frontend.tail.shape[1] - fresh.frontend.tail.shape[1]
    if held != state.samples_in - consumed * step or not 0 <= held < step + getattr(fe, "right", 0):
        raise StateError(f"saved stream state: state.frontend holds {held} samples beyond its start, but "
                         f"samples_in {state.samples_in} less {consumed} x {step} consumed leaves "
                         f"{state.samples_in - consumed * step}")
    inner = getattr(state.frontend, "speech", None)  # the embedding front end's speech front end, in step
    if inner is not None and (inner.consumed != consumed or inner.tail.shape[1] - fresh.frontend.speech.tail.shape[1]
                              != held):
        raise StateError(f"saved stream state: state.frontend.speech consumed {inner.consumed} frames and holds "
                         f"{inner.tail.shape[1] - fresh.frontend.speech.tail.shape[1]} samples, the embedding "
                         f"{consumed} and {held}")
    # the extractor holds the features not yet made into frames
    feats = consumed * (fe.block // fe.stride * fe.repeat if hasattr(fe, "block") else 1)
    buf = state.extractor.buf.shape[2]
    if buf != ex.pad + feats - state.frames_out * ex.stride or not ex.pad <= buf < ex.k:
        raise StateError(f"saved stream state: state.extractor.buf holds {buf} features, but {feats} features "
                         f"made {state.frames_out} frames (frames_out)")
    if (state.smoother is not None) != (stream.smoother is not None and state.frames_out > 0):
        raise StateError(f"saved stream state: state.smoother is {'set' if state.smoother is not None else 'None'}"
                         f" after {state.frames_out} frames")
    _finite(state, fresh, "state", consumed == 0)


def _finite(v: Any, ref: Any, path: str, fresh_nan: bool) -> None:
    """Every float finite, but where the fresh state holds NaN (a speech front end's noise floor) before the
    front end's first frame."""
    if isinstance(v, (torch.Tensor, np.ndarray)):
        a = floats(v)
        if a is None or np.isfinite(a).all():  # (numpy: ten times torch's isfinite on a CPU)
            return
        bad = ~np.isfinite(a)
        if fresh_nan and isinstance(ref, torch.Tensor) and tuple(ref.shape) == a.shape:
            bad &= ~(np.isnan(a) & np.isnan(floats(ref)))
        if bad.any():
            raise StateError(f"saved stream state: {path} holds {int(bad.sum())} values that are NaN or infinite")
    elif isinstance(v, tuple):
        names = getattr(v, "_fields", None)
        refs = ref if isinstance(ref, tuple) and len(ref) == len(v) else (None,) * len(v)
        for i, (x, r) in enumerate(zip(v, refs)):
            _finite(x, r, f"{path}.{names[i]}" if names else f"{path}[{i}]", fresh_nan)
    elif hasattr(v, "__dataclass_fields__"):
        for name in v.__dataclass_fields__:
            _finite(getattr(v, name), getattr(ref, name, None), f"{path}.{name}", fresh_nan)


def floats(v) -> np.ndarray | None:
    """A float tensor or array as a numpy array (None: not floats)."""
    if isinstance(v, torch.Tensor):
        if not v.is_floating_point():
            return None
        v = v.detach().cpu()
        return (v.float() if v.dtype in (torch.float16, torch.bfloat16) else v).numpy()
    return v if v.dtype.kind == "f" else None
