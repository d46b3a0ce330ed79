"""A stream's state as bytes: saved by one process, resumed by another, exactly.

A `StreamState` (dimgestor.stream) is a small tree of named tuples and frozen dataclasses whose leaves are
tensors, arrays and numbers. `dumps` writes it as

    b"DGSTATE" | version (u16) | header length (u32) | JSON header | raw leaf bytes

where the header holds the tree (each node's type by name, each leaf's dtype, shape and byte range), the model's
fingerprint (its config and every parameter and buffer, hashed), the stream's sampling settings and the caller's
`meta`. `loads` rebuilds the tree from a fixed list of known types (never pickle: a state may come from a store
shared by many machines), and refuses, with the reason, a state of another version, of another model or of
other settings, and bytes that are cut short or do not parse: a state is resumed exactly or not at all.
Bump STATE_VERSION whenever the tree of any state type changes.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import struct
from typing import Any

import numpy as np
import torch

from .sampler import StepStates
from .frontend import FrontEndState
from .frontend_speech import SpeechState
from .mamba2 import Mamba2State
from .model import DenoiserState, ExtractorState
from .smoothing import OneEuroState
from .stream import GestureStream, StreamState

__all__ = ["STATE_VERSION", "StateError", "dumps", "loads", "model_fingerprint", "stream_settings"]

MAGIC = b"DGSTATE"
STATE_VERSION = 1
_PREFIX = struct.Struct("<7sHI")
_TYPES = {t.__name__: t for t in (StreamState, FrontEndState, SpeechState, ExtractorState, DenoiserState,
                                  Mamba2State, StepStates, OneEuroState)}
_DTYPES = {str(d).removeprefix("torch."): d for d in (torch.float32, torch.float64, torch.float16, torch.bfloat16,
                                                      torch.int64, torch.int32, torch.bool)}


class StateError(ValueError):
    """A saved state that cannot be resumed here; the message says why."""


def model_fingerprint(model: torch.nn.Module) -> str:
    """sha256 of the model's config and of every parameter and buffer (names, dtypes, shapes, values): equal for
    the same weights loaded anywhere. Cached on the model until a tensor is replaced or changed in place."""
    tensors = list(model.named_parameters()) + list(model.named_buffers())
    key = tuple((t.data_ptr(), t._version) for _, t in tensors)
    cached = getattr(model, "_state_fingerprint", None)
    if cached is not None and cached[0] == key:
        return cached[1]
    h = hashlib.sha256(json.dumps(model.config.model_dump(mode="json"), sort_keys=True).encode())
    for name, t in tensors:
        t = t.detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    model._state_fingerprint = (key, h.hexdigest())
    return model._state_fingerprint[1]


def stream_settings(stream: GestureStream) -> dict:
    """What makes two streams' frames differ for the same state and audio, besides the weights."""
    s = stream.smoother
    return {"seed": stream.seed, "sampler": stream.sampler, "eta": stream.eta, "guidance": stream.guidance,
            "pairs": [list(p) for p in stream.pairs],
            "smoother": None if s is None else [s.fps, s.min_cutoff_hz, s.beta, s.d_cutoff_hz]}


def dumps(stream: GestureStream, state: StreamState | None = None, meta: dict | None = None) -> bytes:
    """`state` (default: the stream's own) as bytes, with `meta` (JSON-serialisable) beside it."""
    blobs: list[bytes] = []
    offset = [0]

    def leaf(kind: str, dtype: str, shape, raw: bytes) -> dict:
        node = {"t": kind, "dtype": dtype, "shape": list(shape), "at": offset[0], "n": len(raw)}
        blobs.append(raw)
        offset[0] += len(raw)
        return node

    def node(v: Any) -> Any:
        if v is None or isinstance(v, (bool, int, float, str)):
            return {"t": "value", "v": v}
        if isinstance(v, torch.Tensor):
            t = v.detach().cpu().contiguous()
            return leaf("tensor", str(t.dtype).removeprefix("torch."), t.shape,
                        t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
        if isinstance(v, np.ndarray):
            a = np.ascontiguousarray(v)
            return leaf("ndarray", a.dtype.str, a.shape, a.tobytes())
        if isinstance(v, np.generic):
            return {"t": "value", "v": v.item()}
        name = type(v).__name__
        if _TYPES.get(name) is type(v):
            fields = v._fields if isinstance(v, tuple) else [f.name for f in dataclasses.fields(v)]
            return {"t": name, "f": {f: node(getattr(v, f)) for f in fields}}
        if isinstance(v, (tuple, list)):
            return {"t": "tuple", "items": [node(x) for x in v]}
        raise TypeError(f"cannot save a {type(v).__name__} in a stream state")

    state = stream.state if state is None else state
    header = {"model": model_fingerprint(stream.model), "settings": stream_settings(stream), "meta": meta or {},
              "state": node(state)}
    text = json.dumps(header, allow_nan=True).encode()
    return _PREFIX.pack(MAGIC, STATE_VERSION, len(text)) + text + b"".join(blobs)


def loads(stream: GestureStream, data: bytes) -> tuple[StreamState, dict]:
    """(the state, its meta) of bytes from `dumps`, for `stream` (the same weights and settings), on the stream's
    device; StateError with the reason when it cannot be resumed exactly."""
    data = bytes(data)
    if len(data) < _PREFIX.size or data[:len(MAGIC)] != MAGIC:
        raise StateError("not a saved stream state (no DGSTATE header)")
    _, version, n = _PREFIX.unpack_from(data)
    if version != STATE_VERSION:
        raise StateError(f"saved stream state version {version}, this engine reads version {STATE_VERSION} only: "
                         "it was saved by another release; start a fresh stream")
    body = _PREFIX.size + n
    if len(data) < body:
        raise StateError(f"saved stream state cut short: header of {n} bytes, {len(data) - _PREFIX.size} present")
    try:
        header = json.loads(data[_PREFIX.size:body])
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise StateError(f"saved stream state header does not parse: {e}") from None
    if not isinstance(header, dict) or not {"model", "settings", "state"} <= set(header):
        raise StateError("saved stream state header lacks model, settings or state")
    if header["model"] != model_fingerprint(stream.model):
        raise StateError("saved stream state is of another model (weights or config differ): start a fresh stream")
    mine = stream_settings(stream)
    if header["settings"] != json.loads(json.dumps(mine)):
        diff = sorted(k for k in mine if header["settings"].get(k) != json.loads(json.dumps(mine[k])))
        raise StateError(f"saved stream state has other sampling settings ({', '.join(diff)}): "
                         f"saved {[header['settings'].get(k) for k in diff]}, here {[mine[k] for k in diff]}")
    raw = memoryview(data)[body:]
    dev = next(stream.model.parameters()).device

    def build(nd: Any, path: str) -> Any:
        if not isinstance(nd, dict) or "t" not in nd:
            raise StateError(f"saved stream state: malformed node at {path}")
        kind = nd["t"]
        if kind == "value":
            return nd.get("v")
        if kind in ("tensor", "ndarray"):
            at, size, shape = int(nd["at"]), int(nd["n"]), tuple(int(s) for s in nd["shape"])
            if at < 0 or at + size > len(raw):
                raise StateError(f"saved stream state cut short at {path}: needs bytes {at}-{at + size}, "
                                 f"{len(raw)} present")
            chunk = bytes(raw[at:at + size])
            if kind == "ndarray":
                dtype = np.dtype(nd["dtype"])
                if dtype.kind not in "fiub" or dtype.itemsize * int(np.prod(shape)) != size:
                    raise StateError(f"saved stream state: array {path} of {nd['dtype']} {shape} in {size} bytes")
                return np.frombuffer(chunk, dtype).reshape(shape).copy()
            dtype = _DTYPES.get(nd["dtype"])
            if dtype is None:
                raise StateError(f"saved stream state: tensor {path} of unknown dtype {nd['dtype']!r}")
            t = torch.frombuffer(bytearray(chunk), dtype=torch.uint8) if size else torch.zeros(0, dtype=torch.uint8)
            if t.numel() != torch.empty(shape, dtype=dtype).element_size() * int(np.prod(shape)):
                raise StateError(f"saved stream state: tensor {path} of {nd['dtype']} {shape} in {size} bytes")
            return t.view(dtype).reshape(shape).to(dev)
        if kind == "tuple":
            return tuple(build(x, f"{path}[{i}]") for i, x in enumerate(nd.get("items", [])))
        cls = _TYPES.get(kind)
        if cls is None:
            raise StateError(f"saved stream state: unknown type {kind!r} at {path}")
        names = cls._fields if issubclass(cls, tuple) else [f.name for f in dataclasses.fields(cls)]
        got = nd.get("f", {})
        if set(got) != set(names):
            raise StateError(f"saved stream state: {kind} at {path} has fields {sorted(got)}, expected {sorted(names)}")
        values = {f: build(got[f], f"{path}.{f}") for f in names}
        return cls(**values)

    state = build(header["state"], "state")
    if not isinstance(state, StreamState):
        raise StateError("saved stream state: its root is not a StreamState")
    template = stream.initial_state()
    if _shape_tree(state.denoiser) != _shape_tree(template.denoiser):
        raise StateError("saved stream state: its denoiser state's shapes differ from this stream's")
    return state, header.get("meta", {})


def _shape_tree(v: Any) -> Any:
    if isinstance(v, torch.Tensor):
        return (str(v.dtype), tuple(v.shape))
    if isinstance(v, tuple):
        return tuple(_shape_tree(x) for x in v)
    return None
