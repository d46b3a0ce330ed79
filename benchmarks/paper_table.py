"""Paper Table 4 side by side: AdaLN Mamba-2 denoiser vs AdaLN-Transformer (6 and 12 blocks), same width.

For 20/40/60/80/100 s sequences at 20 fps: parameter count, inference time, peak memory. Each
(model, length) is measured in a fresh subprocess, so a peak-memory reading cannot be inflated by an
earlier measurement. On CPU memory is read two ways: tensor memory (weights + inputs + the forward's
peak of live tensors, from torch's profiler: what torch.cuda.max_memory_allocated counts on a GPU) and
the OS's peak RSS (which adds the allocator's slack and BLAS/OpenMP buffers, a constant that is not the
model's). On CUDA the reading is torch.cuda.max_memory_allocated.

    python benchmarks/paper_table.py                                   # small CPU default, a few minutes
    python benchmarks/paper_table.py --preset paper --hidden 0 --device cuda --mode sample --steps 50
"""

from __future__ import annotations

import argparse
import gc
import json
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

from common import (RESULTS, code_version, describe_device, load_average, peak_rss_mb, rss_mb, test_audio, utc_now,
                    write_json)

MODELS = ("mamba2_6", "transformer_6", "transformer_12")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="paper", help="model preset whose structure is used (default: paper)")
    p.add_argument("--hidden", type=int, default=256,
                   help="override the width (default 256 so the CPU run takes minutes; 0 keeps the preset's)")
    p.add_argument("--d-state", type=int, default=0, help="override the Mamba-2 state size (0 keeps the preset's)")
    p.add_argument("--motion-dim", type=int, default=0, help="override motion feature columns (0 keeps the preset's)")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--lengths", type=float, nargs="+", default=[20, 40, 60, 80, 100], help="sequence lengths (s)")
    p.add_argument("--mode", choices=["denoiser", "sample"], default="denoiser",
                   help="time one denoiser forward over the whole sequence (default), or a whole K-step sampling "
                        "(front end + condition + K denoiser passes)")
    p.add_argument("--steps", type=int, default=8, help="DDIM steps for --mode sample")
    p.add_argument("--attention", choices=["sdpa", "naive"], default="sdpa",
                   help="Transformer attention kernel: torch's fused sdpa, or the plain materialized softmax")
    p.add_argument("--repeats", type=int, default=5,
                   help="timed runs per measurement; the fastest is reported (least disturbed by other processes)")
    p.add_argument("--threads", type=int, default=1,
                   help="torch intra-op threads (default 1: on a shared machine more threads spin against other processes)")
    p.add_argument("--out", type=Path, default=RESULTS / "paper_table.json")
    p.add_argument("--plot", type=Path, default=None, help="plot path (default: beside --out, .png)")
    p.add_argument("--note", default="measured on a shared machine: other processes were running",
                   help="free text stored in the JSON")
    p.add_argument("--plot-only", action="store_true", help="redraw the plot from an existing --out JSON")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # internal: measure one (model, length)
    return p.parse_args(argv)


def model_config(args):
    from dimgestor.config import get_preset

    overrides = {k: v for k, v in (("hidden", args.hidden), ("d_state", args.d_state),
                                   ("motion_dim", args.motion_dim)) if v}
    return get_preset(args.preset, **overrides)


def build(name: str, config, attention: str):
    from dimgestor.model.baselines import AdaLNTransformer
    from dimgestor.model.network import DiMGestor

    kind, n_blocks = name.rsplit("_", 1)
    if kind == "mamba2":
        return DiMGestor(config.model_copy(update={"n_blocks": int(n_blocks)}))
    return AdaLNTransformer(config, n_blocks=int(n_blocks), impl=attention)


def measure(args, name: str, length_s: float) -> dict:
    """In a fresh process: build one model, run it on a `length_s` sequence, report time and peak memory."""
    import torch

    from dimgestor.model.baselines import denoiser_params
    from dimgestor.streaming.stream import generate_offline

    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    rss_before = rss_mb()
    torch.manual_seed(0)
    model = build(name, model_config(args), args.attention).to(device).eval()
    with torch.no_grad():  # random, non-zero weights: adaLN-Zero init would skip nothing, but be safe
        for p in model.parameters():
            p.add_(0.02 * torch.randn_like(p))
    cfg = model.config
    T = int(round(length_s * cfg.fps))
    audio = test_audio(length_s, cfg.sample_rate)
    params = sum(p.numel() for p in model.parameters())

    if args.mode == "denoiser":
        # The condition path is the same module in every model and its values do not change the cost of
        # a denoiser forward: drop it, so neither its weights nor its work enter the denoiser's memory.
        del model.frontend, model.extractor
        gc.collect()
        cond = torch.randn(1, T, cfg.hidden, device=device)  # (1, T, H)
        x = torch.randn(1, T, cfg.motion_dim, device=device)
        if device.type == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(device)

        def run():
            with torch.inference_mode():
                model(x, cfg.n_steps // 2, cond)
    else:
        def run():
            generate_offline(model, audio, steps=args.steps)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    run()  # warm-up (allocator, kernels)
    sync()
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        run()
        sync()
        times.append(time.perf_counter() - t0)
    weights_mb = sum(p.numel() * p.element_size() for p in model.parameters()) / 2**20
    inputs_mb = sum(t.numel() * t.element_size() for t in (cond, x)) / 2**20 if args.mode == "denoiser" else 0.0
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device) / 2**20
        tensor_mb, work_mb = peak, peak - weights_mb - inputs_mb
    else:
        peak = peak_rss_mb() - rss_before  # weights + inputs + activations + allocator slack
        work_mb = peak_tensor_mb(run)  # what the forward allocates on top of weights and inputs, at its peak
        tensor_mb = weights_mb + inputs_mb + work_mb  # what CUDA's max_memory_allocated counts
    return {"model": name, "length_s": length_s, "frames": T, "params": params,
            "denoiser_params": denoiser_params(model), "time_s": min(times), "time_s_median": float(np.median(times)),
            "peak_mem_mb": peak, "peak_rss_mb_total": peak_rss_mb(), "tensor_mem_mb": tensor_mb,
            "weights_mb": weights_mb, "inputs_mb": inputs_mb, "work_mem_mb": work_mb}


def peak_tensor_mb(run) -> float:
    """Peak bytes of live tensors that `run()` allocates (weights and inputs made before are not counted),
    from torch's profiler: every allocation and free in order, as a running sum. Exact for tensors, blind
    to the allocator's slack and to libraries' scratch buffers (peak RSS sees those)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        run()
    live = peak = 0
    for e in sorted(prof.events(), key=lambda e: e.time_range.start):
        live += e.self_cpu_memory_usage  # an op's own allocations net of its frees; "[memory]" rows: frees
        peak = max(peak, live)
    return peak / 2**20


def run_child(args, name: str, length_s: float) -> dict:
    argv = [a for a in sys.argv[1:]]
    cmd = [sys.executable, str(Path(__file__).resolve()), *argv, "--child", json.dumps([name, length_s])]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"measurement {name} @ {length_s}s failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def loglog_slope(lengths, values) -> float:
    """Exponent p of value ~ length^p (1: linear, 2: quadratic)."""
    return float(np.polyfit(np.log(lengths), np.log(values), 1)[0])


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(10, 4))
    for name, m in result["models"].items():
        ax_t.plot(result["lengths_s"], m["time_s"], "o-", label=f"{name} ({m['denoiser_params'] / 1e6:.1f} M denoiser params)")
        line, = ax_m.plot(result["lengths_s"], m.get("tensor_mem_mb", m["peak_mem_mb"]), "o-", label=f"{name} tensors")
        if "tensor_mem_mb" in m:
            ax_m.plot(result["lengths_s"], m["peak_mem_mb"], "x--", color=line.get_color(), alpha=0.6,
                      label=f"{name} RSS")
    attention = result.get("config", {}).get("attention", "sdpa")
    ax_t.set(xlabel="sequence length (s)", ylabel="time (s)", title="inference time")
    ax_m.set(xlabel="sequence length (s)", ylabel="peak memory (MB)", title=f"peak memory (attention: {attention})")
    for ax in (ax_t, ax_m):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(result["device"], fontsize=8)
    caption = textwrap.fill(f"time: {result['timing']}. memory: {result['memory']}.", 150)
    fig.text(0.5, 0.01, caption, ha="center", va="bottom", fontsize=7)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.plot_only:
        plot(json.loads(args.out.read_text()), args.plot or args.out.with_suffix(".png"))
        return
    if args.child:
        name, length_s = json.loads(args.child)
        print(json.dumps(measure(args, name, length_s)))
        return
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = model_config(args)
    load_before, started = load_average(), time.time()
    rows = {name: [] for name in MODELS}
    for length_s in args.lengths:
        for name in MODELS:
            r = run_child(args, name, length_s)
            rows[name].append(r)
            print(f"{name:15s} {length_s:6.0f} s: {r['time_s'] * 1000:9.1f} ms  tensors {r['tensor_mem_mb']:7.1f} MB "
                  f"(working {r['work_mem_mb']:6.1f})  RSS {r['peak_mem_mb']:7.1f} MB", flush=True)
    timing = (f"fastest of {args.repeats} runs of " if args.repeats > 1 else "") + (
              "one denoiser forward over the whole sequence (B=1, given condition)" if args.mode == "denoiser"
              else f"whole {args.steps}-step DDIM sampling incl. front end and condition (B=1)")
    memory = ("torch.cuda.max_memory_allocated" if args.device.startswith("cuda")
              else "tensor_mem_mb: weights + inputs + the forward's peak of live tensors (torch profiler), what "
                   "CUDA's max_memory_allocated counts; peak_mem_mb: peak RSS of a fresh process minus its RSS "
                   "before the model was built (adds the allocator's slack and BLAS/OpenMP buffers)") + (
              " (denoiser weights, inputs, activations)" if args.mode == "denoiser" else " (whole model and sampling)")
    result = {
        "device": describe_device(args.device),
        "lengths_s": [float(x) for x in args.lengths],
        "models": {name: {"params": r[0]["params"], "denoiser_params": r[0]["denoiser_params"],
                          "time_s": [x["time_s"] for x in r], "peak_mem_mb": [x["peak_mem_mb"] for x in r],
                          "time_s_median": [x["time_s_median"] for x in r],
                          **{k: [x[k] for x in r] for k in ("tensor_mem_mb", "weights_mb", "inputs_mb", "work_mem_mb")}}
                   for name, r in rows.items()},
        "timing": timing, "memory": memory, "fps": cfg.fps,
        "config": {"preset": args.preset, "hidden": cfg.hidden, "d_state": cfg.d_state, "motion_dim": cfg.motion_dim,
                   "attention": args.attention, "repeats": args.repeats, "dtype": "float32"},
        "shared_machine": {"note": args.note, "load_avg_before": load_before, "load_avg_after": load_average()},
        "measured_at": utc_now(), "wall_s": round(time.time() - started, 1),
        "code_version": code_version(),
    }
    base = result["models"]["mamba2_6"]
    result["ratios_vs_mamba2_6"] = {
        name: {"time": [a / b for a, b in zip(m["time_s"], base["time_s"])],
               "peak_mem": [a / b for a, b in zip(m["peak_mem_mb"], base["peak_mem_mb"])]}
        for name, m in result["models"].items() if name != "mamba2_6"}
    # the headline: Mamba-2 (6 blocks) over the 12-block Transformer, per length (< 1: Mamba-2 wins)
    result["ratios"] = {
        f"mamba2_6 / {name}": {key: [a / b for a, b in zip(base[key], m[key])]
                               for key in ("time_s", "tensor_mem_mb", "work_mem_mb", "peak_mem_mb")}
        for name, m in result["models"].items() if name != "mamba2_6"}
    if len(args.lengths) > 1:
        result["time_growth_exponent"] = {n: loglog_slope(args.lengths, m["time_s"]) for n, m in result["models"].items()}
    write_json(args.out, result)
    plot(result, args.plot or args.out.with_suffix(".png"))
    print(f"\n{result['device']}\ntiming: {timing}\nmemory: {memory}")
    for name, ratio in result["ratios"].items():
        print(f"{name} at {args.lengths[-1]:g} s: time x{ratio['time_s'][-1]:.2f}, tensor memory "
              f"x{ratio['tensor_mem_mb'][-1]:.2f} (working x{ratio['work_mem_mb'][-1]:.2f}), "
              f"RSS x{ratio['peak_mem_mb'][-1]:.2f}")
    if "time_growth_exponent" in result:
        print("time ~ length^p, p =", {k: round(v, 2) for k, v in result["time_growth_exponent"].items()})


if __name__ == "__main__":
    main()
