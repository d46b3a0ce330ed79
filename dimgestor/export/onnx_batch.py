"""Many streams' windows as one ONNX Runtime call: the serving path of `streamer serve --backend onnxruntime`.

The exported frame step costs about the same per call whatever it computes (on CPU a model this small pays for
its ~4,600 ops, not for arithmetic: `dimgestor.export.onnx_export`), so the calls of B streams made as one call of a
graph of B streams (`dimgestor export-onnx --batch B`, a stream per row) pay that once. `BatchRunner` holds a
session per exported batch size and makes n streams' calls with the cheapest mix of those sizes, padding a call
with idle rows where a bigger graph costs less than more calls (`plan`, on each graph's cost measured at load).

The states are the streams' own values, as on the single-stream path: a batched call's outputs are fresh arrays
(bound by address, never written again) and each stream keeps views of its rows. Gathering B streams' states
into one batch copies them (the denoiser's SSM state is ~2 MB a stream at K = 8), so when the same streams come
back in the same order (a busy server: every stream has a window due each cycle) the last call's outputs are fed
back as they are, with no copy at all, as `dimgestor.model.sampler.denoise` does for torch.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from ..audio import check_audio
from .onnx_stream import FrameStepStream, OnnxModel, OnnxStreamState, initial_tensor, providers

__all__ = ["BatchRunner", "BatchStats", "push_many"]

_CALL_INPUTS = ("samples", "seed", "frame")


@dataclass
class BatchStats:
    """What the batched calls cost: calls and rows by graph size, seconds gathering states and running."""

    calls: dict = field(default_factory=dict)  # graph size -> calls
    rows: int = 0  # stream rows computed (padding excluded)
    padded: int = 0  # idle rows computed
    gathers: int = 0  # calls whose states were copied together (not the last call's outputs fed back)
    gather_s: float = 0.0
    run_s: float = 0.0


class BatchRunner:
    """ONNX Runtime sessions on an export's graphs of 1 and of each `batched` size: n streams' calls as few calls.

    cost: seconds per call by graph size, measured at load (`plan` mixes sizes by it); give it to skip that."""

    def __init__(self, folder: str | Path, manifest: dict, threads: int = 1, cost: dict[int, float] | None = None,
                 device: str = "cpu"):
        import onnxruntime as ort

        self.manifest, self.threads = manifest, threads
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        graphs = {1: manifest["graph"], **{e["batch"]: e["graph"] for e in manifest.get("batched", [])}}
        self.sessions = {b: ort.InferenceSession(str(Path(folder) / g), opts, providers=providers(device))
                         for b, g in sorted(graphs.items())}
        self.sizes = sorted(self.sessions)
        self.states = manifest["state"]
        self.names = [o.name for o in self.sessions[1].get_outputs()]
        self.stats = BatchStats()
        self._idle_rows: dict[int, dict[str, np.ndarray]] = {}
        self.cost = dict(cost) if cost is not None else self._measure()
        self._plans: dict[int, list[int]] = {}

    @classmethod
    def of(cls, model: OnnxModel, threads: int = 1) -> "BatchRunner":
        """Sessions on a loaded export's graphs: the calls of many of its streams as few calls (`push_many`)."""
        return cls(model.folder, model.manifest, threads, device=model.device)

    # ---- shapes ----------------------------------------------------------------------------------

    def _shape(self, entry: dict, size: int) -> list[int]:
        shape = list(entry["shape"])
        shape[entry["batch_dim"]] *= size
        return shape

    def idle_inputs(self, size: int) -> dict[str, np.ndarray]:
        """Inputs of `size` idle rows (silence, a stream's start state), to pad a call (made once: only read)."""
        if size in self._idle_rows:
            return self._idle_rows[size]
        c = self.manifest["call"]
        feeds = {"samples": np.zeros((size, c["samples_per_call"]), np.float32),
                 "seed": np.zeros(size, np.int64), "frame": np.zeros(size, np.int64)}
        feeds |= {s["input"]: initial_tensor({**s, "shape": self._shape(s, size)}) for s in self.states}
        self._idle_rows[size] = feeds
        return feeds

    def _measure(self, repeats: int = 2) -> dict[int, float]:
        """Seconds per call of each graph (the best of `repeats` after one warm call): what `plan` weighs."""
        cost = {}
        for size in self.sizes:
            feeds = self.idle_inputs(size)
            times = []
            for _ in range(repeats + 1):
                t0 = time.perf_counter()
                self.run_graph(size, feeds)
                times.append(time.perf_counter() - t0)
            cost[size] = min(times[1:])
        return cost

    def plan(self, n: int) -> list[int]:
        """The graph sizes, largest first, whose calls make n streams' calls at the least measured cost (the last
        one may hold idle rows)."""
        if n not in self._plans:
            best = {0: (0.0, [])}  # rows covered -> (cost, sizes)
            for m in range(1, n + 1):
                best[m] = min(((best[max(m - s, 0)][0] + self.cost[s], best[max(m - s, 0)][1] + [s])
                               for s in self.sizes), key=lambda x: (x[0], len(x[1])))
            self._plans[n] = sorted(best[n][1], reverse=True)
        return self._plans[n]

    # ---- calls -----------------------------------------------------------------------------------

    def run_graph(self, size: int, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """One run of the graph of `size` streams, its outputs written into fresh arrays (bound by address)."""
        session = self.sessions[size]
        io, out = session.io_binding(), {}
        for name, value in feeds.items():
            io.bind_cpu_input(name, value)
        c = self.manifest
        frames = [size, c["call"]["frames_per_call"], c["outputs"][0]["shape"][-1]]
        for name, shape, dtype in [("frames", frames if size > 1 else frames[1:], np.float32)] + [
                (s["output"], self._shape(s, size), s["dtype"]) for s in self.states]:
            out[name] = a = np.empty(shape, dtype)
            io.bind_output(name, "cpu", element_type=a.dtype.type, shape=a.shape, buffer_ptr=a.ctypes.data)
        session.run_with_iobinding(io)
        return out

    def run(self, calls: Sequence[tuple[dict, OnnxStreamState]]) -> list[tuple[np.ndarray, dict, tuple]]:
        """Each stream's call (its `call_inputs`, the state it continues) -> (its frames (M, D), its new state
        tensors (views of its rows), where they lie (the call's outputs, row, graph size)), in order."""
        results, i = [], 0
        for size in self.plan(len(calls)):
            part = calls[i:i + size]
            i += len(part)
            feeds = self._feeds(size, part)
            t0 = time.perf_counter()
            out = self.run_graph(size, feeds)
            self.stats.run_s += time.perf_counter() - t0
            self.stats.calls[size] = self.stats.calls.get(size, 0) + 1
            self.stats.rows += len(part)
            self.stats.padded += size - len(part)
            for r in range(len(part)):
                frames = out["frames"][r] if size > 1 else out["frames"]
                results.append((frames, self._rows(out, r, size), (out, r, size)))
        return results

    def _rows(self, out: dict, r: int, size: int) -> dict[str, np.ndarray]:
        """Row r's state in a call's outputs: views (no copy)."""
        if size == 1:
            return {s["input"]: out[s["output"]] for s in self.states}
        views = {}
        for s in self.states:
            k, d = s["shape"][s["batch_dim"]], s["batch_dim"]
            views[s["input"]] = out[s["output"]][(slice(None),) * d + (slice(r * k, (r + 1) * k),)]
        return views

    def _feeds(self, size: int, part: Sequence[tuple[dict, OnnxStreamState]]) -> dict[str, np.ndarray]:
        """A call's inputs: the streams' rows, then idle rows; the states fed back as they lie where the same
        streams were this call's rows last time, else copied together."""
        n = len(part)
        feeds = {k: np.concatenate([inputs[k] for inputs, _ in part]) for k in _CALL_INPUTS}
        first = part[0][1].rows
        same = first is not None and all(st.rows is not None and st.rows[0] is first[0] and st.rows[1:] == (r, size)
                                         for r, (_, st) in enumerate(part))
        if n < size:
            idle = self.idle_inputs(size - n)
            feeds = {k: np.concatenate([v, idle[k]]) for k, v in feeds.items()}
        if same:  # (the idle rows' states are the last call's too: they stay a silent stream's)
            return feeds | {s["input"]: first[0][s["output"]] for s in self.states}
        t0 = time.perf_counter()
        for s in self.states:
            parts = [_array(st.tensors[s["input"]]) for _, st in part]
            if n < size:
                parts.append(idle[s["input"]])
            feeds[s["input"]] = np.ascontiguousarray(parts[0]) if len(parts) == 1 else np.concatenate(
                parts, s["batch_dim"])
        self.stats.gathers += 1
        self.stats.gather_s += time.perf_counter() - t0
        return feeds


def _array(value) -> np.ndarray:
    """A state tensor as numpy: an ONNX Runtime value (the single-stream runner's) is copied out."""
    return value if isinstance(value, np.ndarray) else value.numpy()


def push_many(runner: BatchRunner, streams: Sequence[FrameStepStream], chunks: Sequence,
              return_exceptions: bool = False) -> list:
    """Push chunks[i] into streams[i] (distinct streams of one export) -> each one's new frames, as `push` would,
    every stream's j-th call of this push made together with the others' (`BatchRunner.run`). A stream whose
    audio is bad (or that has finished) gets its exception in its place and keeps its state (return_exceptions),
    else the first is raised."""
    if len({id(s) for s in streams}) != len(streams):
        raise ValueError("push_many: each stream at most once per call")
    if len(chunks) != len(streams):
        raise ValueError(f"push_many: {len(streams)} streams but {len(chunks)} chunks")
    out: list = [None] * len(streams)
    audio: dict[int, np.ndarray] = {}
    for i, (s, chunk) in enumerate(zip(streams, chunks)):
        try:
            if s.state.finished:
                raise RuntimeError("push() after finish(): start a new stream")
            audio[i] = np.concatenate([s.state.pending, check_audio(chunk)])
        except Exception as e:
            if not return_exceptions:
                raise
            out[i] = e
    calls = {i: len(a) // streams[i].chunk for i, a in audio.items()}
    states = {i: streams[i].state for i in audio}
    made: dict[int, list] = {i: [] for i in audio}
    for j in range(max(calls.values(), default=0)):  # every stream's j-th call together
        live = [i for i in audio if calls[i] > j]
        todo = []
        for i in live:
            s, c = streams[i], streams[i].chunk
            todo.append((s.call_inputs(states[i].calls + j, audio[i][j * c:(j + 1) * c]), states[i]))
        for i, (frames, tensors, rows) in zip(live, runner.run(todo)):
            made[i].append(frames)
            states[i] = replace(states[i], tensors=tensors, rows=rows)
    for i in audio:
        s, start = streams[i], streams[i].state
        frames, new = s.made(states[i], made[i], states[i].tensors)  # (states[i].calls: still the push's first)
        s.state = replace(new, pending=audio[i][calls[i] * s.chunk:],
                          samples_in=start.samples_in + len(audio[i]) - len(start.pending))
        out[i] = frames
    return out
