"""Arithmetic the denoiser does, and the arithmetic this machine can do: achieved GFLOP/s beside the matmul peak.

- `denoiser_flops_per_frame_step`: FLOPs of one denoiser forward per frame, counted by
  `torch.utils.flop_counter.FlopCounterMode` (matmuls, linears, convolutions, bmm: 2 FLOPs per
  multiply-add; element-wise ops are not counted, so achieved GFLOP/s is a lower bound on work done).
- `matmul_peak`: the best GFLOP/s of an n x n x n matmul over a few repeats, with a given thread count
  and dtype: what a well-fed core of this CPU does, measured in the same run as the streams.
"""

from __future__ import annotations

import time

import torch


def denoiser_flops_per_frame_step(model, frames: int = 20) -> float:
    """FLOPs per frame of one denoiser forward (one sampler step) over a window of `frames` frames."""
    from torch.utils.flop_counter import FlopCounterMode

    cfg = model.config
    dev = next(model.parameters()).device
    x = torch.zeros(1, frames, cfg.motion_dim, device=dev)
    cond = torch.zeros(1, frames, cfg.hidden, device=dev)
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        model(x, 500 % cfg.n_steps, cond, model.init_state(1, dev))
    return counter.get_total_flops() / frames


def matmul_peak(n: int = 1024, threads: int = 1, dtype: torch.dtype = torch.float32, repeats: int = 7,
                min_time_s: float = 0.2) -> dict:
    """Best-of-`repeats` GFLOP/s of an (n, n) @ (n, n) matmul on `threads` torch threads (restored after)."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        g = torch.Generator().manual_seed(0)
        a = torch.randn(n, n, generator=g).to(dtype)
        b = torch.randn(n, n, generator=g).to(dtype)
        out = torch.empty(n, n, dtype=dtype)
        torch.mm(a, b, out=out)  # warm-up: the BLAS picks its kernels and packs buffers
        flops = 2.0 * n ** 3
        # enough calls per repeat to last min_time_s, so a small n is not timer noise
        t0 = time.perf_counter()
        torch.mm(a, b, out=out)
        calls = max(1, int(min_time_s / max(time.perf_counter() - t0, 1e-6)))
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(calls):
                torch.mm(a, b, out=out)
            best = min(best, (time.perf_counter() - t0) / calls)
    finally:
        torch.set_num_threads(before)
    return {"n": n, "threads": threads, "dtype": str(dtype).replace("torch.", ""), "repeats": repeats,
            "calls_per_repeat": calls, "best_s": best, "gflops": flops / best / 1e9}
