"""The `dimgestor` command: serve, generate, train, render, eval, convert, info, export, export-onnx, devices, web.

Subcommands live in their modules and join through `register(subparsers)` (serve, devices and web from
`streamer`). Errors a user can fix (bad files, bad options) print one `error: ...` line and exit 2;
DIMGESTOR_DEBUG=1 shows the traceback. Help is grouped by purpose, states each option's default once and ends
with examples (`HelpFormatter`); old spellings of renamed options still work and say once what replaced them
(`deprecated_alias`).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from dimgestor import __version__
from dimgestor.cli_help import HelpFormatter, deprecated_alias, examples

__all__ = ["main", "streamer_main", "model_info", "build_parser", "COMMANDS"]

COMMANDS = ("serve", "generate", "train", "render", "eval", "convert", "info", "export", "export-onnx", "devices", "web")


def _user_errors() -> tuple[type[BaseException], ...]:
    from dimgestor.audio import AudioError
    from dimgestor.bvh import BvhError
    from dimgestor.config import ConfigError
    from dimgestor.streaming.checkpoint import CheckpointError
    from dimgestor.training.dataset import DatasetError
    return (ConfigError, CheckpointError, BvhError, AudioError, DatasetError, FileNotFoundError,
            NotADirectoryError, IsADirectoryError, PermissionError, ValueError)


def model_info(config, steps: int = 8) -> dict:
    """Parameter counts per component and streaming state per stream for a config."""
    from dimgestor.model.network import DiMGestor
    model = DiMGestor(config)
    counts = model.param_counts()
    return {"config": config.model_dump(mode="json"), "parameters": {**counts, "total": sum(counts.values())},
            "stream_state_bytes": {"steps": steps, **model.stream_state_nbytes(steps)},
            "lookahead_s": model.lookahead_s}


def _info(args) -> int:
    from dimgestor.config import get_preset
    from dimgestor.streaming.checkpoint import load_checkpoint
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
          + (f"speakers {', '.join(c.speakers)}, " if c.speakers else "")
          + f"prediction {c.prediction}, "
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
    from dimgestor.streaming.checkpoint import export_checkpoint
    inference = {k: v for k, v in (("smooth_hz", args.smooth), ("smooth_beta", args.smooth_beta),
                                   ("sample_steps", args.sample_steps), ("guidance", args.guidance)) if v is not None}
    if inference.get("sample_steps", 1) < 1:
        raise ValueError("--steps must be >= 1")
    if "guidance" in inference:
        from dimgestor.model.diffusion import check_guidance
        check_guidance(inference["guidance"])
    if inference.get("smooth_hz", 1) < 0 or inference.get("smooth_beta", 0) < 0:
        raise ValueError("--smooth and --smooth-beta must be >= 0")
    if inference.get("smooth_hz") == 0:
        inference["smooth_hz"] = None
    print(f"exported {export_checkpoint(args.checkpoint, args.out, **inference)}")
    return 0


def _register_info(sub) -> None:
    from dimgestor.config import PRESETS

    p = sub.add_parser("info", help="parameter counts and streaming state size of a preset or checkpoint",
                       description="Parameter counts per component, the algorithmic latency and the streaming state "
                                   "one stream carries, for a preset or a checkpoint.",
                       epilog=examples("dimgestor info", "dimgestor info --preset paper --steps 4",
                                       "dimgestor info --checkpoint runs/mine --json"))
    p.add_argument("--preset", default="realtime", choices=list(PRESETS), help="model preset to describe")
    p.add_argument("--checkpoint", default=None, help="describe a checkpoint (or run folder) instead of a preset")
    p.add_argument("--motion-dim", type=int, default=None, help="feature columns (default: the preset's)")
    p.add_argument("--steps", type=int, default=8, metavar="K", help="DDIM steps K the stream carries state for")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_info)


def _register_export(sub) -> None:
    p = sub.add_parser("export", help="copy a checkpoint's inference files (no optimizer state), e.g. to "
                                      "dimgestor/default_model/",
                       description="Copy a checkpoint's inference files (config, weights, normalisation; no "
                                   "optimizer state) to a folder, optionally with new sampling defaults that "
                                   "generate and serve then use when not told.",
                       epilog=examples("dimgestor export --checkpoint runs/mine --out my_model",
                                       "dimgestor export --checkpoint runs/mine --out my_model --steps 4 --smooth 4",
                                       deprecated="--sample-steps (now --steps)"))
    p.add_argument("--checkpoint", required=True, help="checkpoint folder or run folder (its latest)")
    p.add_argument("--out", required=True, help="destination folder (replaced)")
    sampling = p.add_argument_group("sampling defaults written into the copy",
                                    "an option not given keeps the checkpoint's own value")
    steps = sampling.add_argument("--steps", dest="sample_steps", type=int, default=None, metavar="K",
                                  help="DDIM steps K that generate and serve use by default")
    deprecated_alias(p, "--sample-steps", steps)
    sampling.add_argument("--smooth", type=float, default=None, metavar="HZ",
                          help="the One Euro output filter's cutoff generate and serve use by default (0 = off)")
    sampling.add_argument("--smooth-beta", type=float, default=None, metavar="BETA",
                          help="the One Euro output filter's speed coefficient")
    sampling.add_argument("--guidance", type=float, default=None, metavar="S",
                          help="classifier-free guidance scale generate, serve and eval use by default (1 = unguided)")
    p.set_defaults(func=_export)


def build_parser(prog: str = "dimgestor") -> argparse.ArgumentParser:
    """The whole command line; `prog` is how it was called (`streamer`, the old name, builds the same)."""
    parser = argparse.ArgumentParser(
        prog=prog, formatter_class=HelpFormatter,
        description="DiM-Gestor co-speech gesture engine: speech in, avatar motion out. `dimgestor COMMAND --help` "
                    "says what each command takes.",
        epilog=examples("dimgestor serve                                  # the demo clip; viewer at "
                        "http://127.0.0.1:8765/",
                        "dimgestor serve --source mic --vmc 127.0.0.1:39539 --checkpoint live",
                        "dimgestor generate --audio speech.wav --out motion.bvh",
                        "dimgestor train --data my_data --out runs/mine"))
    parser.add_argument("--version", action="version", version=f"dimgestor {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    from dimgestor.evaluation import eval as evaluation
    from dimgestor.export import onnx_export
    from dimgestor.training import distill, train
    from streamer import cli as streamer_cli
    from streamer import web

    from . import convert, generate, render
    streamer_cli.register_serve(sub)
    for module in (generate, train, distill, render, evaluation, convert):
        module.register(sub)
    _register_info(sub)
    _register_export(sub)
    onnx_export.register(sub)
    streamer_cli.register_devices(sub)
    web.register(sub)
    for p in sub.choices.values():  # (one formatter for all: grouped, one default each, examples kept as written)
        p.formatter_class = HelpFormatter
    return parser


def main(argv: list[str] | None = None, prog: str = "dimgestor") -> int:
    args = build_parser(prog).parse_args(argv)
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


def streamer_main(argv: list[str] | None = None) -> int:
    """`streamer ...`, the old name of this command: runs `dimgestor ...` after saying so, once."""
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), "")  # (never the rest: it may hold a token)
    command = command if command in COMMANDS else "COMMAND"
    print(f"streamer is now `dimgestor`: run `dimgestor {command} ...` (the same options)", file=sys.stderr,
          flush=True)
    return main(argv, prog="streamer")


if __name__ == "__main__":
    sys.exit(main())
