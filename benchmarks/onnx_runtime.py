"""One stream's per-window cost, torch against ONNX Runtime: the embedded default model at K = 1, 4, 8, 1 thread;
and how many real-time streams one process keeps on each backend.

For each K the model is exported (`dimgestor export-onnx`, one window a call) and both backends stream the same
audio window by window as fast as possible, interleaved so that a shared machine's load falls on both alike:
`--interleave rounds` (default) alternates whole rounds (each backend streams the audio alone, its weights warm
in the cache, as one stream in a process is), `windows` alternates single windows (window k of one backend, then
of the other: the same load second by second, but each evicts the other's weights from the cache). Each push
is timed; the result is the median and p90 per window, the
real-time factor (mean cost / window length), the ONNX Runtime / torch ratio of the medians, and the largest
difference between the two backends' frames (normalized features).

Streams per process (`--streams K...`, default K = 8): `benchmarks/streams.py`'s serving trial (paced sessions
on one executor, staggered phases; a count keeps real time when its p95 lag stays under a window + 150 ms) for
torch batched (one StreamBatcher on every core: `streamer serve`'s default), torch unbatched and ONNX Runtime (one
session shared by all streams, each window alone on a RankedExecutor thread per core: `streamer serve
--backend onnxruntime`), doubling then bisecting the count to 10 %.

    python benchmarks/onnx_runtime.py                       # K = 1, 4, 8 at 100 ms windows; streams at K = 8
    python benchmarks/onnx_runtime.py --exports /tmp/onnx   # keep the exported graphs for the next run
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, percentile_ms, test_audio, utc_now, write_json


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, nargs="+", default=[1, 4, 8], help="DDIM steps K")
    p.add_argument("--window-ms", type=int, default=100, help="audio pushed per call (a multiple of 50 ms)")
    p.add_argument("--audio-s", type=float, default=6.0, help="audio per round")
    p.add_argument("--rounds", type=int, default=4, help="rounds per K (fresh streams each)")
    p.add_argument("--interleave", choices=("rounds", "windows"), default="rounds",
                   help="alternate the backends by whole rounds (each cache-warm) or by single windows")
    p.add_argument("--exports", type=Path, default=None,
                   help="folder of the exported graphs (reused when present; default: a temporary folder)")
    p.add_argument("--streams", type=int, nargs="*", default=[8], metavar="K",
                   help="K values for the streams-per-process comparison (none: skip it)")
    p.add_argument("--streams-s", type=float, default=8.0, help="audio per streams trial (s)")
    p.add_argument("--streams-max", type=int, default=160, help="largest stream count tried")
    p.add_argument("--out", type=Path, default=RESULTS / "onnx_runtime.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def export_for(folder: Path, steps: int, frames: int) -> Path:
    from dimgestor.onnx_export import MANIFEST, export_onnx

    out = folder / f"default_k{steps}_f{frames}"
    if not (out / MANIFEST).is_file():
        t0 = time.perf_counter()
        export_onnx(None, out, steps=steps, frames=frames)
        print(f"exported K={steps} in {time.perf_counter() - t0:.0f} s")
    return out


def lockstep(streams: dict, audio: np.ndarray, window: int) -> tuple[dict, dict]:
    """Push the audio window by window into every stream, window k of each before window k + 1 of any, the
    order alternating -> (seconds per push, the frames), each by backend."""
    names = list(streams)
    times, frames = {b: [] for b in names}, {b: [] for b in names}
    for k, a in enumerate(range(0, len(audio), window)):
        for b in names if k % 2 == 0 else names[::-1]:
            t0 = time.perf_counter()
            frames[b].append(streams[b].push(audio[a:a + window]))
            times[b].append(time.perf_counter() - t0)
    return times, {b: np.concatenate(f) for b, f in frames.items()}


def summary(times: list[float], window_s: float) -> dict:
    return {"ms_p50": percentile_ms(times, 50), "ms_p90": percentile_ms(times, 90),
            "ms_mean": float(np.mean(times) * 1000), "rtf": float(np.mean(times) / window_s), "windows": len(times)}


def measure(bundle, folder: Path, steps: int, args) -> dict:
    from dimgestor.onnx_stream import ort_stream

    c = bundle.config
    frames = args.window_ms * c.fps // 1000
    export = export_for(folder, steps, frames)
    window = c.sample_rate * args.window_ms // 1000
    audio = test_audio(args.audio_s, c.sample_rate)
    skip = int(np.ceil(1000 * bundle.model.lookahead_s / args.window_ms)) + 1  # warm-up windows make no frame
    make = {"torch": lambda: bundle.stream(steps=steps), "onnxruntime": lambda: ort_stream(export, threads=1)}
    lockstep({b: new() for b, new in make.items()}, audio[: window * (skip + 2)], window)  # first calls allocate
    times, out = {b: [] for b in make}, {}
    for r in range(args.rounds):
        if args.interleave == "windows":
            t, out = lockstep({b: new() for b, new in make.items()}, audio, window)
        else:  # whole rounds, the first backend alternating
            t = {}
            for b in list(make) if r % 2 == 0 else list(make)[::-1]:
                tb, fb = lockstep({b: make[b]()}, audio, window)
                t[b], out[b] = tb[b], fb[b]
        for b in make:
            times[b] += t[b][skip:]
    window_s = args.window_ms / 1000
    row = {"steps": steps, "frames_per_call": frames, **{b: summary(times[b], window_s) for b in make}}
    row["ratio_p50"] = row["onnxruntime"]["ms_p50"] / row["torch"]["ms_p50"]
    row["ratio_mean"] = row["onnxruntime"]["ms_mean"] / row["torch"]["ms_mean"]
    row["max_abs_diff"] = float(np.abs(out["onnxruntime"] - out["torch"]).max())
    print(f"K={steps}: torch p50 {row['torch']['ms_p50']:.2f} ms, ONNX Runtime p50 {row['onnxruntime']['ms_p50']:.2f} ms "
          f"(ratio {row['ratio_p50']:.2f}), frames differ by {row['max_abs_diff']:.1e}")
    return row


def streams(bundle, folder: Path, steps: int, args) -> dict:
    """Real-time streams in one process at K = steps: torch batched and unbatched, ONNX Runtime (shared session)."""
    import os

    from dimgestor.onnx_stream import OnnxModel
    from streams import max_streams

    c = bundle.config
    onnx = OnnxModel.load(export_for(folder, steps, args.window_ms * c.fps // 1000))
    cores = os.cpu_count() or 1
    common = dict(steps=steps, window_ms=args.window_ms, seconds=args.streams_s, cap=args.streams_max)
    row = {"steps": steps, "cores": cores,
           "torch_batched": max_streams(bundle, batched=True, threads=cores, **common),
           "torch_unbatched": max_streams(bundle, batched=False, threads=1, **common),
           "onnxruntime": max_streams(bundle, batched=False, threads=1, onnx=onnx, **common)}
    n = {k: row[k]["max_realtime_streams"] for k in ("torch_batched", "torch_unbatched", "onnxruntime")}
    row["max_realtime_streams"] = n
    row["ratio_onnxruntime_to_torch_batched"] = n["onnxruntime"] / max(n["torch_batched"], 1)
    print(f"K={steps} streams per process: torch batched {n['torch_batched']}, unbatched {n['torch_unbatched']}, "
          f"ONNX Runtime {n['onnxruntime']} ({row['ratio_onnxruntime_to_torch_batched']:.2f}x torch batched)")
    return row


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common import save_panels

    rows = result["results"]
    x = np.arange(len(rows))
    srows = result.get("streams") or []
    fig, axes = plt.subplots(1, 3 if srows else 2, figsize=(13.5 if srows else 9, 3.4))
    for i, backend in enumerate(("torch", "onnxruntime")):
        p50 = [r[backend]["ms_p50"] for r in rows]
        p90 = [r[backend]["ms_p90"] for r in rows]
        axes[0].bar(x + (i - 0.5) * 0.38, p50, 0.38, yerr=[[0] * len(rows), np.subtract(p90, p50)], capsize=3,
                    label=f"{backend} (p50, p90 whisker)")
    axes[0].set_xticks(x, [f"K={r['steps']}" for r in rows])
    axes[0].set_ylabel(f"ms per {result['window_ms']} ms window")
    axes[1].plot([r["steps"] for r in rows], [r["ratio_p50"] for r in rows], "o-", label="ONNX Runtime / torch (p50)")
    axes[1].axhline(0.5, color="k", lw=1, ls="--", label="target 0.5")
    axes[1].set_xlabel("K")
    axes[1].set_ylim(0, max(1.1, max(r["ratio_p50"] for r in rows) * 1.1))
    if srows:
        names = ("torch_batched", "torch_unbatched", "onnxruntime")
        xs = np.arange(len(srows))
        for i, name in enumerate(names):
            axes[2].bar(xs + (i - 1) * 0.27, [r["max_realtime_streams"][name] for r in srows], 0.27,
                        label=name.replace("_", " "))
        axes[2].set_xticks(xs, [f"K={r['steps']}" for r in srows])
        axes[2].set_ylabel(f"real-time streams, one process, {srows[0]['cores']} cores")
        axes[2].legend(fontsize=7)
    save_panels(fig, axes, f"one stream, default model, 1 thread, interleaved by {result['interleave']}: "
                           f"{result['device']}", path)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    import torch

    from dimgestor.checkpoint import load_checkpoint

    torch.set_num_threads(1)
    bundle = load_checkpoint(None)
    bundle.model.eval()
    with tempfile.TemporaryDirectory(prefix="onnx-bench-") as tmp:
        folder = args.exports or Path(tmp)
        rows = [measure(bundle, folder, k, args) for k in args.steps]
        srows = [streams(bundle, folder, k, args) for k in args.streams]
    import onnxruntime

    result = {"benchmark": "onnx_runtime", "date": utc_now(), "code": code_version(), "argv": args.argv,
              "device": describe_device("cpu") + f", onnxruntime {onnxruntime.__version__}",
              "load_average": load_average(), "note": args.note, "window_ms": args.window_ms,
              "interleave": args.interleave,
              "model": "embedded default (speech front end, guidance %g: 2 rows)" % bundle.config.guidance,
              "results": rows, "streams": srows}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
