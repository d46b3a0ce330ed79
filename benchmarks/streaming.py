"""Streaming benchmark: real-time factor, per-window latency, end-to-end latency, memory over an hour,
concurrent real-time streams, and the seam check.

Sections (run all by default, or some with --sections; each updates its part of the result file):
  sweep    per preset x K steps x window size: audio pushed as fast as possible, timing every push
  hour     one configuration streamed for --hour-s of audio (default 1 h) as fast as possible, RSS traced
  streams  per preset: the most streams one process keeps in real time (audio paced by the clock)
  seams    jerk at window boundaries vs inside windows (benchmarks/seams.py)

    python benchmarks/streaming.py                          # CPU defaults (realtime + tiny presets)
    python benchmarks/streaming.py --paper --device cuda    # adds the paper preset
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from common import (RESULTS, code_version, describe_device, load_average, percentile_ms, rss_mb, test_audio, utc_now,
                    write_json)

SECTIONS = ("sweep", "hour", "streams", "seams")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    p.add_argument("--presets", nargs="+", default=["realtime", "tiny"])
    p.add_argument("--paper", action="store_true", help="add the paper preset (slow on CPU)")
    p.add_argument("--checkpoint", default=None,
                   help="time this checkpoint's model as an extra preset row (speed does not depend on the weights)")
    p.add_argument("--steps", type=int, nargs="+", default=[1, 2, 4, 8, 16], help="DDIM steps K")
    p.add_argument("--windows-ms", type=int, nargs="+", default=[100, 200, 500], help="audio pushed per call")
    p.add_argument("--audio-s", type=float, default=5.0,
                   help="audio per sweep configuration (at least 20 windows are always pushed)")
    p.add_argument("--hour-preset", default="realtime")
    p.add_argument("--hour-steps", type=int, default=1)
    p.add_argument("--hour-window-ms", type=int, default=500)
    p.add_argument("--hour-s", type=float, default=3600.0, help="audio streamed in the memory run")
    p.add_argument("--streams-steps", type=int, default=8, help="K for the concurrent-streams test")
    p.add_argument("--streams-window-ms", type=int, default=200, help="window for the concurrent-streams test")
    p.add_argument("--streams-s", type=float, default=6.0, help="seconds of paced audio per trial")
    p.add_argument("--streams-max", type=int, default=64, help="stop searching at this many streams")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1,
                   help="torch intra-op threads (default 1: on a shared 2-core machine more threads spin against "
                        "other processes; each stream then uses one core and streams run side by side)")
    p.add_argument("--out", type=Path, default=RESULTS / "streaming.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # internal: the hour run, in its own process
    return p.parse_args(argv)


def build_model(preset: str, args):
    """(model, label): a checkpoint's network for preset 'checkpoint', else the preset with random weights."""
    import torch

    from dimgestor.config import get_preset
    from dimgestor.model import DiMGestor

    if preset == "checkpoint":
        from dimgestor.checkpoint import load_checkpoint

        return load_checkpoint(args.checkpoint).model.to(args.device).eval(), f"checkpoint {args.checkpoint}"
    torch.manual_seed(0)
    model = DiMGestor(get_preset(preset)).to(args.device).eval()
    with torch.no_grad():  # adaLN-Zero init makes blocks the identity; random weights cost the same as trained ones
        for p in model.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return model, preset


def stream_timed(model, steps: int, window_ms: int, audio_s: float, device: str) -> dict:
    """Push `audio_s` of audio in `window_ms` pieces as fast as possible; time every push."""
    import torch

    from dimgestor.stream import GestureStream

    cfg = model.config
    window = cfg.sample_rate * window_ms // 1000
    n_windows = max(int(round(audio_s * 1000 / window_ms)), 20)
    audio = test_audio(n_windows * window / cfg.sample_rate, cfg.sample_rate)
    stream = GestureStream(model, steps=steps)
    stream.push(audio[:window])  # warm-up on a throwaway stream: first calls allocate
    stream = GestureStream(model, steps=steps)
    rss_start = rss_mb()
    compute, cpu, e2e = [], [], []
    for k in range(n_windows):
        t0, c0 = time.perf_counter(), time.thread_time()
        frames = stream.push(audio[k * window : (k + 1) * window])
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        dt = time.perf_counter() - t0
        compute.append(dt)
        cpu.append(time.thread_time() - c0)
        audio_clock = (k + 1) * window / cfg.sample_rate  # when this window's last sample was spoken
        first = stream.frames_out - len(frames)
        # frame i is presented from i / fps; live, it is ready at audio_clock + compute
        e2e += [audio_clock + dt - i / cfg.fps for i in range(first, stream.frames_out)]
    audio_total = n_windows * window / cfg.sample_rate
    rtf = sum(compute) / audio_total
    return {"steps": steps, "window_ms": window_ms, "lookahead_ms": 1000 * stream.lookahead_s,
            "rtf": rtf, "latency_ms_p50": percentile_ms(compute, 50), "latency_ms_p95": percentile_ms(compute, 95),
            "rtf_cpu": sum(cpu) / audio_total, "cpu_ms_p50": percentile_ms(cpu, 50),
            "e2e_latency_ms": percentile_ms(e2e, 95), "e2e_latency_ms_p50": percentile_ms(e2e, 50),
            "realtime": rtf < 1 and percentile_ms(compute, 95) < window_ms,
            "rss_mb_start": rss_start, "rss_mb_end": rss_mb(), "audio_s": audio_total, "rss_mb_after_1h": None}


def sweep(args, presets) -> list[dict]:
    rows = []
    for preset in presets:
        model, label = build_model(preset, args)
        for steps in args.steps:
            for window_ms in args.windows_ms:
                r = {"preset": label, **stream_timed(model, steps, window_ms, args.audio_s, args.device)}
                rows.append(r)
                print(f"{label:9s} K={steps:2d} window {window_ms:3d} ms: rtf {r['rtf']:.3f} (cpu {r['rtf_cpu']:.3f})  compute p50/p95 "
                      f"{r['latency_ms_p50']:.1f}/{r['latency_ms_p95']:.1f} ms  e2e p95 {r['e2e_latency_ms']:.0f} ms",
                      flush=True)
    return rows


def hour_child(args) -> dict:
    """In a fresh process: stream --hour-s of audio as fast as possible, RSS sampled every simulated minute."""
    from dimgestor.stream import GestureStream

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
        if k == 19:
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
    cmd = [sys.executable, str(Path(__file__).resolve()), *sys.argv[1:], "--child", "hour"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"hour run failed:\n{proc.stderr[-3000:]}")
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"hour run ({r['preset']}, K={r['steps']}, {r['window_ms']} ms): {r['audio_s']:.0f} s of audio in "
          f"{r['wall_s']:.0f} s, RSS {r['rss_mb_start']:.1f} -> {r['rss_mb_after_1h']:.1f} MB", flush=True)
    return r


def paced_trial(model, n: int, steps: int, window_ms: int, seconds: float, threads: int = 1) -> dict:
    """n streams in n threads, each pushing a window when its audio would have arrived in real time.

    Lag of window k = time its push finished - time its last sample arrived. The streams keep up
    when the 95th percentile lag stays under one window and the last windows are not late.
    """
    import torch

    from dimgestor.stream import GestureStream

    cfg = model.config
    window = cfg.sample_rate * window_ms // 1000
    n_windows = int(seconds * 1000 // window_ms)
    audio = test_audio(n_windows * window / cfg.sample_rate, cfg.sample_rate)
    lags = [[] for _ in range(n)]
    start = time.perf_counter() + 0.05
    barrier = threading.Barrier(n)

    def run(j: int):
        torch.set_num_threads(threads)  # OpenMP's thread count is per calling thread: set it in each worker
        stream = GestureStream(model, steps=steps, seed=j)
        stream.push(audio[:window])  # warm-up
        stream = GestureStream(model, steps=steps, seed=j)
        barrier.wait()
        for k in range(n_windows):
            arrival = start + (k + 1) * window_ms / 1000
            time.sleep(max(0.0, arrival - time.perf_counter()))
            stream.push(audio[k * window : (k + 1) * window])
            lags[j].append(time.perf_counter() - arrival)

    workers = [threading.Thread(target=run, args=(j,)) for j in range(n)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    all_lags = [x for lag in lags for x in lag]
    p95 = percentile_ms(all_lags, 95)
    last = max(lag[-1] for lag in lags) * 1000
    return {"streams": n, "lag_ms_p95": p95, "last_lag_ms": last, "ok": p95 < window_ms and last < window_ms}


def max_streams(args, preset: str) -> dict:
    """Double the number of streams until one trial fails, then bisect between the last pass and the fail."""
    model, label = build_model(preset, args)
    trials, good, bad, n = [], 0, None, 1
    while n <= args.streams_max:
        r = paced_trial(model, n, args.streams_steps, args.streams_window_ms, args.streams_s, args.threads)
        trials.append(r)
        print(f"{label:9s} {n:3d} streams: lag p95 {r['lag_ms_p95']:.0f} ms, last {r['last_lag_ms']:.0f} ms "
              f"-> {'ok' if r['ok'] else 'falls behind'}", flush=True)
        if not r["ok"]:
            bad = n
            break
        good, n = n, n * 2
    while bad is not None and bad - good > 1:
        mid = (good + bad) // 2
        r = paced_trial(model, mid, args.streams_steps, args.streams_window_ms, args.streams_s, args.threads)
        trials.append(r)
        print(f"{label:9s} {mid:3d} streams: lag p95 {r['lag_ms_p95']:.0f} ms -> {'ok' if r['ok'] else 'falls behind'}",
              flush=True)
        good, bad = (mid, bad) if r["ok"] else (good, mid)
    return {"max_realtime_streams": good, "capped": bad is None, "steps": args.streams_steps,
            "window_ms": args.streams_window_ms, "trial_s": args.streams_s, "trials": trials}


def seams(args) -> list[dict]:
    from seams import load_model, seam_check

    model, bundle, source = load_model(args.checkpoint, "realtime")
    rows = [{"model": source, **seam_check(model, bundle, w, 8, 30.0)} for w in args.windows_ms]
    for r in rows:
        print(f"seams, window {r['window_ms']} ms: boundary/inside jerk {r['ratio']:.3f}", flush=True)
    return rows


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    rows = result.get("results", [])
    for (preset, window_ms) in sorted({(r["preset"], r["window_ms"]) for r in rows}):
        sel = sorted((r for r in rows if r["preset"] == preset and r["window_ms"] == window_ms), key=lambda r: r["steps"])
        ks = [r["steps"] for r in sel]
        axes[0].plot(ks, [r["rtf"] for r in sel], "o-", label=f"{preset}, {window_ms} ms")
        axes[1].plot(ks, [r["e2e_latency_ms"] for r in sel], "o-", label=f"{preset}, {window_ms} ms")
    axes[0].axhline(1.0, color="k", lw=0.8, ls="--")
    axes[0].set(yscale="log", ylabel="real-time factor", title="compute / audio time (dashed: real time)")
    axes[1].set(yscale="log", ylabel="ms", title="end-to-end latency p95")
    ks = sorted({r["steps"] for r in rows})
    for ax in axes[:2]:
        ax.set_xscale("log", base=2)
        ax.set_xticks(ks, [str(k) for k in ks])
        ax.set_xlabel("DDIM steps K")
    axes[0].legend(fontsize=7)
    hour_run = result.get("hour_run")
    if hour_run:
        trace = np.asarray([[0.0, hour_run["rss_mb_start"]]] + hour_run["rss_trace_mb"])
        axes[2].plot(trace[:, 0] / 60, trace[:, 1], ".-")
        axes[2].set(xlabel="audio streamed (min)", ylabel="process RSS (MB)",
                    title=f"memory: {hour_run['preset']}, K={hour_run['steps']}, {hour_run['window_ms']} ms windows")
        axes[2].set_ylim(0, max(trace[:, 1]) * 1.2)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(result.get("device", ""), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main(argv=None) -> None:
    args = parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    if args.child == "hour":
        print(json.dumps(hour_child(args)))
        return
    presets = list(args.presets) + (["paper"] if args.paper else []) + (["checkpoint"] if args.checkpoint else [])
    result = json.loads(args.out.read_text()) if args.out.is_file() else {}  # sections not run are kept
    load_before, started = load_average(), time.time()
    if "sweep" in args.sections:
        result["results"] = sweep(args, presets)
    if "hour" in args.sections and args.hour_s > 0:
        h = result["hour_run"] = hour(args)
        for r in result.get("results", []):
            if (r["preset"], r["steps"], r["window_ms"]) == (h["preset"], h["steps"], h["window_ms"]):
                r["rss_mb_after_1h"] = h["rss_mb_after_1h"] if h["audio_s"] >= 3600 else None
    if "streams" in args.sections:
        trials = {p: max_streams(args, p) for p in presets}
        result["max_realtime_streams"] = {p: t["max_realtime_streams"] for p, t in trials.items()}
        result["streams_trials"] = trials
    if "seams" in args.sections:
        result["seams"] = seams(args)
    result.update({
        "device": describe_device(args.device), "threads": args.threads, "note": args.note,
        "load_avg_before": load_before, "load_avg_after": load_average(), "measured_at": utc_now(),
        "code_version": code_version(),
        "wall_s_last_run": round(time.time() - started, 1), "sections_last_run": args.sections,
        "definitions": {
            "rtf": "compute time / audio time, audio pushed as fast as possible",
            "rtf_cpu, cpu_ms_p50": "the same with the pushing thread's CPU time (time.thread_time): on a loaded machine "
                                   "it leaves out the time the thread waited for a core; with --threads 1 torch runs "
                                   "its ops in that thread",
            "latency_ms_p50/p95": "compute time of one push() of a window",
            "lookahead_ms": "algorithmic latency: audio needed after a frame's start before it exists (GestureStream.lookahead_s)",
            "e2e_latency_ms": "p95 over frames of (time the frame is ready) - (its presentation time on the audio clock), "
                              "audio arriving in real time in windows: frame + lookahead + window fill + compute",
            "rss_mb_after_1h": "process RSS after an hour of audio; only the hour_run configuration streams a full hour",
            "max_realtime_streams": "streams in threads of one process, audio paced by the clock, lag p95 and last lag < one window",
        },
    })
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))


if __name__ == "__main__":
    main()
