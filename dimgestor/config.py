"""Typed, frozen model configuration and the named presets (`paper`, `realtime`, `tiny`).

Rates are derived from each other with `exact_div` (as whisper does) so a config that would
silently misalign audio and motion frames fails when it is built, with a message saying why.
"""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from dimgestor.audio import SAMPLE_RATE

__all__ = ["ModelConfig", "PRESETS", "get_preset", "exact_div", "ConfigError"]


class ConfigError(ValueError):
    """A preset name or an override that cannot make a valid model."""


def exact_div(x: int, y: int, what: str = "") -> int:
    """x / y when it divides exactly; otherwise a ValueError naming the two quantities."""
    if y == 0 or x % y != 0:
        raise ValueError(f"{what or 'value'}: {x} is not a multiple of {y}")
    return x // y


class ModelConfig(BaseModel):
    """Everything needed to rebuild a DiM-Gestor network; saved inside every checkpoint."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    # --- denoiser (AdaLN Mamba-2 blocks) ---
    hidden: int = 256  # width of the motion tokens and of the condition; the paper uses 1280
    n_blocks: int = 4  # AdaLN Mamba-2 blocks; the paper stacks 6
    d_state: int = 64  # SSM state size N per head: memory of each block (paper: 256)
    d_conv: int = 4  # depthwise causal conv inside Mamba-2 (reference default)
    expand: int = 2  # Mamba-2 inner width = expand * hidden (reference default)
    headdim: int = 32  # Mamba-2 head size P; nheads = expand * hidden / headdim
    chunk_size: int = 64  # SSD chunk length: trades the quadratic intra-chunk part against the scan
    mlp_ratio: float = 4.0  # width of the per-block MLP relative to hidden (as in DiT)

    # --- audio front end ---
    # logmel: the paper-style spectrum; speech: level-free bands + prosody relative to each stream's running
    # statistics (dimgestor/frontend/speech.py), so gestures follow what is said, not the voice or microphone
    # embedding: speech + a pretrained speech embedding (dimgestor/frontend/embed.py; needs openwakeword 0.5.1's ONNX files)
    frontend: Literal["logmel", "speech", "embedding", "pretrained"] = "logmel"
    pretrained_path: str | None = None  # LOCAL wav2vec2/HuBERT folder when frontend == "pretrained"
    pretrained_block_ms: int = 1000  # pretrained encoder runs on fixed blocks of this length ...
    pretrained_left_ms: int = 1000  # ... with this much past audio as context ...
    pretrained_right_ms: int = 200  # ... and this much future audio (adds to the latency)
    n_mels: int = 80  # log-mel channels (the usual speech setting)
    n_fft: int = 512  # FFT size; the 400-sample (25 ms) window is zero-padded to it
    win_length: int = 400  # analysis window: 25 ms at 16 kHz, the speech standard
    sample_rate: int = SAMPLE_RATE  # every audio path resamples to this
    feature_rate: int = 100  # audio feature frames per second (hop 160 samples)
    fps: int = 20  # motion frames per second, as in the paper

    # --- fuzzy feature extractor ---
    style_width: int = 128  # width of the Mamba-2 global style extractor
    style_d_state: int = 32  # its SSM state size
    style_headdim: int = 32  # its head size
    down_kernel: int = 31  # Conv1D downsampler kernel over 100 Hz features (paper: 201)
    lookahead_ms: int | None = 150  # future audio a frame may see beyond its own end; None = centred kernel

    # --- motion ---
    motion_dim: int = 12  # feature columns per frame; set from the data's FeatureSpec when training
    # speakers the model can be asked for (`train --speaker-condition`): a learnt vector per speaker added to the
    # condition; () = no speaker condition (the default, and every model before it)
    speakers: tuple[str, ...] = ()

    # --- diffusion ---
    n_steps: int = 1000  # N diffusion steps, as in the paper
    beta_start: float = 1e-4  # paper schedule
    beta_end: float = 8e-2  # paper schedule
    # sqrt_linear: the authors' earlier code; cosine: Nichol & Dhariwal's alpha_bar (betas unused), for short chains
    schedule: Literal["linear", "sqrt_linear", "cosine"] = "linear"
    prediction: Literal["eps", "v", "x0"] = "eps"  # the network predicts the noise (paper), v, or the clean motion
    # Temporal correlation of the diffusion noise: each frame's noise is a causal Hann-weighted sum of this
    # many white per-frame draws (unit variance). 1 = white noise (the paper). Longer kernels push what a
    # causal denoiser cannot remove below a few Hz, where it reads as motion rather than jitter.
    noise_taps: int = Field(1, ge=1, le=64)

    # --- inference defaults (what generate/serve/eval use when not told) ---
    sample_steps: int = Field(8, ge=1)  # DDIM steps K
    ddim_spacing: Literal["trailing", "linspace"] = "trailing"  # where the K steps sit (diffusion.ddim_pairs)
    # the sampler's own timesteps, highest first, where it has them: a progressively distilled student's are
    # every r-th of its teacher's (`dimgestor distill`); they replace ddim_spacing when K is their count
    ddim_timesteps: tuple[int, ...] | None = None
    # classifier-free guidance scale s: out_u + s (out_c - out_u), out_u with the condition zeroed. 1 = the
    # plain conditional sampler (no unconditional rows at all), 0 = the unconditional model; > 1 needs a model
    # trained with condition dropout (`dimgestor train --cond-drop`) and costs a second batch row per stream
    guidance: float = Field(1.0, ge=0, allow_inf_nan=False)

    # a distilled student (`dimgestor distill`): its sampled motion is rescaled per feature, x * out_gain +
    # out_shift (buffers in its weights, measured by distill), to move as much as its teacher: a student learnt by
    # the mean squared difference moves less than the teacher whose chain it replaces (benchmarks/README.md)
    calibrated: bool = False

    # --- output smoothing (not in the paper; see dimgestor/smoothing.py) ---
    smooth_hz: float | None = None  # One Euro filter min cutoff on the output features; None = off
    smooth_beta: float = 0.0  # its speed coefficient (cutoff rises by beta per normalized unit/s)

    # ---- derived quantities (never stored twice) ----
    @property
    def hop_length(self) -> int:
        """Audio samples per feature frame (160)."""
        return exact_div(self.sample_rate, self.feature_rate, "sample_rate / feature_rate")

    @property
    def feats_per_frame(self) -> int:
        """Audio feature frames per motion frame (5): the downsampler stride."""
        return exact_div(self.feature_rate, self.fps, "feature_rate / fps")

    @property
    def samples_per_frame(self) -> int:
        """Audio samples per motion frame (800)."""
        return exact_div(self.sample_rate, self.fps, "sample_rate / fps")

    @property
    def lookahead_feats(self) -> int:
        """Audio feature frames a motion frame sees beyond its own last feature frame."""
        if self.lookahead_ms is None:  # centred kernel: the frame's middle feature is the kernel centre
            return (self.down_kernel - 1) // 2 - (self.feats_per_frame - 1) // 2
        return exact_div(self.lookahead_ms * self.feature_rate, 1000, "lookahead_ms * feature_rate / 1000")

    @property
    def d_inner(self) -> int:
        return self.expand * self.hidden

    @model_validator(mode="after")
    def _check(self) -> "ModelConfig":
        positive = ["hidden", "n_blocks", "d_state", "d_conv", "expand", "headdim", "chunk_size", "n_mels",
                    "n_fft", "win_length", "sample_rate", "feature_rate", "fps", "style_width",
                    "style_d_state", "style_headdim", "down_kernel", "motion_dim", "n_steps"]
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.mlp_ratio <= 0:
            raise ValueError(f"mlp_ratio must be positive, got {self.mlp_ratio}")
        self.hop_length, self.feats_per_frame, self.samples_per_frame  # noqa: B018 (raise if not exact)
        exact_div(self.d_inner, self.headdim, "expand * hidden / headdim (Mamba-2 heads)")
        exact_div(2 * self.style_width, self.style_headdim, "2 * style_width / style_headdim")
        if self.win_length > self.n_fft:
            raise ValueError(f"win_length {self.win_length} exceeds n_fft {self.n_fft}")
        if self.win_length < self.hop_length:
            raise ValueError(f"win_length {self.win_length} is shorter than the hop {self.hop_length}")
        if self.lookahead_ms is not None and self.lookahead_ms < 0:
            raise ValueError(f"lookahead_ms must be >= 0 or None (centred), got {self.lookahead_ms}")
        la = self.lookahead_feats
        if la + self.feats_per_frame > self.down_kernel:
            raise ValueError(
                f"down_kernel {self.down_kernel} cannot see {la} feature frames of lookahead plus the frame's own "
                f"{self.feats_per_frame}: lower lookahead_ms or raise down_kernel to >= {la + self.feats_per_frame}")
        if self.sample_steps > self.n_steps:
            raise ValueError(f"sample_steps {self.sample_steps} exceeds the {self.n_steps} diffusion steps")
        ts = self.ddim_timesteps
        if ts is not None and (not ts or any(a <= b for a, b in zip(ts, ts[1:])) or ts[0] >= self.n_steps
                               or ts[-1] < 0):
            raise ValueError(f"ddim_timesteps must be strictly decreasing steps in 0..{self.n_steps - 1}, "
                             f"got {list(ts)}")
        if not 0 < self.beta_start < self.beta_end < 1:
            raise ValueError(f"need 0 < beta_start < beta_end < 1, got {self.beta_start}, {self.beta_end}")
        if len(set(self.speakers)) != len(self.speakers) or any(not s for s in self.speakers):
            raise ValueError(f"speakers must be distinct non-empty names, got {list(self.speakers)}")
        if self.frontend == "pretrained" and not self.pretrained_path:
            raise ValueError("frontend 'pretrained' needs pretrained_path: a local wav2vec2/HuBERT folder")
        for name in ("pretrained_block_ms", "pretrained_left_ms", "pretrained_right_ms"):
            exact_div(getattr(self, name) * self.feature_rate, 1000, f"{name} * feature_rate / 1000")
        return self


PRESETS: dict[str, dict] = {
    # Zhang et al.: hidden 1280, 6 blocks, N=256, centred 201-tap downsampler (1 s either side at 100 Hz).
    "paper": dict(hidden=1280, n_blocks=6, d_state=256, d_conv=4, expand=2, headdim=64, chunk_size=64,
                  style_width=256, style_d_state=64, style_headdim=64, down_kernel=201, lookahead_ms=None),
    # Live use: ~200 ms algorithmic latency (50 ms frame + 150 ms lookahead); sized for RTF < 0.25
    # with K=8 DDIM steps on 2 CPU cores. Its own diffusion settings (v-prediction over the default 1000
    # linear steps, where alpha_bar(999) ~ e^-42 leaves an eps-model's x0 estimate ill-conditioned) only
    # apply without a recipe: the shipped model is trained with the "streaming" recipe (dimgestor.training.train),
    # which overrides them with 8 cosine steps predicting x0.
    "realtime": dict(hidden=128, n_blocks=4, d_state=32, d_conv=4, expand=2, headdim=32, chunk_size=64,
                     style_width=64, style_d_state=16, style_headdim=32, down_kernel=31, lookahead_ms=150,
                     n_mels=64, prediction="v"),
    # Unit tests: small, odd-sized chunks so chunk boundaries are exercised.
    "tiny": dict(hidden=32, n_blocks=2, d_state=16, d_conv=4, expand=2, headdim=16, chunk_size=16,
                 mlp_ratio=2.0, style_width=16, style_d_state=8, style_headdim=8, n_mels=20,
                 down_kernel=11, lookahead_ms=30, motion_dim=12, prediction="v"),
}


def get_preset(name: str, **overrides) -> ModelConfig:
    """A preset by name with field overrides; unknown names or bad values raise ConfigError."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    try:
        return ModelConfig(**{**PRESETS[name], **overrides})
    except ValidationError as e:
        msgs = "; ".join(f"{'.'.join(map(str, err['loc'])) or 'config'}: {err['msg']}" for err in e.errors())
        raise ConfigError(f"preset {name!r}: {msgs}") from None
