"""Streaming benchmark: real-time factor, per-window latency, end-to-end latency, memory over an hour,
concurrent real-time streams through the serving path, achieved GFLOP/s beside the matmul peak, and the seam check.

Sections (run all by default, or some with --sections; each updates its part of the result file):
  sweep    per preset x K steps x window size: audio pushed as fast as possible, timing every push (1 thread)
  paper    the paper preset (hidden 1280, ~200 M params) at K = 1, 2, 4 with 0.5 s and 1 s windows on all
           cores, and the same with bfloat16 matmuls (torch.autocast) beside it, with its error
  hour     one configuration streamed for --hour-s of audio (default 1 h) as fast as possible, RSS traced
  streams  the most real-time streams one process keeps through the serving path (Sessions on one
           StreamBatcher vs one RankedScheduler, audio paced by the clock) at K = 1, 4, 8 (benchmarks/streams.py)
  gflops   the machine's matmul peak (1 thread, all threads; fp32, bf16) beside the GFLOP/s the denoiser
           achieved in the sweep and streams sections of this run (benchmarks/flops.py)
  seams    jerk at window boundaries vs inside windows (benchmarks/seams.py)

    python benchmarks/streaming.py                          # CPU defaults (realtime + tiny presets)
    python benchmarks/streaming.py --sections paper         # the paper preset alone (a few minutes)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from common import (RESULTS, code_version, describe_device, load_average, percentile_ms, rss_mb, test_audio, utc_now,
                    write_json)

SECTIONS = ("sweep", "paper", "hour", "streams", "gflops", "seams")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    p.add_argument("--presets", nargs="+", default=["realtime", "tiny"])
    p.add_argument("--paper", action="store_true", help="add the paper preset to the sweep (slow on CPU; see --sections paper)")
    p.add_argument("--checkpoint", default=None,
                   help="time this checkpoint's model as an extra preset row (speed does not depend on the weights)")
    p.add_argument("--steps", type=int, nargs="+", default=[1, 2, 4, 8, 16], help="DDIM steps K")
    p.add_argument("--windows-ms", type=int, nargs="+", default=[100, 200, 500], help="audio pushed per call")
    p.add_argument("--audio-s", type=float, default=5.0,
                   help="audio per sweep configuration (at least 20 windows are always pushed)")
    p.add_argument("--paper-preset", default="paper", help="the model of the paper section (tests shrink it)")
    p.add_argument("--paper-steps", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--paper-windows-ms", type=int, nargs="+", default=[500, 1000])
    p.add_argument("--paper-threads", type=int, default=os.cpu_count() or 1,
                   help="torch threads of the paper section (default: every core)")
    p.add_argument("--paper-audio-s", type=float, default=10.0, help="audio per paper configuration")
    p.add_argument("--hour-preset", default="realtime")
    p.add_argument("--hour-steps", type=int, default=1)
    p.add_argument("--hour-window-ms", type=int, default=500)
    p.add_argument("--hour-s", type=float, default=3600.0, help="audio streamed in the memory run")
    p.add_argument("--streams-preset", default="realtime", help="a preset (random weights) or \"default\" (the embedded model)")
    p.add_argument("--streams-steps", type=int, nargs="+", default=[1, 4, 8], help="K for the concurrent-streams test")
    p.add_argument("--streams-window-ms", type=int, default=100, help="window for the concurrent-streams test")
    p.add_argument("--streams-s", type=float, default=6.0, help="seconds of paced audio per trial")
    p.add_argument("--streams-max", type=int, default=128, help="stop searching at this many streams")
    p.add_argument("--streams-threads", type=int, default=1,
                   help="torch threads of the StreamBatcher's one inference thread (default 1: at 24 realtime K=8 "
                        "streams on 2 cores, 2 threads gave lag p95 0.51-0.55 s against 0.17-0.21 s with 1: the ops "
                        "are too small to split and the event loop needs the other core); the unbatched scheduler "
                        "runs min(4, cores) workers of one torch thread each")
    p.add_argument("--streams-aligned", type=int, nargs="*", default=[8],
                   help="K values whose batched search is repeated with every session's windows due at the same "
                        "instant (the best case for batching; the main search staggers them over a window)")
    p.add_argument("--matmul-n", type=int, default=1024, help="matmul size n (n x n x n) of the peak measurement")
    p.add_argument("--seams-s", type=float, default=30.0, help="audio per seam check")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1,
                   help="torch intra-op threads of the sweep (default 1: the cost of one stream on one core)")
    p.add_argument("--out", type=Path, default=RESULTS / "streaming.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # internal: the hour run, in its own process
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def build_model(preset: str, args):
    """(model, label): a checkpoint's network for preset 'checkpoint', else the preset with random weights."""
    import torch

    from dimgestor.config import get_preset
    from dimgestor.model.network import DiMGestor

    if preset == "checkpoint":
        from dimgestor.streaming.checkpoint import load_checkpoint

        return load_checkpoint(args.checkpoint).model.to(args.device).eval(), f"checkpoint {args.checkpoint}"
    torch.manual_seed(0)
    model = DiMGestor(get_preset(preset)).to(args.device).eval()
    with torch.no_grad():  # adaLN-Zero init makes blocks the identity; random weights cost the same as trained ones
        for p in model.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return model, preset


def stream_timed(model, steps: int, window_ms: int, audio_s: float, device: str, flops: float = float("nan"),
                 context=None) -> dict:
    """Push `audio_s` of audio in `window_ms` pieces as fast as possible; time every push.

    flops: the denoiser's FLOPs per frame per step (achieved GFLOP/s = frames * steps * flops / compute time);
    context: a context manager around the pushes (torch.autocast for the bf16 rows).
    """
    import contextlib

    import torch

    from dimgestor.streaming.stream import GestureStream

    cfg = model.config
    window = cfg.sample_rate * window_ms // 1000
    n_windows = max(int(round(audio_s * 1000 / window_ms)), 20)
    audio = test_audio(n_windows * window / cfg.sample_rate, cfg.sample_rate)
    context = context or contextlib.nullcontext
    warm = GestureStream(model, steps=steps)  # a throwaway stream: first calls allocate and pick kernels
    with context():
        for k in range(min(n_windows, math.ceil(1000 * warm.lookahead_s / window_ms) + 2)):  # until frames come
            warm.push(audio[k * window : (k + 1) * window])
    stream = GestureStream(model, steps=steps)
    rss_start = rss_mb()
    compute, cpu, e2e, outs = [], [], [], []
    with context():
        for k in range(n_windows):
            t0, c0 = time.perf_counter(), time.thread_time()
            frames = stream.push(audio[k * window : (k + 1) * window])
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            dt = time.perf_counter() - t0
            compute.append(dt)
            cpu.append(time.thread_time() - c0)
            outs.append(frames)
            audio_clock = (k + 1) * window / cfg.sample_rate  # when this window's last sample was spoken
            first = stream.frames_out - len(frames)
            # frame i is presented from i / fps; live, it is ready at audio_clock + compute
            e2e += [audio_clock + dt - i / cfg.fps for i in range(first, stream.frames_out)]
    audio_total = n_windows * window / cfg.sample_rate
    rtf = sum(compute) / audio_total
    return {"steps": steps, "window_ms": window_ms, "lookahead_ms": 1000 * stream.lookahead_s,
            "threads": torch.get_num_threads(),
            "rtf": rtf, "rtf_median_window": float(np.median(compute)) * 1000 / window_ms,
            "latency_ms_p50": percentile_ms(compute, 50), "latency_ms_p95": percentile_ms(compute, 95),
            "rtf_cpu": sum(cpu) / audio_total, "cpu_ms_p50": percentile_ms(cpu, 50),
            "e2e_latency_ms": percentile_ms(e2e, 95), "e2e_latency_ms_p50": percentile_ms(e2e, 50),
            "realtime": rtf < 1 and percentile_ms(compute, 95) < window_ms,
            "frames": stream.frames_out, "achieved_gflops": stream.frames_out * steps * flops / sum(compute) / 1e9,
            "rss_mb_start": rss_start, "rss_mb_end": rss_mb(), "audio_s": audio_total, "rss_mb_after_1h": None,
            "_frames": np.concatenate(outs)}


def _row_line(label: str, r: dict) -> str:
    return (f"{label:9s} K={r['steps']:2d} window {r['window_ms']:4d} ms, {r['threads']} thr: rtf {r['rtf']:.3f} "
            f"(cpu {r['rtf_cpu']:.3f})  compute p50/p95 {r['latency_ms_p50']:.1f}/{r['latency_ms_p95']:.1f} ms  "
            f"e2e p95 {r['e2e_latency_ms']:.0f} ms  {r['achieved_gflops']:.1f} GFLOP/s")


def sweep(args, presets) -> list[dict]:
    from flops import denoiser_flops_per_frame_step

    rows = []
    for preset in presets:
        model, label = build_model(preset, args)
        flops = denoiser_flops_per_frame_step(model)
        for steps in args.steps:
            for window_ms in args.windows_ms:
                r = stream_timed(model, steps, window_ms, args.audio_s, args.device, flops)
                r.pop("_frames")
                rows.append({"preset": label, **r, "flops_per_frame_step": flops})
                print(_row_line(label, r), flush=True)
    return rows


def paper(args) -> dict:
    """The paper preset on all cores at K x window, fp32; then bf16 matmuls (autocast) at the largest K and window."""
    import torch

    from flops import denoiser_flops_per_frame_step

    before = torch.get_num_threads()
    torch.set_num_threads(args.paper_threads)
    try:
        model, label = build_model(args.paper_preset, args)
        flops = denoiser_flops_per_frame_step(model)
        rows, frames = [], {}
        for steps in args.paper_steps:
            for window_ms in args.paper_windows_ms:
                r = stream_timed(model, steps, window_ms, args.paper_audio_s, args.device, flops)
                frames[(steps, window_ms)] = r.pop("_frames")
                rows.append({"preset": label, **r, "flops_per_frame_step": flops, "dtype": "float32"})
                print(_row_line(label, r), flush=True)
        # bf16 matmuls at the largest K and window, between two fp32 runs (a busy neighbour hits all alike)
        k, w = max(args.paper_steps), max(args.paper_windows_ms)
        bf = stream_timed(model, k, w, args.paper_audio_s, args.device, flops,
                          context=lambda: torch.autocast("cpu", dtype=torch.bfloat16))
        again = stream_timed(model, k, w, args.paper_audio_s, args.device, flops)
        ref, got = frames[(k, w)], bf.pop("_frames")
        fp = next(r for r in rows if (r["steps"], r["window_ms"]) == (k, w))
        rtf_fp32 = [fp["rtf"], again["rtf"]]
        bf.update(preset=label, flops_per_frame_step=flops, dtype="bfloat16 matmuls (torch.autocast, fp32 weights)",
                  rel_rms_error_vs_fp32=float(np.sqrt(np.mean((got - ref) ** 2)) / max(np.sqrt(np.mean(ref ** 2)), 1e-12)),
                  max_abs_error_vs_fp32=float(np.abs(got - ref).max()), rtf_fp32_before_after=rtf_fp32,
                  rtf_fp32=min(rtf_fp32), speedup_vs_fp32=min(rtf_fp32) / bf["rtf"],
                  rtf_median_window_fp32=min(fp["rtf_median_window"], again["rtf_median_window"]))
        print(_row_line(label + " bf16", bf) + f"  x{bf['speedup_vs_fp32']:.2f} vs the faster fp32 run "
              f"(rtf {rtf_fp32[0]:.3f} before, {rtf_fp32[1]:.3f} after), rel. rms error "
              f"{bf['rel_rms_error_vs_fp32']:.2e}", flush=True)
    finally:
        torch.set_num_threads(before)
    params = sum(p.numel() for p in model.parameters())
    return {"rows": rows, "bf16": bf, "threads": args.paper_threads, "params": params, "preset": label,
            "note": "random weights (speed does not depend on them); the same seed and audio for fp32 and bf16, "
                    "so the error is that of bf16 matmuls alone"}


def hour_child(args) -> dict:
    """In a fresh process: stream --hour-s of audio as fast as possible, RSS sampled every simulated minute."""
    from dimgestor.streaming.stream import GestureStream

    model, label = build_model(args.hour_preset, args)
    cfg = model.config
    window = cfg.sample_rate * args.hour_window_ms // 1000
    stream = GestureStream(model, steps=args.hour_steps)
    per_minute = 60 * cfg.sample_rate // window
    trace, frames, started = [], 0, time.perf_counter()
    n_windows = int(args.hour_s * cfg.sample_rate // window)
    rss_start = None
    for k in range(n_windows):
        frames += len(stream.push(test_audio(window / cfg.sample_rate, cfg.sample_rate, start_s=k * window / cfg.sample_rate)))
        if k == 19 or rss_start is None and k == n_windows - 1:
            rss_start = rss_mb()  # after warm-up: allocator pools and lazy inits are in place
        if (k + 1) % per_minute == 0:
            trace.append([round((k + 1) * window / cfg.sample_rate, 1), round(rss_mb(), 2)])
    wall = time.perf_counter() - started
    audio_s = n_windows * window / cfg.sample_rate
    return {"preset": label, "steps": args.hour_steps, "window_ms": args.hour_window_ms, "audio_s": audio_s,
            "frames": frames, "wall_s": wall, "rtf": wall / audio_s, "rss_mb_start": rss_start,
            "rss_mb_after_1h": rss_mb(), "rss_trace_mb": trace,
            "note": "rss_mb_start is read after the first 20 windows (warm-up); RSS is the whole process"}


def hour(args) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), *args.argv, "--child", "hour"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"hour run failed:\n{proc.stderr[-3000:]}")
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"hour run ({r['preset']}, K={r['steps']}, {r['window_ms']} ms): {r['audio_s']:.0f} s of audio in "
          f"{r['wall_s']:.0f} s, RSS {r['rss_mb_start']:.1f} -> {r['rss_mb_after_1h']:.1f} MB", flush=True)
    return r


def streams(args) -> dict:
    """Batched and unbatched: the largest number of paced sessions that keep real time, per K."""
    from flops import denoiser_flops_per_frame_step
    from streams import max_streams, random_bundle

    bundle = random_bundle(args.streams_preset)
    flops = denoiser_flops_per_frame_step(bundle.model)
    by_k = {}
    for steps in args.streams_steps:
        by_k[str(steps)] = {}
        modes = [("batched", True, False), ("unbatched", False, False)]
        if steps in args.streams_aligned:
            modes.append(("batched_aligned", True, True))
        for mode, batched, aligned in modes:
            r = max_streams(bundle, steps, args.streams_window_ms, args.streams_s, batched, args.streams_threads,
                            args.streams_max, aligned, log=lambda line: print(line, flush=True))
            for t in r["trials"]:
                t["achieved_gflops"] = t["frames"] * steps * flops / t["wall_s"] / 1e9
            by_k[str(steps)][mode] = r
    return {"preset": args.streams_preset, "window_ms": args.streams_window_ms, "trial_s": args.streams_s,
            "cap": args.streams_max, "flops_per_frame_step": flops, "by_k": by_k,
            "phases": "session j's audio starts j/n of a window after session 0's (clients connect at random "
                      "times); batched_aligned: all at once",
            "pass_rule": "over the second half of the trial, lag p95 < window + 150 ms, and every stream's last "
                         "window < 500 ms late; lag = frames out - last audio sample of the window in"}


def streams_summary(st: dict) -> dict:
    """max_realtime_streams: preset -> the batched count at the largest K (what `dimgestor serve` holds; the
    schema of issue 7); max_realtime_streams_by_k: mode -> K -> count."""
    by_k = {mode: {k: v[mode]["max_realtime_streams"] for k, v in st["by_k"].items() if mode in v}
            for mode in ("batched", "unbatched", "batched_aligned")}
    top = max(st["by_k"], key=int)
    return {"max_realtime_streams": {st["preset"]: st["by_k"][top]["batched"]["max_realtime_streams"]},
            "max_realtime_streams_by_k": by_k}


def gflops(args, result: dict) -> dict:
    """The matmul peak of this machine now, beside what the denoiser achieved in this run's sweep and streams."""
    import torch

    from flops import matmul_peak

    cores = os.cpu_count() or 1
    peaks = {f"{dt}_{th}thr": matmul_peak(args.matmul_n, th, getattr(torch, dt))
             for dt in ("float32", "bfloat16") for th in sorted({1, cores})}
    for k, p in peaks.items():
        print(f"matmul {p['n']}^3 {k}: {p['gflops']:.0f} GFLOP/s", flush=True)
    f32_1, f32_all = peaks["float32_1thr"]["gflops"], peaks[f"float32_{cores}thr"]["gflops"]
    out = {"matmul_peak": peaks, "achieved": []}
    one = [r for r in result.get("results", []) if r.get("achieved_gflops") is not None]
    # the configuration of the issue: one stream, K = 8, 100 ms windows (the nearest one the sweep ran)
    for r in sorted(one, key=lambda r: (r["preset"] != args.streams_preset, abs(r["steps"] - 8),
                                        abs(r["window_ms"] - 100)))[:1]:
        out["achieved"].append({"what": f"one stream, {r['preset']}, K={r['steps']}, {r['window_ms']} ms windows, "
                                        f"{r['threads']} thread(s)", "gflops": r["achieved_gflops"],
                                "peak_gflops": f32_1 if r["threads"] == 1 else f32_all,
                                "threads": r["threads"]})
    st = result.get("streams") or {}
    for k, modes in st.get("by_k", {}).items():  # each batched search at its largest real-time count
        for mode in ("batched", "batched_aligned"):
            r = modes.get(mode)
            t = next((t for t in r["trials"] if t["streams"] == r["max_realtime_streams"]), None) if r else None
            if t is None:
                continue
            out["achieved"].append({"what": f"{t['streams']} {mode.replace('_', ' ')} real-time streams, {st['preset']}, "
                                            f"K={k}, {st['window_ms']} ms windows (frames x K / trial wall time)",
                                    "gflops": t["achieved_gflops"], "peak_gflops": f32_all, "threads": cores})
    for a in out["achieved"]:
        a["fraction_of_peak"] = a["gflops"] / a["peak_gflops"]
        print(f"achieved {a['gflops']:.2f} GFLOP/s = {100 * a['fraction_of_peak']:.2f} % of the fp32 peak: {a['what']}",
              flush=True)
    out["flops_counted"] = ("torch.utils.flop_counter.FlopCounterMode over one denoiser forward of 20 frames "
                            "(matmuls, linears, convolutions; 2 FLOPs per multiply-add; element-wise ops not "
                            "counted), divided by the frames")
    return out


def seams(args) -> list[dict]:
    from seams import load_model, seam_check

    model, bundle, source = load_model(args.checkpoint, "realtime")
    rows = [{"model": source, **seam_check(model, bundle, w, 8, args.seams_s)} for w in args.windows_ms]
    for r in rows:
        print(f"seams, window {r['window_ms']} ms: boundary/inside jerk {r['ratio']:.3f}", flush=True)
    return rows


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(16, 9))
    ax_rtf, ax_e2e, ax_mem, ax_n, ax_lag, ax_gf = axes.ravel()
    rows = result.get("results", []) + (result.get("paper") or {}).get("rows", [])
    for (preset, window_ms) in sorted({(r["preset"], r["window_ms"]) for r in rows}):
        sel = sorted((r for r in rows if r["preset"] == preset and r["window_ms"] == window_ms), key=lambda r: r["steps"])
        ks = [r["steps"] for r in sel]
        label = f"{preset}, {window_ms} ms, {sel[0].get('threads', 1)} thr"
        ax_rtf.plot(ks, [r["rtf"] for r in sel], "o-", label=label)
        ax_e2e.plot(ks, [r["e2e_latency_ms"] for r in sel], "o-", label=label)
    bf = (result.get("paper") or {}).get("bf16")
    if bf:
        ax_rtf.plot([bf["steps"]], [bf["rtf"]], "k*", ms=10, label=f"{bf['preset']}, {bf['window_ms']} ms, bf16 matmuls")
    ax_rtf.axhline(1.0, color="k", lw=0.8, ls="--")
    ax_rtf.set(yscale="log", ylabel="real-time factor", title="one stream: compute / audio time (dashed: real time)")
    ax_e2e.set(yscale="log", ylabel="ms", title="one stream: end-to-end latency p95")
    ks = sorted({r["steps"] for r in rows})
    for ax in (ax_rtf, ax_e2e):
        ax.set_xscale("log", base=2)
        ax.set_xticks(ks, [str(k) for k in ks])
        ax.set_xlabel("DDIM steps K")
    ax_rtf.legend(fontsize=6)
    hour_run = result.get("hour_run")
    if hour_run:
        trace = np.asarray([[0.0, hour_run["rss_mb_start"]]] + hour_run["rss_trace_mb"])
        ax_mem.plot(trace[:, 0] / 60, trace[:, 1], ".-")
        ax_mem.set(xlabel="audio streamed (min)", ylabel="process RSS (MB)",
                   title=f"memory: {hour_run['preset']}, K={hour_run['steps']}, {hour_run['window_ms']} ms windows")
        ax_mem.set_ylim(0, max(trace[:, 1]) * 1.2)
    st = result.get("streams")
    if st:
        ks = sorted(int(k) for k in st["by_k"])
        modes = [m for m in ("batched", "unbatched", "batched_aligned") if any(m in v for v in st["by_k"].values())]
        width = 0.8 / len(modes)
        for i, mode in enumerate(modes):
            at = [j for j, k in enumerate(ks) if mode in st["by_k"][str(k)]]
            n = [st["by_k"][str(ks[j])][mode]["max_realtime_streams"] for j in at]
            bars = ax_n.bar(np.asarray(at) + (i - (len(modes) - 1) / 2) * width, n, width, label=mode.replace("_", ", "))
            ax_n.bar_label(bars, fontsize=8)
            for k, color in zip(ks, plt.rcParams["axes.prop_cycle"].by_key()["color"]):
                if mode not in st["by_k"][str(k)]:
                    continue
                trials = st["by_k"][str(k)][mode]["trials"]
                ax_lag.plot([t["streams"] for t in trials], [min(t["lag_ms_p95"], 1e5) for t in trials],
                            {"batched": "o-", "unbatched": "x--", "batched_aligned": "s:"}[mode], color=color,
                            label=f"K={k}, {mode.replace('_', ', ')}")
        ax_n.set_xticks(range(len(ks)), [f"K={k}" for k in ks])
        capped = any(st["by_k"][str(k)]["batched"]["capped"] for k in ks)
        ax_n.set(ylabel="streams", title=f"real-time streams, one process ({st['preset']}, {st['window_ms']} ms"
                                         f"{', cap ' + str(st['cap']) if capped else ''})")
        ax_n.legend(fontsize=7)
        ax_lag.axhline(st["window_ms"] + 150, color="k", lw=0.8, ls="--")
        ax_lag.set(xscale="log", yscale="log", xlabel="concurrent streams", ylabel="ms",
                   title="lag p95, second half of each trial (dashed: pass limit)")
        ax_lag.set_xscale("log", base=2)
        ax_lag.legend(fontsize=6)
    gf = result.get("gflops")
    if gf:
        ach = gf["achieved"]
        y = np.arange(len(ach))
        ax_gf.barh(y, [a["gflops"] for a in ach], color="C0", label="achieved by the denoiser")
        for yi, a in zip(y, ach):
            ax_gf.plot([a["peak_gflops"]], [yi], "k|", ms=14)
            ax_gf.text(a["gflops"], yi, f" {a['gflops']:.3g} ({100 * a['fraction_of_peak']:.2g} % of peak)",
                       va="center", fontsize=7)
        ax_gf.set_yticks(y, [textwrap_short(a["what"]) for a in ach], fontsize=6)
        peaks = gf["matmul_peak"]
        ax_gf.set(xscale="log", xlabel="GFLOP/s (|: fp32 matmul peak, same threads, same run)",
                  title="denoiser GFLOP/s achieved vs matmul peak")
        ax_gf.set_xlim(right=30 * max(a["peak_gflops"] for a in ach))
        ax_gf.text(0.99, 0.99, f"{peaks[next(iter(peaks))]['n']}^3 matmul peak:\n" + "\n".join(
            f"{k}: {v['gflops']:.0f}" for k, v in peaks.items()), transform=ax_gf.transAxes, ha="right", va="top",
            fontsize=7)
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
    fig.suptitle(f"{result.get('device', '')}  |  code {result.get('code_version', '?')}  |  load avg "
                 f"{result.get('load_avg_before')} -> {result.get('load_avg_after')}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def textwrap_short(text: str, width: int = 34) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width)[:3])


def main(argv=None) -> None:
    args = parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    if args.child == "hour":
        print(json.dumps(hour_child(args)))
        return
    presets = list(args.presets) + (["paper"] if args.paper else []) + (["checkpoint"] if args.checkpoint else [])
    result = json.loads(args.out.read_text()) if args.out.is_file() else {}  # sections not run are kept
    for old in ("max_realtime_streams", "streams_trials"):  # the thread-per-stream test this file ran before
        result.pop(old, None)
    load_before, started = load_average(), time.time()
    runs = result.setdefault("section_runs", {})  # sections may come from different runs: each says when and how

    def section(name: str, fn):
        before, t0 = load_average(), time.time()
        out = fn()
        runs[name] = {"measured_at": utc_now(), "code_version": code_version(), "load_avg_before": before,
                      "load_avg_after": load_average(), "wall_s": round(time.time() - t0, 1)}
        return out

    if "sweep" in args.sections:
        result["results"] = section("sweep", lambda: sweep(args, presets))
    if "paper" in args.sections:
        result["paper"] = section("paper", lambda: paper(args))
    if "hour" in args.sections and args.hour_s > 0:
        h = result["hour_run"] = section("hour", lambda: hour(args))
        for r in result.get("results", []):
            if (r["preset"], r["steps"], r["window_ms"]) == (h["preset"], h["steps"], h["window_ms"]):
                r["rss_mb_after_1h"] = h["rss_mb_after_1h"] if h["audio_s"] >= 3600 else None
    if "streams" in args.sections:
        result["streams"] = section("streams", lambda: streams(args))
        result.update(streams_summary(result["streams"]))
    if "gflops" in args.sections:
        result["gflops"] = section("gflops", lambda: gflops(args, result))
    if "seams" in args.sections:
        result["seams"] = section("seams", lambda: seams(args))
    result.update({
        "device": describe_device(args.device), "threads": args.threads, "note": args.note,
        "threads_by_section": {"sweep": args.threads, "paper": args.paper_threads,
                               "streams": {"batched": f"1 inference thread x {args.streams_threads} torch threads",
                                           "unbatched": f"min(4, cores) = {min(4, os.cpu_count() or 1)} workers x 1 "
                                                        "torch thread"}},
        "load_avg_before": load_before, "load_avg_after": load_average(), "measured_at": utc_now(),
        "code_version": code_version(),
        "wall_s_last_run": round(time.time() - started, 1), "sections_last_run": args.sections,
        "definitions": {
            "rtf": "compute time / audio time, audio pushed as fast as possible",
            "rtf_cpu, cpu_ms_p50": "the same with the pushing thread's CPU time (time.thread_time): on a loaded machine "
                                   "it leaves out the time the thread waited for a core; with --threads 1 torch runs "
                                   "its ops in that thread",
            "latency_ms_p50/p95": "compute time of one push() of a window",
            "rtf_median_window": "median compute time of one window / the window's audio: steadier than rtf when a "
                                 "neighbour's burst stalls a few windows",
            "lookahead_ms": "algorithmic latency: audio needed after a frame's start before it exists (GestureStream.lookahead_s)",
            "e2e_latency_ms": "p95 over frames of (time the frame is ready) - (its presentation time on the audio clock), "
                              "audio arriving in real time in windows: frame + lookahead + window fill + compute",
            "rss_mb_after_1h": "process RSS after an hour of audio; only the hour_run configuration streams a full hour",
            "achieved_gflops": "denoiser FLOPs (flops_per_frame_step x frames x K) / compute time (sweep) or / trial wall "
                               "time (streams); the front end and condition path are not counted",
            "max_realtime_streams": "preset -> real-time streams through the serving path, batched (one StreamBatcher, "
                                    "as dimgestor serve), at the largest K of the streams section; see "
                                    "max_realtime_streams_by_k for every K and mode and streams.by_k for the trials",
            "max_realtime_streams_by_k": "Sessions on one scheduler in one asyncio loop, audio paced by the clock (see "
                                         "streams.pass_rule); batched = one StreamBatcher, unbatched = one "
                                         "RankedScheduler (--no-batch)",
        },
    })
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))


if __name__ == "__main__":
    main()
