"""Stored session states written bad, then resumed over a real connection (issue 52, item 3): for the test of a worker
whose store anyone may write to (no --state-secret-file), beside a bystander paced in real time.

`mutate` changes one thing in a real saved state (a float of any size or NaN in one of its arrays, every float of
them, a bit of the arrays' bytes, a counter or a root value in its header) and seals it anew without a secret, as
anyone who can write to the store can. `fuzz` (run in a process of its own: `run`) writes one mutation after another
into a real redis-server and resumes each on a new connection, then talks for a moment, and keeps what came back."""

from __future__ import annotations

import asyncio
import json
import math
import time

import numpy as np

from dimgestor.streaming import savestate

COUNTERS = (-1, 2 ** 31, 2 ** 33, 2 ** 63, 10 ** 200, -10 ** 12)
KINDS = ("scale", "nan", "every", "flip", "counter", "root")


def _leaves(v):
    """The header's tensor and array nodes."""
    if isinstance(v, dict):
        if v.get("t") in ("tensor", "ndarray"):
            yield v
        for x in v.values():
            yield from _leaves(x)


def _ints(v, path=()):
    """(path, parent) of every integer in the header (not a boolean)."""
    items = v.items() if isinstance(v, dict) else enumerate(v) if isinstance(v, list) else ()
    for k, x in items:
        if isinstance(x, int) and not isinstance(x, bool):
            yield path + (k,), v
        else:
            yield from _ints(x, path + (k,))


def mutate(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """One change to the saved state `data`, sealed anew without a secret -> (the bytes, what was done)."""
    header, raw = savestate.split(data)
    kind = KINDS[rng.integers(len(KINDS))]
    floats = [x for x in _leaves(header["state"]) if x["n"] and "float" in x["dtype"]]
    b = bytearray(raw)
    if kind in ("scale", "nan"):
        leaf = floats[rng.integers(len(floats))]
        size = 8 if "64" in leaf["dtype"] else 4
        i = leaf["at"] + size * int(rng.integers(leaf["n"] // size))
        old = float(np.frombuffer(bytes(b[i:i + size]), f"<f{size}")[0])
        if kind == "scale":
            power = int(rng.integers(0, 39))
            value = float(rng.choice([old * 10.0 ** power, -old * 10.0 ** power, 10.0 ** power, -(10.0 ** power)]))
        else:
            value = float(rng.choice([np.nan, np.inf, -np.inf]))
        with np.errstate(over="ignore"):
            b[i:i + size] = np.array(value, f"<f{size}").tobytes()
        return savestate.pack(header, bytes(b)), f"{kind}: {value:.3g} into {leaf['dtype']} at byte {i}"
    if kind == "every":
        value = float(rng.choice([1e30, -1e30, 1e6, 3e38]))
        for leaf in floats:
            size = 8 if "64" in leaf["dtype"] else 4
            b[leaf["at"]:leaf["at"] + leaf["n"]] = np.full(leaf["n"] // size, value, f"<f{size}").tobytes()
        return savestate.pack(header, bytes(b)), f"every float {value:.3g}"
    if kind == "flip":
        i = int(rng.integers(len(b)))
        b[i] ^= 1 << int(rng.integers(8))
        return savestate.pack(header, bytes(b)), f"flip a bit of byte {i}"
    if kind == "counter":
        paths = list(_ints(header))
        path, parent = paths[rng.integers(len(paths))]
        parent[path[-1]] = int(rng.choice(COUNTERS))
        return savestate.pack(header, bytes(b)), f"{'.'.join(map(str, path))} = {parent[path[-1]]}"
    key = ("x", "z", "heading")[rng.integers(3)]
    header["meta"]["decoder"][key] = float(rng.choice([1e38, -1e300, np.nan, np.inf, 1e5]))
    return savestate.pack(header, bytes(b)), f"meta.decoder.{key} = {header['meta']['decoder'][key]}"


def _finite(v) -> bool:
    if isinstance(v, float):
        return math.isfinite(v)
    if isinstance(v, dict):
        return all(map(_finite, v.values()))
    if isinstance(v, list):
        return all(map(_finite, v))
    return True


async def _attempt(url: str, token: str) -> dict:
    """resume_session with `token` on a new connection, then 0.5 s of audio and audio_end -> what came back."""
    from websockets.asyncio.client import connect

    async with connect(url, max_size=None) as ws:
        assert json.loads(await asyncio.wait_for(ws.recv(), 30))["type"] == "hello"
        await ws.send(json.dumps({"type": "hello", "protocol": 1, "encoding": "json"}))
        await ws.send(json.dumps({"type": "resume_session", "token": token}))
        while (reply := json.loads(await asyncio.wait_for(ws.recv(), 30)))["type"] not in ("session_resumed", "error"):
            pass  # (a `status`, say)
        speech = (0.1 * np.sin(np.arange(8000) * 0.05) * 32767).astype("<i2")
        await ws.send(speech.tobytes())
        await ws.send(json.dumps({"type": "audio_end"}))
        out = {"reply": reply["type"] if reply["type"] != "error" else reply["code"],
               "reason": reply.get("message", ""), "frames": 0, "non_finite": 0, "errors": [], "end": False}
        while True:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 30))
            if msg["type"] == "frame":
                out["frames"] += 1
                out["non_finite"] += not _finite(msg)
            elif msg["type"] == "error":
                out["errors"].append(f"{msg['code']}: {msg.get('message', '')}")
            elif msg["type"] == "end":
                out["end"] = True
                return out


async def fuzz(url: str, store_url: str, data: bytes, seconds: float, seed: int, started) -> list[dict]:
    """Mutations of `data` written into the store at `store_url` and resumed one after another for `seconds`."""
    from streamer.handover import open_store

    store, rng = open_store(store_url), np.random.default_rng(seed)
    results, t_end, i = [], time.monotonic() + seconds, 0
    while time.monotonic() < t_end:
        mutated, what = mutate(data, rng)
        store.put(f"fuzz-{seed}-{i}", mutated)
        result = await _attempt(url, f"fuzz-{seed}-{i}")
        results.append({"what": what, **result})
        started.set()
        i += 1
    return results


def run(url: str, store_url: str, data: bytes, seconds: float, seed: int, started, out: str) -> None:
    """`fuzz` in this process; its results written to the JSON file `out`."""
    results = asyncio.run(fuzz(url, store_url, data, seconds, seed, started))
    with open(out, "w") as f:
        json.dump(results, f)
