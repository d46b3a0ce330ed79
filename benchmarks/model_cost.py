"""What the embedded default model costs per window beside the `realtime` preset the speed numbers are for.

The default model is the realtime preset with the speech front end (frame-by-frame running statistics in
numpy), a wider downsampler (kernel 41 for 300 ms of lookahead), 228 motion features and classifier-free
guidance (a second batch row per stream). The serving-capacity numbers of `streaming.py` are measured on the
preset; this measures the ratio (and the default model served with `--guidance 1`): B streams pushed together (`push_many`, one forward per sampler step) in
100 ms windows on one torch thread, each model in turn, rounds alternating (a busy neighbour slows both alike).

    .venv/bin/python benchmarks/model_cost.py                       # B = 1, 8, 16, 32; K = 4, 8
    .venv/bin/python benchmarks/model_cost.py --batches 1 8 --steps 4 --out /tmp/cost.json
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, test_audio, utc_now, write_json


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None, help="the model to time (default: the embedded default model)")
    p.add_argument("--preset", default="realtime", help="the preset it is compared with (random weights)")
    p.add_argument("--steps", type=int, nargs="+", default=[4, 8], help="DDIM steps K")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 8, 16, 32], help="streams pushed together")
    p.add_argument("--window-ms", type=int, default=100, help="audio pushed per call")
    p.add_argument("--rounds", type=int, default=30, help="timed rounds per configuration (after 6 warm-up rounds)")
    p.add_argument("--out", type=Path, default=RESULTS / "model_cost.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def models(args) -> dict:
    """{name: (model, what, guidance)}: the checkpoint at its own guidance and unguided, the preset (random
    weights) unguided."""
    import torch

    from dimgestor.config import get_preset
    from dimgestor.model.network import DiMGestor
    from dimgestor.streaming.checkpoint import load_checkpoint

    bundle = load_checkpoint(args.checkpoint)
    torch.manual_seed(0)
    preset = DiMGestor(get_preset(args.preset, motion_dim=bundle.feature_spec.dim)).eval()
    with torch.no_grad():  # adaLN-Zero init makes blocks the identity; random weights cost the same as trained ones
        for p in preset.parameters():
            p.add_(0.02 * torch.randn_like(p))
    c = bundle.config
    what = f"checkpoint {args.checkpoint or 'embedded default'}: front end {c.frontend}, kernel {c.down_kernel}"
    return {"default": (bundle.model.eval(), f"{what}, guidance {c.guidance:g}", None),
            "default_unguided": (bundle.model, f"{what}, served with --guidance 1", 1.0),
            "preset": (preset, f"preset {args.preset} (random weights, {preset.config.frontend}, kernel "
                               f"{preset.config.down_kernel}, unguided, {bundle.feature_spec.dim} motion features)", None)}


def timed(arms: dict, steps: int, B: int, args) -> dict:
    """Per-round time (s) of B streams of each model, one push_many round each, rounds alternating."""
    from dimgestor.streaming.batch import push_many
    from dimgestor.streaming.stream import GestureStream

    window = 16 * args.window_ms  # samples at 16 kHz
    n = args.rounds + 6
    audios = [test_audio(n * window / 16000, 16000, seed=j) for j in range(B)]
    groups = {name: [GestureStream(m, steps=steps, seed=j, smoothing=None, guidance=g) for j in range(B)]
              for name, (m, _, g) in arms.items()}
    times = {name: [] for name in arms}
    for k in range(n):
        for name in (list(arms) if k % 2 == 0 else list(arms)[::-1]):
            t0 = time.perf_counter()
            push_many(groups[name], [a[k * window:(k + 1) * window] for a in audios])
            if k >= 6:  # the lookahead has filled, the batch buffers formed
                times[name].append(time.perf_counter() - t0)
    row = {name: {"ms_p50": 1000 * float(np.median(t)), "ms_mean": 1000 * float(np.mean(t)),
                  "load_of_real_time": float(np.median(t)) * 1000 / args.window_ms} for name, t in times.items()}
    return {"steps": steps, "batch": B, "window_ms": args.window_ms, "rounds": args.rounds, **row,
            "ratio_p50": row["default"]["ms_p50"] / row["preset"]["ms_p50"],
            "ratio_p50_unguided": row["default_unguided"]["ms_p50"] / row["preset"]["ms_p50"]}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.8))
    for k in sorted({r["steps"] for r in result["rows"]}):
        rows = [r for r in result["rows"] if r["steps"] == k]
        b = [r["batch"] for r in rows]
        ax.plot(b, [r["default"]["ms_p50"] for r in rows], "o-", label=f"default model, K={k}")
        ax.plot(b, [r["default_unguided"]["ms_p50"] for r in rows], "^:", label=f"default, --guidance 1, K={k}")
        ax.plot(b, [r["preset"]["ms_p50"] for r in rows], "s--", label=f"{result['preset']}, K={k}")
    ax.axhline(result["window_ms"], color="grey", lw=0.8, label="real time (one window)")
    ax.set_xlabel("streams pushed together")
    ax.set_ylabel("ms per 100 ms window (p50)")
    ax.set_title("per-window cost: embedded default model vs preset", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    args = parse_args(argv)
    import torch

    torch.set_num_threads(1)
    arms = models(args)
    result = {"benchmark": "model_cost", "created": utc_now(), "code_version": code_version(),
              "device": describe_device("cpu"), "torch": torch.__version__, "load_avg_before": load_average(),
              "command": " ".join(["python", "benchmarks/model_cost.py"] + args.argv), "preset": args.preset,
              "window_ms": args.window_ms, "models": {name: what for name, (_, what, _) in arms.items()}, "rows": [],
              "note": args.note}
    for steps in args.steps:
        for B in args.batches:
            row = timed(arms, steps, B, args)
            result["rows"].append(row)
            print(f"K={steps} B={B:3d}: default {row['default']['ms_p50']:.1f} ms ({row['ratio_p50']:.2f}x), unguided "
                  f"{row['default_unguided']['ms_p50']:.1f} ms ({row['ratio_p50_unguided']:.2f}x), {args.preset} "
                  f"{row['preset']['ms_p50']:.1f} ms per window (p50)", flush=True)
    result["load_avg_after"] = load_average()
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))


if __name__ == "__main__":
    main()
