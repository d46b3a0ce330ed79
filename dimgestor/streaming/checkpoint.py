"""Checkpoints: a folder with safetensors weights, the JSON config, normalization stats and the skeleton.

    ckpt_0001000/
      model.safetensors   EMA weights (the pretrained front end's encoder is not stored: it is loaded
                          from its own local folder, named in the config)
      config.json         {"format", "model": ModelConfig, "feature_spec", "skeleton", "info"}
      norm.safetensors    mean, std of the motion features
      train_state.pt      (runs only) optimizer, raw weights, step and RNG states for --resume

A run folder holds ckpt_XXXXXXX/ folders; the latest is used when a run folder is given.
`load_checkpoint(None)` loads the embedded default model in dimgestor/default_model/; the names of the embedded
models (`EMBEDDED`: "default", and "live", 150 ms sooner for talking live) load them where no such path exists.
"""
from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from pydantic import ValidationError
from safetensors.torch import load_file, save_file

from ..bvh import Skeleton
from ..config import ModelConfig
from ..features import FeatureSpec
from ..model.network import DiMGestor
from .stream import MODEL_SPEAKER, GestureStream, generate_offline

__all__ = ["Bundle", "CheckpointError", "save_checkpoint", "load_checkpoint", "resolve_checkpoint",
           "latest_checkpoint", "export_checkpoint", "DEFAULT_MODEL_DIR", "LIVE_MODEL_DIR", "EMBEDDED", "FORMAT"]

FORMAT = 1
DEFAULT_MODEL_DIR = Path(__file__).resolve().parents[1] / "default_model"
# The same recipe with 150 ms of lookahead instead of 300 (200 ms of algorithmic latency, not 350): for a live
# microphone (MODEL_CARD.md, "The live model").
LIVE_MODEL_DIR = Path(__file__).resolve().parents[1] / "live_model"
EMBEDDED = {"default": "DEFAULT_MODEL_DIR", "live": "LIVE_MODEL_DIR"}  # --checkpoint NAME -> the module global
_CKPT = re.compile(r"^ckpt_(\d+)$")


class CheckpointError(Exception):
    """A checkpoint that is missing, incomplete or unreadable; the message names the path."""


def _weights(model: DiMGestor) -> dict[str, torch.Tensor]:
    # the front end holds no trained weights (log-mel) or a frozen encoder that lives in its own folder
    return {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items() if not k.startswith("frontend.")}


@dataclass
class Bundle:
    """A loaded checkpoint: the network and everything needed to turn its output into motion."""

    model: DiMGestor
    config: ModelConfig
    feature_spec: FeatureSpec
    skeleton: Skeleton
    mean: np.ndarray  # (D,) float32
    std: np.ndarray  # (D,) float32
    info: dict = field(default_factory=dict)
    path: Path | None = None

    def normalize(self, f: np.ndarray) -> np.ndarray:
        return ((f - self.mean) / self.std).astype(np.float32)

    def denormalize(self, f: np.ndarray) -> np.ndarray:
        return (f * self.std + self.mean).astype(np.float32)

    def stream(self, steps: int | None = None, seed: int = 0, sampler: str = "ddim", eta: float = 0.0,
               smoothing="config", guidance: float | None = None, speaker=MODEL_SPEAKER) -> GestureStream:
        """A live stream; steps and guidance None and smoothing "config" take the checkpoint's defaults, speaker
        MODEL_SPEAKER the model's own (a name, or None for no speaker in particular: `GestureStream`)."""
        return GestureStream(self.model, steps=steps, seed=seed, sampler=sampler, eta=eta, smoothing=smoothing,
                             guidance=guidance, speaker=speaker)

    def generate(self, audio: np.ndarray, steps: int | None = None, seed: int = 0, sampler: str = "ddim",
                 eta: float = 0.0, smoothing="config", guidance: float | None = None) -> np.ndarray:
        """Offline generation: 16 kHz mono audio -> (T, D) denormalized motion features (defaults as stream)."""
        return self.denormalize(generate_offline(self.model, audio, steps, seed, sampler, eta, smoothing,
                                                 guidance=guidance))


def save_checkpoint(folder: str | Path, model: DiMGestor, feature_spec: FeatureSpec, skeleton: Skeleton,
                    mean, std, info: dict | None = None, train_state: dict | None = None,
                    weights: dict[str, torch.Tensor] | None = None) -> Path:
    """Write a checkpoint folder atomically (a temp folder renamed into place); returns its path.

    `weights` overrides the model's own state (the trainer passes the EMA weights).
    """
    folder = Path(folder)
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    tensors = _weights(model) if weights is None else {k: v.detach().cpu().contiguous() for k, v in weights.items()
                                                       if not k.startswith("frontend.")}
    save_file(tensors, str(tmp / "model.safetensors"))
    save_file({"mean": torch.as_tensor(np.asarray(mean), dtype=torch.float32).contiguous(),
               "std": torch.as_tensor(np.asarray(std), dtype=torch.float32).contiguous()},
              str(tmp / "norm.safetensors"))
    meta = {"format": FORMAT, "model": model.config.model_dump(mode="json"),
            "feature_spec": feature_spec.to_dict(), "skeleton": skeleton.to_dict(), "info": info or {}}
    (tmp / "config.json").write_text(json.dumps(meta, indent=1))
    if train_state is not None:
        torch.save(train_state, tmp / "train_state.pt")
    if folder.exists():
        shutil.rmtree(folder)
    os.replace(tmp, folder)
    return folder


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The ckpt_XXXXXXX folder with the highest step in a run folder, or None."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        return None
    found = [(int(m.group(1)), p) for p in run_dir.iterdir() if p.is_dir() and (m := _CKPT.match(p.name))
             and (p / "model.safetensors").is_file()]
    return max(found)[1] if found else None


def resolve_checkpoint(path: str | Path | None) -> Path:
    """A checkpoint folder from a checkpoint folder, a file inside one, a run folder, None (the embedded default)
    or the name of an embedded model ("default", "live") where no such path exists."""
    if path is None or (str(path) in EMBEDDED and not Path(path).exists()):
        name = "default" if path is None else str(path)
        folder = globals()[EMBEDDED[name]]
        if not (folder / "model.safetensors").is_file():
            raise CheckpointError(f"no embedded {name} model at {folder}; train one with "
                                  "`dimgestor train` and pass it with --checkpoint")
        return folder
    p = Path(path)
    if p.is_file() and p.parent.joinpath("config.json").is_file():
        p = p.parent  # e.g. .../ckpt_0001000/model.safetensors
    if not p.exists():
        raise CheckpointError(f"checkpoint not found: {p}")
    if (p / "model.safetensors").is_file():
        return p
    latest = latest_checkpoint(p)
    if latest is None:
        raise CheckpointError(f"{p} is neither a checkpoint folder (model.safetensors, config.json, "
                              "norm.safetensors) nor a run folder with ckpt_* checkpoints")
    return latest


def read_meta(folder: Path) -> dict:
    path = folder / "config.json"
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise CheckpointError(f"{path}: missing") from None
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{path}:{e.lineno}: not valid JSON ({e.msg})") from None
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: checkpoint format {meta.get('format')!r}, this version reads {FORMAT}")
    return meta


def load_checkpoint(path: str | Path | None = None, device: str | torch.device = "cpu") -> Bundle:
    """Load a checkpoint (folder, run folder, or None for the embedded default) as a Bundle in eval mode."""
    folder = resolve_checkpoint(path)
    meta = read_meta(folder)
    try:
        config = ModelConfig(**meta["model"])
        spec = FeatureSpec.from_dict(meta["feature_spec"])
        skeleton = Skeleton.from_dict(meta["skeleton"])
    except (KeyError, ValidationError, ValueError, TypeError) as e:
        raise CheckpointError(f"{folder / 'config.json'}: invalid contents ({e})") from None
    model = DiMGestor(config)
    try:
        weights = load_file(str(folder / "model.safetensors"))
        norm = load_file(str(folder / "norm.safetensors"))
    except FileNotFoundError as e:
        raise CheckpointError(f"{folder}: missing {Path(e.filename).name if e.filename else 'a weights file'}") from None
    except Exception as e:  # safetensors raises its own error types for corrupt files
        raise CheckpointError(f"{folder}: unreadable weights ({e})") from None
    missing, unexpected = model.load_state_dict(weights, strict=False)
    missing = [k for k in missing if not k.startswith("frontend.")]
    if missing or unexpected:
        raise CheckpointError(f"{folder / 'model.safetensors'}: weights do not fit the config "
                              f"(missing {missing[:5]}, unexpected {unexpected[:5]})")
    mean, std = norm["mean"].numpy(), norm["std"].numpy()
    if mean.shape != (config.motion_dim,) or std.shape != (config.motion_dim,):
        raise CheckpointError(f"{folder / 'norm.safetensors'}: stats of shape {tuple(mean.shape)}, "
                              f"expected ({config.motion_dim},)")
    return Bundle(model.to(device).eval(), config, spec, skeleton, mean, std, meta.get("info", {}), folder)


def export_checkpoint(src: str | Path | None, dst: str | Path, **inference) -> Path:
    """Copy a checkpoint's inference files (no train_state.pt) to `dst`, e.g. dimgestor/default_model/.

    `inference` sets inference-only config fields (sample_steps, smooth_hz, smooth_beta, guidance) in the
    exported config.
    """
    allowed = {"smooth_hz", "smooth_beta", "sample_steps", "guidance"}
    if set(inference) - allowed:
        raise ValueError(f"export can only set {sorted(allowed)}, got {sorted(set(inference) - allowed)}")
    bundle = load_checkpoint(src)  # validates before anything is written
    if inference:  # validated as a whole config (model_copy would not check the new values)
        bundle.model.config = ModelConfig(**{**bundle.model.config.model_dump(), **inference})
    info = {**bundle.info, "exported_from": str(bundle.path)}
    ts = bundle.path / "train_state.pt" if bundle.path is not None else None
    if "options" not in info and ts is not None and ts.is_file():  # checkpoints older than info["options"]
        opts = torch.load(ts, map_location="cpu", weights_only=False).get("options", {})
        info["options"] = {k: v for k, v in opts.items() if k not in ("progress", "resume", "cache_dir")}
    return save_checkpoint(dst, bundle.model, bundle.feature_spec, bundle.skeleton, bundle.mean, bundle.std,
                           info=info)
