"""The DiM-Gestor network (Zhang et al.): fuzzy feature extractor + AdaLN Mamba-2 denoiser.

    audio feats (100 Hz) -> FuzzyFeatureExtractor -> c[t] per 20 fps frame
    x_t (noisy motion) -> causal Conv1D k=3 encoder -> N x AdaLNMamba2Block(c + emb(t)) -> final AdaLN
                       -> Conv1D k=1 decoder -> eps, v or x0 (config.prediction)

Everything on the motion side is causal, and every forward takes and returns its state as a value,
so running window by window gives the numbers of one whole-sequence run.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from ..config import ModelConfig
from ..frontend.base import build_frontend
from .mamba2 import Mamba2, Mamba2State

__all__ = ["DiMGestor", "AdaLNMamba2Block", "FuzzyFeatureExtractor", "FinalLayer", "GestureEncoder",
           "TimestepEmbedder", "ExtractorState", "DenoiserState", "modulate"]


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return torch.addcmul(shift, x, 1 + scale)  # x * (1 + scale) + shift, one op fewer per call


def _nbytes(t: torch.Tensor) -> int:
    return t.numel() * t.element_size()


class ExtractorState(NamedTuple):
    style: Mamba2State  # the style extractor's Mamba-2 state
    buf: torch.Tensor  # (B, F + S, m): features and style tokens not yet consumed by the downsampler


class DenoiserState(NamedTuple):
    enc: torch.Tensor  # (B, motion_dim, 2): the last two input frames of the causal k=3 encoder
    blocks: tuple[Mamba2State, ...]  # one per AdaLN Mamba-2 block

    def nbytes(self) -> int:
        return _nbytes(self.enc) + sum(s.nbytes() for s in self.blocks)


class TimestepEmbedder(nn.Module):
    """Diffusion step t -> sinusoidal features -> MLP (as in DiT)."""

    def __init__(self, hidden: int, freq_dim: int = 256):
        super().__init__()
        self.freq_dim = freq_dim
        self.mlp = nn.Sequential(nn.Linear(freq_dim, hidden), nn.SiLU(), nn.Linear(hidden, hidden))

    @staticmethod
    def sinusoid(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
        half = dim // 2
        freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
        args = t.float()[:, None] * freqs[None]
        return torch.cat([torch.cos(args), torch.sin(args)], dim=-1)  # (B, dim)

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.sinusoid(t, self.freq_dim))  # (B, hidden)


class Mlp(nn.Module):
    def __init__(self, hidden: int, ratio: float):
        super().__init__()
        inner = int(hidden * ratio)
        self.fc1, self.act, self.fc2 = nn.Linear(hidden, inner), nn.GELU(approximate="tanh"), nn.Linear(inner, hidden)

    def forward(self, x):
        return self.fc2(self.act(self.fc1(x)))


def _mamba(config: ModelConfig, d_model: int, d_state: int, headdim: int) -> Mamba2:
    return Mamba2(d_model, d_state=d_state, d_conv=config.d_conv, expand=config.expand, headdim=headdim,
                  chunk_size=config.chunk_size)


class AdaLNMamba2Block(nn.Module):
    """Algorithm 1 of the paper, adaLN-Zero per token: x += g1 * Mamba2(mod(LN x)); x += g2 * MLP(mod(LN x))."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        H = config.hidden
        self.norm1 = nn.LayerNorm(H, elementwise_affine=False, eps=1e-6)
        self.mixer = _mamba(config, H, config.d_state, config.headdim)
        self.norm2 = nn.LayerNorm(H, elementwise_affine=False, eps=1e-6)
        self.mlp = Mlp(H, config.mlp_ratio)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(H, 6 * H))

    def forward(self, x: torch.Tensor, c: torch.Tensor, state: Mamba2State | None = None
                ) -> tuple[torch.Tensor, Mamba2State]:
        shift1, scale1, gate1, shift2, scale2, gate2 = self.adaLN_modulation(c).chunk(6, dim=-1)  # (B, T, H) each
        h, state = self.mixer(modulate(self.norm1(x), shift1, scale1), state)
        x = torch.addcmul(x, gate1, h)  # x + g1 * h
        x = torch.addcmul(x, gate2, self.mlp(modulate(self.norm2(x), shift2, scale2)))
        return x, state


class FinalLayer(nn.Module):
    """Final AdaLN (shift/scale from the condition), then the Conv1D k=1 decoder to motion features."""

    def __init__(self, hidden: int, motion_dim: int):
        super().__init__()
        self.norm = nn.LayerNorm(hidden, elementwise_affine=False, eps=1e-6)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden, 2 * hidden))
        self.decoder = nn.Conv1d(hidden, motion_dim, kernel_size=1)

    def forward(self, x, c):
        x = modulate(self.norm(x), *self.adaLN_modulation(c).chunk(2, dim=-1))
        # the k=1 Conv1D as the matmul it is (CPU conv kernels cost ~0.4 ms a call on streaming windows)
        return F.linear(x, self.decoder.weight[:, :, 0], self.decoder.bias)  # (B, T, motion_dim)


class GestureEncoder(nn.Module):
    """Causal Conv1D k=3 over noisy motion frames; the last two inputs are the carried tail."""

    def __init__(self, motion_dim: int, hidden: int, kernel: int = 3):
        super().__init__()
        self.conv = nn.Conv1d(motion_dim, hidden, kernel_size=kernel)

    def zero_tail(self, batch: int, device=None, dtype=None) -> torch.Tensor:
        k = self.conv.kernel_size[0]
        return torch.zeros(batch, self.conv.in_channels, k - 1, device=device, dtype=dtype)

    def forward(self, x: torch.Tensor, tail: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        xs = torch.cat([tail, x.transpose(1, 2)], dim=2)  # (B, D, k-1 + T)
        new_tail = xs[:, :, xs.shape[2] - tail.shape[2]:].clone()  # not a view that keeps all of xs alive
        # the conv as one matmul over unfolded windows: same weights and numbers, far fewer ops per call
        windows = xs.unfold(2, self.conv.kernel_size[0], 1).transpose(1, 2).flatten(2)  # (B, T, D * k)
        w = self.conv.weight.flatten(1)  # (H, D * k), matching the unfolded (D, k) order
        return F.linear(windows, w, self.conv.bias), new_tail  # (B, T, H)


class FuzzyFeatureExtractor(nn.Module):
    """Audio features -> per-frame condition: global style (Mamba-2, running token) + local Conv1D downsampler.

    The feature sequence is left-padded with P = k - stride - lookahead zero frames, so the downsampler's
    window for motion frame t ends `lookahead` feature frames after the frame's own last one. The style
    token taken for frame t is the style extractor's output at that same last visible feature frame.
    Features and style tokens share one buffer, so a single tail carries both across windows.
    """

    def __init__(self, config: ModelConfig, feat_dim: int):
        super().__init__()
        self.feat_dim, self.S = feat_dim, config.style_width
        self.k, self.stride = config.down_kernel, config.feats_per_frame
        self.pad = config.down_kernel - config.feats_per_frame - config.lookahead_feats  # >= 0 (validated)
        self.style_in = nn.Linear(feat_dim, config.style_width)
        self.style = _mamba(config, config.style_width, config.style_d_state, config.style_headdim)
        self.style_out = nn.Linear(config.style_width, config.hidden)
        self.down = nn.Conv1d(feat_dim, config.hidden, kernel_size=self.k, stride=self.stride)

    def init_state(self, batch: int, device=None, dtype=None) -> ExtractorState:
        return ExtractorState(self.style.zero_state(batch, device, dtype),
                              torch.zeros(batch, self.feat_dim + self.S, self.pad, device=device, dtype=dtype))

    def forward(self, feats: torch.Tensor, state: ExtractorState | None = None
                ) -> tuple[torch.Tensor, ExtractorState]:
        """feats (B, n, F) -> (cond (B, T, hidden) for the frames that became complete, state)."""
        if state is None:
            state = self.init_state(feats.shape[0], feats.device, feats.dtype)
        if feats.shape[1] == 0:  # nothing new (the mixer needs L >= 1)
            s, style_state = feats.new_zeros(feats.shape[0], 0, self.S), state.style
        else:
            s, style_state = self.style(self.style_in(feats), state.style)  # (B, n, S): style so far
        buf = torch.cat([state.buf, torch.cat([feats, s], dim=-1).transpose(1, 2)], dim=2)  # (B, F+S, m+n)
        n_out = max((buf.shape[2] - self.k) // self.stride + 1, 0)
        if n_out == 0:
            return buf.new_zeros(buf.shape[0], 0, self.style_out.out_features), ExtractorState(style_state, buf)
        used = (n_out - 1) * self.stride + self.k
        feats_in = buf[:, : self.feat_dim, :used]
        if n_out <= 8:  # a streaming window: the conv as one matmul over its few windows (CPU conv2d costs ~0.2 ms)
            windows = feats_in.unfold(2, self.k, self.stride).transpose(1, 2).flatten(2)  # (B, n_out, F * k)
            down = F.linear(windows, self.down.weight.flatten(1), self.down.bias)  # (B, n_out, H)
        else:
            down = self.down(feats_in).transpose(1, 2)  # (B, n_out, H)
        last = buf[:, self.feat_dim:, self.k - 1: used: self.stride]  # (B, S, n_out): style at the last seen frame
        cond = down + self.style_out(last.transpose(1, 2))  # (B, n_out, H)
        return cond, ExtractorState(style_state, buf[:, :, n_out * self.stride:].clone())  # not a view of all of buf


class DiMGestor(nn.Module):
    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        # frames per denoiser pass on long sequences: a multiple of the SSD chunk, so the chunks (and the
        # numbers) are those of one whole pass; bounds the activations of an offline 100 s sequence
        self.segment_frames = 2 * config.chunk_size
        self.frontend = build_frontend(config)
        self.extractor = FuzzyFeatureExtractor(config, self.frontend.dim)
        self.t_embedder = TimestepEmbedder(config.hidden)
        self.encoder = GestureEncoder(config.motion_dim, config.hidden)
        self.blocks = nn.ModuleList([AdaLNMamba2Block(config) for _ in range(config.n_blocks)])
        self.final = FinalLayer(config.hidden, config.motion_dim)
        # the speaker condition (config.speakers): a vector per speaker added to every frame's condition; the
        # speaker a model plays by default is none (index -1: nothing added), `use_speaker` picks one
        self.speaker_embed = nn.Embedding(len(config.speakers), config.hidden) if config.speakers else None
        self.register_buffer("speaker_index", torch.tensor(-1, dtype=torch.long), persistent=False)
        if config.calibrated:  # (a distilled student's: `calibrate`)
            self.register_buffer("out_gain", torch.ones(config.motion_dim))
            self.register_buffer("out_shift", torch.zeros(config.motion_dim))
        self.initialize_weights()

    def initialize_weights(self):
        """DiT's adaLN-Zero init: zero every modulation and the decoder, so each block starts as the identity.

        The Mamba-2 mixers keep their own reference initialisation (dt, A_log, D).
        """
        def xavier(m: nn.Linear):
            nn.init.xavier_uniform_(m.weight)
            nn.init.zeros_(m.bias)

        for block in self.blocks:
            xavier(block.mlp.fc1)
            xavier(block.mlp.fc2)
            nn.init.zeros_(block.adaLN_modulation[-1].weight)
            nn.init.zeros_(block.adaLN_modulation[-1].bias)
        for m in (self.extractor.style_in, self.extractor.style_out):
            xavier(m)
        for m in self.t_embedder.mlp[::2]:
            nn.init.normal_(m.weight, std=0.02)
            nn.init.zeros_(m.bias)
        nn.init.zeros_(self.final.adaLN_modulation[-1].weight)
        nn.init.zeros_(self.final.adaLN_modulation[-1].bias)
        nn.init.zeros_(self.final.decoder.weight)
        nn.init.zeros_(self.final.decoder.bias)
        if self.speaker_embed is not None:  # (unit scale: the audio condition's own is far larger than DiT's 0.02)
            nn.init.normal_(self.speaker_embed.weight, std=1.0)

    # ---- condition side ----
    def condition(self, feats: torch.Tensor, state: ExtractorState | None = None,
                  speaker: torch.Tensor | None = None):
        """Audio features (B, n, F) -> (c (B, T, hidden), ExtractorState).

        With a speaker condition, each row's speaker vector is added: `speaker` (B,) indices into
        config.speakers, -1 for none; without it, the model's own (`use_speaker`, none by default)."""
        cond, state = self.extractor(feats, state)
        if self.speaker_embed is None:
            return cond, state
        if speaker is None:
            speaker = self.speaker_index.expand(cond.shape[0])
        vec = self.speaker_embed(speaker.clamp_min(0)) * (speaker >= 0).to(cond.dtype)[:, None]
        return cond + vec[:, None, :], state

    @property
    def speaker(self) -> str | None:
        """The speaker the model plays (`use_speaker`), None for none in particular."""
        k = int(self.speaker_index)
        return None if k < 0 else self.config.speakers[k]

    def use_speaker(self, name: str | None) -> None:
        """Play `name` (one of config.speakers), or no speaker (None: the speaker-agnostic model)."""
        self.speaker_index.fill_(self.speaker_number(name))

    def speaker_number(self, name: str | None) -> int:
        """`name`'s index in config.speakers (None: -1, no speaker in particular); ValueError naming the speakers
        this model knows for any other name."""
        if name is None:
            return -1
        if name not in self.config.speakers:
            known = ", ".join(self.config.speakers) or "none: it was trained without --speaker-condition"
            raise ValueError(f"speaker {name!r}: this model knows {known}")
        return self.config.speakers.index(name)

    def samples_needed(self, n_frames: int) -> int:
        """Audio samples after which the condition for `n_frames` motion frames exists."""
        c = self.config
        return self.frontend.samples_needed(n_frames * c.feats_per_frame + c.lookahead_feats) if n_frames else 0

    @property
    def lookahead_s(self) -> float:
        """Algorithmic latency: audio that must arrive after a frame's start before the frame exists."""
        return (self.samples_needed(1)) / self.config.sample_rate

    # ---- denoiser ----
    def init_state(self, batch: int, device=None, dtype=None) -> DenoiserState:
        return DenoiserState(self.encoder.zero_tail(batch, device, dtype),
                             tuple(b.mixer.zero_state(batch, device, dtype) for b in self.blocks))

    def forward(self, x: torch.Tensor, t: torch.Tensor | int, cond: torch.Tensor,
                state: DenoiserState | None = None) -> tuple[torch.Tensor, DenoiserState]:
        """x (B, T, motion_dim) noisy frames at step t, cond (B, T, hidden) -> (eps, v or x0 (B, T, motion_dim), state).

        A sequence longer than `segment_frames` runs segment by segment carrying the state (window by
        window equals the whole), so activation memory stays that of one segment at any length.
        """
        B, T = x.shape[:2]
        if state is None:
            state = self.init_state(B, x.device, x.dtype)
        if not torch.is_tensor(t):
            t = torch.full((B,), int(t), device=x.device, dtype=torch.long)
        seg = self.segment_frames
        if T <= seg:
            return self._denoise(x, t, cond, state)
        outs, carry = [], [state]
        del state  # each segment's state is handed over as its only reference, so it is freed block by block
        for a in range(0, T, seg):
            out, new = self._denoise(x[:, a:a + seg], t, cond[:, a:a + seg], carry.pop())
            outs.append(out)
            carry.append(new)
            del new
        return torch.cat(outs, dim=1), carry[0]

    def _denoise(self, x, t, cond, state: DenoiserState) -> tuple[torch.Tensor, DenoiserState]:
        c = cond + self.t_embedder(t)[:, None, :]  # (B, T, H): diffusion-step embedding added to the condition
        h, enc_tail = self.encoder(x, state.enc)
        old = list(state.blocks)
        del state
        block_states = []
        for j, block in enumerate(self.blocks):
            s, old[j] = old[j], None  # the block's old state goes once its new one exists
            h, s = block(h, c, s)
            block_states.append(s)
        return self.final(h, c), DenoiserState(enc_tail, tuple(block_states))

    def calibrate(self, x: torch.Tensor) -> torch.Tensor:
        """The sampled motion (..., motion_dim) as the model gives it: a distilled student's rescaled per feature
        (config.calibrated: x * out_gain + out_shift, measured against its teacher by `dimgestor distill`);
        any other model's as it is."""
        return torch.addcmul(self.out_shift.to(x.dtype), x, self.out_gain.to(x.dtype)) if self.config.calibrated else x

    # ---- bookkeeping for `dimgestor info` ----
    def param_counts(self) -> dict[str, int]:
        n = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
        ex = self.extractor
        return {
            "frontend": n(self.frontend),
            "style_extractor": n(ex.style_in) + n(ex.style) + n(ex.style_out),
            "downsampler": n(ex.down),
            "step_embedder": n(self.t_embedder),
            "denoiser_blocks": n(self.blocks),
            "encoder_decoder": n(self.encoder) + n(self.final),
        }

    def stream_state_nbytes(self, steps: int) -> dict[str, int]:
        """Bytes of carried state per stream (float32) for `steps` denoising steps."""
        fe = self.frontend.init_state(1)
        ex = self.extractor.init_state(1)
        c = self.config
        # the front-end tail and the extractor buffer vary in length; count their largest size
        if c.frontend == "pretrained":
            fe_bytes = (fe.tail.shape[1] + self.frontend.block + self.frontend.right) * 4
        else:
            fe_bytes = (fe.tail.shape[1] + c.hop_length) * 4 + (fe.nbytes() - fe.tail.numel() * 4
                                                                if hasattr(fe, "nbytes") else 0)
        ex_bytes = ex.style.nbytes() + ex.buf.shape[1] * (self.extractor.k - 1) * 4
        per_step = self.init_state(1).nbytes()
        return {"frontend": fe_bytes, "extractor": ex_bytes, "denoiser_per_step": per_step,
                "denoiser_all_steps": per_step * steps, "total": fe_bytes + ex_bytes + per_step * steps}
