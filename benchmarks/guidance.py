"""What classifier-free guidance costs: per-window compute and real-time factor, guided against unguided.

A guided stream runs its unconditional branch as a second batch row (`dimgestor.model.sampler`), so its denoiser
does twice the rows per sampler step; the front end and the condition are computed once. Measured with
100 ms windows (the served window size) on one torch thread, at each K:

  single   one stream pushed as fast as possible at scale 1 and at scale S, windows alternating between
           the two streams (a busy neighbour slows both alike); per-window time p50/p95, RTF, ratio
  batched  B streams pushed together (`push_many`: one forward per sampler step) at scale 1 and at scale S,
           and 2B unguided streams (the same number of network rows as B guided ones), rounds alternating

    .venv/bin/python benchmarks/guidance.py                    # the embedded default model, K = 4, 8
    .venv/bin/python benchmarks/guidance.py --batches 8 32 --steps 4 8
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, percentile_ms, test_audio, utc_now, write_json


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None, help="model to time (default: the embedded default model)")
    p.add_argument("--preset", default=None, help="time a preset with random weights instead (tests use tiny)")
    p.add_argument("--steps", type=int, nargs="+", default=[4, 8], help="DDIM steps K")
    p.add_argument("--guidance", type=float, default=2.0, help="the guided streams' scale S (cost does not depend on it)")
    p.add_argument("--window-ms", type=int, default=100, help="audio pushed per call")
    p.add_argument("--audio-s", type=float, default=20.0, help="audio per single-stream configuration")
    p.add_argument("--batches", type=int, nargs="*", default=[8, 32], help="streams per batch in the batched section")
    p.add_argument("--batch-audio-s", type=float, default=4.0, help="audio per batched configuration")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--out", type=Path, default=RESULTS / "guidance.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def load_model(args):
    import torch

    if args.preset:
        from dimgestor.config import get_preset
        from dimgestor.model.network import DiMGestor

        torch.manual_seed(0)
        model = DiMGestor(get_preset(args.preset)).eval()
        with torch.no_grad():  # adaLN-Zero init makes blocks the identity; random weights cost the same
            for p in model.parameters():
                p.add_(0.02 * torch.randn_like(p))
        return model, f"preset {args.preset} (random weights)"
    from dimgestor.streaming.checkpoint import load_checkpoint

    bundle = load_checkpoint(args.checkpoint)
    return bundle.model.eval(), f"checkpoint {args.checkpoint or 'embedded default'}"


def _summary(times: list[float], audio_s: float, window_ms: int) -> dict:
    return {"ms_p50": percentile_ms(times, 50), "ms_p95": percentile_ms(times, 95), "ms_mean": 1000 * float(np.mean(times)),
            "rtf": sum(times) / audio_s, "rtf_median_window": float(np.median(times)) * 1000 / window_ms}


def _warm(model, steps, window, audio, guidance):
    from dimgestor.streaming.stream import GestureStream

    s = GestureStream(model, steps=steps, smoothing=None, guidance=guidance)
    for k in range(8):  # past the lookahead: frames come, kernels are picked, buffers allocated
        s.push(audio[k * window:(k + 1) * window])


def single(model, steps: int, args) -> dict:
    """One stream at scale 1 and one at scale S, pushed window by window in alternating order."""
    from dimgestor.streaming.stream import GestureStream

    cfg = model.config
    window = cfg.sample_rate * args.window_ms // 1000
    n = max(int(round(args.audio_s * 1000 / args.window_ms)), 20)
    audio = test_audio(n * window / cfg.sample_rate, cfg.sample_rate)
    for g in (1.0, args.guidance):
        _warm(model, steps, window, audio, g)
    streams = {g: GestureStream(model, steps=steps, smoothing=None, guidance=g) for g in (1.0, args.guidance)}
    times = {g: [] for g in streams}
    for k in range(n):
        order = list(streams) if k % 2 == 0 else list(streams)[::-1]
        for g in order:
            t0 = time.perf_counter()
            streams[g].push(audio[k * window:(k + 1) * window])
            times[g].append(time.perf_counter() - t0)
    audio_s = n * window / cfg.sample_rate
    rows = {("unguided" if g == 1.0 else "guided"): _summary(t, audio_s, args.window_ms) for g, t in times.items()}
    rows["ratio_p50"] = rows["guided"]["ms_p50"] / rows["unguided"]["ms_p50"]
    rows["ratio_rtf"] = rows["guided"]["rtf"] / rows["unguided"]["rtf"]
    return {"steps": steps, "window_ms": args.window_ms, "windows": n, **rows}


def batched(model, steps: int, B: int, args) -> dict:
    """B streams at scale 1, B at scale S and 2B at scale 1, one push_many round each, rounds alternating."""
    from dimgestor.streaming.batch import push_many
    from dimgestor.streaming.stream import GestureStream

    cfg = model.config
    window = cfg.sample_rate * args.window_ms // 1000
    n = max(int(round(args.batch_audio_s * 1000 / args.window_ms)), 12)
    audios = [test_audio(n * window / cfg.sample_rate, cfg.sample_rate, seed=j) for j in range(2 * B)]
    arms = {"unguided": (B, 1.0), "guided": (B, args.guidance), "unguided_2x": (2 * B, 1.0)}
    groups = {name: [GestureStream(model, steps=steps, seed=j, smoothing=None, guidance=g) for j in range(count)]
              for name, (count, g) in arms.items()}
    times = {name: [] for name in arms}
    warm = 6  # rounds not timed: the lookahead fills and the batch buffers form
    for k in range(n):
        names = list(arms) if k % 2 == 0 else list(arms)[::-1]
        for name in names:
            streams = groups[name]
            t0 = time.perf_counter()
            push_many(streams, [a[k * window:(k + 1) * window] for a in audios[:len(streams)]])
            if k >= warm:
                times[name].append(time.perf_counter() - t0)
    audio_s = (n - warm) * window / cfg.sample_rate
    rows = {name: {**_summary(t, audio_s, args.window_ms), "streams": arms[name][0], "guidance": arms[name][1],
                   "rows": arms[name][0] * (2 if arms[name][1] != 1.0 else 1)} for name, t in times.items()}
    return {"steps": steps, "window_ms": args.window_ms, "batch": B, "rounds": n - warm, **rows,
            "ratio_p50": rows["guided"]["ms_p50"] / rows["unguided"]["ms_p50"],
            "ratio_p50_vs_2x_unguided": rows["guided"]["ms_p50"] / rows["unguided_2x"]["ms_p50"]}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    ax = axes[0]
    ks = [r["steps"] for r in result["single"]]
    x = np.arange(len(ks))
    for i, (arm, color) in enumerate((("unguided", "tab:blue"), ("guided", "tab:orange"))):
        p50 = [r[arm]["ms_p50"] for r in result["single"]]
        p95 = [r[arm]["ms_p95"] for r in result["single"]]
        ax.bar(x + (i - 0.5) * 0.38, p50, 0.38, color=color,
               label=f"scale {'1' if arm == 'unguided' else format(result['guidance'], 'g')}")
        ax.scatter(x + (i - 0.5) * 0.38, p95, color="k", marker="_", s=120, zorder=3)
    for xi, r in zip(x, result["single"]):
        ax.text(xi, max(r["guided"]["ms_p95"], r["unguided"]["ms_p95"]) * 1.03, f"x{r['ratio_p50']:.2f}", ha="center",
                fontsize=8)
    ax.set_xticks(x, [f"K={k}" for k in ks])
    ax.set_ylabel(f"ms per {result['window_ms']} ms window (bar p50, tick p95)")
    ax.set_title("one stream", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, axis="y")
    ax = axes[1]
    labels = [f"K={r['steps']} B={r['batch']}" for r in result["batched"]]
    x = np.arange(len(labels))
    for i, (arm, color, text) in enumerate((("unguided", "tab:blue", "B at scale 1"),
                                            ("guided", "tab:orange", f"B at scale {result['guidance']:g}"),
                                            ("unguided_2x", "tab:gray", "2B at scale 1"))):
        ax.bar(x + (i - 1) * 0.27, [r[arm]["ms_p50"] / r["batch"] for r in result["batched"]], 0.27, color=color,
               label=text)
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel("ms per window per stream (p50 of a round / B)")
    ax.set_title("batched streams (push_many)", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, axis="y")
    fig.suptitle(f"classifier-free guidance cost: {result['model']}, {result['threads']} thread; {result['device']}; "
                 f"code {result['code_version']}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main(argv=None) -> int:
    args = parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    model, label = load_model(args)
    result = {"measured_at": utc_now(), "code_version": code_version(), "device": describe_device("cpu"),
              "argv": args.argv, "note": args.note, "load_avg_before": load_average(), "model": label,
              "threads": args.threads, "guidance": args.guidance, "window_ms": args.window_ms,
              "single": [], "batched": []}
    with torch.inference_mode():
        for K in args.steps:
            r = single(model, K, args)
            result["single"].append(r)
            print(f"one stream K={K}: scale 1 {r['unguided']['ms_p50']:.2f} ms (rtf {r['unguided']['rtf']:.3f}), "
                  f"scale {args.guidance:g} {r['guided']['ms_p50']:.2f} ms (rtf {r['guided']['rtf']:.3f}): "
                  f"x{r['ratio_p50']:.2f} per window", flush=True)
        for K in args.steps:
            for B in args.batches:
                r = batched(model, K, B, args)
                result["batched"].append(r)
                print(f"{B} streams K={K}: round p50 scale 1 {r['unguided']['ms_p50']:.1f} ms, scale {args.guidance:g} "
                      f"{r['guided']['ms_p50']:.1f} ms (x{r['ratio_p50']:.2f}), {2 * B} unguided "
                      f"{r['unguided_2x']['ms_p50']:.1f} ms", flush=True)
    result["load_avg_after"] = load_average()
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
