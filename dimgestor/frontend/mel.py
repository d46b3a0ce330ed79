"""The mel filterbank both spectral front ends project their power spectra through (`frontend`, `frontend_speech`)."""
from __future__ import annotations

import torch

from dimgestor.audio import mel_weights

__all__ = ["mel_filterbank"]


def mel_filterbank(n_mels: int, n_fft: int, sample_rate: int, f_min: float = 0.0,
                   f_max: float | None = None) -> torch.Tensor:
    """(n_fft//2+1, n_mels) triangular HTK-mel filters, area-normalised (Slaney): built here, no download
    (`dimgestor.audio.mel_weights` as a float32 tensor)."""
    return torch.from_numpy(mel_weights(n_mels, n_fft, sample_rate, f_min, f_max))
