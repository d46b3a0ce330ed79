"""Baseline denoiser: AdaLN-Transformer (Persona-Gestor-like) with DiM-Gestor's condition path.

Persona-Gestor (Zhang et al. 2024) is the Transformer predecessor of DiM-Gestor: the same fuzzy feature
extractor and adaLN-Zero conditioning, but self-attention over the whole sequence instead of a Mamba-2
mixer. `AdaLNTransformer` keeps everything of `DiMGestor` (front end, FuzzyFeatureExtractor, step
embedder, causal Conv1D encoder, final AdaLN + decoder, width, MLP) and swaps only the blocks, so a
comparison measures the mixer. It has the same call signature, so `generate_offline` samples from it;
it carries no state (attention needs the whole sequence), so it cannot stream window by window.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from ..config import ModelConfig
from .network import DiMGestor, Mlp, modulate

__all__ = ["AdaLNAttentionBlock", "AdaLNTransformer", "rotary"]


def rotary(x: torch.Tensor, base: float = 10000.0) -> torch.Tensor:
    """Rotary position embedding (Su et al. 2021) on x (B, heads, T, d): relative positions, any length."""
    T, d = x.shape[-2], x.shape[-1]
    half = d // 2
    freqs = base ** (-torch.arange(half, device=x.device, dtype=torch.float32) / half)
    angles = torch.arange(T, device=x.device, dtype=torch.float32)[:, None] * freqs[None]  # (T, d/2)
    cos, sin = angles.cos().to(x.dtype), angles.sin().to(x.dtype)
    x1, x2 = x[..., :half], x[..., half : 2 * half]
    rotated = torch.cat([x1 * cos - x2 * sin, x1 * sin + x2 * cos], dim=-1)
    return torch.cat([rotated, x[..., 2 * half :]], dim=-1)


class SelfAttention(nn.Module):
    """Bidirectional multi-head self-attention over the whole sequence, rotary positions.

    `impl="sdpa"` uses torch's fused kernel (flash / memory-efficient where available, so the (T, T)
    score matrix is not always stored); `impl="naive"` materializes softmax(QK^T / sqrt d) as a plain
    Transformer implementation does.
    """

    def __init__(self, hidden: int, n_heads: int, impl: Literal["sdpa", "naive"] = "sdpa"):
        super().__init__()
        if hidden % n_heads:
            raise ValueError(f"hidden {hidden} is not a multiple of n_heads {n_heads}")
        if impl not in ("sdpa", "naive"):
            raise ValueError(f"unknown attention impl {impl!r}; choose 'sdpa' or 'naive'")
        self.n_heads, self.impl = n_heads, impl
        self.qkv = nn.Linear(hidden, 3 * hidden)
        self.proj = nn.Linear(hidden, hidden)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, T, H = x.shape
        q, k, v = self.qkv(x).view(B, T, 3, self.n_heads, H // self.n_heads).permute(2, 0, 3, 1, 4)  # (B, h, T, d)
        q, k = rotary(q), rotary(k)
        if self.impl == "sdpa":
            y = F.scaled_dot_product_attention(q, k, v)
        else:
            att = (q @ k.transpose(-2, -1)) * q.shape[-1] ** -0.5  # (B, h, T, T)
            y = att.softmax(dim=-1) @ v
        return self.proj(y.transpose(1, 2).reshape(B, T, H))


class AdaLNAttentionBlock(nn.Module):
    """DiT block with per-token adaLN-Zero: x += g1 * Attn(mod(LN x)); x += g2 * MLP(mod(LN x))."""

    def __init__(self, config: ModelConfig, n_heads: int, impl: str = "sdpa"):
        super().__init__()
        H = config.hidden
        self.norm1 = nn.LayerNorm(H, elementwise_affine=False, eps=1e-6)
        self.attn = SelfAttention(H, n_heads, impl)
        self.norm2 = nn.LayerNorm(H, elementwise_affine=False, eps=1e-6)
        self.mlp = Mlp(H, config.mlp_ratio)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(H, 6 * H))

    def forward(self, x: torch.Tensor, c: torch.Tensor, state: None = None) -> tuple[torch.Tensor, None]:
        shift1, scale1, gate1, shift2, scale2, gate2 = self.adaLN_modulation(c).chunk(6, dim=-1)  # (B, T, H) each
        x = x + gate1 * self.attn(modulate(self.norm1(x), shift1, scale1))
        x = x + gate2 * self.mlp(modulate(self.norm2(x), shift2, scale2))
        return x, None


class AdaLNTransformer(DiMGestor):
    """DiM-Gestor with its AdaLN Mamba-2 blocks replaced by `n_blocks` AdaLN attention blocks."""

    streams = False  # attention over the whole sequence: offline generation only

    def __init__(self, config: ModelConfig, n_blocks: int = 6, n_heads: int | None = None, impl: str = "sdpa"):
        config = config.model_copy(update={"n_blocks": n_blocks})
        super().__init__(config)
        n_heads = n_heads or max(1, config.hidden // 64)  # 64-wide heads, as DiT and GPT use
        self.blocks = nn.ModuleList([AdaLNAttentionBlock(config, n_heads, impl) for _ in range(n_blocks)])
        self.initialize_weights()  # adaLN-Zero for the new blocks (same attribute names as the Mamba-2 block)
        for block in self.blocks:
            nn.init.xavier_uniform_(block.attn.qkv.weight)
            nn.init.zeros_(block.attn.qkv.bias)
            nn.init.xavier_uniform_(block.attn.proj.weight)
            nn.init.zeros_(block.attn.proj.bias)

    def init_state(self, batch: int, device=None, dtype=None):
        return None  # nothing to carry: every call sees the whole sequence

    def forward(self, x: torch.Tensor, t: torch.Tensor | int, cond: torch.Tensor, state: None = None
                ) -> tuple[torch.Tensor, None]:
        """x (B, T, motion_dim) at step t, cond (B, T, hidden) -> (eps or v (B, T, motion_dim), None)."""
        if state is not None:
            raise ValueError("AdaLNTransformer attends over the whole sequence and cannot continue from a state")
        B = x.shape[0]
        if not torch.is_tensor(t):
            t = torch.full((B,), int(t), device=x.device, dtype=torch.long)
        c = cond + self.t_embedder(t)[:, None, :]  # (B, T, H)
        h, _ = self.encoder(x, self.encoder.zero_tail(B, x.device, x.dtype))
        for block in self.blocks:
            h, _ = block(h, c)
        return self.final(h, c), None

    def stream_state_nbytes(self, steps: int) -> dict[str, int]:
        raise NotImplementedError("AdaLNTransformer does not stream: attention needs the whole sequence")


def denoiser_params(model: nn.Module) -> int:
    """Parameters of the denoiser path (step embedder, encoder, blocks, final layer), without the condition path."""
    parts = (model.t_embedder, model.encoder, model.blocks, model.final)
    return sum(p.numel() for m in parts for p in m.parameters())
