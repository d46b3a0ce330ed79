"""Many streams on one GPU: torch CUDA against ONNX Runtime's CUDA provider, the embedded default model.

Each backend runs B streams in lockstep, one window of audio each per round, for B in the export's batch sizes:

- torch: the engine's own batched path (`dimgestor.streaming.batch.push_many` on B `GestureStream`s of the model on the
  GPU: one front-end and extractor call, then one denoiser forward per sampler step for the whole batch);
- onnxruntime: the export's graph of B streams (`dimgestor export-onnx --batch B`) on the CUDA execution
  provider, every input and output bound to a fixed GPU buffer (IO binding): the states never leave the GPU,
  each call's state outputs are copied into the next call's inputs on the device, and only the samples go up
  and the frames come down;
- onnxruntime_graph: the same with ONNX Runtime's CUDA graphs (the whole call replayed as one graph: no launch
  cost per node), where the session accepts them (every node on the CUDA provider).

A round's time is from the host's audio to the host's frames (synchronized). A batch size keeps real time when
its p95 round is under one window. The frames of the first streams are compared across backends (normalized
features), and one profiled call says where ONNX Runtime's nodes ran (CUDA or CPU) and their time.

    dimgestor export-onnx --out /tmp/k8 --steps 8 --batch 16 64 256 1024
    python benchmarks/onnx_cuda.py --exports /tmp/k8                  # on a machine with an NVIDIA GPU
    python benchmarks/onnx_cuda.py --exports /tmp/k8 --no-tf32 --out results/onnx_cuda_fp32.json   # frames compared
    python benchmarks/onnx_cuda.py --exports /tmp/k8 --device cpu     # the same code path on the CPU (a check)
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from common import RESULTS, code_version, describe_device, percentile_ms, test_audio, utc_now, write_json

BACKENDS = ("torch", "onnxruntime", "onnxruntime_graph")
NUMPY = {"float32": np.float32, "float64": np.float64, "int64": np.int64}
TORCH = {"float32": torch.float32, "float64": torch.float64, "int64": torch.int64}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--exports", type=Path, required=True, help="an export-onnx folder with graphs of several batch sizes")
    p.add_argument("--batches", type=int, nargs="*", default=None, help="batch sizes (default: every graph exported)")
    p.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS))
    p.add_argument("--device", default="cuda", help="cuda (the GPU) or cpu (checks this script where no GPU is)")
    p.add_argument("--rounds", type=int, default=16, help="timed rounds per batch size (after the warm-up)")
    p.add_argument("--warmup-rounds", type=int, default=3, help="untimed rounds after the model's own warm-up")
    p.add_argument("--compare-streams", type=int, default=4, help="streams whose frames are compared across backends")
    p.add_argument("--slow", type=float, default=4.0,
                   help="stop a backend's larger sizes once a round takes this many windows (median)")
    p.add_argument("--no-tf32", action="store_true",
                   help="full float32 on both backends (torch's cuDNN convolutions and ONNX Runtime's CUDA provider "
                        "use TF32 by default): for comparing their frames")
    p.add_argument("--code", default=None, help="the code version to record (default: git here)")
    p.add_argument("--out", type=Path, default=RESULTS / "onnx_cuda.json")
    p.add_argument("--note", default="")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


class AudioRows:
    """B streams' audio: the same speech-like signal at a different offset per stream (every row differs)."""

    def __init__(self, batch: int, window: int, rounds: int, sr: int):
        self.window = window
        span = window * rounds
        base = test_audio(span / sr + 7.0, sr)
        self.rows = [base[(i * 5813) % (7 * sr):][:span] for i in range(batch)]

    def round(self, k: int) -> list[np.ndarray]:
        return [r[k * self.window:(k + 1) * self.window] for r in self.rows]


def run_torch(bundle, steps: int, batch: int, audio: AudioRows, rounds: int, device: str, keep: int):
    from dimgestor.streaming.batch import push_many

    streams = [bundle.stream(steps=steps, seed=i) for i in range(batch)]
    times, frames = [], [[] for _ in range(min(keep, batch))]
    for k in range(rounds):
        chunks = audio.round(k)
        sync(device)
        t0 = time.perf_counter()
        outs = push_many(streams, chunks)
        sync(device)
        times.append(time.perf_counter() - t0)
        for r in range(len(frames)):
            frames[r].append(np.asarray(outs[r]))
    return times, [np.concatenate(f) for f in frames]


class OrtBatch:
    """An export's graph of B streams on ONNX Runtime, every input and output bound once to a fixed buffer (torch
    tensors on the device): a call copies the samples up, runs, copies the state outputs onto the inputs on the
    device and the frames down. Fixed addresses are what ONNX Runtime's CUDA graphs need."""

    def __init__(self, folder: Path, manifest: dict, batch: int, device: str, cuda_graph: bool, tf32: bool = True):
        import onnxruntime as ort

        graph = manifest["graph"] if batch == 1 else next(e["graph"] for e in manifest["batched"] if e["batch"] == batch)
        self.path = folder / graph
        self.manifest, self.batch, self.device = manifest, batch, device
        self.on_gpu = device.startswith("cuda")
        c = manifest["call"]
        self.per_call, self.warmup = c["frames_per_call"], c["warmup_calls"]
        dev = torch.device(device)

        def shape(entry):
            s = list(entry["shape"])
            s[entry["batch_dim"]] *= batch
            return s

        self.ins = {s["input"]: torch.from_numpy(np.full(shape(s), float(s["init"]), NUMPY[s["dtype"]])).to(dev)
                    for s in manifest["state"]}
        self.outs = {s["output"]: torch.empty(shape(s), dtype=TORCH[s["dtype"]], device=dev) for s in manifest["state"]}
        self.pairs = [(s["input"], s["output"]) for s in manifest["state"]]
        self.samples = torch.zeros(batch, c["samples_per_call"], device=dev)
        self.seed = torch.arange(batch, dtype=torch.int64, device=dev)
        self.frame = torch.zeros(batch, dtype=torch.int64, device=dev)
        D = manifest["outputs"][0]["shape"][-1]
        self.frames = torch.empty(([batch] if batch > 1 else []) + [self.per_call, D], device=dev)
        opts = ort.SessionOptions()
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        if self.on_gpu:
            cuda = {"device_id": str(dev.index or 0), "cudnn_conv_algo_search": "HEURISTIC",
                    "enable_cuda_graph": "1" if cuda_graph else "0", "use_tf32": "1" if tf32 else "0"}
            providers = [("CUDAExecutionProvider", cuda), "CPUExecutionProvider"]
        else:
            if cuda_graph:
                raise RuntimeError("CUDA graphs need the CUDA provider")
            opts.intra_op_num_threads = 1
            providers = ["CPUExecutionProvider"]
        self.session = ort.InferenceSession(str(self.path), opts, providers=providers)
        self.io = self.session.io_binding()
        kind = "cuda" if self.on_gpu else "cpu"
        for name, t in [("samples", self.samples), ("seed", self.seed), ("frame", self.frame), *self.ins.items()]:
            self.io.bind_input(name, kind, dev.index or 0, _np_type(t), list(t.shape), t.data_ptr())
        for name, t in [("frames", self.frames), *self.outs.items()]:
            self.io.bind_output(name, kind, dev.index or 0, _np_type(t), list(t.shape), t.data_ptr())
        self.calls = 0

    def push(self, chunks: list[np.ndarray]) -> np.ndarray | None:
        """One window of each stream (samples_per_call each) -> (B, M, D) frames, or None in the warm-up."""
        self.samples.copy_(torch.from_numpy(np.stack(chunks)))
        self.frame.fill_((self.calls - self.warmup) * self.per_call)
        sync(self.device)
        self.session.run_with_iobinding(self.io)
        self.io.synchronize_outputs()
        for i, o in self.pairs:
            self.ins[i].copy_(self.outs[o])
        frames = self.frames.to("cpu", copy=True).numpy().reshape(self.batch, self.per_call, -1)  # (a copy on the CPU too)
        self.calls += 1
        return frames if self.calls > self.warmup else None


def _np_type(t: torch.Tensor):
    return {torch.float32: np.float32, torch.float64: np.float64, torch.int64: np.int64}[t.dtype]


def run_ort(folder, manifest, batch, audio: AudioRows, rounds, device, keep, cuda_graph, tf32=True):
    runner = OrtBatch(folder, manifest, batch, device, cuda_graph, tf32)
    times, frames = [], [[] for _ in range(min(keep, batch))]
    for k in range(rounds):
        chunks = audio.round(k)
        t0 = time.perf_counter()
        out = runner.push(chunks)
        sync(device)
        times.append(time.perf_counter() - t0)
        if out is not None:
            for r in range(len(frames)):
                frames[r].append(out[r])
    return times, [np.concatenate(f) if f else np.zeros((0, 0)) for f in frames]


def where_nodes_ran(folder: Path, manifest: dict, device: str) -> dict:
    """One profiled call of the graph of 1 stream (after two unprofiled): nodes and their time by provider."""
    import onnxruntime as ort

    providers = [("CUDAExecutionProvider", {"cudnn_conv_algo_search": "HEURISTIC"}), "CPUExecutionProvider"] if (
        device.startswith("cuda")) else ["CPUExecutionProvider"]
    c = manifest["call"]
    feeds = {"samples": np.zeros((1, c["samples_per_call"]), np.float32), "seed": np.zeros(1, np.int64),
             "frame": np.zeros(1, np.int64)}
    feeds |= {s["input"]: np.full(s["shape"], float(s["init"]), NUMPY[s["dtype"]]) for s in manifest["state"]}
    with tempfile.TemporaryDirectory(prefix="onnx-cuda-profile-") as tmp:  # (read here, then gone: ~5 MB a run)
        opts = ort.SessionOptions()
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(tmp) / "profile")
        session = ort.InferenceSession(str(folder / manifest["graph"]), opts, providers=providers)
        for _ in range(3):
            session.run(None, feeds)
        events = json.loads(Path(session.end_profiling()).read_text())
    runs = [e for e in events if e.get("name") == "model_run"]
    last_start = runs[-1]["ts"] if runs else 0
    by, ops = {}, {}
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time") and e["ts"] >= last_start:
            p = e.get("args", {}).get("provider", "?")
            n, us = by.get(p, (0, 0))
            by[p] = (n + 1, us + e.get("dur", 0))
            op = e.get("args", {}).get("op_name", "?")
            ops.setdefault(p, {})[op] = ops.get(p, {}).get(op, 0) + 1
    return {p: {"nodes": n, "ms": us / 1000, "op_types": dict(sorted(ops[p].items(), key=lambda kv: -kv[1])[:25])}
            for p, (n, us) in by.items()}


def main(argv=None) -> int:
    args = parse_args(argv)
    from dimgestor.export.onnx_stream import load_manifest
    from dimgestor.streaming.checkpoint import load_checkpoint

    if args.device.startswith("cuda"):
        import onnxruntime as ort

        if hasattr(ort, "preload_dlls"):
            ort.preload_dlls()  # CUDA, cuDNN from the nvidia-* wheels torch uses
    else:
        torch.set_num_threads(1)
    if args.no_tf32:
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    import onnxruntime as ort

    manifest = load_manifest(args.exports)
    steps = manifest["sampler"]["steps"]
    sizes = sorted({1} | {e["batch"] for e in manifest.get("batched", [])})
    sizes = [b for b in sizes if args.batches is None or b in args.batches]
    c = manifest["call"]
    window = c["samples_per_call"]
    window_s = window / c["sample_rate"]
    bundle = load_checkpoint(None, device=args.device)
    rounds = c["warmup_calls"] + args.warmup_rounds + args.rounds
    skip = c["warmup_calls"] + args.warmup_rounds
    rows, stopped, errors, cmp = [], {}, {}, []
    for b in sizes:
        audio = AudioRows(b, window, rounds, c["sample_rate"])
        row = {"batch": b}
        kept = {}
        for name in args.backends:
            if name in stopped or name in errors:
                continue
            if args.device.startswith("cuda"):
                torch.cuda.reset_peak_memory_stats()
            try:
                if name == "torch":
                    with torch.no_grad():
                        times, frames = run_torch(bundle, steps, b, audio, rounds, args.device, args.compare_streams)
                else:
                    times, frames = run_ort(args.exports, manifest, b, audio, rounds, args.device,
                                            args.compare_streams, name == "onnxruntime_graph", not args.no_tf32)
            except Exception as e:  # noqa: BLE001  (a backend that cannot run here is recorded, not fatal)
                import traceback

                errors[name] = f"B={b}: {type(e).__name__}: {e}"[:2000]
                traceback.print_exc()
                print(f"{name} B={b}: failed: {errors[name][:300]}")
                continue
            t = times[skip:]
            r = {"ms_p50": percentile_ms(t, 50), "ms_p95": percentile_ms(t, 95), "ms_mean": float(np.mean(t) * 1000),
                 "rounds": len(t), "realtime": percentile_ms(t, 95) < window_s * 1000}
            r["ms_per_stream"] = r["ms_p50"] / b
            if name == "torch" and args.device.startswith("cuda"):
                r["peak_allocated_mb"] = torch.cuda.max_memory_allocated() / 2**20
            row[name] = r
            kept[name] = frames
            print(f"B={b:5d} {name:18s} p50 {r['ms_p50']:8.2f} ms a round ({r['ms_per_stream']:.3f} ms a stream), "
                  f"p95 {r['ms_p95']:8.2f}, real time {r['realtime']}")
            if r["ms_p50"] > args.slow * window_s * 1000:
                stopped[name] = b
        for a in kept:
            for z in kept:
                if a < z:
                    n = min(min(len(x) for x in kept[a]), min(len(x) for x in kept[z]))
                    d = max(float(np.abs(x[:n] - y[:n]).max()) for x, y in zip(kept[a], kept[z])) if n else None
                    cmp.append({"batch": b, "a": a, "b": z, "frames": n, "max_abs_diff": d})
                    print(f"B={b}: {a} vs {z}: frames differ by {d} over {n} frames of {len(kept[a])} streams")
        rows.append(row)
        if args.device.startswith("cuda"):
            torch.cuda.empty_cache()
    try:
        placement = where_nodes_ran(args.exports, manifest, args.device)
    except Exception as e:  # noqa: BLE001
        placement = {"error": f"{type(e).__name__}: {e}"[:500]}
    print("nodes by provider, one call of 1 stream:", placement)
    best = {n: max([r["batch"] for r in rows if r.get(n, {}).get("realtime")], default=0) for n in args.backends}
    device = describe_device(args.device) + f", onnxruntime {ort.__version__} ({ort.get_device()})"
    result = {"benchmark": "onnx_cuda", "date": utc_now(), "code": args.code or code_version(), "argv": args.argv,
              "device": device, "note": args.note, "steps": steps, "guidance": manifest["sampler"]["guidance"],
              "tf32": "off on both" if args.no_tf32 else "each library's default (torch: cuDNN convolutions; ONNX "
                                                          "Runtime CUDA: on)",
              "window_ms": window_s * 1000, "model": "embedded default", "rows": rows, "compare": cmp,
              "largest_realtime_batch": best, "stopped_after": stopped, "errors": errors,
              "onnxruntime_nodes_by_provider": placement}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common import save_panels

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for name in BACKENDS:
        pts = [(r["batch"], r[name]) for r in result["rows"] if name in r]
        if not pts:
            continue
        bs = [b for b, _ in pts]
        axes[0].plot(bs, [m["ms_p50"] for _, m in pts], "o-", label=f"{name} (p50)")
        axes[1].plot(bs, [m["ms_per_stream"] for _, m in pts], "o-", label=name)
    axes[0].axhline(result["window_ms"], color="k", lw=1, ls="--", label="one window (real time)")
    for ax in axes:
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("streams in lockstep (batch)")
    axes[0].set_ylabel("ms per round (every stream's window)")
    axes[1].set_ylabel("ms per stream per window")
    save_panels(fig, axes, f"K = {result['steps']}, {result['window_ms']:.0f} ms windows: {result['device']}", path)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
