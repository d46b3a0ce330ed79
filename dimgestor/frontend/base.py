"""Audio front ends: 16 kHz samples -> 100 Hz feature frames, incrementally, with state as a value.

Both front ends share one contract: `forward(samples, state) -> (feats, state)`, where feeding the
audio in any chunking yields the same frames as feeding it at once, and `samples_needed(n)` says
how much audio must have arrived before `n` frames exist (the front end's share of the latency). A state is
a NamedTuple of tensors with one stream per row (dim 0) and a `consumed` count the forward only adds to, so
the states of many streams stack into one batched call and split back (`dimgestor.model.conditioning`).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import torch
from torch import nn

from ..config import ModelConfig, exact_div
from .mel import mel_filterbank
from .speech import SpeechFrontEnd

__all__ = ["AudioFrontEnd", "LogMelFrontEnd", "PretrainedFrontEnd", "FrontEndState", "build_frontend"]


class FrontEndState(NamedTuple):
    tail: torch.Tensor  # (B, m) samples received but not yet consumed by a complete frame/block
    consumed: int  # frames (LogMel) or blocks (pretrained) already emitted


class AudioFrontEnd(nn.Module):
    """Interface: incremental audio features at `config.feature_rate`."""

    dim: int  # feature channels F

    def init_state(self, batch: int, device=None) -> FrontEndState:
        raise NotImplementedError

    def forward(self, samples: torch.Tensor, state: FrontEndState) -> tuple[torch.Tensor, FrontEndState]:
        """samples (B, N) float32 -> (feats (B, n, F), new state)."""
        raise NotImplementedError

    def samples_needed(self, n_feats: int) -> int:
        """Fewest input samples after which `n_feats` feature frames have been emitted."""
        raise NotImplementedError


class LogMelFrontEnd(AudioFrontEnd):
    """Streaming log-mel: frame i covers the `win_length` samples ending at sample (i+1)*hop.

    The first frames see zeros before the start (the initial tail), so frame i exists as soon as
    (i+1)*hop samples have arrived: no lookahead at all.
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.hop, self.win, self.n_fft = config.hop_length, config.win_length, config.n_fft
        self.dim = config.n_mels
        self.register_buffer("window", torch.hann_window(self.win, periodic=True), persistent=False)
        self.register_buffer("fb", mel_filterbank(config.n_mels, config.n_fft, config.sample_rate),
                             persistent=False)

    def init_state(self, batch: int, device=None) -> FrontEndState:
        return FrontEndState(torch.zeros(batch, self.win - self.hop, device=device), 0)

    def forward(self, samples, state):
        buf = torch.cat([state.tail, samples.to(state.tail)], dim=1)  # (B, m + N)
        n = max((buf.shape[1] - (self.win - self.hop)) // self.hop, 0)
        if n == 0:
            return buf.new_zeros(buf.shape[0], 0, self.dim), FrontEndState(buf, state.consumed)
        frames = buf.unfold(1, self.win, self.hop)[:, :n]  # (B, n, win)
        spec = torch.fft.rfft(frames * self.window, n=self.n_fft)  # (B, n, n_fft//2+1)
        mel = (spec.real.square() + spec.imag.square()) @ self.fb  # (B, n, n_mels)
        # log10 power scaled as whisper does so speech lands roughly in [-1, 1.5]; silence is -1.
        feats = (torch.log10(mel.clamp(min=1e-8)) + 4.0) / 4.0
        return feats, FrontEndState(buf[:, n * self.hop:], state.consumed + n)

    def samples_needed(self, n_feats: int) -> int:
        return n_feats * self.hop


class PretrainedFrontEnd(AudioFrontEnd):
    """A local wav2vec2/HuBERT encoder run on fixed blocks with left/right context.

    Block b covers samples [b*S, (b+1)*S) and is encoded from [b*S - left, (b+1)*S + right]
    (zeros before the start), so offline and streaming see identical windows. The encoder's
    50 Hz frames are repeated to `feature_rate`. Weights are never downloaded (local_files_only).
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        path = Path(config.pretrained_path or "")
        if not path.is_dir():
            raise FileNotFoundError(f"pretrained front end: {path} is not a local model folder "
                                    "(a wav2vec2/HuBERT folder with config.json and weights)")
        try:
            from transformers import AutoConfig, AutoModel
        except ImportError as e:
            raise ImportError("the pretrained front end needs `transformers`: pip install 'dimgestor[pretrained]'") from e
        hf_config = AutoConfig.from_pretrained(path, local_files_only=True)
        self.encoder = AutoModel.from_pretrained(path, local_files_only=True).eval()
        self.encoder.requires_grad_(False)  # a frozen feature extractor, as in the paper
        stride = math.prod(hf_config.conv_stride)
        self.receptive = self._receptive_field(hf_config.conv_kernel, hf_config.conv_stride)
        sr = config.sample_rate
        self.block = exact_div(config.pretrained_block_ms * sr, 1000, "pretrained block samples")
        self.left = exact_div(config.pretrained_left_ms * sr, 1000, "pretrained left context samples")
        self.right = exact_div(config.pretrained_right_ms * sr, 1000, "pretrained right context samples")
        self.stride = stride
        exact_div(self.block, stride, "pretrained block / encoder stride")
        exact_div(self.left, stride, "pretrained left context / encoder stride")
        # encoder frames per second = sr / stride (50 Hz); repeat each to reach feature_rate (100 Hz)
        self.repeat = exact_div(config.feature_rate * stride, sr, "feature_rate / encoder frame rate")
        if self.right < self.receptive - stride:
            raise ValueError(f"pretrained_right_ms too small: the block's last encoder frame needs "
                             f"{self.receptive - stride} samples beyond the block")
        self.normalize = bool(getattr(hf_config, "feat_extract_norm", "group") == "layer")
        self.dim = hf_config.hidden_size

    @staticmethod
    def _receptive_field(kernels, strides) -> int:
        r, jump = 1, 1
        for k, s in zip(kernels, strides):
            r += (k - 1) * jump
            jump *= s
        return r

    def init_state(self, batch: int, device=None) -> FrontEndState:
        return FrontEndState(torch.zeros(batch, self.left, device=device), 0)

    def forward(self, samples, state):
        buf = torch.cat([state.tail, samples.to(state.tail)], dim=1)  # starts at block_start - left
        span = self.left + self.block + self.right  # samples one block's encoder window needs
        nb = max((buf.shape[1] - span) // self.block + 1, 0)
        if nb == 0:
            return buf.new_zeros(buf.shape[0], 0, self.dim), FrontEndState(buf, state.consumed)
        windows = buf.unfold(1, span, self.block)[:, :nb]  # (B, nb, span)
        B = windows.shape[0]
        w = windows.reshape(B * nb, span)
        if self.normalize:  # wav2vec2 "layer" models expect zero-mean unit-variance input per window
            w = (w - w.mean(1, keepdim=True)) / torch.sqrt(w.var(1, keepdim=True, unbiased=False) + 1e-7)
        with torch.no_grad():
            h = self.encoder(w).last_hidden_state  # (B*nb, frames, dim); frame j starts at sample j*stride
        first = self.left // self.stride
        h = h[:, first:first + self.block // self.stride]  # frames that start inside the block
        h = h.reshape(B, nb * h.shape[1], self.dim).repeat_interleave(self.repeat, dim=1)
        return h, FrontEndState(buf[:, nb * self.block:], state.consumed + nb)

    def samples_needed(self, n_feats: int) -> int:
        per_block = self.block // self.stride * self.repeat
        blocks = -(-n_feats // per_block)
        return 0 if blocks == 0 else blocks * self.block + self.right

    def train(self, mode: bool = True):
        super().train(mode)
        self.encoder.eval()  # dropout off always: features must not depend on train/eval mode
        return self


def build_frontend(config: ModelConfig) -> AudioFrontEnd:
    if config.frontend == "logmel":
        return LogMelFrontEnd(config)
    if config.frontend == "speech":
        return SpeechFrontEnd(config)
    if config.frontend == "embedding":
        from .embed import EmbeddingFrontEnd
        return EmbeddingFrontEnd(config)
    return PretrainedFrontEnd(config)
