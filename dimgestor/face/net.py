"""The face's own listener: a small network that hears the mouth in the stream's audio (issue 49).

Every 10 ms it reads 40 log-mel bands of the last 25 ms of audio, each band's level taken against its running
mean (an exponential average over `NORM_S`, starting from the training speech's mean), and gives the 15 visemes'
probabilities and the jaw's opening. The network is seven convolutions over time (one of kernel 5, six residual
ones of kernel 3, dilated up to 16; 96 channels, ~0.19 M weights) that look `LEFT` frames back and `RIGHT` frames
ahead: a frame's mouth is known 0.13 s after its time (`LOOKAHEAD_S`), inside the body's own lookahead (300 ms for
the default model, 150 ms for the live one), so the face adds no latency.

Streams equal the whole recording exactly: features and every layer step on the stream's absolute 10 ms clock and
are computed once each, in steps whose sizes are set by that clock and the frame rate (not by how the audio came),
and the whole recording is made by the same stepping (`NetListener.offline`). The weights ship in the package
(`listener.safetensors`, trained by `benchmarks/face_net.py`, where its data and measurements are).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from dimgestor.face.visemes import VISEMES

__all__ = ["NetListener", "ListenerNet", "Heard", "LOOKAHEAD_S", "WEIGHTS", "CLASSES", "OUTPUTS", "log_mel",
           "normalise", "load_weights", "save_weights", "weights_meta", "torch_listener", "LAYERS", "RIGHT", "LEFT",
           "N_MELS", "HOP", "RATE", "WIN", "NFFT", "SMOOTH", "NORM_S", "mel_filters"]

RATE, HOP, WIN, NFFT, N_MELS = 16000, 160, 400, 512, 40
NORM_S = 3.0                        # the running mean's time constant
# (kernel, dilation, frames ahead) of each convolution; the first one maps the bands in, the others are residual
LAYERS = ((5, 1, 2), (3, 1, 1), (3, 2, 2), (3, 4, 4), (3, 8, 0), (3, 16, 0), (3, 1, 1))
RIGHT = sum(r for _, _, r in LAYERS)                                  # 10 frames ahead
LEFT = sum((k - 1) * d - r for k, d, r in LAYERS)                      # 58 frames back
SMOOTH = 2                          # a face frame is the triangle-weighted mean of the 10 ms frames +-SMOOTH
LOOKAHEAD_S = ((RIGHT + SMOOTH) * HOP + WIN // 2) / RATE              # 0.1325 s
WEIGHTS = Path(__file__).with_name("listener.safetensors")
CLASSES = VISEMES
OUTPUTS = len(CLASSES) + 1          # the visemes' logits, then the jaw's opening


@lru_cache(maxsize=1)
def mel_filters() -> np.ndarray:
    from dimgestor.audio import mel_weights

    return mel_weights(N_MELS, NFFT, RATE, 50.0, 7600.0).astype(np.float64)


@lru_cache(maxsize=1)
def _window() -> np.ndarray:
    return np.hanning(WIN + 1)[:WIN]   # periodic Hann


def log_mel(audio: np.ndarray, first: int = 0, count: int | None = None, offset: int = 0) -> np.ndarray:
    """(count, N_MELS) log mel power of frames first.. (frame t: the samples t * HOP - WIN/2 .. t * HOP + WIN/2 of
    the stream, zeros before its start); `audio` holds the stream's samples from index `offset` on."""
    audio = np.asarray(audio, np.float64)
    if count is None:
        count = max(0, (offset + len(audio) - WIN // 2) // HOP + 1 - first)
    lo = (first * HOP - WIN // 2) - offset
    need = lo + (count - 1) * HOP + WIN
    pad_l = max(0, -lo)
    x = np.concatenate([np.zeros(pad_l), audio[max(lo, 0):need]])
    if len(x) < need - lo:
        raise ValueError(f"log_mel: frames up to {first + count - 1} need samples up to {need + offset}")
    frames = np.lib.stride_tricks.sliding_window_view(x, WIN)[::HOP][:count]
    power = np.abs(np.fft.rfft(frames * _window(), NFFT)) ** 2
    return np.log(power @ mel_filters() + 1e-8)


def normalise(mel: np.ndarray, state: np.ndarray | None, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each band against its running mean (exponential, `NORM_S`); `state` the mean before these frames (None: the
    prior). Computed frame by frame in float64, so any split of the frames gives the same numbers."""
    a = 1.0 / (NORM_S * RATE / HOP)
    m = np.array(prior if state is None else state, np.float64)
    out = np.empty(mel.shape, np.float32)
    for t, row in enumerate(np.asarray(mel, np.float64)):
        m += a * (row - m)
        out[t] = row - m
    return out, m


class ListenerNet:
    """The network's weights as `NetListener` reads them: each convolution as one matrix over its taps, the head's
    matrix, the normalisation's prior."""

    def __init__(self, weights: dict[str, np.ndarray]):
        self.w = weights
        self.prior = weights["prior"].astype(np.float64)
        # each convolution as one matrix over its taps, tap-major: (k * C_in, C_out)
        convs = [weights[f"conv{j}.weight"] for j in range(len(LAYERS))]
        self.mats = [np.ascontiguousarray(w.transpose(2, 1, 0).reshape(-1, w.shape[0])) for w in convs]
        self.head = np.ascontiguousarray(weights["head.weight"][:, :, 0].T)
        self.channels = int(convs[0].shape[0])

    def layer(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """Convolution j: its (k * C_in, C_out) matrix and bias."""
        return self.mats[j], self.w[f"conv{j}.bias"]


@dataclass
class Heard:
    """One face frame's mouth as the network hears it: viseme probabilities (15,), the jaw's opening."""

    visemes: np.ndarray
    opening: float


def _layernorm(h: np.ndarray, g: np.ndarray, b: np.ndarray) -> np.ndarray:
    mu = h.mean(-1, keepdims=True)
    var = ((h - mu) ** 2).mean(-1, keepdims=True)
    return (h - mu) / np.sqrt(var + 1e-5) * g + b


def _gelu(x: np.ndarray) -> np.ndarray:
    """GELU, tanh form (torch's approximate="tanh"), in x's precision."""
    inner = x * x
    inner *= np.float32(0.044715)
    inner += np.float32(1.0)
    inner *= x
    inner *= np.float32(0.7978845608028654)
    np.tanh(inner, out=inner)
    inner += np.float32(1.0)
    inner *= x
    inner *= np.float32(0.5)
    return inner


@lru_cache(maxsize=4)
def load_weights(path: str | None = None) -> ListenerNet:
    from safetensors.numpy import load_file

    p = Path(path) if path else WEIGHTS
    if not p.is_file():
        raise FileNotFoundError(f"{p}: the face listener's weights are not there")
    w = load_file(str(p))
    return ListenerNet({k: v.astype(np.float32) if k != "prior" else v for k, v in w.items()})


def weights_meta(path: str | None = None) -> dict:
    from safetensors import safe_open

    with safe_open(str(path or WEIGHTS), "np") as f:
        return json.loads((f.metadata() or {}).get("training", "{}"))


class NetListener:
    """Push 16 kHz audio (the stream's, from `start_sample`); `ready` holds (frame index, Heard) for each face
    frame (fps) whose LOOKAHEAD_S of audio is in. `late`: frame i shows what was heard that many 10 ms frames
    before its time (for a caller whose lookahead is shorter than the network's)."""

    def __init__(self, fps: int, *, start_sample: int = 0, start_frame: int = 0, weights: str | None = None,
                 frames_per_step: int = 1, late: int = 0):
        self.fps, self.group, self.late = fps, int(frames_per_step), int(late)
        self.net = load_weights(weights)
        mel_filters(), _window()  # (built once a process, here: not in the first frame's time)
        self.audio = np.zeros(0, np.float64)      # the stream's samples from audio_at on
        self.audio_at = self.audio_end = start_sample
        # the first 10 ms frame whose samples were all heard; the ones before it are zeros to the network
        self.first_mel = -(-(start_sample + WIN // 2) // HOP) if start_sample else 0
        self.next_mel = self.first_mel
        self.norm_state = None
        # each layer's inputs (normalised) and residual inputs, from frame ins_at[j] on: zeros before the start,
        # as far back as its first output's taps reach
        back = [(k - 1) * d - r for k, d, r in LAYERS]
        width = [N_MELS] + [self.net.channels] * (len(LAYERS) - 1)
        self.ins = [np.zeros((b, c), np.float32) for b, c in zip(back, width)]
        self.raws = [np.zeros((b, c), np.float32) for b, c in zip(back, width)]
        self.ins_at = [self.first_mel - b for b in back]   # the frame index of ins[j][0] and raws[j][0]
        self.made = [self.first_mel] * len(LAYERS)        # each layer's next output frame
        self.out = np.zeros((0, OUTPUTS), np.float32)  # the head's outputs, from out_at on
        self.out_at = self.first_mel
        self.next_frame = start_frame
        self.ready: list[tuple[int, Heard]] = []
        self.pending: list[np.ndarray] = []      # steps' normalised bands not yet through the network, in order
        self.to_emit: list[int] = []             # face frames to make once they are

    @staticmethod
    def late_frames(lookahead_s: float) -> int:
        """With less lookahead than the network's, how many 10 ms frames late the mouth follows the sound."""
        return max(0, int(math.ceil((LOOKAHEAD_S - lookahead_s) * RATE / HOP - 1e-9)))

    @staticmethod
    def frames_per_step(fps: float, lookahead_s: float) -> int:
        """How many face frames one step can make when a frame may wait `lookahead_s` for its audio: fewer,
        larger steps cost less (a step's fixed cost is most of a frame's)."""
        return max(1, int(math.floor((lookahead_s - LOOKAHEAD_S) * fps + 1e-9)) + 1)

    @classmethod
    def offline(cls, audio: np.ndarray, fps: int, weights: str | None = None, frames_per_step: int = 1) -> list[Heard]:
        """Every face frame of a whole recording (the same steps a stream takes)."""
        listener = cls(fps, weights=weights, frames_per_step=frames_per_step)
        listener.push(audio)
        listener.finish(int(math.ceil(len(audio) / RATE * fps - 1e-9)))
        return [h for _, h in listener.ready]

    # -- audio in ---------------------------------------------------------------------------------------------
    def push(self, samples: np.ndarray, run: bool = True) -> None:
        """Hear `samples`; run=False leaves the network's steps pending, for `run_many` to run with other streams'."""
        samples = np.asarray(samples, np.float64).reshape(-1)
        self.audio = np.concatenate([self.audio, samples])
        self.audio_end += len(samples)
        # steps of `group` face frames on the stream's clock (frames g * group .. g * group + group - 1)
        while self._due(last := (self.next_frame // self.group + 1) * self.group - 1) <= self.audio_end:
            last_mel = self._centre(last) + SMOOTH + RIGHT
            if last_mel >= self.next_mel:
                self.pending.append(self._mel_step(last_mel + 1))
            self.to_emit.extend(range(self.next_frame, last + 1))
            self.next_frame = last + 1
        cut = (self.next_mel * HOP - WIN // 2) - self.audio_at  # (the audio of the next 10 ms frame on)
        if cut > 16000:
            self.audio, self.audio_at = self.audio[cut:], self.audio_at + cut
        if run:
            NetListener.run_many([self])

    @staticmethod
    def run_many(listeners: list["NetListener"]) -> None:
        """The pending steps of several streams' listeners through the network together (one matrix product per
        layer for all of them, each stream's steps in its own order), then their frames made. Each stream's
        numbers are those it gets alone wherever the matrix product gives a row the same result in any batch."""
        rounds = max((len(x.pending) for x in listeners), default=0)
        for k in range(rounds):  # (a stream's k-th step with the others' k-th: the steps a stream takes alone)
            _layers_many([x for x in listeners if len(x.pending) > k],
                         [x.pending[k] for x in listeners if len(x.pending) > k])
        for x in listeners:
            x.pending = []
            x._emit(x.to_emit)
            x.to_emit = []
            x._trim()

    def finish(self, frames: int) -> None:
        """The audio ended: every face frame before `frames` made (silence heard after the end)."""
        if self.next_frame < frames:
            last = ((frames - 1) // self.group + 1) * self.group - 1
            self.push(np.zeros(max(0, self._due(last) - self.audio_end)))
        self.ready = [(i, h) for i, h in self.ready if i < frames]

    def close(self) -> None:
        """Nothing to give back (the interface of the pocketsphinx listener)."""

    def _due(self, frame: int) -> int:
        """The stream's sample count at which face frame `frame`'s mouth can be made."""
        return (self._centre(frame) + SMOOTH + RIGHT) * HOP + WIN // 2

    def _centre(self, frame: int) -> int:
        """The 10 ms frame at face frame `frame`'s time."""
        return int(math.floor(frame * (RATE / HOP) / self.fps + 0.5)) - self.late

    # -- the network ------------------------------------------------------------------------------------------
    def _mel_step(self, upto: int) -> np.ndarray:
        """The normalised bands of 10 ms frames next_mel..upto - 1 (the network's next step's input)."""
        mel = log_mel(self.audio, self.next_mel, upto - self.next_mel, offset=self.audio_at)
        x, self.norm_state = normalise(mel, self.norm_state, self.net.prior)
        self.next_mel = upto
        return x

    def _taps(self, j: int, h: np.ndarray, conv_in: np.ndarray) -> np.ndarray | None:
        """Layer j takes in new input rows (conv_in; h: the residual's) -> the (n, k * C_in) taps of the outputs
        whose taps are all in now (None: none are)."""
        k, d, r = LAYERS[j]
        self.ins[j] = np.concatenate([self.ins[j], conv_in])
        if j:
            self.raws[j] = np.concatenate([self.raws[j], h])
        upto = self.ins_at[j] + len(self.ins[j]) - r       # outputs whose taps are all in: [made, upto)
        n = upto - self.made[j]
        if n <= 0:
            return None
        a = self.made[j] + r - (k - 1) * d - self.ins_at[j]  # the first output's first tap; tap i is i * d later
        return np.concatenate([self.ins[j][a + i * d:a + i * d + n] for i in range(k)], axis=1)

    def _layer_out(self, j: int, g: np.ndarray) -> np.ndarray:
        """Layer j's new outputs from their activations g (the residual added after the first layer)."""
        n = len(g)
        h = g if j == 0 else (self.raws[j][self.made[j] - self.ins_at[j]:self.made[j] + n - self.ins_at[j]] + g)
        self.made[j] += n
        return h

    def _emit(self, frames: list[int]) -> None:
        """Face frames -> `ready`: each the triangle-weighted mean of the 10 ms frames +-SMOOTH around its time
        (those heard: a resumed stream's first frames have fewer), probabilities and opening."""
        if not frames:
            return
        c = np.array([self._centre(f) for f in frames])[:, None]
        idx = c + np.arange(-SMOOTH, SMOOTH + 1)[None, :]                   # (F, 2 * SMOOTH + 1)
        k = np.where(idx >= self.first_mel, 1.0 + SMOOTH - np.abs(idx - c), 0.0)
        total = k.sum(1, keepdims=True)
        k = k / np.where(total > 0, total, 1.0)
        out = self.out if len(self.out) else np.zeros((1, OUTPUTS), np.float32)  # (none heard yet: weights 0)
        rows = out[np.clip(idx - self.out_at, 0, len(out) - 1)].astype(np.float64)  # (F, 5, OUTPUTS)
        p = np.exp(rows[..., :-1] - rows[..., :-1].max(-1, keepdims=True))
        p /= p.sum(-1, keepdims=True)
        visemes = (k[..., None] * p).sum(1)
        opening = np.clip((np.clip(rows[..., -1], 0, 1) * k).sum(1), 0, 1)
        for f, t, v, o in zip(frames, total[:, 0], visemes, opening):
            # (a resumed stream's frames before its first heard audio: silence)
            self.ready.append((f, Heard(v, float(o)) if t > 0 else Heard(np.eye(len(CLASSES))[0], 0.0)))

    def _trim(self) -> None:
        """Keep what the next steps read: each layer's taps back from its next output, the head's outputs back
        from the next frame's smoothing."""
        for j, (k, d, r) in enumerate(LAYERS):
            keep_from = self.made[j] + r - (k - 1) * d
            cut = keep_from - self.ins_at[j]
            if cut > 64:
                self.ins[j] = self.ins[j][cut:]
                if j:
                    self.raws[j] = self.raws[j][cut:]
                self.ins_at[j] = keep_from
        cut = self._centre(self.next_frame) - SMOOTH - self.out_at
        if cut > 64:
            self.out, self.out_at = self.out[cut:], self.out_at + cut


def _split(x: np.ndarray, sizes: list[int]) -> list[np.ndarray]:
    return np.split(x, np.cumsum(sizes)[:-1]) if len(sizes) > 1 else [x]


def _layers_many(listeners: list[NetListener], xs: list[np.ndarray]) -> None:
    """One step of each listener (its new rows of normalised bands, xs) through every layer and the head, the
    streams' rows stacked into one product per layer; a stream whose layer has no new output this step goes no
    further (its next step carries on)."""
    net = listeners[0].net
    w, hs, live = net.w, list(xs), list(listeners)
    for j in range(len(LAYERS)):
        W, b = net.layer(j)                                   # (k * C_in, C_out), (C_out,)
        if j:
            normed = _layernorm(np.concatenate(hs) if len(hs) > 1 else hs[0], w[f"norm{j}.weight"],
                                w[f"norm{j}.bias"]).astype(np.float32)
            ins = _split(normed, [len(h) for h in hs])
        else:
            ins = hs
        taps = [x._taps(j, h, c) for x, h, c in zip(live, hs, ins)]
        live = [x for x, t in zip(live, taps) if t is not None]
        taps = [t for t in taps if t is not None]
        if not live:
            return
        y = (np.concatenate(taps) if len(taps) > 1 else taps[0]) @ W + b
        g = _gelu(y).astype(np.float32)
        hs = [x._layer_out(j, gi) for x, gi in zip(live, _split(g, [len(t) for t in taps]))]
    o = ((np.concatenate(hs) if len(hs) > 1 else hs[0]) @ net.head + w["head.bias"]).astype(np.float32)
    for x, oi in zip(live, _split(o, [len(h) for h in hs])):
        x.out = np.concatenate([x.out, oi]) if len(x.out) else oi


def torch_listener(channels: int = 96):
    """The same network in torch, for training and export: (B, T, N_MELS) normalised bands -> (B, T, OUTPUTS),
    frame t's output from frames t - LEFT .. t + RIGHT (zeros outside the input). `weights()` gives what
    `NetListener` reads."""
    import torch
    import torch.nn as nn
    import torch.nn.functional as F

    class TorchListener(nn.Module):
        def __init__(self):
            super().__init__()
            self.convs = nn.ModuleList([nn.Conv1d(N_MELS if j == 0 else channels, channels, k, dilation=d)
                                        for j, (k, d, _) in enumerate(LAYERS)])
            self.norms = nn.ModuleList([nn.LayerNorm(channels) for _ in LAYERS[1:]])
            self.head = nn.Conv1d(channels, OUTPUTS, 1)
            self.register_buffer("prior", torch.zeros(N_MELS, dtype=torch.float64))

        def forward(self, x):  # (B, T, N_MELS)
            h = x
            for j, (conv, (k, d, r)) in enumerate(zip(self.convs, LAYERS)):
                inp = h if j == 0 else self.norms[j - 1](h)
                y = conv(F.pad(inp.transpose(1, 2), ((k - 1) * d - r, r))).transpose(1, 2)
                h = F.gelu(y, approximate="tanh") if j == 0 else h + F.gelu(y, approximate="tanh")
            return self.head(h.transpose(1, 2)).transpose(1, 2)

        def weights(self) -> dict:
            out = {"prior": self.prior.detach().cpu().numpy().astype(np.float64),
                   "head.weight": self.head.weight.detach().cpu().numpy(), "head.bias": self.head.bias.detach().cpu().numpy()}
            for j, conv in enumerate(self.convs):
                out[f"conv{j}.weight"] = conv.weight.detach().cpu().numpy()
                out[f"conv{j}.bias"] = conv.bias.detach().cpu().numpy()
            for j, norm in enumerate(self.norms, 1):
                out[f"norm{j}.weight"] = norm.weight.detach().cpu().numpy()
                out[f"norm{j}.bias"] = norm.bias.detach().cpu().numpy()
            return out

    return TorchListener()


def save_weights(model, path: Path, training: dict) -> None:
    from safetensors.numpy import save_file

    w = {k: np.ascontiguousarray(v) for k, v in model.weights().items()}
    save_file(w, str(path), metadata={"training": json.dumps(training)})
