"""Diffusion schedule, training loss, DDPM/DDIM steps, and counter-based per-frame noise.

Notation (Ho et al. 2020; Song et al. 2021): beta_t, alpha_t = 1 - beta_t, a_t = alpha_bar_t =
prod_{s<=t} alpha_s; x_t = sqrt(a_t) x_0 + sqrt(1 - a_t) eps. The sampler is separate from the model
and the caller writes the loop over explicit (t, t_prev) pairs; t_prev = -1 means a = 1 (clean).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .config import ModelConfig

__all__ = ["Diffusion", "ddim_pairs", "frame_noise", "hash32"]


def ddim_pairs(K: int, N: int) -> list[tuple[int, int]]:
    """K evenly spaced ("trailing") steps over N: starts at t = N-1, ends with t_prev = -1."""
    if not 1 <= K <= N:
        raise ValueError(f"number of sampling steps must be in 1..{N}, got {K}")
    ts = [N * (K - i) // K - 1 for i in range(K)]  # exact integers, strictly decreasing
    return list(zip(ts, ts[1:] + [-1]))


class Diffusion:
    """The N-step noise schedule of a config, with its loss and single sampler steps."""

    def __init__(self, config: ModelConfig):
        self.N, self.prediction = config.n_steps, config.prediction
        if config.schedule == "linear":
            betas = torch.linspace(config.beta_start, config.beta_end, self.N, dtype=torch.float64)
        else:  # "sqrt_linear": linear in sqrt(beta), as in the authors' earlier (DiffuseStyleGesture-era) code
            betas = torch.linspace(config.beta_start ** 0.5, config.beta_end ** 0.5, self.N, dtype=torch.float64) ** 2
        self.betas = betas  # float64: the coefficients below are taken as Python floats
        self.alphas_cumprod = torch.cumprod(1.0 - betas, dim=0)

    def a(self, t: int) -> float:
        """alpha_bar_t, with alpha_bar_{-1} = 1."""
        return 1.0 if t < 0 else float(self.alphas_cumprod[t])

    # ---- training ----
    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """x_t = sqrt(a_t) x0 + sqrt(1 - a_t) eps (eq. 4 of Ho et al.), t: (B,) long."""
        a = self.alphas_cumprod.to(x0.device)[t].to(x0.dtype)[:, None, None]
        return a.sqrt() * x0 + (1 - a).sqrt() * noise

    def target(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """What the network learns to output: eps, or v = sqrt(a) eps - sqrt(1 - a) x0 (Salimans & Ho)."""
        if self.prediction == "eps":
            return noise
        a = self.alphas_cumprod.to(x0.device)[t].to(x0.dtype)[:, None, None]
        return a.sqrt() * noise - (1 - a).sqrt() * x0

    def training_loss(self, model, x0: torch.Tensor, feats: torch.Tensor, t: torch.Tensor,
                      noise: torch.Tensor, vel_weight: float = 0.0) -> torch.Tensor:
        """MSE between the network output on x_t and the target; feats: (B, n, F) audio features.

        vel_weight > 0 adds an MSE between the frame-to-frame differences of the predicted x0 and of the
        real x0 (the velocity loss of MDM, Tevet et al. 2023): a penalty on jitter that the paper's loss
        alone learns slowly from little data. 0 is the paper's objective.
        """
        cond, _ = model.condition(feats)
        cond = cond[:, : x0.shape[1]]
        x_t = self.q_sample(x0, t, noise)
        out, _ = model(x_t, t, cond)
        loss = F.mse_loss(out, self.target(x0, t, noise))
        if vel_weight > 0 and x0.shape[1] > 1:
            a = self.alphas_cumprod.to(x0.device)[t].to(x0.dtype)[:, None, None]
            if self.prediction == "eps":  # x0 = (x_t - sqrt(1-a) eps) / sqrt(a); weighted by a so t -> N stays finite
                x0_pred, w = (x_t - (1 - a).sqrt() * out) / a.sqrt().clamp_min(1e-4), a
            else:
                x0_pred, w = a.sqrt() * x_t - (1 - a).sqrt() * out, torch.ones_like(a)
            d = (x0_pred.diff(dim=1) - x0.diff(dim=1)) ** 2
            loss = loss + vel_weight * (w * d).mean()
        return loss

    # ---- sampling ----
    def split(self, out: torch.Tensor, x_t: torch.Tensor, t: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Network output -> (eps, x0_pred), each computed the well-conditioned way for the prediction type."""
        a = self.a(t)
        if self.prediction == "eps":
            return out, (x_t - math.sqrt(1 - a) * out) / math.sqrt(a)
        return math.sqrt(a) * out + math.sqrt(1 - a) * x_t, math.sqrt(a) * x_t - math.sqrt(1 - a) * out

    def ddim_step(self, x_t: torch.Tensor, eps: torch.Tensor, t: int, t_prev: int, eta: float = 0.0,
                  noise: torch.Tensor | None = None, x0: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """One DDIM update (Song et al., eq. 12 with sigma from eq. 16) -> (x_{t_prev}, x0_pred)."""
        a_t, a_prev = self.a(t), self.a(t_prev)
        if x0 is None:  # eq. 12, "predicted x0"
            x0 = (x_t - math.sqrt(1 - a_t) * eps) / math.sqrt(a_t)
        sigma = eta * math.sqrt((1 - a_prev) / (1 - a_t)) * math.sqrt(1 - a_t / a_prev)  # eq. 16
        x_prev = math.sqrt(a_prev) * x0 + math.sqrt(max(1 - a_prev - sigma ** 2, 0.0)) * eps  # eq. 12
        if sigma > 0:
            if noise is None:
                raise ValueError("ddim_step with eta > 0 needs noise")
            x_prev = x_prev + sigma * noise
        return x_prev, x0

    def ddpm_step(self, x_t: torch.Tensor, x0: torch.Tensor, t: int, noise: torch.Tensor | None
                  ) -> torch.Tensor:
        """Ancestral step x_t -> x_{t-1} from the posterior q(x_{t-1} | x_t, x0) (Ho et al., eqs. 6-7)."""
        a_t, a_prev, beta = self.a(t), self.a(t - 1), float(self.betas[t])
        mean = (math.sqrt(a_prev) * beta / (1 - a_t)) * x0 + (math.sqrt(1 - beta) * (1 - a_prev) / (1 - a_t)) * x_t
        if t == 0:
            return mean
        var = beta * (1 - a_prev) / (1 - a_t)  # beta_tilde_t, eq. 7
        return mean + math.sqrt(var) * noise

    def sampling_pairs(self, sampler: str, steps: int) -> list[tuple[int, int]]:
        if sampler == "ddim":
            return ddim_pairs(steps, self.N)
        if sampler == "ddpm":
            return ddim_pairs(self.N, self.N)  # every step: (N-1, N-2), ..., (0, -1)
        raise ValueError(f"unknown sampler {sampler!r}; choose 'ddim' or 'ddpm'")


# ---------------- counter-based noise ----------------
_M32 = 0xFFFFFFFF


def _mul32(x: torch.Tensor, c: int) -> torch.Tensor:
    """(x * c) mod 2^32 for x in [0, 2^32) in int64 without signed overflow (c split into 16-bit halves)."""
    lo, hi = c & 0xFFFF, c >> 16
    return (x * lo + (((x * hi) & 0xFFFF) << 16)) & _M32


def hash32(x: torch.Tensor) -> torch.Tensor:
    """A 32-bit integer mixer (Wellons' "lowbias32") on int64 tensors holding values in [0, 2^32)."""
    x = x ^ (x >> 16)
    x = _mul32(x, 0x7FEB352D)
    x = x ^ (x >> 15)
    x = _mul32(x, 0x846CA68B)
    return x ^ (x >> 16)


def frame_noise(seed: int, frame_start: int, n_frames: int, step: int, dim: int,
                device=None) -> torch.Tensor:
    """(n_frames, dim) standard normal noise, a pure function of (seed, frame index, step, channel).

    Each value hashes its counter (Philox-style, but with a plain integer mixer) into two uniforms
    and maps them through Box-Muller, so any window of frames draws exactly the same numbers.
    """
    frames = torch.arange(frame_start, frame_start + n_frames, dtype=torch.int64, device=device)[:, None]
    chans = torch.arange(dim, dtype=torch.int64, device=device)[None, :]
    h = torch.full((1, 1), 0x9E3779B9, dtype=torch.int64, device=device)
    for key in (seed & _M32, (seed >> 32) & _M32, step & _M32):
        h = hash32(h ^ key)
    h = hash32(h ^ (frames & _M32))
    h = hash32(h ^ ((frames >> 32) & _M32))
    h = hash32(h ^ chans)  # (n_frames, dim)
    u1 = (hash32(h ^ 0x68E31DA4).double() + 0.5) / 2.0 ** 32  # (0, 1): log never sees 0
    u2 = (hash32(h ^ 0xB5297A4D).double() + 0.5) / 2.0 ** 32
    z = torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * math.pi * u2)
    return z.float()
