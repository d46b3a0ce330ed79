"""Diffusion schedule, training loss, DDPM/DDIM steps, and counter-based per-frame noise.

Notation (Ho et al. 2020; Song et al. 2021): beta_t, alpha_t = 1 - beta_t, a_t = alpha_bar_t =
prod_{s<=t} alpha_s; x_t = sqrt(a_t) x_0 + sqrt(1 - a_t) eps. The sampler is separate from the model
and the caller writes the loop over explicit (t, t_prev) pairs; t_prev = -1 means a = 1 (clean).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..config import ModelConfig

__all__ = ["Diffusion", "ddim_pairs", "guide", "check_guidance", "frame_noise", "frame_noise_rows", "motion_noise", "motion_noise_rows",
           "noise_kernel", "correlate", "hash32"]


def ddim_pairs(K: int, N: int, spacing: str = "trailing") -> list[tuple[int, int]]:
    """K evenly spaced steps over N, from t = N-1 to t_prev = -1 (clean).

    "trailing" spaces them N/K apart from the top (its last step starts at t = N/K - 1); "linspace" puts
    the first at N-1 and the last at t = 0, so every K >= 2 ends with the least-noisy trained level (a
    short chain's finest step is where a causal denoiser's residual noise is smallest).
    """
    if not 1 <= K <= N:
        raise ValueError(f"number of sampling steps must be in 1..{N}, got {K}")
    if spacing == "trailing":
        ts = [N * (K - i) // K - 1 for i in range(K)]  # exact integers, strictly decreasing
    elif spacing == "linspace":
        ts = [N - 1] if K == 1 else [((N - 1) * (K - 1 - i) * 2 + (K - 1)) // (2 * (K - 1)) for i in range(K)]
    else:
        raise ValueError(f"unknown DDIM spacing {spacing!r}; choose 'trailing' or 'linspace'")
    return list(zip(ts, ts[1:] + [-1]))


def guide(out_c: torch.Tensor, out_u: torch.Tensor, s) -> torch.Tensor:
    """Classifier-free guidance (Ho & Salimans 2022, eq. 6 written as an extrapolation): out_u + s (out_c - out_u).

    out_c, out_u: the network's output with the condition and with the null (zero) condition; s a float or a
    tensor broadcasting over rows. Linear in the output, so eps, v and x0 predictions are guided alike.
    """
    return out_u + s * (out_c - out_u)


def check_guidance(s: float) -> float:
    """A guidance scale as a float: finite and >= 0 (0 = unconditional, 1 = unguided)."""
    s = float(s)
    if not (math.isfinite(s) and s >= 0):
        raise ValueError(f"guidance scale must be a finite number >= 0 (1 = unguided), got {s}")
    return s


class Diffusion:
    """The N-step noise schedule of a config, with its loss and single sampler steps."""

    def __init__(self, config: ModelConfig):
        self.N, self.prediction, self.spacing = config.n_steps, config.prediction, config.ddim_spacing
        self.timesteps = config.ddim_timesteps
        self.noise_taps = config.noise_taps
        if config.schedule == "linear":
            betas = torch.linspace(config.beta_start, config.beta_end, self.N, dtype=torch.float64)
        elif config.schedule == "sqrt_linear":  # linear in sqrt(beta), as in the authors' earlier code
            betas = torch.linspace(config.beta_start ** 0.5, config.beta_end ** 0.5, self.N, dtype=torch.float64) ** 2
        else:  # "cosine" (Nichol & Dhariwal 2021, eq. 17, s = 0.008): alpha_bar spread evenly in log-SNR
            s = 0.008
            f = torch.cos((torch.arange(self.N + 1, dtype=torch.float64) / self.N + s) / (1 + s) * math.pi / 2) ** 2
            betas = (1 - f[1:] / f[:-1]).clamp(max=0.999)
        self.betas = betas  # float64: the coefficients below are taken as Python floats
        self.alphas_cumprod = torch.cumprod(1.0 - betas, dim=0)
        # the sampler's coefficients as Python floats, read once here: a step reads no tensor element, so
        # tracing it (the ONNX export) sees constants
        self._a, self._betas = self.alphas_cumprod.tolist(), betas.tolist()

    def a(self, t: int) -> float:
        """alpha_bar_t, with alpha_bar_{-1} = 1."""
        return 1.0 if t < 0 else self._a[t]

    # ---- training ----
    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """x_t = sqrt(a_t) x0 + sqrt(1 - a_t) eps (eq. 4 of Ho et al.), t: (B,) long."""
        a = self.alphas_cumprod.to(x0.device)[t].to(x0.dtype)[:, None, None]
        return a.sqrt() * x0 + (1 - a).sqrt() * noise

    def target(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """What the network learns to output: eps, x0, or v = sqrt(a) eps - sqrt(1 - a) x0 (Salimans & Ho)."""
        if self.prediction == "eps":
            return noise
        if self.prediction == "x0":
            return x0
        a = self.alphas_cumprod.to(x0.device)[t].to(x0.dtype)[:, None, None]
        return a.sqrt() * noise - (1 - a).sqrt() * x0

    def noise_like(self, x0: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Training noise for x0 (B, T, D): white, or correlated over frames as `motion_noise` makes it."""
        L = self.noise_taps
        white = torch.randn((x0.shape[0], x0.shape[1] + L - 1, x0.shape[2]), generator=generator)
        return correlate(white, L).to(x0.device, x0.dtype)

    def training_loss(self, model, x0: torch.Tensor, feats: torch.Tensor, t: torch.Tensor,
                      noise: torch.Tensor, vel_weight: float = 0.0, acc_weight: float = 0.0,
                      root_weight: float = 0.0, root_columns: tuple[int, ...] = (0, 1, 2),
                      drop: torch.Tensor | None = None, speaker: torch.Tensor | None = None) -> torch.Tensor:
        """MSE between the network output on x_t and the target; feats: (B, n, F) audio features.

        vel_weight / acc_weight > 0 add MSEs between the first / second frame differences of the predicted
        x0 and of the real x0 (the geometric losses of MDM, Tevet et al. 2023): penalties on the jitter a
        causal denoiser passes through from the noise it cannot tell from motion. root_weight > 0 adds an MSE
        between the integrated root velocities (`root_columns`: ground travel, and turning when the heading is
        a velocity) of the predicted and the real x0, per frame of the window: a small bias in a velocity is
        a walk or a spin once integrated, and the per-frame losses barely see it. 0 is the paper's objective.
        drop: (B,) bool, the windows whose condition is replaced by the null condition (zeros) for
        classifier-free guidance (Ho & Salimans 2022): the same network then learns the unconditional model.
        speaker: (B,) speaker indices (-1: none) for a model with a speaker condition.
        """
        cond, _ = model.condition(feats) if speaker is None else model.condition(feats, speaker=speaker)
        cond = cond[:, : x0.shape[1]]
        if drop is not None:
            cond = torch.where(drop.to(cond.device)[:, None, None], torch.zeros_like(cond), cond)
        x_t = self.q_sample(x0, t, noise)
        out, _ = model(x_t, t, cond)
        loss = F.mse_loss(out, self.target(x0, t, noise))
        if (vel_weight > 0 or acc_weight > 0 or root_weight > 0) and x0.shape[1] > 2:
            a = self.alphas_cumprod.to(x0.device)[t].to(x0.dtype)[:, None, None]
            if self.prediction == "eps":  # x0 = (x_t - sqrt(1-a) eps) / sqrt(a); weighted by a so t -> N stays finite
                x0_pred, w = (x_t - (1 - a).sqrt() * out) / a.sqrt().clamp_min(1e-4), a
            elif self.prediction == "v":
                x0_pred, w = a.sqrt() * x_t - (1 - a).sqrt() * out, torch.ones_like(a)
            else:
                x0_pred, w = out, torch.ones_like(a)
            for order, weight in ((1, vel_weight), (2, acc_weight)):
                if weight > 0:
                    d = (x0_pred.diff(n=order, dim=1) - x0.diff(n=order, dim=1)) ** 2
                    loss = loss + weight * (w * d).mean()
            if root_weight > 0:  # the root velocities integrated over the window
                cols = list(root_columns)
                drift = (x0_pred[..., cols] - x0[..., cols]).cumsum(dim=1) ** 2
                loss = loss + root_weight * (w * drift).mean() / x0.shape[1]
        return loss

    # ---- sampling ----
    def x0_reaching(self, x_t: torch.Tensor, x_prev: torch.Tensor, t: int, t_prev: int) -> torch.Tensor:
        """The x0 whose deterministic DDIM step (eta 0) takes x_t at t to x_prev at t_prev: what a progressively
        distilled student's one step learns from its teacher's several (Salimans & Ho 2022, eq. 8)."""
        a_t, a_p = self.a(t), self.a(t_prev)
        r = math.sqrt(1 - a_p) / math.sqrt(1 - a_t)
        return (x_prev - r * x_t) / (math.sqrt(a_p) - r * math.sqrt(a_t))

    def split(self, out: torch.Tensor, x_t: torch.Tensor, t: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Network output -> (eps, x0_pred), each computed the well-conditioned way for the prediction type."""
        a = self.a(t)
        if self.prediction == "eps":
            return out, (x_t - math.sqrt(1 - a) * out) / math.sqrt(a)
        if self.prediction == "x0":
            return (x_t - math.sqrt(a) * out) / math.sqrt(1 - a), out
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
        a_t, a_prev, beta = self.a(t), self.a(t - 1), self._betas[t]
        mean = (math.sqrt(a_prev) * beta / (1 - a_t)) * x0 + (math.sqrt(1 - beta) * (1 - a_prev) / (1 - a_t)) * x_t
        if t == 0:
            return mean
        var = beta * (1 - a_prev) / (1 - a_t)  # beta_tilde_t, eq. 7
        return mean + math.sqrt(var) * noise

    @staticmethod
    def needs_noise(sampler: str, t: int, t_prev: int, eta: float = 0.0) -> bool:
        """Whether `sampler`'s step (t, t_prev) adds noise (then `sample_step` takes it)."""
        return sampler == "ddpm" and t > 0 or sampler == "ddim" and eta > 0 and t_prev >= 0

    def sample_step(self, sampler: str, x_t: torch.Tensor, eps: torch.Tensor, x0: torch.Tensor, t: int, t_prev: int,
                    eta: float = 0.0, noise: torch.Tensor | None = None) -> torch.Tensor:
        """One step of `sampler` ("ddim" or "ddpm") from the network's (eps, x0) -> x_{t_prev}: every sampler's
        dispatch (the fast runner and its reference both step through it)."""
        if sampler == "ddpm":
            return self.ddpm_step(x_t, x0, t, noise)
        return self.ddim_step(x_t, eps, t, t_prev, eta, noise, x0=x0)[0]

    def sampling_pairs(self, sampler: str, steps: int) -> list[tuple[int, int]]:
        """The (t, t_prev) of each of `steps` sampler steps: the config's own DDIM timesteps when it has that
        many, else `ddim_pairs` at its spacing."""
        if sampler == "ddim":
            if self.timesteps is not None and len(self.timesteps) == steps:
                ts = list(self.timesteps)
                return list(zip(ts, ts[1:] + [-1]))
            return ddim_pairs(steps, self.N, self.spacing)
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
    return frame_noise_rows([seed], [frame_start], n_frames, step, dim, device)[0]


def _counters(values, device) -> torch.Tensor:
    """Seeds or frame indices (B,) as int64: a sequence of ints, or a tensor (in a traced graph, its inputs)."""
    if torch.is_tensor(values):
        return values.to(device=device, dtype=torch.int64)
    return torch.as_tensor(list(values), dtype=torch.int64, device=device)


def frame_noise_rows(seeds, frame_starts, n_frames: int, step: int, dim: int, device=None) -> torch.Tensor:
    """`frame_noise` of several streams at once: (B, n_frames, dim), row b that of (seeds[b], frame_starts[b]).

    seeds, frame_starts: sequences of ints or int64 tensors (B,) (the ONNX graph's inputs)."""
    seed = _counters(seeds, device)[:, None, None]  # (B, 1, 1)
    start = _counters(frame_starts, device)[:, None, None]
    frames = start + torch.arange(n_frames, dtype=torch.int64, device=device)[None, :, None]  # (B, n, 1)
    chans = torch.arange(dim, dtype=torch.int64, device=device)[None, None, :]
    h = torch.full((1, 1, 1), 0x9E3779B9, dtype=torch.int64, device=device)
    for key in (seed & _M32, (seed >> 32) & _M32, step & _M32):
        h = hash32(h ^ key)
    h = hash32(h ^ (frames & _M32))
    h = hash32(h ^ ((frames >> 32) & _M32))
    h = hash32(h ^ chans)  # (B, n_frames, dim)
    u1 = (hash32(h ^ 0x68E31DA4).double() + 0.5) / 2.0 ** 32  # (0, 1): log never sees 0
    u2 = (hash32(h ^ 0xB5297A4D).double() + 0.5) / 2.0 ** 32
    z = torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * math.pi * u2)
    return z.float()


def noise_kernel(taps: int) -> torch.Tensor:
    """(taps,) causal weights, newest first: a Hann bump scaled to unit L2 norm (so unit variance out)."""
    if taps == 1:
        return torch.ones(1, dtype=torch.float64)
    w = torch.sin(math.pi * (torch.arange(taps, dtype=torch.float64) + 1) / (taps + 1)) ** 2
    return w / w.norm()


def correlate(white: torch.Tensor, taps: int) -> torch.Tensor:
    """(..., n + taps - 1, D) white draws, oldest first -> (..., n, D): each frame a weighted sum of its last `taps`."""
    if taps == 1:
        return white
    k = noise_kernel(taps).to(white.device, white.dtype).flip(0)  # oldest first, to match unfold's order
    return (white.unfold(-2, taps, 1) * k).sum(-1)  # unfold -> (..., n, D, taps)


def motion_noise(seed: int, frame_start: int, n_frames: int, step: int, dim: int, taps: int = 1,
                 device=None) -> torch.Tensor:
    """(n_frames, dim) diffusion noise for frames [frame_start, frame_start + n): `frame_noise` correlated over
    `taps` frames. A pure function of (seed, frame index, step), so every window draws the same numbers."""
    return motion_noise_rows([seed], [frame_start], n_frames, step, dim, taps, device)[0]


def motion_noise_rows(seeds, frame_starts, n_frames: int, step: int, dim: int, taps: int = 1,
                      device=None) -> torch.Tensor:
    """`motion_noise` of several streams at once: (B, n_frames, dim), row b that of (seeds[b], frame_starts[b])."""
    starts = frame_starts - (taps - 1) if torch.is_tensor(frame_starts) else [f - taps + 1 for f in frame_starts]
    white = frame_noise_rows(seeds, starts, n_frames + taps - 1, step, dim, device)
    return white if taps == 1 else correlate(white.double(), taps).float()
