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
on one scheduler, staggered phases; a count keeps real time when its p95 lag stays under a window + 150 ms) for
torch batched (one StreamBatcher on every core, or `--batched-threads`: `dimgestor serve`'s default), torch unbatched, ONNX Runtime
unbatched (one session shared by all streams, each window alone on a RankedScheduler thread per core: `streamer
serve --backend onnxruntime --no-batch`) and ONNX Runtime batched (a StreamBatcher a core, `--batched-threads`,
each with its share of the sessions and its cycles run as calls of the export's graphs of 1 and `--batches`
streams on its own one-thread sessions: `dimgestor serve --backend onnxruntime`'s `BatcherPool`), doubling then bisecting the count to 10 %. Beside it, what one call costs at K = 8 with B streams
(`--call-batches`): ms per call and per stream, and the copies of gathering B streams' states into a call (what
a call costs when the streams come back in another order or company).

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
    p.add_argument("--streams-repeats", type=int, default=1, metavar="N",
                   help="search each scheduler's count N times, the schedulers taking turns (order rotating): the "
                        "count is the median, every search's kept (one search's count moves by up to 1.5x between "
                        "runs minutes apart on a quiet machine)")
    p.add_argument("--batches", type=int, nargs="*", default=[4, 8, 16, 32], metavar="B",
                   help="graphs of B streams a call exported for the batched ONNX Runtime path (besides 1)")
    p.add_argument("--call-batches", type=int, nargs="*", default=[1, 8, 32], metavar="B",
                   help="batch sizes of the per-call cost table (1 or among --batches)")
    p.add_argument("--call-reps", type=int, default=8, help="calls timed per batch size (interleaved)")
    p.add_argument("--batched-threads", type=int, default=None, metavar="N",
                   help="threads of the batched schedulers (torch's and ONNX Runtime's); default: every core. On a "
                        "machine loaded by others, 1: two threads each waiting on the other's slice of a core "
                        "stall the batch")
    p.add_argument("--out", type=Path, default=RESULTS / "onnx_runtime.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def export_for(folder: Path, steps: int, frames: int, batches=()) -> Path:
    """The export of K = steps (with graphs of `batches` streams), reused when its folder already has them."""
    import json

    from dimgestor.export.onnx_export import export_onnx
    from dimgestor.export.onnx_stream import MANIFEST

    out = folder / f"default_k{steps}_f{frames}"
    have = {e["batch"] for e in json.loads((out / MANIFEST).read_text()).get("batched", [])} if (
        out / MANIFEST).is_file() else None
    if have is None or not set(batches) - {1} <= have:
        t0 = time.perf_counter()
        export_onnx(None, out, steps=steps, frames=frames, batches=sorted(set(batches) | (have or set())))
        print(f"exported K={steps} (batches {sorted(set(batches))}) in {time.perf_counter() - t0:.0f} s")
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
    from dimgestor.export.onnx_stream import ort_stream

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

    from dimgestor.export.onnx_batch import BatchRunner
    from dimgestor.export.onnx_stream import OnnxModel
    from streams import max_streams

    c = bundle.config
    onnx = OnnxModel.load(export_for(folder, steps, args.window_ms * c.fps // 1000, args.batches))
    cores = os.cpu_count() or 1
    threads = args.batched_threads or cores
    # ONNX Runtime batched: a StreamBatcher a core, each on its own one-thread runner (`dimgestor serve`'s
    # `onnx_batchers`); their graphs' costs measured once, for every trial
    runners = [BatchRunner.of(onnx, threads=1) for _ in range(threads)]
    runner = runners[0]
    common = dict(steps=steps, window_ms=args.window_ms, seconds=args.streams_s, cap=args.streams_max)
    search = {"torch_batched": lambda: max_streams(bundle, batched=True, threads=threads, **common),
              "torch_unbatched": lambda: max_streams(bundle, batched=False, threads=1, **common),
              "onnxruntime": lambda: max_streams(bundle, batched=False, threads=1, onnx=onnx, **common),
              "onnxruntime_batched": lambda: max_streams(bundle, batched=True, threads=threads, onnx=onnx,
                                                         batch_runner=runners, **common)}
    found = {name: [] for name in STREAM_ROWS}
    for rep in range(args.streams_repeats):
        order = STREAM_ROWS[rep % len(STREAM_ROWS):] + STREAM_ROWS[:rep % len(STREAM_ROWS)]
        for name in order:
            found[name].append(search[name]())
    row = {"steps": steps, "cores": cores, "batched_threads": threads, "graph_batches": runner.sizes,
           "graph_cost_ms": {str(b): 1000 * t for b, t in runner.cost.items()}}
    for name, runs in found.items():  # the last search's trials; every search's count; the median as the count
        counts = [r["max_realtime_streams"] for r in runs]
        row[name] = {**runs[-1], "searches": counts, "max_realtime_streams": int(np.median(counts))}
    calls = {}
    for r in runners:
        for b, k in r.stats.calls.items():
            calls[str(b)] = calls.get(str(b), 0) + k
    row["onnxruntime_batched"]["calls"] = calls
    row["onnxruntime_batched"]["gathers"] = sum(r.stats.gathers for r in runners)
    n = {k: row[k]["max_realtime_streams"] for k in STREAM_ROWS}
    row["max_realtime_streams"] = n
    row["ratio_onnxruntime_to_torch_batched"] = n["onnxruntime"] / max(n["torch_batched"], 1)
    row["ratio_onnxruntime_batched_to_torch_batched"] = n["onnxruntime_batched"] / max(n["torch_batched"], 1)
    row["ratio_by_search"] = [o / max(t, 1) for o, t in zip(row["onnxruntime_batched"]["searches"],
                                                            row["torch_batched"]["searches"])]
    print(f"K={steps} streams per process: torch batched {n['torch_batched']}, unbatched {n['torch_unbatched']}, "
          f"ONNX Runtime {n['onnxruntime']} ({row['ratio_onnxruntime_to_torch_batched']:.2f}x torch batched), "
          f"batched {n['onnxruntime_batched']} ({row['ratio_onnxruntime_batched_to_torch_batched']:.2f}x)")
    return row


STREAM_ROWS = ("torch_batched", "torch_unbatched", "onnxruntime", "onnxruntime_batched")


def call_costs(bundle, folder: Path, steps: int, args) -> dict:
    """One ONNX Runtime call of B streams at K = steps, 1 thread: ms per call and per stream (the median of
    `--call-reps`, the sizes interleaved), and the gather: B streams' states copied into the call's inputs."""
    from dimgestor.export.onnx_batch import BatchRunner
    from dimgestor.export.onnx_stream import load_manifest

    export = export_for(folder, steps, args.window_ms * bundle.config.fps // 1000, args.batches)
    manifest = load_manifest(export)
    runner = BatchRunner(export, manifest, threads=1, cost={1: 1.0})  # (plan unused: each size called directly)
    sizes = [b for b in args.call_batches if b in runner.sizes]
    feeds = {b: runner.idle_inputs(b) for b in sizes}
    for b in sizes:
        runner.run_graph(b, feeds[b])  # first calls allocate
    run, gather = {b: [] for b in sizes}, {b: [] for b in sizes}
    for _ in range(args.call_reps):
        for b in sizes:
            t0 = time.perf_counter()
            runner.run_graph(b, feeds[b])
            run[b].append(time.perf_counter() - t0)
            rows = [runner.idle_inputs(1)] * b  # B streams' own states (not the rows of one buffer): copied together
            t0 = time.perf_counter()
            for s in manifest["state"]:
                parts = [r[s["input"]] for r in rows]
                np.ascontiguousarray(parts[0]) if b == 1 else np.concatenate(parts, s["batch_dim"])
            gather[b].append(time.perf_counter() - t0)
    state_bytes = sum(v.nbytes for k, v in runner.idle_inputs(1).items() if k not in ("samples", "seed", "frame"))
    out = []
    for b in sizes:
        ms = float(np.median(run[b]) * 1000)
        out.append({"batch": b, "ms_per_call": ms, "ms_per_stream": ms / b, "gather_ms": float(
            np.median(gather[b]) * 1000), "calls": len(run[b])})
        print(f"K={steps} B={b:3d}: {ms:7.1f} ms a call, {ms / b:6.2f} ms a stream, gathering the states "
              f"{out[-1]['gather_ms']:.2f} ms")
    return {"steps": steps, "threads": 1, "state_bytes_per_stream": int(state_bytes), "rows": out}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common import save_panels

    rows = result["results"]
    x = np.arange(len(rows))
    srows, crows = result.get("streams") or [], result.get("calls") or []
    fig, axes = plt.subplots(1, 2 + bool(srows) + bool(crows), figsize=(4.5 * (2 + bool(srows) + bool(crows)), 3.4))
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
        xs = np.arange(len(srows))
        for i, name in enumerate(STREAM_ROWS):
            med = [r["max_realtime_streams"].get(name, 0) for r in srows]
            found = [r.get(name, {}).get("searches") or [m] for r, m in zip(srows, med)]
            axes[2].bar(xs + (i - 1.5) * 0.2, med, 0.2, yerr=[np.subtract(med, [min(f) for f in found]),
                                                             np.subtract([max(f) for f in found], med)], capsize=3,
                        label=name.replace("_", " ") + (" (median; whisker: min-max of searches)" if i == 0 else ""))
        axes[2].set_xticks(xs, [f"K={r['steps']}" for r in srows])
        axes[2].set_ylabel(f"real-time streams, one process, {srows[0]['cores']} cores")
        top = max(max(r[name].get("searches") or [r["max_realtime_streams"].get(name, 0)]) for r in srows
                  for name in STREAM_ROWS if name in r)
        axes[2].set_ylim(0, 1.7 * max(top, 1))  # room for the legend above the bars
        axes[2].legend(fontsize=6, loc="upper left")
    if crows:
        ax = axes[-1]
        for r in crows:
            bs = [c["batch"] for c in r["rows"]]
            ax.plot(bs, [c["ms_per_stream"] for c in r["rows"]], "o-", label=f"K={r['steps']}: ms a stream")
            ax.plot(bs, [c["gather_ms"] / c["batch"] for c in r["rows"]], "x--",
                    label=f"K={r['steps']}: gathering its state")
        ax.set_xscale("log", base=2)
        ax.set_xlabel("streams per ONNX Runtime call (1 thread)")
        ax.set_ylabel("ms per stream per 100 ms window")
        ax.legend(fontsize=7)
    save_panels(fig, axes, f"one stream, default model, 1 thread, interleaved by {result['interleave']}: "
                           f"{result['device']}", path)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    import torch

    from dimgestor.streaming.checkpoint import load_checkpoint

    torch.set_num_threads(1)
    bundle = load_checkpoint(None)
    bundle.model.eval()
    with tempfile.TemporaryDirectory(prefix="onnx-bench-") as tmp:
        folder = args.exports or Path(tmp)
        rows = [measure(bundle, folder, k, args) for k in args.steps]
        crows = [call_costs(bundle, folder, k, args) for k in args.streams]
        srows = [streams(bundle, folder, k, args) for k in args.streams]
    import onnxruntime

    result = {"benchmark": "onnx_runtime", "date": utc_now(), "code": code_version(), "argv": args.argv,
              "device": describe_device("cpu") + f", onnxruntime {onnxruntime.__version__}",
              "load_average": load_average(), "note": args.note, "window_ms": args.window_ms,
              "interleave": args.interleave,
              "model": "embedded default (speech front end, guidance %g: 2 rows)" % bundle.config.guidance,
              "results": rows, "streams": srows, "calls": crows}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
