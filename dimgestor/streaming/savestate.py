"""A stream's state as bytes: saved by one process, resumed by another, exactly.

A `StreamState` (dimgestor.streaming.stream) is a small tree of named tuples and frozen dataclasses whose leaves are
tensors, arrays and numbers. `dumps` writes it as

    b"DGSTATE" | version (u16) | header length (u32) | seal (32 bytes) | JSON header | raw leaf bytes

where the seal is over all the rest (the prefix, the header and the leaves): HMAC-SHA256 with the workers'
shared secret (`dimgestor serve --state-secret-file`) when there is one, else plain SHA-256. Without a secret the
seal detects corruption and truncation, not forgery (anyone can compute a SHA-256); with one, a state not saved by
a worker holding the secret is refused, whatever its values. The header holds the tree (each node's type by name,
each leaf's dtype, shape and byte range), the model's fingerprint (its config and every parameter and buffer,
hashed), the stream's sampling settings and the caller's `meta`. `loads` checks the seal first, then rebuilds the
tree from a fixed list of known types (never pickle: a state may come from a store shared by many machines), and
refuses, with the reason, a state of another version, of another model or of other settings, bytes that are cut
short or do not parse, and any field that is not what this stream's own state would hold
(`dimgestor.streaming.savestate_checks`, checked before anything is built: what a state re-sealed by someone without the
secret meets), and values beyond what this model's own states ever hold (`dimgestor.streaming.state_bounds`). A state
is resumed exactly or not at all.
Bump STATE_VERSION whenever the tree of any state type changes.
"""
from __future__ import annotations

import dataclasses
import hashlib
import hmac
import json
import struct
import weakref
from typing import Any

import numpy as np
import torch

from ..frontend.base import FrontEndState
from ..frontend.embed import EmbeddingState
from ..frontend.speech import SpeechState
from ..model.mamba2 import Mamba2State
from ..model.network import DenoiserState, ExtractorState
from ..model.sampler import StepStates
from ..smoothing import OneEuroState
from . import savestate_checks as checks
from . import state_bounds
from .savestate_checks import StateError
from .stream import GestureStream, StreamState

__all__ = ["STATE_VERSION", "StateError", "dumps", "loads", "model_fingerprint", "pack", "reseal", "split",
           "stream_settings"]

MAGIC = b"DGSTATE"
STATE_VERSION = 2  # 2: sealed
_PREFIX = struct.Struct("<7sHI")
SEAL_SIZE = 32
_BODY = _PREFIX.size + SEAL_SIZE  # where the header begins
_TYPES = {t.__name__: t for t in (StreamState, FrontEndState, SpeechState, EmbeddingState, ExtractorState,
                                  DenoiserState, Mamba2State, StepStates, OneEuroState)}
_DTYPES = {str(d).removeprefix("torch."): d for d in (torch.float32, torch.float64, torch.float16, torch.bfloat16,
                                                      torch.int64, torch.int32, torch.bool)}


def model_fingerprint(model: torch.nn.Module) -> str:
    """sha256 of the model's config and of every parameter and buffer (names, dtypes, shapes, values): equal for
    the same weights loaded anywhere. Remembered per model (here, not on it) until a tensor is replaced or changed
    in place."""
    tensors = list(model.named_parameters()) + list(model.named_buffers())
    key = tuple((t.data_ptr(), t._version) for _, t in tensors)
    known = _FINGERPRINTS.get(model)
    if known is not None and known[0] == key:
        return known[1]
    h = hashlib.sha256(json.dumps(model.config.model_dump(mode="json"), sort_keys=True).encode())
    for name, t in tensors:
        t = t.detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    _FINGERPRINTS[model] = (key, h.hexdigest())
    return h.hexdigest()


# model -> (its tensors' pointers and versions, its fingerprint), forgotten with the model
_FINGERPRINTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def stream_settings(stream: GestureStream) -> dict:
    """What makes two streams' frames differ for the same state and audio, besides the weights."""
    s = stream.smoother
    out = {"seed": stream.seed, "sampler": stream.sampler, "eta": stream.eta, "guidance": stream.guidance,
           "pairs": [list(p) for p in stream.pairs],
           "smoother": None if s is None else [s.fps, s.min_cutoff_hz, s.beta, s.d_cutoff_hz]}
    if stream.model.config.speakers:  # (a model without speakers: the settings, and its saved states, as before)
        out["speaker"] = stream.speaker
    return out


def describe(v: Any, blobs: list[bytes]) -> Any:
    """The header's node of `v` (a state or any part of it); its leaves' bytes are appended to `blobs`."""
    if v is None or isinstance(v, (bool, int, float, str)):
        return {"t": "value", "v": v}
    if isinstance(v, np.generic):
        return {"t": "value", "v": v.item()}
    if isinstance(v, torch.Tensor):
        t = v.detach().cpu().contiguous()
        raw = t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b""
        kind, dtype = "tensor", str(t.dtype).removeprefix("torch.")
    elif isinstance(v, np.ndarray):
        a = np.ascontiguousarray(v)
        raw, kind, dtype = a.tobytes(), "ndarray", a.dtype.str
    else:
        name = type(v).__name__
        if _TYPES.get(name) is type(v):
            fields = v._fields if isinstance(v, tuple) else [f.name for f in dataclasses.fields(v)]
            return {"t": name, "f": {f: describe(getattr(v, f), blobs) for f in fields}}
        if isinstance(v, (tuple, list)):
            return {"t": "tuple", "items": [describe(x, blobs) for x in v]}
        raise TypeError(f"cannot save a {type(v).__name__} in a stream state")
    node = {"t": kind, "dtype": dtype, "shape": list(v.shape), "at": sum(map(len, blobs)), "n": len(raw)}
    blobs.append(raw)
    return node


def dumps(stream: GestureStream, state: StreamState | None = None, meta: dict | None = None,
          key: bytes | None = None) -> bytes:
    """`state` (default: the stream's own) as bytes, with `meta` (JSON-serialisable) beside it, sealed with `key`
    (the workers' shared secret; None: plain SHA-256)."""
    blobs: list[bytes] = []
    state = stream.state if state is None else state
    header = {"model": model_fingerprint(stream.model), "settings": stream_settings(stream), "meta": meta or {},
              "state": describe(state, blobs)}
    return _sealed(json.dumps(header, allow_nan=True).encode(), blobs, key)


def loads(stream: GestureStream, data: bytes, key: bytes | None = None) -> tuple[StreamState, dict]:
    """(the state, its meta) of bytes from `dumps` sealed with the same `key`, for `stream` (the same weights and
    settings), on the stream's device; StateError with the reason when it cannot be resumed exactly."""
    data = bytes(data)
    if len(data) < _PREFIX.size or data[:len(MAGIC)] != MAGIC:
        raise StateError("not a saved stream state (no DGSTATE header)")
    _, version, n = _PREFIX.unpack_from(data)
    if version != STATE_VERSION:
        raise StateError(f"saved stream state version {version}, this engine reads version {STATE_VERSION} only: "
                         "it was saved by another release; start a fresh stream")
    if len(data) < _BODY or not hmac.compare_digest(data[_PREFIX.size:_BODY], _seal(key, data[:_PREFIX.size],
                                                                                     memoryview(data)[_BODY:])):
        raise StateError("saved stream state seal does not match: corrupted or cut short, or saved by a worker "
                         "with another state secret (--state-secret-file), or without one")
    body = _BODY + n
    if len(data) < body:
        raise StateError(f"saved stream state cut short: header of {n} bytes, {len(data) - _BODY} present")
    header = _parse(data[_BODY:body])
    if not isinstance(header, dict) or not {"model", "settings", "state"} <= set(header):
        raise StateError("saved stream state header lacks model, settings or state")
    if header["model"] != model_fingerprint(stream.model):
        raise StateError("saved stream state is of another model (weights or config differ): start a fresh stream")
    mine, saved = json.loads(json.dumps(stream_settings(stream))), header["settings"]
    if saved != mine:
        diff = sorted(k for k in mine if not isinstance(saved, dict) or saved.get(k) != mine[k])
        raise StateError(f"saved stream state has other sampling settings ({', '.join(diff)}): saved "
                         f"{checks.show([saved.get(k) for k in diff] if isinstance(saved, dict) else saved)}, "
                         f"here {[mine[k] for k in diff]}")
    meta = header.get("meta", {})
    if not isinstance(meta, dict):
        raise StateError(f"saved stream state: its meta is {type(meta).__name__}, not an object")
    raw = memoryview(data)[body:]
    fresh = stream.initial_state()
    alternatives = {}
    if stream.smoother is not None:  # the output filter's state, once it filtered a frame
        d = stream.model.config.motion_dim
        alternatives["state.smoother"] = describe(OneEuroState(np.zeros(d), np.zeros(d)), [])
    checks.check_tree(header["state"], describe(fresh, []), len(raw), alternatives)
    state = _build(header["state"], raw, next(stream.model.parameters()).device)
    checks.check_state(stream, state, fresh)
    state_bounds.check_bounds(stream, state)
    return state, meta


def split(data: bytes) -> tuple[Any, bytes]:
    """(the header, the raw leaf bytes) of a state, unchecked and its seal unread: for tools and tests that look
    into states or change them (then `pack`)."""
    data = bytes(data)
    _, _, n = _PREFIX.unpack_from(data)
    return json.loads(data[_BODY:_BODY + n]), data[_BODY + n:]


def pack(header: Any, raw: bytes, key: bytes | None = None) -> bytes:
    """A state of this version from its header (a JSON value, or its text as str or bytes) and raw leaf bytes,
    sealed with `key`; `split`'s inverse."""
    if not isinstance(header, (str, bytes)):
        header = json.dumps(header, allow_nan=True)
    return _sealed(header.encode() if isinstance(header, str) else header, [raw], key)


def reseal(data: bytes, key: bytes | None = None) -> bytes:
    """`data` (at least the prefix and a seal's room) with its seal made anew with `key`, all else as it is."""
    data = bytes(data)
    if len(data) < _BODY:
        raise ValueError(f"a state has at least {_BODY} bytes, got {len(data)}")
    return data[:_PREFIX.size] + _seal(key, data[:_PREFIX.size], memoryview(data)[_BODY:]) + data[_BODY:]


def _sealed(text: bytes, blobs: list[bytes], key: bytes | None) -> bytes:
    prefix = _PREFIX.pack(MAGIC, STATE_VERSION, len(text))
    return prefix + _seal(key, prefix, text, *blobs) + text + b"".join(blobs)


def _seal(key: bytes | None, *parts) -> bytes:
    """HMAC-SHA256 of the parts with `key`, or their SHA-256 without one (integrity, not authenticity)."""
    h = hashlib.sha256() if key is None else hmac.new(key, digestmod=hashlib.sha256)
    for p in parts:
        h.update(p)
    return h.digest()


def _parse(text: bytes) -> Any:
    """The header's JSON; StateError for what does not parse, NaN and infinities, and nesting too deep."""
    def refuse(v):
        raise StateError(f"saved stream state header holds {v}")

    def number(s: str) -> float:
        x = float(s)
        return x if np.isfinite(x) else refuse(s)
    try:
        return json.loads(text, parse_constant=refuse, parse_float=number)
    except RecursionError:
        raise StateError("saved stream state header is nested too deep") from None
    except StateError:
        raise
    except ValueError as e:  # (not JSON, not UTF-8, an integer of thousands of digits)
        raise StateError(f"saved stream state header does not parse: {e}") from None


def _build(nd: dict, raw: memoryview, dev: torch.device) -> Any:
    """The value of a node `savestate_checks.check_tree` accepted."""
    kind = nd["t"]
    if kind == "value":
        return nd["v"]
    if kind in ("tensor", "ndarray"):
        at, n, shape = nd["at"], nd["n"], tuple(nd["shape"])
        if kind == "ndarray":
            return np.frombuffer(raw[at:at + n], np.dtype(nd["dtype"])).reshape(shape).copy()
        dtype = _DTYPES[nd["dtype"]]
        if n == 0:
            return torch.zeros(shape, dtype=dtype, device=dev)
        return torch.frombuffer(bytearray(raw[at:at + n]), dtype=torch.uint8).view(dtype).reshape(shape).to(dev)
    if kind == "tuple":
        return tuple(_build(x, raw, dev) for x in nd["items"])
    return _TYPES[kind](**{f: _build(x, raw, dev) for f, x in nd["f"].items()})
