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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.distributed as dist
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from torch import nn
from torch.utils.data import DistributedSampler

from ..config import ModelConfig, exact_div, get_preset
from ..features import HEADING_COLUMN, VELOCITY_COLUMNS, FeatureSpec
from ..model.diffusion import Diffusion
from ..model.network import DiMGestor
from ..streaming.checkpoint import latest_checkpoint, read_meta, save_checkpoint
from .augment import AugmentConfig, augment
from .dataset import GestureDataset, compute_stats

__all__ = ["TrainConfig", "Recipe", "train", "register", "Objective", "RECIPES"]

SMALL_DATA_MIN = 30.0  # below this many minutes of training data, mirroring, speed perturbation and audio
# augmentation default on
SMALL_DATA_SPEEDS = (0.9, 1.1)


class Recipe(BaseModel):
    """A named way to train: the diffusion process (model-config overrides), root heading and loss weights."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    config: dict[str, Any] = {}  # ModelConfig fields over the preset's (validated with it when the model is built)
    heading: Literal["velocity", "facing"] = "velocity"  # root heading features (dimgestor.features)
    vel_weight: float = Field(0.0, ge=0)  # velocity loss on the predicted x0
    acc_weight: float = Field(0.0, ge=0)  # acceleration loss on the predicted x0
    root_weight: float = Field(0.0, ge=0)  # integrated root travel and turning (against spin and drift)
    cond_drop: float = Field(0.0, ge=0, le=1)  # condition dropout for classifier-free guidance


# "paper" is Zhang et al.'s (N = 1000 linear betas, noise MSE); "streaming" is this engine's default, chosen
# by measurement (benchmarks/recipes.py, results in benchmarks/results/recipes.json): a short cosine chain
# whose every level is trained, x0 prediction with velocity and acceleration losses, and noise correlated
# over a few frames, so that what a causal denoiser passes through is slow sway, not jitter.
RECIPES: dict[str, Recipe] = {
    "paper": Recipe(config=dict(n_steps=1000, schedule="linear", beta_start=1e-4, beta_end=8e-2, prediction="eps",
                                noise_taps=1), heading="velocity"),
    "streaming": Recipe(config=dict(n_steps=8, schedule="cosine", prediction="x0", noise_taps=1, sample_steps=4,
                                    ddim_spacing="linspace"), heading="facing",
                        vel_weight=4.0, acc_weight=4.0, root_weight=0.1),
}
NO_RECIPE = Recipe()  # recipe=None: the preset's diffusion, plain loss


class TrainConfig(BaseModel):
    """Everything a run is given: validated once, frozen, saved in every checkpoint (info["options"])."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    data: str | tuple[str, ...]  # folder(s) of NAME.bvh (or BEAT2 NAME.npz) + NAME.wav pairs
    skeleton: str | None = None  # the training skeleton's file (BVH or take); None: the first clip's
    balance_speakers: bool = True  # speakers take equal turns in the batches whatever their hours
    speaker_condition: bool = False  # a learnt vector per speaker in the condition (generate --speaker)
    out: str  # run folder: ckpt_XXXXXXX/ checkpoints and log.jsonl
    preset: str = "realtime"
    overrides: dict[str, Any] | None = None  # ModelConfig fields replacing the preset's (and the recipe's)
    recipe: str | None = "streaming"  # a RECIPES name: its config and loss weights (explicit weights below win)
    max_steps: int = Field(20000, gt=0)
    batch_size: int = Field(8, gt=0)  # global batch, split over DDP ranks
    lr: float = Field(5e-4, gt=0)
    warmup: int = Field(200, ge=0)  # linear LR warm-up steps (Adam on a fresh model)
    weight_decay: float = Field(0.0, ge=0)  # AdamW's decoupled weight decay
    grad_clip: float = Field(1.0, ge=0)  # max global gradient norm (0 = no clipping)
    vel_weight: float | None = Field(None, ge=0)  # weight of the x0 velocity loss (None: the recipe's; 0 = none)
    acc_weight: float | None = Field(None, ge=0)  # weight of the x0 acceleration loss (None: the recipe's)
    root_weight: float | None = Field(None, ge=0)  # weight of the integrated-root (drift) loss (None: the recipe's)
    heading: Literal["velocity", "facing"] | None = None  # root heading features (None: the recipe's)
    # probability that a training window's condition is zeroed (classifier-free guidance learns the unconditional
    # model from these windows; sampling with guidance != 1 needs it). None: the recipe's; 0 = never
    cond_drop: float | None = Field(None, ge=0, le=1)
    speeds: tuple[float, ...] = ()  # speed perturbation factors for extra training copies, e.g. (0.9, 1.1)
    ema: float = Field(0.999, ge=0, lt=1)  # EMA decay of the saved weights
    window_s: float = Field(10.0, gt=0)
    hop_s: float | None = Field(None, gt=0)  # default: a quarter window (overlapping windows are cheap data)
    mirror: bool = False  # left/right mirrored copies of every window
    arm_mix: bool = False  # body-part mixing: a copy of every window with one arm on both sides (mix_arms)
    augment: bool = False  # audio augmentation (dimgestor.training.augment: voice, room, noise, microphone, level)
    aug_copies: int = Field(4, gt=0)  # augmented versions of each window's audio; a batch item takes clean or one
    aug_config: dict[str, Any] | None = None  # AugmentConfig fields replacing its defaults
    valid_fraction: float = Field(0.15, ge=0, lt=1)
    valid_seconds: float | None = Field(None, gt=0)  # hold out the last S seconds of every clip instead
    ckpt_every: int = Field(1000, gt=0)
    valid_every: int = Field(250, ge=0)  # 0: no held-out loss (the run's last step still logs its train loss)
    keep: int = Field(3, ge=0)  # checkpoints kept in the run folder (oldest removed; 0 = all)
    seed: int = 0
    device: str = "auto"
    resume: bool = False
    cache_dir: str | None = None
    progress: bool = True

    @field_validator("data", "out", "cache_dir", "skeleton", mode="before")
    @classmethod
    def _path_as_text(cls, v):
        if isinstance(v, (list, tuple)):
            v = tuple(os.fspath(x) for x in v)
            return v[0] if len(v) == 1 else v
        return os.fspath(v) if isinstance(v, os.PathLike) else v

    @field_validator("recipe")
    @classmethod
    def _known_recipe(cls, v):
        if v is not None and v not in RECIPES:
            raise ValueError(f"unknown recipe {v!r}; choose one of {', '.join(RECIPES)}")
        return v

    @field_validator("speeds")
    @classmethod
    def _positive_speeds(cls, v):
        if any(r <= 0 for r in v):
            raise ValueError(f"speed factors must be positive, got {v}")
        return v

    @model_validator(mode="after")
    def _augment_config(self):
        AugmentConfig(**(self.aug_config or {}))  # fails here, not after the dataset is built
        return self

    @property
    def chosen_recipe(self) -> Recipe:
        return RECIPES[self.recipe] if self.recipe else NO_RECIPE

    @classmethod
    def from_saved(cls, options: dict) -> "TrainConfig":
        """The config a checkpoint was trained with, from its saved `options` (info["options"] or train_state.pt's);
        older runs lack newer fields, which take their defaults; a field this version dropped is an error."""
        unknown = set(options) - set(cls.model_fields)
        if unknown:
            raise ValueError(f"saved training options name fields this version does not have: {sorted(unknown)}")
        return cls(**options)


TrainOptions = TrainConfig  # the former name, kept for scripts and tests that use it

# the runtime-only options, left out of a checkpoint's info (they do not describe the model)
RUNTIME_OPTIONS = {"progress", "resume", "cache_dir"}


class Objective(nn.Module):
    """The training loss as a module, so DDP sees one forward that uses every trained parameter."""

    def __init__(self, model: DiMGestor, diffusion: Diffusion, weights: dict[str, float]):
        super().__init__()
        self.model, self.diffusion, self.weights = model, diffusion, weights

    def forward(self, x0, feats, t, noise, drop=None, speaker=None):
        return self.diffusion.training_loss(self.model, x0, feats, t, noise, drop=drop, speaker=speaker, **self.weights)


LOSS_WEIGHTS = ("vel_weight", "acc_weight", "root_weight")
SPEAKER_DROP = 0.1  # windows trained with no speaker, for a model with a speaker condition


def resolve_recipe(opts: TrainConfig) -> tuple[dict, dict[str, float]]:
    """(config overrides, {loss weight name: value}) of the options' recipe and explicit settings."""
    r = opts.chosen_recipe
    weights = {k: float(getattr(r, k) if getattr(opts, k) is None else getattr(opts, k)) for k in LOSS_WEIGHTS}
    return {**r.config, **(opts.overrides or {})}, weights


def resolve_cond_drop(opts: TrainConfig) -> float:
    """The condition-dropout probability: the explicit option, else the recipe's (0 without a recipe)."""
    return float(opts.chosen_recipe.cond_drop if opts.cond_drop is None else opts.cond_drop)


class WindowBank:
    """Normalized motion and front-end features of every window, computed once.

    With `copies` > 0 it also holds the features of that many augmented versions of each window's audio
    (augmented before the front end, so any front end works), seeded by (seed, audio window, copy);
    mirrored windows hear the same audio and share its versions.

    The front end runs over up to `WARM_S` of the clip's audio before each window (and over the clip's real
    audio after it, which the last frames' lookahead hears) and the warm-up's features are dropped: a stream's front end has heard the speech before any frame it conditions (the speech front
    end's running level and means need a few seconds), so a window must not start from a cold state, which
    would read the first syllables of every window as the start of a stream.
    """

    WARM_S = 4.0

    def __init__(self, ds: GestureDataset, model: DiMGestor, mean, std, device, copies: int = 0,
                 aug_config: AugmentConfig | None = None, seed: int = 0):
        self.motion, self.feats, self.versions = [], [], []  # versions[i]: features of window i's augmented audio
        self.copies = copies
        names = model.config.speakers  # each window's speaker index, for a model with a speaker condition
        self.speaker = torch.tensor([names.index(s) for s in ds.window_speakers()]) if names else None
        mean, std = torch.from_numpy(mean), torch.from_numpy(std)
        # babble is made of the training speech itself, pitch-shifted and time-shifted
        babble = [ds.clips[c].audio[a * ds.spf: b * ds.spf] for c, a, b in ds.segments] if copies else None
        shared: dict[tuple, list[torch.Tensor]] = {}
        with torch.no_grad():
            for i in range(len(ds)):
                item = ds[i]
                T = len(item["motion"])
                audio, warm = self._with_context(ds, i, item["audio"], model.samples_needed(T) - T * ds.spf)
                self.feats.append(self._features(model, audio, warm, T, device))
                self.motion.append((torch.from_numpy(item["motion"]) - mean) / std)
                if copies:
                    key = ds.windows[i][:3]  # (clip, start, length): the same audio, mirrored or not
                    if key not in shared:
                        u = len(shared)
                        shared[key] = [self._features(model, augment(audio, model.config.sample_rate,
                                                                     (seed, u, k), aug_config, babble),
                                                      warm, T, device)
                                       for k in range(copies)]
                    self.versions.append(shared[key])

    @classmethod
    def _with_context(cls, ds: GestureDataset, i: int, window_audio: np.ndarray, after: int = 0
                      ) -> tuple[np.ndarray, int]:
        """(the clip's audio from up to WARM_S before window i to `after` samples past its end (the lookahead
        its last frames hear; silence is padded only where the clip ends), samples before the window)."""
        c, start, n, _ = ds.windows[i]
        a, b = start * ds.spf, (start + n) * ds.spf
        warm = min(a, int(cls.WARM_S * ds.fps) * ds.spf)  # whole motion frames: a multiple of the hop
        clip = ds.clips[c].audio
        return np.concatenate([np.asarray(clip[a - warm:a], np.float32), window_audio,
                               np.asarray(clip[b:b + max(after, 0)], np.float32)]), warm

    @staticmethod
    def _features(model: DiMGestor, audio: np.ndarray, warm: int, T: int, device) -> torch.Tensor:
        """Features of the window that starts `warm` samples into `audio` (the front end hears all of it)."""
        fe, c = model.frontend, model.config
        padded = np.zeros(max(warm + model.samples_needed(T), len(audio)), np.float32)
        padded[: len(audio)] = audio  # silence beyond the window, as at a stream's end
        f, _ = fe(torch.from_numpy(padded)[None].to(device), fe.init_state(1, device))
        first = exact_div(warm, c.hop_length, "warm-up samples / hop")
        return f[0, first: first + T * c.feats_per_frame + c.lookahead_feats].cpu()

    def __len__(self):
        return len(self.motion)

    def draw_versions(self, n: int, g: torch.Generator) -> list[int] | None:
        """Per batch item 0 (clean) or k (augmented copy k), uniformly; None (nothing drawn) without copies."""
        return torch.randint(0, self.copies + 1, (n,), generator=g).tolist() if self.copies else None

    def speakers(self, idx: list[int]) -> torch.Tensor | None:
        """The windows' speaker indices (None: the model has no speaker condition)."""
        return None if self.speaker is None else self.speaker[idx]

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


def _batch_indices(sampler, step: int, B: int) -> list[int]:
    """The global batch for `step`: epochs of the shuffled order, wrapped when short."""
    n = len(sampler)
    per_epoch = max(1, n // B)
    epoch, pos = divmod(step, per_epoch)
    sampler.set_epoch(epoch)
    order = list(sampler)
    order = order * math.ceil(B / n) if n < B else order
    return order[pos * B: pos * B + B]


def _lr(opts: TrainConfig, step: int) -> float:
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
        speaker = bank.speakers([i] * n_t)
        loss = diffusion.training_loss(model, x0.to(device), feats.to(device), ts.to(device), noise.to(device),
                                       speaker=None if speaker is None else speaker.to(device))
        total, count = total + loss.item(), count + 1
    return total / count


@dataclass
class Run:
    """A run between steps: what `setup` builds and the step, evaluation and checkpoint functions use."""

    opts: TrainConfig
    out: Path
    world: int
    rank: int
    device: torch.device
    resume_from: Path | None
    config: ModelConfig
    train_ds: GestureDataset
    model: DiMGestor
    ema: DiMGestor  # the weights that are evaluated and saved
    diffusion: Diffusion
    optimizer: torch.optim.Optimizer
    objective: nn.Module  # the loss (wrapped in DDP when world > 1)
    g: torch.Generator  # the global batch's diffusion steps, noise, augmented versions and dropout (same on every rank)
    train_bank: WindowBank
    valid_bank: WindowBank | None  # None without validation (valid_every 0)
    sampler: DistributedSampler | BalancedOrder
    mean: np.ndarray
    std: np.ndarray
    cond_drop: float
    step: int = 0
    history: list[dict] = field(default_factory=list)

    @property
    def main(self) -> bool:
        return self.rank == 0


def _init_distributed(opts: TrainConfig) -> tuple[int, int, torch.device]:
    """(world size, rank, device); joins the process group when launched by torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if opts.batch_size % world:  # (before joining: every rank refuses alike)
        raise ValueError(f"--batch-size {opts.batch_size} does not split evenly over {world} processes: give a "
                         f"multiple of {world} (the global batch; each process trains on an equal share)")
    device = _device(opts.device)
    if world > 1:
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        if device.type == "cuda":
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
            torch.cuda.set_device(device)
    return world, rank, device


def _resume_point(opts: TrainConfig) -> Path | None:
    """The checkpoint to continue from (--resume), after checking the run folder matches the intent."""
    out = Path(opts.out)
    resume_from = latest_checkpoint(out) if opts.resume else None
    if opts.resume and resume_from is None:
        raise ValueError(f"--resume: no checkpoint found in {out}")
    if not opts.resume and latest_checkpoint(out) is not None:
        raise ValueError(f"{out} already holds checkpoints: pass --resume to continue, or choose a new --out")
    return resume_from


def _config_and_data(opts: TrainConfig, resume_from: Path | None):
    """(model config, training set, validation set): the checkpoint's config when resuming, else the preset
    with the recipe and the data's feature width."""
    overrides, _ = resolve_recipe(opts)
    if resume_from is not None:
        meta = read_meta(resume_from)
        config = ModelConfig(**meta["model"])
        heading = FeatureSpec.from_dict(meta["feature_spec"]).heading
    else:
        config = get_preset(opts.preset, **overrides)
        heading = opts.heading or opts.chosen_recipe.heading
    spec = FeatureSpec(fps=config.fps, heading=heading)
    ds_kw = dict(window_s=opts.window_s, hop_s=opts.hop_s if opts.hop_s is not None else opts.window_s / 4,
                 cache_dir=opts.cache_dir, valid_fraction=opts.valid_fraction, valid_seconds=opts.valid_seconds,
                 skeleton=opts.skeleton)
    train_ds = GestureDataset(opts.data, spec, split="train", mirror=opts.mirror, speeds=opts.speeds,
                              arm_mix=opts.arm_mix, **ds_kw)
    valid_ds = GestureDataset(opts.data, spec, split="valid", **ds_kw)
    if resume_from is None:
        speakers = tuple(train_ds.speakers) if opts.speaker_condition else ()
        config = get_preset(opts.preset, **{**overrides, "motion_dim": train_ds.motion_dim, "speakers": speakers})
    elif config.motion_dim != train_ds.motion_dim:
        raise ValueError(f"{resume_from}: trained on {config.motion_dim} features, the data has {train_ds.motion_dim}")
    elif set(train_ds.speakers) - set(config.speakers) and config.speakers:
        raise ValueError(f"{resume_from}: trained on speakers {list(config.speakers)}; the data also has "
                         f"{sorted(set(train_ds.speakers) - set(config.speakers))}")
    return config, train_ds, valid_ds


class BalancedOrder:
    """The training windows' order with every speaker taking equal turns, whatever their hours: an epoch (as many
    draws as windows) goes round the speakers, each round in a new shuffled order, and each speaker's windows come
    in a shuffled order of their own (a speaker with fewer windows repeats them, one with more is sampled).
    Seeded by seed + epoch, as DistributedSampler's order is, so a resumed run draws what it would have drawn."""

    def __init__(self, speakers: list[str], seed: int = 0):
        self.groups = [[i for i, s in enumerate(speakers) if s == name] for name in sorted(set(speakers))]
        self.n, self.seed, self.epoch = len(speakers), seed, 0

    def __len__(self) -> int:
        return self.n

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __iter__(self):
        g = torch.Generator().manual_seed(self.seed + self.epoch)
        queues = [[] for _ in self.groups]
        order: list[int] = []
        while len(order) < self.n:
            for k in torch.randperm(len(self.groups), generator=g).tolist():
                if not queues[k]:
                    queues[k] = [self.groups[k][i] for i in torch.randperm(len(self.groups[k]), generator=g).tolist()]
                order.append(queues[k].pop())
                if len(order) == self.n:
                    break
        return iter(order)


def setup(opts: TrainConfig) -> Run:
    """Everything a run needs, fresh or restored from its latest checkpoint (--resume)."""
    world, rank, device = _init_distributed(opts)
    resume_from = _resume_point(opts)
    config, train_ds, valid_ds = _config_and_data(opts, resume_from)
    mean, std = compute_stats(train_ds) if resume_from is None else (None, None)  # before seeding, as runs always did
    torch.manual_seed(opts.seed)
    random.seed(opts.seed)
    np.random.seed(opts.seed)
    model = DiMGestor(config).to(device)
    ema = DiMGestor(config).to(device).requires_grad_(False)
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=opts.lr,
                                  weight_decay=opts.weight_decay)
    # Every rank draws the whole global batch (windows, versions, t, noise, dropout) from the same generator and
    # trains on its slice: N processes take the same steps as one process with the same --batch-size.
    g = torch.Generator().manual_seed(opts.seed * 1000)
    step, history = 0, []
    if resume_from is not None:
        ts = torch.load(resume_from / "train_state.pt", map_location="cpu", weights_only=False)
        model.load_state_dict(ts["model"])
        ema.load_state_dict(ts["ema"])
        optimizer.load_state_dict(ts["optimizer"])
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
    valid_bank = WindowBank(valid_ds, model, mean, std, device) if opts.valid_every else None
    speakers = train_ds.window_speakers()
    if opts.balance_speakers and len(set(speakers)) > 1:
        sampler = BalancedOrder(speakers, opts.seed)
    else:
        sampler = DistributedSampler(range(len(train_bank)), num_replicas=1, rank=0, shuffle=True,  # the global order
                                     seed=opts.seed, drop_last=False)
    diffusion = Diffusion(config)
    run = Run(opts, Path(opts.out), world, rank, device, resume_from, config, train_ds, model, ema, diffusion,
              optimizer, _objective(model, diffusion, resolve_recipe(opts)[1], train_ds.spec, world, device), g,
              train_bank, valid_bank, sampler, mean, std, resolve_cond_drop(opts), step, history)
    if run.main:
        run.out.mkdir(parents=True, exist_ok=True)
        print(f"{train_ds.summary()}\n{valid_ds.summary()}\n{_describe(run, t_bank)}")
    return run


def _objective(model: DiMGestor, diffusion: Diffusion, weights: dict[str, float], spec: FeatureSpec, world: int,
               device: torch.device) -> nn.Module:
    root_columns = tuple(VELOCITY_COLUMNS) + ((HEADING_COLUMN,) if spec.heading == "velocity" else ())
    objective = Objective(model, diffusion, {**weights, "root_columns": root_columns})
    if world > 1:
        objective = nn.parallel.DistributedDataParallel(objective, device_ids=[device] if device.type == "cuda" else None)
    return objective


def _describe(run: Run, t_bank: float) -> str:
    """One line on the model, recipe and losses of a run, printed when it starts."""
    opts, config, w = run.opts, run.config, resolve_recipe(run.opts)[1]
    return (f"model {opts.preset if run.resume_from is None else '(from checkpoint)'}: "
            f"{sum(p.numel() for p in run.model.parameters()) / 1e6:.2f} M parameters, device {run.device}, "
            f"world {run.world}, recipe {opts.recipe or '(none)'}: {config.n_steps} {config.schedule} steps, "
            f"predicts {config.prediction}, {run.train_ds.spec.heading} heading, "
            f"noise over {config.noise_taps} frames, loss weights velocity/acceleration/root "
            f"{w['vel_weight']:g}/{w['acc_weight']:g}/{w['root_weight']:g}"
            + (f", {opts.aug_copies} augmented copies of the training audio ({t_bank:.0f} s)" if opts.augment else "")
            + (f", condition dropped in {run.cond_drop:.0%} of windows" if run.cond_drop > 0 else "")
            + (", speakers in equal turns" if isinstance(run.sampler, BalancedOrder) else "")
            + (f", speaker condition ({len(config.speakers)} speakers)" if config.speakers else "")
            + (f", resuming at step {run.step} from {run.resume_from}" if run.resume_from else ""))


def train_step(run: Run, B: int) -> float:
    """One optimizer step on the global batch of B windows for `run.step` (this rank's slice of it, when
    several processes train), then the EMA update; returns the loss (over the global batch)."""
    c, g = run.config, run.g
    idx = _batch_indices(run.sampler, run.step, B)
    versions = run.train_bank.draw_versions(len(idx), g)  # from g, so --resume stays exact
    x0, feats = run.train_bank.batch(idx, c.lookahead_feats, c.feats_per_frame, versions)
    t = torch.randint(0, run.diffusion.N, (len(idx),), generator=g)
    noise = run.diffusion.noise_like(x0, g)
    # drawn after t and noise, and only when used: runs without dropout draw exactly what they drew before
    drop = torch.rand(len(idx), generator=g) < run.cond_drop if run.cond_drop > 0 else None
    speaker = run.train_bank.speakers(idx)
    if speaker is not None:  # some windows train the speaker-agnostic model (no speaker), what plays by default
        speaker = torch.where(torch.rand(len(idx), generator=g) < SPEAKER_DROP, -1, speaker)
    if run.world > 1:  # this rank's equal share; DDP averages the gradients, so the step is the global batch's
        part = slice(run.rank * B // run.world, (run.rank + 1) * B // run.world)
        x0, feats, t, noise = x0[part], feats[part], t[part], noise[part]
        drop = None if drop is None else drop[part]
        speaker = None if speaker is None else speaker[part]
    for group in run.optimizer.param_groups:
        group["lr"] = _lr(run.opts, run.step)
    d = run.device
    loss = run.objective(x0.to(d), feats.to(d), t.to(d), noise.to(d), None if drop is None else drop.to(d),
                         None if speaker is None else speaker.to(d))
    run.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if run.opts.grad_clip > 0:
        nn.utils.clip_grad_norm_(run.model.parameters(), run.opts.grad_clip)
    run.optimizer.step()
    run.step += 1
    decay = min(run.opts.ema, (1 + run.step) / (10 + run.step))  # short memory early, when the weights move fast
    with torch.no_grad():
        for pe, pm in zip(run.ema.parameters(), run.model.parameters()):
            pe.lerp_(pm, 1 - decay)
    value = loss.detach()
    if run.world > 1:  # the mean of the ranks' means: the global batch's loss
        dist.all_reduce(value)
        value /= run.world
    return value.item()


def evaluate(run: Run) -> float:
    """The EMA model's validation loss (fixed steps and noise, so runs and resumes compare)."""
    return validation_loss(run.ema, run.diffusion, run.valid_bank, run.opts.seed, run.device)


def log(run: Run, record: dict) -> None:
    run.history.append(record)
    with open(run.out / "log.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")


def checkpoint(run: Run) -> Path:
    """Save the EMA model with everything --resume needs (on rank 0; every rank takes part in the gather)."""
    gens = [run.g.get_state()]
    if run.world > 1:
        gens = [None] * run.world
        dist.all_gather_object(gens, run.g.get_state())
    if not run.main:
        return run.out
    opts, history = run.opts, run.history
    data = opts.data if isinstance(opts.data, str) else list(opts.data)
    info = {"step": run.step, "preset": opts.preset, "data": data, "history": history[-1:],
            "options": opts.model_dump(exclude=RUNTIME_OPTIONS),
            "train_wall_s": history[-1].get("elapsed_s") if history else None}
    state = {"step": run.step, "model": run.model.state_dict(), "ema": run.ema.state_dict(),
             "optimizer": run.optimizer.state_dict(), "generators": gens, "torch_rng": torch.get_rng_state(),
             "history": history, "mean": run.mean, "std": run.std, "options": opts.model_dump()}
    path = save_checkpoint(run.out / f"ckpt_{run.step:07d}", run.ema, run.train_ds.spec, run.train_ds.skeleton,
                           run.mean, run.std, info=info, train_state=state)
    if opts.keep > 0:
        kept = sorted(p for p in run.out.glob("ckpt_*") if p.is_dir() and "." not in p.name)
        for old in kept[: -opts.keep]:
            shutil.rmtree(old, ignore_errors=True)
    return path


def train(opts: TrainConfig) -> Path:
    """Run (or resume) training; returns the last checkpoint folder."""
    from tqdm import tqdm

    run = setup(opts)
    if run.main and run.step == 0 and opts.valid_every:
        log(run, {"step": 0, "valid_loss": evaluate(run)})
    bar = tqdm(total=opts.max_steps, initial=run.step, disable=not (run.main and opts.progress), dynamic_ncols=True,
               desc="train")
    smooth, last = None, run.resume_from or run.out
    B = opts.batch_size  # the global batch; each of the run.world processes trains on B / world of it
    t0 = time.time()
    run.model.train()
    while run.step < opts.max_steps:
        loss = train_step(run, B)
        smooth = loss if smooth is None else 0.98 * smooth + 0.02 * loss
        bar.update(1)
        bar.set_postfix(loss=f"{smooth:.4f}", refresh=False)
        step = run.step
        is_valid = bool(opts.valid_every) and (step % opts.valid_every == 0 or step == opts.max_steps)
        if is_valid and run.main:
            vl = evaluate(run)
            log(run, {"step": step, "train_loss": smooth, "valid_loss": vl, "elapsed_s": round(time.time() - t0, 1)})
            bar.set_postfix(loss=f"{smooth:.4f}", valid=f"{vl:.4f}")
        elif step == opts.max_steps and run.main:
            log(run, {"step": step, "train_loss": smooth, "elapsed_s": round(time.time() - t0, 1)})
        if step % opts.ckpt_every == 0 or step == opts.max_steps:
            last = checkpoint(run)
        if run.world > 1 and is_valid:
            dist.barrier()
    bar.close()
    if run.world > 1:
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
    from ..cli_help import examples
    from ..config import PRESETS

    p = subparsers.add_parser(
        "train", help="train a model on folders of NAME.bvh (or BEAT2 NAME.npz) + NAME.wav pairs",
        description="Train a model on a folder of NAME.bvh + NAME.wav pairs (motion capture with its speech). "
                    "Checkpoints and log.jsonl go to the run folder; several GPUs: launch it with torchrun.",
        epilog=examples("dimgestor train --data my_data --out runs/mine",
                        "dimgestor train --data my_data --out runs/mine --resume            # after a stop",
                        "dimgestor train --data my_data --out runs/small --preset tiny --max-steps 2000 --device cpu",
                        "dimgestor train --data zeggs --data beat2 --skeleton zeggs/001.bvh --speaker-condition --out runs/mix",
                        "torchrun --nproc-per-node 2 -m dimgestor_app.cli train --data my_data --out runs/ddp"))
    d = TrainConfig(data="", out="")  # the defaults, one place
    g = p.add_argument_group("data")
    g.add_argument("--data", required=True, metavar="DIR", action="append",
                   help="folder of NAME.bvh (or BEAT2 NAME.npz) + NAME.wav pairs (sub-folders allowed); give it again "
                        "for more folders (their clips are named FOLDER/NAME)")
    g.add_argument("--skeleton", default=None, metavar="FILE",
                   help="a BVH or BEAT2 take whose skeleton the model is trained on (default: the first clip's); clips "
                        "on other skeletons are retargeted onto it by their bones' names")
    g.add_argument("--balance-speakers", action=argparse.BooleanOptionalAction, default=None,
                   help="speakers take equal turns in the batches whatever their hours (default: on; a clip's speaker "
                        "is BEAT's ID_NAME_... name, else its sub-folder, else its data folder)")
    g.add_argument("--speaker-condition", action=argparse.BooleanOptionalAction, default=None,
                   help="learn a vector per speaker, so `generate --speaker NAME` plays one speaker's style "
                        "(default: off; without --speaker the model plays no speaker in particular)")
    g.add_argument("--cache-dir", default=None, metavar="DIR",
                   help="dataset feature cache (default: $DIMGESTOR_CACHE or ~/.cache/dimgestor)")
    g.add_argument("--window-s", type=float, default=d.window_s, metavar="S", help="training window length in seconds")
    g.add_argument("--hop-s", type=float, default=None, metavar="S", help="window hop (default: a quarter window)")
    g.add_argument("--valid-fraction", type=float, default=d.valid_fraction, metavar="F",
                   help="held-out tail of every clip, as a fraction (without a split file)")
    g.add_argument("--valid-seconds", type=float, default=None, metavar="S",
                   help="held-out tail of every clip in seconds (overrides --valid-fraction)")
    g.add_argument("--heading", choices=["velocity", "facing"], default=None,
                   help="root heading features: a per-frame turn (PyMO, the paper) or relative to the clip's mean "
                        "facing (bounded, no spin) (default: the recipe's)")
    g.add_argument("--mirror", action=argparse.BooleanOptionalAction, default=None,
                   help="add left/right mirrored windows (default: on when the training split is under 30 min)")
    g.add_argument("--arm-mix", action=argparse.BooleanOptionalAction, default=None,
                   help="add a copy of every training window with one arm's motion on both sides (its mirror image "
                        "on the other; the sides take turns): two-handed versions of one-handed gestures")
    g.add_argument("--speeds", default=None, metavar="R,R",
                   help="speed-perturbed copies of the training audio+motion, e.g. 0.9,1.1 ('' = none; "
                        "default: 0.9,1.1 when the training split is under 30 min)")
    g.add_argument("--augment", action=argparse.BooleanOptionalAction, default=None,
                   help="train on augmented copies of the audio too (pitch/formant, reverb, noise, EQ/band limits, "
                        "gain) so gestures follow other voices and microphones (default: on when the training split "
                        "is under 30 min)")
    g.add_argument("--aug-copies", type=int, default=d.aug_copies, metavar="N",
                   help="augmented versions of each training window (features of all are kept in memory)")

    g = p.add_argument_group("model and recipe")
    g.add_argument("--preset", default=d.preset, choices=list(PRESETS),
                   help="model size: 'realtime' (live use on a CPU), 'paper' (the paper's size), 'tiny' (tests)")
    g.add_argument("--recipe", default=d.recipe, choices=list(RECIPES),
                   help="diffusion training recipe: 'streaming' (short cosine chain, x0 + derivative losses; smooth "
                        "at any K) or 'paper' (Zhang et al.: 1000 linear steps, noise MSE)")
    g.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a model config field (dimgestor info --json lists them), repeatable")
    g.add_argument("--vel-weight", type=float, default=None, metavar="W",
                   help="weight of a velocity loss on the predicted x0 (default: the recipe's; 0 = none)")
    g.add_argument("--acc-weight", type=float, default=None, metavar="W",
                   help="weight of an acceleration loss on the predicted x0 (default: the recipe's; 0 = none)")
    g.add_argument("--root-weight", type=float, default=None, metavar="W",
                   help="weight of a loss on the integrated root travel and turning of the predicted x0, against "
                        "spin and drift (default: the recipe's; 0 = none)")
    g.add_argument("--cond-drop", type=float, default=None, metavar="P",
                   help="probability that a training window's audio condition is dropped (zeroed), so the model also "
                        "learns the unconditional motion that `--guidance S` sampling extrapolates away from "
                        "(default: the recipe's; 0 = none)")

    g = p.add_argument_group("optimisation")
    g.add_argument("--max-steps", type=int, default=d.max_steps, metavar="N", help="optimizer steps to train for")
    g.add_argument("--batch-size", type=int, default=d.batch_size, metavar="N",
                   help="global batch (split over DDP ranks)")
    g.add_argument("--lr", type=float, default=d.lr, help="peak learning rate (AdamW)")
    g.add_argument("--warmup", type=int, default=d.warmup, metavar="N", help="linear learning-rate warm-up steps")
    g.add_argument("--weight-decay", type=float, default=d.weight_decay, metavar="W",
                   help="AdamW's decoupled weight decay")
    g.add_argument("--grad-clip", type=float, default=d.grad_clip, metavar="NORM",
                   help="max gradient norm (0 = no clipping)")
    g.add_argument("--ema", type=float, default=d.ema, metavar="DECAY",
                   help="decay of the exponential moving average of the weights, which checkpoints save")
    g.add_argument("--seed", type=int, default=d.seed, help="seed of initialisation, batches and noise")

    g = p.add_argument_group("run and checkpoints")
    g.add_argument("--out", required=True, metavar="DIR", help="run folder for ckpt_XXXXXXX/ checkpoints and log.jsonl")
    g.add_argument("--ckpt-every", type=int, default=d.ckpt_every, metavar="N", help="save a checkpoint every N steps")
    g.add_argument("--valid-every", type=int, default=d.valid_every, metavar="N",
                   help="compute the held-out loss every N steps (logged to log.jsonl); 0: never (the held-out windows "
                        "are then not featurized either)")
    g.add_argument("--keep", type=int, default=d.keep, metavar="N", help="checkpoints to keep (0 = all)")
    g.add_argument("--resume", action="store_true", help="continue from the latest checkpoint in --out")
    g.add_argument("--device", default=d.device, help="torch device: auto (CUDA when present), cpu, cuda, cuda:1, ...")
    g.add_argument("--threads", type=int, default=None, metavar="N",
                   help="CPU threads for torch (default: torch's choice; 1 is much faster on a busy shared machine)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar (logs still go to log.jsonl)")
    p.set_defaults(func=_run)


def _parse_speeds(text: str | None) -> tuple[float, ...] | None:
    try:
        return None if text is None else tuple(float(r) for r in text.split(",") if r.strip())
    except ValueError:
        raise ValueError(f"--speeds expects comma-separated factors such as 0.9,1.1, got {text!r}") from None


def small_data_defaults(args, speeds: tuple[float, ...] | None) -> dict:
    """mirror, speeds and augment: as given, else on when the training split is under SMALL_DATA_MIN minutes."""
    few = False
    if args.mirror is None or speeds is None or args.augment is None:  # only then is the data read
        minutes = GestureDataset(args.data, FeatureSpec(), split="train", cache_dir=args.cache_dir,
                                 valid_fraction=args.valid_fraction, valid_seconds=args.valid_seconds,
                                 window_s=args.window_s, skeleton=args.skeleton
                                 ).seconds() / 60  # the heading layout does not change it
        few = minutes < SMALL_DATA_MIN
    return {"mirror": few if args.mirror is None else args.mirror,
            "speeds": (SMALL_DATA_SPEEDS if few else ()) if speeds is None else speeds,
            "augment": few if args.augment is None else args.augment}


def _flag_errors(e: ValidationError) -> str:
    """pydantic's complaints, named by the flags a user typed."""
    lines = []
    for err in e.errors():
        name = str(err["loc"][0]) if err["loc"] else ""
        flag = {"overrides": "--set", "": "options"}.get(name, "--" + name.replace("_", "-"))
        positive = err["type"] == "greater_than" and err.get("ctx", {}).get("gt") == 0
        text = "must be positive" if positive else err["msg"][:1].lower() + err["msg"][1:]
        lines.append(f"{flag} {text}, got {err['input']!r}" if name else f"{flag}: {text}")
    return "; ".join(lines)


def config_from_args(args) -> TrainConfig:
    """The command line as a TrainConfig: flags are named like its fields; data-dependent defaults resolved first."""
    speeds = _parse_speeds(args.speeds)
    fields = {k: v for k, v in vars(args).items() if k in TrainConfig.model_fields and v is not None}
    fields |= {"overrides": _parse_set(args.set), "progress": not args.no_progress}
    try:
        TrainConfig(**{**fields, "speeds": speeds or ()})  # bad flags fail before the data is read
        return TrainConfig(**{**fields, **small_data_defaults(args, speeds)})
    except ValidationError as e:
        raise ValueError(_flag_errors(e)) from None


def _run(args) -> int:
    if args.threads is not None:
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    last = train(config_from_args(args))
    if int(os.environ.get("RANK", "0")) == 0:
        print(f"checkpoint: {last}")
    return 0
