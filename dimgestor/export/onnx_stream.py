"""The exported frame step driven as a stream: audio chunks in, normalized frames out, in ONNX Runtime or torch.

`FrameStepStream` is the Python side of `dimgestor export-onnx`'s graph (`dimgestor.export.onnx_export` says why the
graph is a fixed number of motion frames): it buffers audio to whole calls (800 samples a frame), numbers the
calls' frames (below 0 during the warm-up, whose frames it drops) and passes the seed, from which the graph
draws the torch stream's noise; it pads the end with silence as `GestureStream.finish` does and applies the
same output filter. It calls the frame step through a `run(feeds) -> outputs` function: ONNX Runtime's session
(`ort_runner`), or the traced module itself in torch (`torch_runner`, the graph's reference). Its state is a
value, as `GestureStream`'s is: `step(state, samples) -> (frames, state)`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..audio import check_audio
from ..config import ModelConfig
from ..smoothing import OneEuroState
from ..streaming.stream import make_smoother

__all__ = ["FrameStepStream", "OnnxStreamState", "OnnxModel", "MANIFEST", "initial_tensor", "load_manifest", "ort_runner",
           "providers", "torch_runner", "ort_stream"]

Runner = Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]]
MANIFEST = "manifest.json"  # an export folder's description of its graphs (`dimgestor.export.onnx_export.manifest_of`)


def load_manifest(folder: str | Path) -> dict:
    return json.loads((Path(folder) / MANIFEST).read_text())


def initial_tensor(entry: dict) -> np.ndarray:
    """A manifest's state entry -> the state's start value (its shape and dtype, filled with its `init`)."""
    fill = float(entry["init"])  # "nan" reads as NaN
    return np.full(entry["shape"], fill, dtype=entry["dtype"])


@dataclass(frozen=True)
class OnnxStreamState:
    """What the stream carries between pushes (a value: a step never writes into the arrays it was given)."""

    tensors: dict  # the graph's state inputs by name: numpy arrays, or the runner's own values (OrtValue)
    pending: np.ndarray  # audio samples not yet a whole frame (< samples_per_call)
    smoother: OneEuroState | None = None
    samples_in: int = 0  # audio samples received (the audio clock)
    calls: int = 0  # graph calls made (call j makes frames (j - warmup_calls) M ... + M - 1)
    frames_out: int = 0
    finished: bool = False
    rows: tuple | None = None  # where `tensors` lie when a batched call made them: (its outputs, row, graph size)


class FrameStepStream:
    """A stream over the exported frame step; `run` is ONNX Runtime's session or the module in torch."""

    def __init__(self, manifest: dict, run: Runner, seed: int = 0, smoothing="config", lookahead_s: float | None = None):
        self.manifest, self.run, self.seed = manifest, run, int(seed)
        self.lookahead_s = lookahead_s  # the model's algorithmic latency (GestureStream.lookahead_s), when given
        self._seed = np.array([self.seed], np.int64)
        self.config = ModelConfig(**manifest["checkpoint"]["config"])
        call = manifest["call"]
        self.chunk, self.warmup, self.per_call = call["samples_per_call"], call["warmup_calls"], call["frames_per_call"]
        self.smoother = make_smoother(self.config, smoothing)
        self.state = self.initial_state()

    def initial_state(self) -> OnnxStreamState:
        return OnnxStreamState({s["input"]: initial_tensor(s) for s in self.manifest["state"]}, np.zeros(0, np.float32))

    @property
    def frames_out(self) -> int:
        return self.state.frames_out

    def call_inputs(self, call: int, samples: np.ndarray) -> dict[str, np.ndarray]:
        """The inputs other than the state of the stream's call number `call` (its `samples_per_call` samples)."""
        j = call - self.warmup  # this call makes frames [j M, (j + 1) M) (j < 0: warm-up)
        return {"samples": samples[None], "seed": self._seed, "frame": np.array([j * self.per_call], np.int64)}

    def _frames(self, state: OnnxStreamState, audio: np.ndarray) -> tuple[np.ndarray, OnnxStreamState]:
        """Whole frames of audio (a multiple of samples_per_call) after `state` -> frames, state."""
        n = len(audio) // self.chunk
        tensors, out = state.tensors, []
        for i in range(n):
            result = self.run({**self.call_inputs(state.calls + i, audio[i * self.chunk:(i + 1) * self.chunk]),
                               **tensors})
            tensors = {s["input"]: result[s["output"]] for s in self.manifest["state"]}
            out.append(result["frames"])
        return self.made(state, out, tensors, **({"rows": None} if n else {}))

    def made(self, state: OnnxStreamState, frames: list[np.ndarray], tensors: dict, **more
             ) -> tuple[np.ndarray, OnnxStreamState]:
        """The frames of len(frames) calls made after `state` (warm-up calls' frames dropped: the graph kept the
        denoiser's start state), their last state `tensors` -> the stream's new frames (smoothed), its state."""
        c, n = self.config, len(frames)
        real = [f for i, f in enumerate(frames) if state.calls + i >= self.warmup]
        frames = np.concatenate(real).astype(np.float32) if real else np.zeros((0, c.motion_dim), np.float32)
        smoothed = state.smoother
        if self.smoother is not None and len(frames):
            frames, smoothed = self.smoother.step(smoothed, frames)
        return frames, replace(state, tensors=tensors, smoother=smoothed, calls=state.calls + n,
                               frames_out=state.frames_out + len(frames), **more)

    def step(self, state: OnnxStreamState, samples) -> tuple[np.ndarray, OnnxStreamState]:
        """Mono float32 16 kHz samples (any length) after `state` -> the frames that became final, the state."""
        if state.finished:
            raise RuntimeError("push() after finish(): start a new stream")
        audio = np.concatenate([state.pending, check_audio(samples)])
        whole = len(audio) - len(audio) % self.chunk
        frames, state = self._frames(state, audio[:whole])
        return frames, replace(state, pending=audio[whole:], samples_in=state.samples_in + len(samples))

    def finish_step(self, state: OnnxStreamState) -> tuple[np.ndarray, OnnxStreamState]:
        """The end of the audio: silence up to the last frame's lookahead (as `GestureStream.finish_step`)."""
        if state.finished:
            return np.zeros((0, self.config.motion_dim), np.float32), state
        c = self.config
        T = state.samples_in * c.fps // c.sample_rate
        need = (-(-T // self.per_call) + self.warmup) * self.chunk if T else 0  # samples until frame T - 1 exists
        pad = max(need - state.samples_in, 0)
        frames, end = self.step(state, np.zeros(pad, np.float32))
        out = frames[: max(T - state.frames_out, 0)]
        return out, replace(end, frames_out=state.frames_out + len(out), finished=True)

    def push(self, samples) -> np.ndarray:
        frames, self.state = self.step(self.state, samples)
        return frames

    def finish(self) -> np.ndarray:
        frames, self.state = self.finish_step(self.state)
        return frames


def providers(device: str = "cpu") -> list:
    """ONNX Runtime's execution providers for `device`: "cpu", or "cuda[:N]": the CUDA provider on GPU N (the
    onnxruntime-gpu package), the CPU's for any node it does not run."""
    if device == "cpu":
        return ["CPUExecutionProvider"]
    return [("CUDAExecutionProvider", {"device_id": int(device.partition(":")[2] or 0)}), "CPUExecutionProvider"]


def ort_runner(folder: str | Path, threads: int = 1, device: str = "cpu") -> Runner:
    """ONNX Runtime's session on the exported graph, `threads` intra-op threads (1: the real-time setting), on
    `device` (`providers`).

    The states stay ONNX Runtime's own values (`OrtValue`) from one call to the next, bound as the next call's
    inputs where the last one wrote them: converting them to numpy and back copied every state twice a call
    (the denoiser's SSM state alone is 2 MB at K = 8): 7% of a K = 8 window on a quiet machine, 28% on a loaded one.
    A state output is never written again, so a state stays a value. `frames` comes back as numpy."""
    import onnxruntime as ort

    folder = Path(folder)
    manifest = load_manifest(folder)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = ort.InferenceSession(str(folder / manifest["graph"]), opts, providers=providers(device))
    names = [o.name for o in session.get_outputs()]
    states = {s["output"] for s in manifest["state"]}

    def run(feeds):
        io, held = session.io_binding(), []
        for name, value in feeds.items():
            if isinstance(value, ort.OrtValue):
                io.bind_ortvalue_input(name, value)
            else:
                held.append(array := np.ascontiguousarray(value))  # bound by address: alive until the run
                io.bind_cpu_input(name, array)
        for name in names:
            io.bind_output(name, "cpu")  # a fresh buffer each call: the inputs (last call's outputs) stay intact
        session.run_with_iobinding(io)
        return {n: v if n in states else v.numpy() for n, v in zip(names, io.get_outputs())}

    return run


def torch_runner(step) -> Runner:
    """The frame step module (`dimgestor.export.onnx_export.FrameStep`) in torch, with the graph's names."""
    names_in = ["samples", "seed", "frame", *(s.name for s in step.specs)]
    names_out = ["frames", *(s.out for s in step.specs)]

    def run(feeds):
        with torch.inference_mode():
            out = step(*(torch.from_numpy(np.ascontiguousarray(feeds[k])) for k in names_in))
        return {k: v.numpy() for k, v in zip(names_out, out)}

    return run


@dataclass(frozen=True)
class OnnxModel:
    """An export loaded once: its manifest and one ONNX Runtime session, shared by every stream made from it
    (a session's run is thread-safe, and each call binds its own inputs): `streamer serve --backend onnxruntime`
    loads the graph once for all its clients, not once per client."""

    folder: Path
    manifest: dict
    run: Runner
    device: str = "cpu"  # where its sessions run: "cpu" or "cuda[:N]" (`providers`)

    @classmethod
    def load(cls, folder: str | Path, threads: int = 1, device: str = "cpu") -> "OnnxModel":
        return cls(Path(folder), load_manifest(folder), ort_runner(folder, threads, device), device)

    def stream(self, seed: int = 0, smoothing="config", lookahead_s: float | None = None) -> FrameStepStream:
        return FrameStepStream(self.manifest, self.run, seed, smoothing, lookahead_s)


def ort_stream(folder: str | Path, seed: int = 0, smoothing="config", threads: int = 1,
               lookahead_s: float | None = None) -> FrameStepStream:
    """A stream on ONNX Runtime from an export folder (`dimgestor export-onnx --out folder`), on its own session."""
    return OnnxModel.load(folder, threads).stream(seed, smoothing, lookahead_s)
