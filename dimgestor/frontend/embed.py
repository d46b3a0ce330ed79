"""The speech front end plus a pretrained speech embedding (Google's speech_embedding, as openWakeWord ships it).

Issue "real voices": a listener that hears speech rather than a speaker. The embedding model was trained by Google
on a large amount of speech to tell words apart whoever says them (Lin et al. 2020, "Training keyword spotters
with limited and synthesized speech data"); openWakeWord 0.5.1 ships it, with its mel front end, as two small
ONNX files inside its wheel (`openwakeword/resources/models/`). Here they run through ONNX Runtime:

    mel        32 log-mel bands every 10 ms over 512 samples (openWakeWord's scaling: x / 10 + 2)
    embedding  96 numbers every 80 ms from the last 76 mel frames (775 ms of audio)

Frame i of this front end is the speech front end's frame i (level-free bands and prosody: `SpeechFrontEnd`)
followed by the latest embedding whose 76 mel frames end at or before frame i: causal, no lookahead, held for
8 frames. Every mel frame and every embedding is computed by a call of its own, so any chunking of the audio
gives bit-identical features (streamed = offline).
"""
from __future__ import annotations

import hashlib
import importlib.util
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from ..config import ModelConfig
from .speech import SpeechFrontEnd, SpeechState

__all__ = ["EmbeddingFrontEnd", "EmbeddingState", "EMBED_DIM", "model_files"]

MEL_WIN = 512  # samples per mel frame (openWakeWord's melspectrogram.onnx)
MEL_BANDS = 32
EMBED_FRAMES = 76  # mel frames per embedding
EMBED_STEP = 8  # mel frames between embeddings (80 ms)
EMBED_DIM = 96
EMBED_SCALE = 0.03  # the embedding's numbers have an sd of about 17 on speech: scaled to the speech channels' ~0.5


# The two files as openWakeWord 0.5.1's wheel ships them (sha256, from its RECORD): another release's copy or a
# damaged one is refused rather than run. The package is only their carrier: its code is never imported, so it can
# be installed without its dependencies (its `tflite-runtime` has no wheel for Python 3.12 and later).
MODEL_SHA256 = {"melspectrogram.onnx": "ba2b0e0f8b7b875369a2c89cb13360ff53bac436f2895cced9f479fa65eb176f",
                "embedding_model.onnx": "70d164290c1d095d1d4ee149bc5e00543250a7316b59f31d056cff7bd3075c1f"}
INSTALL = "pip install --no-deps openwakeword==0.5.1"


def model_files() -> tuple[Path, Path]:
    """(melspectrogram.onnx, embedding_model.onnx) from the installed openwakeword package, checked by checksum."""
    spec = importlib.util.find_spec("openwakeword")  # (finds the package without running its __init__)
    if spec is None or not spec.submodule_search_locations:
        raise ImportError(f"frontend 'embedding' needs openwakeword 0.5.1's wheel, which carries the speech "
                          f"embedding's ONNX files: {INSTALL} (and ONNX Runtime: pip install 'dimgestor[embedding]')")
    root = Path(list(spec.submodule_search_locations)[0]) / "resources" / "models"
    files = tuple(root / name for name in MODEL_SHA256)
    for f in files:
        if not f.is_file():
            raise FileNotFoundError(f"{f} is missing: openwakeword 0.5.1 ships it in its wheel (0.6 downloads it): "
                                    f"{INSTALL}")
        if hashlib.sha256(f.read_bytes()).hexdigest() != MODEL_SHA256[f.name]:
            raise ValueError(f"{f} is not the file openwakeword 0.5.1 ships (its sha256 differs): {INSTALL}")
    return files


@lru_cache(maxsize=None)
def _sessions():
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads = 1, 1
    so.log_severity_level = 3
    mel, emb = model_files()
    return (ort.InferenceSession(str(mel), so, providers=["CPUExecutionProvider"]),
            ort.InferenceSession(str(emb), so, providers=["CPUExecutionProvider"]))


def mel_frames(rows: np.ndarray) -> np.ndarray:
    """(n, 512) float32 samples in [-1, 1] -> (n, 32) scaled log-mel, each row on its own."""
    if not len(rows):
        return np.zeros((0, MEL_BANDS), np.float32)
    mel, _ = _sessions()
    x = np.ascontiguousarray(rows * 32768.0, np.float32)
    # one call per frame: the graph clips its decibels relative to the loudest value of its whole input (a
    # top_db floor), so frames computed together would depend on their neighbours, and on the chunking
    out = np.stack([mel.run(None, {"input": x[i:i + 1]})[0].reshape(MEL_BANDS) for i in range(len(x))])
    return (out / 10.0 + 2.0).astype(np.float32)


def embeddings(windows: np.ndarray) -> np.ndarray:
    """(n, 76, 32) scaled mel windows -> (n, 96)."""
    if not len(windows):
        return np.zeros((0, EMBED_DIM), np.float32)
    _, emb = _sessions()
    x = np.ascontiguousarray(windows[..., None], np.float32)
    # one call per window: ONNX Runtime's kernels may round differently for another batch size
    return np.stack([emb.run(None, {"input_1": x[i:i + 1]})[0].reshape(EMBED_DIM) for i in range(len(x))])


class EmbeddingState(NamedTuple):
    speech: SpeechState
    tail: torch.Tensor  # (B, MEL_WIN - hop) the samples before the next mel frame's last hop
    mel: torch.Tensor  # (B, EMBED_FRAMES - 1, 32) the last mel frames
    emb: torch.Tensor  # (B, 96) the latest embedding
    consumed: int  # frames emitted

    def nbytes(self) -> int:
        return self.speech.nbytes() + sum(t.numel() * t.element_size() for t in (self.tail, self.mel, self.emb))


class EmbeddingFrontEnd(nn.Module):
    """`SpeechFrontEnd` channels + the held speech embedding: (B, n, speech.dim + 96) at `feature_rate`."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        if config.sample_rate != 16000 or config.hop_length != 160:
            raise ValueError("frontend 'embedding' runs at 16 kHz with a 10 ms hop (the embedding's own framing), "
                             f"got {config.sample_rate} Hz, hop {config.hop_length}")
        self.speech = SpeechFrontEnd(config)
        self.hop = config.hop_length
        self.dim = self.speech.dim + EMBED_DIM
        silence = mel_frames(np.zeros((1, MEL_WIN), np.float32))[0]
        self._silent_mel = silence
        self._silent_emb = embeddings(np.broadcast_to(silence, (1, EMBED_FRAMES, MEL_BANDS)))[0]

    def init_state(self, batch: int, device=None) -> EmbeddingState:
        mel = torch.from_numpy(np.broadcast_to(self._silent_mel, (batch, EMBED_FRAMES - 1, MEL_BANDS)).copy())
        emb = torch.from_numpy(np.broadcast_to(self._silent_emb, (batch, EMBED_DIM)).copy())
        return EmbeddingState(self.speech.init_state(batch, device), torch.zeros(batch, MEL_WIN - self.hop),
                              mel, emb, 0)

    def samples_needed(self, n_feats: int) -> int:
        return self.speech.samples_needed(n_feats)

    def forward(self, samples: torch.Tensor, state: EmbeddingState) -> tuple[torch.Tensor, EmbeddingState]:
        feats, speech = self.speech(samples, state.speech)
        n, B = feats.shape[1], feats.shape[0]
        buf = torch.cat([state.tail, samples.detach().float().cpu()], 1).numpy()
        if n == 0:
            return feats.new_zeros(B, 0, self.dim), state._replace(speech=speech, tail=torch.from_numpy(buf))
        rows = np.lib.stride_tricks.sliding_window_view(buf, MEL_WIN, axis=1)[:, : n * self.hop: self.hop]  # (B, n, 512)
        mel = mel_frames(rows.reshape(B * n, MEL_WIN)).reshape(B, n, MEL_BANDS)
        hist = np.concatenate([state.mel.numpy(), mel], 1)  # (B, 75 + n, 32): frame i of this call at 75 + i
        ends = [i for i in range(n) if (state.consumed + i + 1) % EMBED_STEP == 0]  # frames that end an embedding
        held = np.repeat(state.emb.numpy()[:, None], n, 1)  # (B, n, 96)
        if ends:
            wins = np.stack([hist[:, i:i + EMBED_FRAMES] for i in ends], 1)  # (B, m, 76, 32): frame i is at 75 + i
            e = embeddings(wins.reshape(-1, EMBED_FRAMES, MEL_BANDS)).reshape(B, len(ends), EMBED_DIM)
            for j, i in enumerate(ends):
                held[:, i:] = e[:, j:j + 1]
        out = torch.cat([feats, torch.from_numpy(held * EMBED_SCALE).to(feats)], -1)
        return out, EmbeddingState(speech, torch.from_numpy(np.ascontiguousarray(buf[:, n * self.hop:])),
                                   torch.from_numpy(np.ascontiguousarray(hist[:, -(EMBED_FRAMES - 1):])),
                                   torch.from_numpy(np.ascontiguousarray(held[:, -1])), state.consumed + n)
