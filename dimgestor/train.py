"""`dimgestor train`: BVH+WAV folder -> checkpoints (EMA weights), resumable, CPU/CUDA/DDP.

The front end has no trained weights, so its features are computed once per window before training
(that and the dataset's own cache keep CPU training fast). A step's batch, diffusion steps and noise
are a pure function of (seed, step) and the saved generator state, so `--resume` continues the run
from its latest checkpoint as if it had not stopped.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import DistributedSampler

from .augment import AugmentConfig, augment
from .checkpoint import latest_checkpoint, read_meta, save_checkpoint
from .config import ModelConfig, get_preset
from .dataset import GestureDataset, compute_stats
from .diffusion import Diffusion
from .features import FeatureSpec
from .model import DiMGestor

__all__ = ["TrainOptions", "train", "register", "Objective", "RECIPES"]

SMALL_DATA_MIN = 30.0  # below this many minutes of training data, mirroring, speed perturbation and audio
# augmentation default on
SMALL_DATA_SPEEDS = (0.9, 1.1)

# Named training recipes: model-config overrides for the diffusion process plus the loss weights.
# "paper" is Zhang et al.'s (N = 1000 linear betas, noise MSE); "streaming" is this engine's default, chosen
# by measurement (benchmarks/recipes.py, results in benchmarks/results/recipes.json): a short cosine chain
# whose every level is trained, x0 prediction with velocity and acceleration losses, and noise correlated
# over a few frames, so that what a causal denoiser passes through is slow sway, not jitter.
RECIPES: dict[str, dict] = {
    "paper": dict(config=dict(n_steps=1000, schedule="linear", beta_start=1e-4, beta_end=8e-2, prediction="eps",
                              noise_taps=1), heading="velocity", vel_weight=0.0, acc_weight=0.0, cond_drop=0.0),
    "streaming": dict(config=dict(n_steps=8, schedule="cosine", prediction="x0", noise_taps=1, sample_steps=4,
                                  ddim_spacing="linspace"), heading="facing",
                      vel_weight=4.0, acc_weight=4.0, root_weight=0.1, cond_drop=0.0),
}


@dataclass
class TrainOptions:
    data: str
    out: str
    preset: str = "realtime"
    overrides: dict | None = None  # ModelConfig fields replacing the preset's (and the recipe's)
    recipe: str | None = "streaming"  # a RECIPES name: its config and loss weights (explicit weights below win)
    max_steps: int = 20000
    batch_size: int = 8
    lr: float = 5e-4
    warmup: int = 200  # linear LR warm-up steps (Adam on a fresh model)
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    vel_weight: float | None = None  # weight of the x0 velocity loss (None: the recipe's; 0 = none)
    acc_weight: float | None = None  # weight of the x0 acceleration loss (None: the recipe's; 0 = none)
    root_weight: float | None = None  # weight of the integrated-root (drift) loss (None: the recipe's; 0 = none)
    heading: str | None = None  # root heading features: "velocity" or "facing" (None: the recipe's)
    # probability that a training window's condition is zeroed (classifier-free guidance learns the unconditional
    # model from these windows; sampling with guidance != 1 needs it). None: the recipe's; 0 = never
    cond_drop: float | None = None
    speeds: tuple[float, ...] = ()  # speed perturbation factors for extra training copies, e.g. (0.9, 1.1)
    ema: float = 0.999  # EMA decay of the saved weights
    window_s: float = 10.0
    hop_s: float | None = None  # default: a quarter window (overlapping windows are cheap data)
    mirror: bool = False  # left/right mirrored copies of every window
    augment: bool = False  # audio augmentation (dimgestor.augment: voice, room, noise, microphone, level)
    aug_copies: int = 4  # augmented versions of each training window's audio; a batch item takes clean or one
    aug_config: dict | None = None  # AugmentConfig fields replacing its defaults
    valid_fraction: float = 0.15
    valid_seconds: float | None = None  # hold out the last S seconds of every clip instead of a fraction
    ckpt_every: int = 1000
    valid_every: int = 250
    keep: int = 3  # checkpoints kept in the run folder (oldest removed)
    seed: int = 0
    device: str = "auto"
    resume: bool = False
    cache_dir: str | None = None
    progress: bool = True


class Objective(nn.Module):
    """The training loss as a module, so DDP sees one forward that uses every trained parameter."""

    def __init__(self, model: DiMGestor, diffusion: Diffusion, weights: dict[str, float]):
        super().__init__()
        self.model, self.diffusion, self.weights = model, diffusion, weights

    def forward(self, x0, feats, t, noise, drop=None):
        return self.diffusion.training_loss(self.model, x0, feats, t, noise, drop=drop, **self.weights)


LOSS_WEIGHTS = ("vel_weight", "acc_weight", "root_weight")


def resolve_recipe(opts: "TrainOptions") -> tuple[dict, dict[str, float]]:
    """(config overrides, {loss weight name: value}) of the options' recipe and explicit settings."""
    if opts.recipe is not None and opts.recipe not in RECIPES:
        raise ValueError(f"unknown recipe {opts.recipe!r}; choose one of {', '.join(RECIPES)}")
    r = RECIPES[opts.recipe] if opts.recipe else {"config": {}}
    weights = {k: float(r.get(k, 0.0) if getattr(opts, k) is None else getattr(opts, k)) for k in LOSS_WEIGHTS}
    return {**r["config"], **(opts.overrides or {})}, weights


def resolve_cond_drop(opts: "TrainOptions") -> float:
    """The condition-dropout probability: the explicit option, else the recipe's, else 0."""
    r = RECIPES.get(opts.recipe, {}) if opts.recipe else {}
    p = float(r.get("cond_drop", 0.0) if opts.cond_drop is None else opts.cond_drop)
    if not 0 <= p <= 1:
        raise ValueError(f"cond_drop must be a probability in [0, 1], got {p}")
    return p


class WindowBank:
    """Normalized motion and front-end features of every window, computed once.

    With `copies` > 0 it also holds the features of that many augmented versions of each window's audio
    (augmented before the front end, so any front end works), seeded by (seed, audio window, copy);
    mirrored windows hear the same audio and share its versions.
    """

    def __init__(self, ds: GestureDataset, model: DiMGestor, mean, std, device, copies: int = 0,
                 aug_config: AugmentConfig | None = None, seed: int = 0):
        self.motion, self.feats, self.versions = [], [], []  # versions[i]: features of window i's augmented audio
        self.copies = copies
        mean, std = torch.from_numpy(mean), torch.from_numpy(std)
        # babble is made of the training speech itself, pitch-shifted and time-shifted
        babble = [ds.clips[c].audio[a * ds.spf: b * ds.spf] for c, a, b in ds.segments] if copies else None
        shared: dict[tuple, list[torch.Tensor]] = {}
        with torch.no_grad():
            for i in range(len(ds)):
                item = ds[i]
                T = len(item["motion"])
                self.feats.append(self._features(model, item["audio"], T, device))
                self.motion.append((torch.from_numpy(item["motion"]) - mean) / std)
                if copies:
                    key = ds.windows[i][:3]  # (clip, start, length): the same audio, mirrored or not
                    if key not in shared:
                        u = len(shared)
                        shared[key] = [self._features(model, augment(item["audio"], model.config.sample_rate,
                                                                     (seed, u, k), aug_config, babble), T, device)
                                       for k in range(copies)]
                    self.versions.append(shared[key])

    @staticmethod
    def _features(model: DiMGestor, window_audio: np.ndarray, T: int, device) -> torch.Tensor:
        fe, c = model.frontend, model.config
        audio = np.zeros(max(model.samples_needed(T), len(window_audio)), np.float32)
        audio[: len(window_audio)] = window_audio  # silence beyond the window, as at a stream's end
        f, _ = fe(torch.from_numpy(audio)[None].to(device), fe.init_state(1, device))
        return f[0, : T * c.feats_per_frame + c.lookahead_feats].cpu()

    def __len__(self):
        return len(self.motion)

    def draw_versions(self, n: int, g: torch.Generator) -> list[int] | None:
        """Per batch item 0 (clean) or k (augmented copy k), uniformly; None (nothing drawn) without copies."""
        return torch.randint(0, self.copies + 1, (n,), generator=g).tolist() if self.copies else None

    def batch(self, idx: list[int], frames_extra: int, fpf: int, versions: list[int] | None = None):
        T = min(len(self.motion[i]) for i in idx)  # crop to the shortest window
        x0 = torch.stack([self.motion[i][:T] for i in idx])
        src = [self.feats[i] if not versions or v == 0 else self.versions[i][v - 1]
               for i, v in zip(idx, versions or [0] * len(idx))]
        feats = torch.stack([f[: T * fpf + frames_extra] for f in src])
        return x0, feats


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: CUDA is not available on this machine")
    return torch.device(name)


def _batch_indices(sampler: DistributedSampler, step: int, B: int) -> list[int]:
    """This rank's batch for `step`: epochs of the (distributed) shuffled order, wrapped when short."""
    n = len(sampler)
    per_epoch = max(1, n // B)
    epoch, pos = divmod(step, per_epoch)
    sampler.set_epoch(epoch)
    order = list(sampler)
    order = order * math.ceil(B / n) if n < B else order
    return order[pos * B: pos * B + B]


def _lr(opts: TrainOptions, step: int) -> float:
    return opts.lr * min(1.0, (step + 1) / max(opts.warmup, 1))


@torch.no_grad()
def validation_loss(model: DiMGestor, diffusion: Diffusion, bank: WindowBank, seed: int, device,
                    n_t: int = 8) -> float:
    """Mean loss over held-out windows at n_t fixed diffusion steps with fixed noise (low variance)."""
    g = torch.Generator().manual_seed(seed + 7919)
    c, total, count = model.config, 0.0, 0
    ts = torch.linspace(0, diffusion.N - 1, n_t).round().long()
    for i in range(len(bank)):
        x0, feats = bank.batch([i] * n_t, c.lookahead_feats, c.feats_per_frame)
        noise = diffusion.noise_like(x0, g)
        loss = diffusion.training_loss(model, x0.to(device), feats.to(device), ts.to(device), noise.to(device))
        total, count = total + loss.item(), count + 1
    return total / count


def train(opts: TrainOptions) -> Path:
    """Run (or resume) training; returns the last checkpoint folder."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    device = _device(opts.device)
    if world > 1:  # launched by torchrun
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        if device.type == "cuda":
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
            torch.cuda.set_device(device)
    main = rank == 0
    out = Path(opts.out)
    resume_from = latest_checkpoint(out) if opts.resume else None
    if opts.resume and resume_from is None:
        raise ValueError(f"--resume: no checkpoint found in {out}")
    if not opts.resume and latest_checkpoint(out) is not None:
        raise ValueError(f"{out} already holds checkpoints: pass --resume to continue, or choose a new --out")

    # ---- config: the checkpoint's when resuming, else the preset with the data's feature width ----
    overrides, weights = resolve_recipe(opts)
    cond_drop = resolve_cond_drop(opts)
    if resume_from is not None:
        config = ModelConfig(**read_meta(resume_from)["model"])
    else:
        config = get_preset(opts.preset, **overrides)
    if resume_from is not None:
        heading = FeatureSpec.from_dict(read_meta(resume_from)["feature_spec"]).heading
    else:
        heading = opts.heading or (RECIPES[opts.recipe].get("heading", "velocity") if opts.recipe else "velocity")
    spec = FeatureSpec(fps=config.fps, heading=heading)
    ds_kw = dict(window_s=opts.window_s, hop_s=opts.hop_s if opts.hop_s is not None else opts.window_s / 4,
                 cache_dir=opts.cache_dir, valid_fraction=opts.valid_fraction,
                 valid_seconds=opts.valid_seconds)
    train_ds = GestureDataset(opts.data, spec, split="train", mirror=opts.mirror, speeds=tuple(opts.speeds), **ds_kw)
    valid_ds = GestureDataset(opts.data, spec, split="valid", **ds_kw)
    if resume_from is None:
        config = get_preset(opts.preset, **{**overrides, "motion_dim": train_ds.motion_dim})
        mean, std = compute_stats(train_ds)
    elif config.motion_dim != train_ds.motion_dim:
        raise ValueError(f"{resume_from}: trained on {config.motion_dim} features, the data has {train_ds.motion_dim}")

    torch.manual_seed(opts.seed)
    random.seed(opts.seed)
    np.random.seed(opts.seed)
    model = DiMGestor(config).to(device)
    ema = DiMGestor(config).to(device).requires_grad_(False)
    diffusion = Diffusion(config)
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=opts.lr,
                            weight_decay=opts.weight_decay)
    g = torch.Generator().manual_seed(opts.seed * 1000 + rank)  # t and noise; batches come from the sampler
    step, history = 0, []
    if resume_from is not None:
        ts = torch.load(resume_from / "train_state.pt", map_location="cpu", weights_only=False)
        model.load_state_dict(ts["model"])
        ema.load_state_dict(ts["ema"])
        opt.load_state_dict(ts["optimizer"])
        g.set_state(ts["generators"][rank] if rank < len(ts["generators"]) else ts["generators"][0])
        torch.set_rng_state(ts["torch_rng"])
        step, history, mean, std = ts["step"], ts["history"], ts["mean"], ts["std"]
    else:
        ema.load_state_dict(model.state_dict())
    ema.eval()

    t_bank = time.time()
    train_bank = WindowBank(train_ds, model, mean, std, device, copies=opts.aug_copies if opts.augment else 0,
                            aug_config=AugmentConfig(**(opts.aug_config or {})), seed=opts.seed)
    t_bank = time.time() - t_bank
    valid_bank = WindowBank(valid_ds, model, mean, std, device)
    sampler = DistributedSampler(range(len(train_bank)), num_replicas=world, rank=rank, shuffle=True,
                                 seed=opts.seed, drop_last=False)
    from .features import HEADING_COLUMN, VELOCITY_COLUMNS

    root_columns = tuple(VELOCITY_COLUMNS) + ((HEADING_COLUMN,) if spec.heading == "velocity" else ())
    objective = Objective(model, diffusion, {**weights, "root_columns": root_columns})
    if world > 1:
        objective = nn.parallel.DistributedDataParallel(objective, device_ids=[device] if device.type == "cuda" else None)
    if main:
        out.mkdir(parents=True, exist_ok=True)
        print(f"{train_ds.summary()}\n{valid_ds.summary()}\n"
              f"model {opts.preset if resume_from is None else '(from checkpoint)'}: "
              f"{sum(p.numel() for p in model.parameters()) / 1e6:.2f} M parameters, device {device}, world {world}, "
              f"recipe {opts.recipe or '(none)'}: {config.n_steps} {config.schedule} steps, predicts {config.prediction}, "
              f"{spec.heading} heading, "
              f"noise over {config.noise_taps} frames, loss weights velocity/acceleration/root "
              f"{weights['vel_weight']:g}/{weights['acc_weight']:g}/{weights['root_weight']:g}"
              + (f", {opts.aug_copies} augmented copies of the training audio ({t_bank:.0f} s)" if opts.augment else "")
              + (f", condition dropped in {cond_drop:.0%} of windows" if cond_drop > 0 else "")
              + (f", resuming at step {step} from {resume_from}" if resume_from else ""))

    def checkpoint(step: int) -> Path:
        gens = [g.get_state()]
        if world > 1:
            gens = [None] * world
            dist.all_gather_object(gens, g.get_state())
        if not main:
            return out
        info = {"step": step, "preset": opts.preset, "data": str(opts.data), "history": history[-1:],
                "options": {k: v for k, v in vars(opts).items() if k not in ("progress", "resume", "cache_dir")},
                "train_wall_s": history[-1].get("elapsed_s") if history else None}
        state = {"step": step, "model": model.state_dict(), "ema": ema.state_dict(), "optimizer": opt.state_dict(),
                 "generators": gens, "torch_rng": torch.get_rng_state(), "history": history,
                 "mean": mean, "std": std, "options": vars(opts)}
        path = save_checkpoint(out / f"ckpt_{step:07d}", ema, train_ds.spec, train_ds.skeleton, mean, std,
                               info=info, train_state=state)
        if opts.keep > 0:
            kept = sorted(p for p in out.glob("ckpt_*") if p.is_dir() and "." not in p.name)
            for old in kept[: -opts.keep]:
                shutil.rmtree(old, ignore_errors=True)
        return path

    def log(record: dict):
        history.append(record)
        with open(out / "log.jsonl", "a") as f:
            f.write(json.dumps(record) + "\n")

    if main and step == 0:
        log({"step": 0, "valid_loss": validation_loss(ema, diffusion, valid_bank, opts.seed, device)})
    from tqdm import tqdm
    bar = tqdm(total=opts.max_steps, initial=step, disable=not (main and opts.progress), dynamic_ncols=True,
               desc="train")
    smooth, last = None, resume_from or out
    B = max(1, opts.batch_size // world)
    t0 = time.time()
    model.train()
    while step < opts.max_steps:
        idx = _batch_indices(sampler, step, B)
        versions = train_bank.draw_versions(len(idx), g)  # from g, so --resume stays exact
        x0, feats = train_bank.batch(idx, config.lookahead_feats, config.feats_per_frame, versions)
        t = torch.randint(0, diffusion.N, (len(idx),), generator=g)
        noise = diffusion.noise_like(x0, g)
        # drawn after t and noise, and only when used: runs without dropout draw exactly what they drew before
        drop = torch.rand(len(idx), generator=g) < cond_drop if cond_drop > 0 else None
        for group in opt.param_groups:
            group["lr"] = _lr(opts, step)
        loss = objective(x0.to(device), feats.to(device), t.to(device), noise.to(device),
                         None if drop is None else drop.to(device))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if opts.grad_clip > 0:
            nn.utils.clip_grad_norm_(model.parameters(), opts.grad_clip)
        opt.step()
        step += 1
        decay = min(opts.ema, (1 + step) / (10 + step))  # short memory early, when the weights move fast
        with torch.no_grad():
            for pe, pm in zip(ema.parameters(), model.parameters()):
                pe.lerp_(pm, 1 - decay)
        smooth = loss.item() if smooth is None else 0.98 * smooth + 0.02 * loss.item()
        bar.update(1)
        bar.set_postfix(loss=f"{smooth:.4f}", refresh=False)
        is_valid = step % opts.valid_every == 0 or step == opts.max_steps
        if is_valid and main:
            vl = validation_loss(ema, diffusion, valid_bank, opts.seed, device)
            log({"step": step, "train_loss": smooth, "valid_loss": vl, "elapsed_s": round(time.time() - t0, 1)})
            bar.set_postfix(loss=f"{smooth:.4f}", valid=f"{vl:.4f}")
        if step % opts.ckpt_every == 0 or step == opts.max_steps:
            last = checkpoint(step)
        if world > 1 and is_valid:
            dist.barrier()
    bar.close()
    if world > 1:
        dist.destroy_process_group()
    return last


# ---------------- CLI ----------------
def _parse_set(items: list[str]) -> dict:
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value  # a bare string such as sqrt_linear
    return out


def register(subparsers) -> None:
    p = subparsers.add_parser("train", help="train a model on a folder of NAME.bvh + NAME.wav pairs",
                              formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    d = TrainOptions(data="", out="")
    p.add_argument("--data", required=True, help="folder of BVH+WAV pairs (sub-folders allowed)")
    p.add_argument("--out", required=True, help="run folder for ckpt_XXXXXXX/ checkpoints and log.jsonl")
    p.add_argument("--preset", default=d.preset, help="model preset: paper, realtime or tiny")
    p.add_argument("--recipe", default="streaming", choices=list(RECIPES),
                   help="diffusion training recipe: 'streaming' (short cosine chain, x0 + derivative losses; smooth "
                        "at any K) or 'paper' (Zhang et al.: 1000 linear steps, noise MSE)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a model config field, repeatable")
    p.add_argument("--max-steps", type=int, default=d.max_steps)
    p.add_argument("--batch-size", type=int, default=d.batch_size, help="global batch (split over DDP ranks)")
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--window-s", type=float, default=d.window_s, help="training window length in seconds")
    p.add_argument("--hop-s", type=float, default=None, help="window hop (default: a quarter window)")
    p.add_argument("--valid-fraction", type=float, default=d.valid_fraction,
                   help="held-out tail of every clip, as a fraction (without a split file)")
    p.add_argument("--valid-seconds", type=float, default=None,
                   help="held-out tail of every clip in seconds (overrides --valid-fraction)")
    p.add_argument("--heading", choices=["velocity", "facing"], default=None,
                   help="root heading features: a per-frame turn (PyMO, the paper) or relative to the clip's mean "
                        "facing (bounded, no spin) (default: the recipe's)")
    p.add_argument("--mirror", action=argparse.BooleanOptionalAction, default=None,
                   help="add left/right mirrored windows (default: on when the training split is under 30 min)")
    p.add_argument("--speeds", default=None, metavar="R,R",
                   help="speed-perturbed copies of the training audio+motion, e.g. 0.9,1.1 ('' = none; "
                        "default: 0.9,1.1 when the training split is under 30 min)")
    p.add_argument("--augment", action=argparse.BooleanOptionalAction, default=None,
                   help="train on augmented copies of the audio too (pitch/formant, reverb, noise, EQ/band limits, "
                        "gain) so gestures follow other voices and microphones (default: on when the training split "
                        "is under 30 min)")
    p.add_argument("--aug-copies", type=int, default=d.aug_copies,
                   help="augmented versions of each training window (features of all are kept in memory)")
    p.add_argument("--ckpt-every", type=int, default=d.ckpt_every)
    p.add_argument("--valid-every", type=int, default=d.valid_every)
    p.add_argument("--keep", type=int, default=d.keep, help="checkpoints to keep (0 = all)")
    p.add_argument("--ema", type=float, default=d.ema)
    p.add_argument("--vel-weight", type=float, default=None,
                   help="weight of a velocity loss on the predicted x0 (default: the recipe's; 0 = none)")
    p.add_argument("--acc-weight", type=float, default=None,
                   help="weight of an acceleration loss on the predicted x0 (default: the recipe's; 0 = none)")
    p.add_argument("--root-weight", type=float, default=None,
                   help="weight of a loss on the integrated root travel and turning of the predicted x0, against "
                        "spin and drift (default: the recipe's; 0 = none)")
    p.add_argument("--cond-drop", type=float, default=None, metavar="P",
                   help="probability that a training window's audio condition is dropped (zeroed), so the model also "
                        "learns the unconditional motion that `--guidance S` sampling extrapolates away from "
                        "(default: the recipe's; 0 = none)")
    p.add_argument("--resume", action="store_true", help="continue from the latest checkpoint in --out")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--device", default=d.device, help="auto (CUDA when present), cpu, cuda, cuda:1, ...")
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads for torch (default: torch's choice; 1 is much faster on a busy shared machine)")
    p.add_argument("--cache-dir", default=None, help="dataset cache (default $DIMGESTOR_CACHE or ~/.cache/dimgestor)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (logs still go to log.jsonl)")
    p.set_defaults(func=_run)


def _run(args) -> int:
    for name in ("max_steps", "batch_size", "ckpt_every", "valid_every", "aug_copies"):
        if getattr(args, name) <= 0:
            raise ValueError(f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.lr <= 0 or args.window_s <= 0 or not 0 <= args.ema < 1 or \
            any((getattr(args, k) or 0) < 0 for k in LOSS_WEIGHTS):
        raise ValueError("--lr and --window-s must be positive, --ema in [0, 1), the loss weights >= 0")
    if args.cond_drop is not None and not 0 <= args.cond_drop <= 1:
        raise ValueError(f"--cond-drop must be a probability in [0, 1], got {args.cond_drop}")
    try:
        speeds = None if args.speeds is None else tuple(float(r) for r in args.speeds.split(",") if r.strip())
    except ValueError:
        raise ValueError(f"--speeds expects comma-separated factors such as 0.9,1.1, got {args.speeds!r}") from None
    if speeds is not None and any(r <= 0 for r in speeds):
        raise ValueError(f"--speeds factors must be positive, got {args.speeds!r}")
    if args.threads is not None:
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    opts = TrainOptions(data=args.data, out=args.out, preset=args.preset, overrides=_parse_set(args.set),
                        max_steps=args.max_steps, batch_size=args.batch_size, lr=args.lr, window_s=args.window_s,
                        hop_s=args.hop_s, valid_fraction=args.valid_fraction,
                        valid_seconds=args.valid_seconds, ckpt_every=args.ckpt_every, recipe=args.recipe,
                        valid_every=args.valid_every, keep=args.keep, ema=args.ema, vel_weight=args.vel_weight,
                        acc_weight=args.acc_weight, root_weight=args.root_weight, heading=args.heading,
                        cond_drop=args.cond_drop,
                        resume=args.resume,
                        seed=args.seed, device=args.device, cache_dir=args.cache_dir, progress=not args.no_progress)
    few = False
    if args.mirror is None or speeds is None or args.augment is None:  # these defaults depend on the data's size
        minutes = GestureDataset(args.data, FeatureSpec(), split="train", cache_dir=args.cache_dir,
                                 valid_fraction=args.valid_fraction, valid_seconds=args.valid_seconds,
                                 window_s=args.window_s).seconds() / 60  # the heading layout does not change it
        few = minutes < SMALL_DATA_MIN
    opts.mirror = few if args.mirror is None else args.mirror
    opts.speeds = (SMALL_DATA_SPEEDS if few else ()) if speeds is None else speeds
    opts.augment, opts.aug_copies = few if args.augment is None else args.augment, args.aug_copies
    last = train(opts)
    if int(os.environ.get("RANK", "0")) == 0:
        print(f"checkpoint: {last}")
    return 0
