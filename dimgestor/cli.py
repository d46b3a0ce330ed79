"""The `dimgestor` command: info, train, generate (and eval when installed).

Subcommands live in their modules and join through `register(subparsers)`. Errors a user can fix
(bad files, bad options) print one `error: ...` line and exit 2; DIMGESTOR_DEBUG=1 shows the traceback.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from . import __version__

__all__ = ["main", "model_info"]


def _user_errors() -> tuple[type[BaseException], ...]:
    from .audio import AudioError
    from .bvh import BvhError
    from .checkpoint import CheckpointError
    from .config import ConfigError
    from .dataset import DatasetError
    return (ConfigError, CheckpointError, BvhError, AudioError, DatasetError, FileNotFoundError,
            NotADirectoryError, IsADirectoryError, PermissionError, ValueError)


def model_info(config, steps: int = 8) -> dict:
    """Parameter counts per component and streaming state per stream for a config."""
    from .model import DiMGestor
    model = DiMGestor(config)
    counts = model.param_counts()
    return {"config": config.model_dump(mode="json"), "parameters": {**counts, "total": sum(counts.values())},
            "stream_state_bytes": {"steps": steps, **model.stream_state_nbytes(steps)},
            "lookahead_s": model.lookahead_s}


def _info(args) -> int:
    from .checkpoint import load_checkpoint
    from .config import get_preset
    if args.checkpoint:
        config = load_checkpoint(args.checkpoint).config
        source = args.checkpoint
    else:
        overrides = {"motion_dim": args.motion_dim} if args.motion_dim else {}
        config = get_preset(args.preset, **overrides)
        source = f"preset {args.preset}"
    info = model_info(config, args.steps)
    if args.json:
        print(json.dumps({"source": source, **info}, indent=1))
        return 0
    c = config
    print(f"{source}: hidden {c.hidden}, {c.n_blocks} blocks, d_state {c.d_state}, headdim {c.headdim}, "
          f"front end {c.frontend} ({c.n_mels} mels), kernel {c.down_kernel}, motion_dim {c.motion_dim}, "
          f"prediction {c.prediction}, "
          + (f"cosine schedule over {c.n_steps} steps" if c.schedule == "cosine" else
             f"{c.schedule} betas {c.beta_start:g}..{c.beta_end:g} over {c.n_steps}")
          + (f", noise correlated over {c.noise_taps} frames" if c.noise_taps > 1 else "")
          + f", DDIM K={c.sample_steps} ({c.ddim_spacing})"
          + (f", guidance {c.guidance:g}" if c.guidance != 1.0 else ""))
    print(f"algorithmic latency: {info['lookahead_s'] * 1000:.0f} ms (one frame + {c.lookahead_feats * 1000 // c.feature_rate} ms audio lookahead)")
    print("parameters:")
    for k, v in info["parameters"].items():
        print(f"  {k:<18}{v:>12,}")
    s = info["stream_state_bytes"]
    print(f"streaming state per stream (K={s['steps']} steps):")
    for k in ("frontend", "extractor", "denoiser_per_step", "denoiser_all_steps", "total"):
        print(f"  {k:<18}{s[k]:>12,} bytes")
    return 0


def _export(args) -> int:
    from .checkpoint import export_checkpoint
    inference = {k: v for k, v in (("smooth_hz", args.smooth), ("smooth_beta", args.smooth_beta),
                                   ("sample_steps", args.sample_steps), ("guidance", args.guidance)) if v is not None}
    if inference.get("sample_steps", 1) < 1:
        raise ValueError("--sample-steps must be >= 1")
    if "guidance" in inference:
        from .diffusion import check_guidance
        check_guidance(inference["guidance"])
    if inference.get("smooth_hz", 1) < 0 or inference.get("smooth_beta", 0) < 0:
        raise ValueError("--smooth and --smooth-beta must be >= 0")
    if inference.get("smooth_hz") == 0:
        inference["smooth_hz"] = None
    print(f"exported {export_checkpoint(args.checkpoint, args.out, **inference)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dimgestor", description="DiM-Gestor co-speech gesture engine")
    parser.add_argument("--version", action="version", version=f"dimgestor {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = sub.add_parser("info", help="parameter counts and streaming state size of a preset or checkpoint")
    p.add_argument("--preset", default="realtime", help="paper, realtime or tiny")
    p.add_argument("--checkpoint", default=None, help="describe a checkpoint instead of a preset")
    p.add_argument("--motion-dim", type=int, default=None, help="feature columns (default: the preset's)")
    p.add_argument("--steps", type=int, default=8, help="DDIM steps the stream carries state for")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_info)

    p = sub.add_parser("export", help="copy a checkpoint's inference files (no optimizer state), e.g. to "
                                      "dimgestor/default_model/")
    p.add_argument("--checkpoint", required=True, help="checkpoint folder or run folder (its latest)")
    p.add_argument("--out", required=True, help="destination folder (replaced)")
    p.add_argument("--smooth", type=float, default=None, metavar="HZ",
                   help="set the output filter's cutoff that generate/serve use by default (0 = off)")
    p.add_argument("--smooth-beta", type=float, default=None, help="set the output filter's speed coefficient")
    p.add_argument("--sample-steps", type=int, default=None, help="set the DDIM steps K generate/serve use by default")
    p.add_argument("--guidance", type=float, default=None, metavar="S",
                   help="set the classifier-free guidance scale generate/serve/eval use by default (1 = unguided)")
    p.set_defaults(func=_export)

    from . import eval as evaluation
    from . import generate, onnx_export, render, train
    for module in (train, generate, evaluation, render, onnx_export):
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except _user_errors() as e:
        if os.environ.get("DIMGESTOR_DEBUG"):
            raise
        msg = str(e) if not isinstance(e, OSError) or not e.filename else f"{e.filename}: {e.strerror or e}"
        print(f"error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
