"""`dimgestor generate`: a checkpoint (or the embedded default model) + a WAV -> a 20 fps BVH."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from .audio import SAMPLE_RATE, AudioError, load_wav
from .bvh import BvhMotion, write_bvh
from .checkpoint import Bundle, load_checkpoint
from .features import features_to_motion
from .diffusion import check_guidance
from .stream import smoothing_from_flag

__all__ = ["generate_motion", "register"]


def generate_motion(bundle: Bundle, audio: np.ndarray, steps: int | None = None, seed: int = 0, sampler: str = "ddim",
                    eta: float = 0.0, smoothing="config", root: str = "free", tether_s: float = 5.0,
                    guidance: float | None = None) -> BvhMotion:
    """16 kHz mono audio -> motion on the checkpoint's skeleton at its feature rate (len(audio) * fps // 16000 frames)."""
    features = bundle.generate(audio, steps=steps, seed=seed, sampler=sampler, eta=eta, smoothing=smoothing,
                               guidance=guidance)
    return features_to_motion(features, bundle.skeleton, bundle.feature_spec, root=root, tether_s=tether_s)


def register(subparsers) -> None:
    p = subparsers.add_parser("generate", help="generate a BVH for a WAV file (offline, whole file)",
                              formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--checkpoint", default=None,
                   help="checkpoint folder, a file in it, or a run folder (its latest); default: the embedded model")
    p.add_argument("--audio", required=True, help="speech WAV (any rate, mono or stereo)")
    p.add_argument("--out", required=True, help="output .bvh")
    p.add_argument("--steps", type=int, default=None,
                   help="DDIM steps K (ignored by ddpm, which uses all N); default: the checkpoint's sample_steps")
    p.add_argument("--sampler", choices=("ddim", "ddpm"), default="ddim")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eta", type=float, default=0.0, help="DDIM stochasticity (0 = deterministic)")
    p.add_argument("--guidance", type=float, default=None, metavar="S",
                   help="classifier-free guidance scale: 1 = unguided, > 1 follows the audio more (needs a model "
                        "trained with --cond-drop; costs a second batch row); default: the checkpoint's")
    p.add_argument("--smooth", type=float, default=None, metavar="HZ",
                   help="One Euro output filter cutoff in Hz, 0 = off (default: the checkpoint's setting)")
    p.add_argument("--root", choices=("free", "tether", "lock"), default="free",
                   help="root ground motion: as generated, pulled back to the start, or locked "
                        "(as `streamer serve --root`)")
    p.add_argument("--tether-s", type=float, default=5.0, help="time constant of --root tether, seconds")
    p.add_argument("--device", default="cpu", help="cpu, cuda, ...")
    p.set_defaults(func=_run)


def _run(args) -> int:
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    if args.eta < 0:
        raise ValueError(f"--eta must be >= 0, got {args.eta}")
    smoothing = smoothing_from_flag(args.smooth)
    if args.guidance is not None:
        check_guidance(args.guidance)
    if not args.tether_s > 0:
        raise ValueError(f"--tether-s must be > 0, got {args.tether_s}")
    out = Path(args.out)
    if out.suffix.lower() != ".bvh":
        raise ValueError(f"--out {out}: expected a .bvh path")
    if not out.parent.exists():
        raise FileNotFoundError(f"--out {out}: folder {out.parent} does not exist")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"--device {args.device}: CUDA is not available on this machine")
    bundle = load_checkpoint(args.checkpoint, device=args.device)
    if args.steps is None:
        args.steps = bundle.config.sample_steps
    if args.steps > bundle.config.n_steps:
        raise ValueError(f"--steps {args.steps} exceeds the model's {bundle.config.n_steps} diffusion steps")
    audio = load_wav(args.audio, SAMPLE_RATE)
    if len(audio) * bundle.feature_spec.fps // SAMPLE_RATE == 0:  # `streamer serve` refuses it too
        raise AudioError(f"{args.audio}: {len(audio)} audio samples, shorter than one motion frame "
                         f"({1000 / bundle.feature_spec.fps:g} ms): nothing to generate")
    motion = generate_motion(bundle, audio, args.steps, args.seed, args.sampler, args.eta, smoothing, args.root,
                             args.tether_s, args.guidance)
    write_bvh(out, motion)
    print(f"wrote {out}: {motion.values.shape[0]} frames at {1 / motion.frame_time:g} fps "
          f"({len(audio) / SAMPLE_RATE:.2f} s of audio) from {bundle.path}")
    return 0
