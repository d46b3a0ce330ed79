"""Seam check: is generated motion rougher where streaming windows meet than inside them?

A stream returns the frames of each pushed window; if carrying state across windows were wrong, the
motion would jump at window boundaries. The jerk (third difference) of frames whose stencil spans a
boundary is compared with the jerk elsewhere: a seam shows as a ratio well above 1. The streamed
frames are also compared with whole-recording generation, which they must equal. The output filter
(`--smooth`) is off here: it would smooth a seam away.

    python benchmarks/seams.py                       # the embedded default model if present
    python benchmarks/seams.py --checkpoint runs/x --window-ms 100 --steps 8
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, test_audio, utc_now, write_json


def load_model(checkpoint: str | None, preset: str):
    """(model, bundle or None, source text): a checkpoint when one loads, else the preset untrained."""
    from dimgestor.config import get_preset
    from dimgestor.model.network import DiMGestor

    try:
        from dimgestor.streaming.checkpoint import load_checkpoint

        bundle = load_checkpoint(checkpoint)
        return bundle.model.eval(), bundle, f"checkpoint {checkpoint or 'embedded default'}"
    except Exception as e:  # noqa: BLE001 - no checkpoint yet is a normal state of a fresh clone
        if checkpoint:
            raise
        import torch

        torch.manual_seed(0)
        model = DiMGestor(get_preset(preset)).eval()
        with torch.no_grad():  # untrained adaLN-Zero outputs 0 everywhere: perturb to get motion
            for p in model.parameters():
                p.add_(0.05 * torch.randn_like(p))
        return model, None, f"untrained {preset} preset with random weights (no checkpoint: {e})"


def stream_in_windows(model, audio: np.ndarray, window: int, steps: int, seed: int = 0):
    """Frames from pushing `audio` in `window`-sample pieces, and the frame index where each push's output began."""
    from dimgestor.streaming.stream import GestureStream

    stream = GestureStream(model, steps=steps, seed=seed, smoothing=None)  # a filter would hide a seam
    parts, starts = [], []
    for i in range(0, len(audio), window):
        starts.append(stream.frames_out)
        parts.append(stream.push(audio[i : i + window]))
    starts.append(stream.frames_out)
    parts.append(stream.finish())
    return np.concatenate(parts), sorted({s for s in starts if s > 0})


def seam_ratio(trajectory: np.ndarray, boundaries: list[int], fps: float) -> dict:
    """Mean jerk of third-difference stencils centred on a boundary / mean jerk of stencils centred elsewhere.

    Stencil i covers frames i..i+3 and is centred on the gap between frames i+1 and i+2; a boundary b
    is the gap between frames b-1 and b, so stencil b-2 is the one centred on it. Centred stencils
    keep the comparison defined down to 2-frame (100 ms) windows.
    """
    x = trajectory.reshape(len(trajectory), -1)
    d3 = np.linalg.norm(np.diff(x, n=3, axis=0), axis=1) * fps**3  # (T - 3,)
    spans = np.zeros(len(d3), dtype=bool)
    for b in boundaries:
        if 0 <= b - 2 < len(d3):
            spans[b - 2] = True
    if spans.all() or not spans.any():
        return {"ratio": float("nan"), "boundary_jerk": float("nan"), "inside_jerk": float("nan")}
    at, inside = float(d3[spans].mean()), float(d3[~spans].mean())
    return {"ratio": at / inside if inside > 0 else float("nan"), "boundary_jerk": at, "inside_jerk": inside,
            "n_boundary_stencils": int(spans.sum()), "n_inside_stencils": int((~spans).sum())}


def seam_check(model, bundle, window_ms: int, steps: int, audio_s: float, audio: np.ndarray | None = None) -> dict:
    from dimgestor.streaming.stream import generate_offline

    cfg = model.config
    audio = test_audio(audio_s, cfg.sample_rate, seed=3) if audio is None else audio
    window = int(cfg.sample_rate * window_ms / 1000)
    streamed, boundaries = stream_in_windows(model, audio, window, steps)
    offline = generate_offline(model, audio, steps=steps, smoothing=None)
    result = {"window_ms": window_ms, "steps": steps, "smoothing": "off", "audio_s": len(audio) / cfg.sample_rate,
              "frames": len(streamed), "boundaries": len(boundaries),
              "max_abs_diff_streamed_vs_offline": float(np.abs(streamed - offline).max())}
    if bundle is not None:  # jerk of joint positions, as the metrics measure it
        from dimgestor.evaluation.eval import joint_positions
        from dimgestor.evaluation.metrics import upper_body_joints

        pos = joint_positions(bundle.denormalize(streamed), bundle.skeleton, bundle.feature_spec)
        trajectory, space = pos[:, upper_body_joints(bundle.skeleton.names)], "upper-body joint positions"
    else:
        trajectory, space = streamed, "normalized motion features"
    result.update(seam_ratio(trajectory, boundaries, cfg.fps), jerk_of=space)
    return result


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default=None, help="checkpoint folder (default: the embedded model)")
    p.add_argument("--preset", default="realtime", help="preset used untrained when no checkpoint loads")
    p.add_argument("--window-ms", type=int, nargs="+", default=[100, 200, 500])
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--audio", default=None, help="a WAV file to stream (default: 30 s of synthetic speech-like audio)")
    p.add_argument("--audio-s", type=float, default=30.0)
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--out", type=Path, default=RESULTS / "seams.json")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    model, bundle, source = load_model(args.checkpoint, args.preset)
    audio = None
    if args.audio:
        from dimgestor.audio import load_wav

        audio = load_wav(args.audio, model.config.sample_rate)
    started = time.time()
    rows = [seam_check(model, bundle, w, args.steps, args.audio_s, audio) for w in args.window_ms]
    for r in rows:
        print(f"window {r['window_ms']:4d} ms: jerk at boundaries / inside = {r['ratio']:.3f} "
              f"(streamed vs offline max |diff| {r['max_abs_diff_streamed_vs_offline']:.2e})")
    result = {"device": describe_device("cpu"), "model": source, "audio": args.audio or "synthetic",
              "rows": rows, "measured_at": utc_now(), "code_version": code_version(),
              "wall_s": round(time.time() - started, 1)}
    write_json(args.out, result)
    return result


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
