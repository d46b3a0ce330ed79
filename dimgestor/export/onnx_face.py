"""The face's listener (`dimgestor.face.net`) as an ONNX graph beside the body's: `face_step.onnx`.

Called like the body's graph, once per call of M frames' new samples, with its state carried in and out:

    samples (1, S), frame (1,), tail, mean, in_0..in_6, res_1..res_6, head  ->  visemes (M, 15), opening (M,),
                                                                                 <state>_out...

    tail       the last TAIL samples before the call (a 10 ms frame reads 25 ms)
    mean       each band's running mean (float64), the features' normalisation
    in_j       convolution j's input frames its taps still need, res_j the residual frames layer j adds back
    head       the last 2 SMOOTH 10 ms outputs (a face frame is the triangle-weighted mean over +-SMOOTH)

`frame` is the index of the call's first 10 ms frame, (call * S - TAIL_AHEAD) / HOP: negative frames are before
the stream and count as silence outside it, as in the engine's stream. A call makes the face frames whose 10 ms
outputs are complete: those of the call `DELAY_CALLS` before it; the first `DELAY_CALLS` calls' frames are
dropped. The numbers are the engine's stream's to float rounding (`tests/test_onnx_face.py`); the spectra are
matrix products (a DFT basis), so no runtime needs a DFT op.

What the graph gives is what the network hears; the engine's face (`FaceStream`) makes the mouth from it
(`_mouth_heard`: shapes by probability, the jaw by the opening and the lips' closure) and adds the loudness scale,
blinks and brows (docs/face.md).
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..face.net import (CLASSES, HOP, LAYERS, N_MELS, NFFT, NORM_S, RATE, RIGHT, SMOOTH, WIN, load_weights,
                        weights_meta)

__all__ = ["FaceStep", "export_face", "FACE_GRAPH", "FACE_MANIFEST"]

FACE_GRAPH = "face_step.onnx"
FACE_MANIFEST = "face_manifest.json"
OPSET = 18  # the body's graph's (onnx_export.OPSET; tests/test_onnx_face.py checks they agree)


class FaceStep(nn.Module):
    """`frames` face frames (at `fps`) a call of the listener, with explicit state (module docstring)."""

    def __init__(self, fps: int, frames: int, weights: str | None = None):
        super().__init__()
        from ..face.net import mel_filters

        net = load_weights(weights)
        w = net.w
        self.fps, self.frames = int(fps), int(frames)
        self.every = RATE // HOP // self.fps
        self.mels = self.frames * self.every
        if self.every * self.fps * HOP != RATE:
            raise ValueError(f"the face's graph needs a frame rate that divides 100: {fps} fps does not")
        self.samples = self.mels * HOP
        # call n completes the 10 ms frames t0 .. t0 + mels - 1, t0 = n * mels + offset (frame t reads the samples
        # t HOP - WIN/2 .. t HOP + WIN/2); it reads `tail` samples from before the call
        self.offset = (self.samples - WIN // 2) // HOP + 1 - self.mels
        self.tail = WIN // 2 - self.offset * HOP
        # the face frames it makes: centres every * i in [t0 - RIGHT - SMOOTH, t0 - RIGHT + mels - 1 - SMOOTH]
        first = -(-(self.offset - RIGHT - SMOOTH) // self.every) * self.every
        self.first_frame = first // self.every                      # of call 0 (negative: dropped)
        self.first_pos = first - (self.offset - RIGHT - 2 * SMOOTH)  # its centre's row in the head's sequence
        n, k = np.arange(WIN), np.arange(NFFT // 2 + 1)
        window = np.hanning(WIN + 1)[:WIN, None]
        self.register_buffer("cos", torch.tensor(window * np.cos(2 * np.pi * np.outer(n, k) / NFFT)))
        self.register_buffer("sin", torch.tensor(window * np.sin(2 * np.pi * np.outer(n, k) / NFFT)))
        self.register_buffer("fbank", torch.tensor(mel_filters()))
        for j in range(len(LAYERS)):
            self.register_buffer(f"conv{j}_w", torch.tensor(w[f"conv{j}.weight"]))
            self.register_buffer(f"conv{j}_b", torch.tensor(w[f"conv{j}.bias"]))
            if j:
                self.register_buffer(f"norm{j}_w", torch.tensor(w[f"norm{j}.weight"]))
                self.register_buffer(f"norm{j}_b", torch.tensor(w[f"norm{j}.bias"]))
        self.register_buffer("head_w", torch.tensor(w["head.weight"][:, :, 0]))
        self.register_buffer("head_b", torch.tensor(w["head.bias"]))
        self.register_buffer("prior", torch.tensor(net.prior, dtype=torch.float64))
        self.register_buffer("triangle", torch.tensor([1.0 + SMOOTH - abs(i) for i in range(-SMOOTH, SMOOTH + 1)],
                                                      dtype=torch.float64))
        self.channels = int(w["conv0.weight"].shape[0])

    def first_mel(self, call: int) -> int:
        """The `frame` input of call `call`."""
        return call * self.mels + self.offset

    def face_frame(self, call: int) -> int:
        """The first face frame call `call` gives (its `frames` frames from there; below 0: dropped)."""
        return self.first_frame + call * self.frames

    # -- state ------------------------------------------------------------------------------------------------
    def initial_state(self) -> dict[str, torch.Tensor]:
        out = {"tail": torch.zeros(1, self.tail), "mean": self.prior.clone()}
        for j, (k, d, _) in enumerate(LAYERS):
            out[f"in_{j}"] = torch.zeros((k - 1) * d, N_MELS if j == 0 else self.channels)
        for j, (_, _, r) in enumerate(LAYERS[1:], 1):
            out[f"res_{j}"] = torch.zeros(r, self.channels)
        out["head"] = torch.zeros(2 * SMOOTH, len(CLASSES) + 1)
        return out

    # -- the call ---------------------------------------------------------------------------------------------
    def forward(self, samples, frame, tail, mean, *state):
        n = len(LAYERS)
        ins, res, head_state = list(state[:n]), [None, *state[n:2 * n - 1]], state[2 * n - 1]
        x = torch.cat([tail, samples], dim=1)[0].double()
        frames = x[:(self.mels - 1) * HOP + WIN].unfold(0, WIN, HOP)             # (mels, WIN)
        re, im = frames @ self.cos, frames @ self.sin
        mel = torch.log((re * re + im * im) @ self.fbank + 1e-8)                # (mels, N_MELS)
        t = frame.double() + torch.arange(self.mels, dtype=torch.float64)      # each new frame's index
        a = 1.0 / (NORM_S * RATE / HOP)
        m, rows = mean, []
        for i in range(self.mels):                                              # (unrolled: fixed shapes)
            m = m + a * (t[i] >= 0).double() * (mel[i] - m)                    # (before the stream: not counted)
            rows.append(mel[i] - m)
        h = torch.stack(rows).float()
        ins_out, res_out, shift = [], [], 0
        for j, (k, d, r) in enumerate(LAYERS):
            live = ((t - shift) >= 0).float()[:, None]                           # this layer's inputs inside the stream
            conv_in = h if j == 0 else nn.functional.layer_norm(h, (self.channels,), getattr(self, f"norm{j}_w"),
                                                                getattr(self, f"norm{j}_b"), 1e-5)
            seq = torch.cat([ins[j], conv_in * live])                            # ((k-1) d + mels, C_in)
            y = nn.functional.conv1d(seq.T[None], getattr(self, f"conv{j}_w"), getattr(self, f"conv{j}_b"),
                                     dilation=d)[0].T                            # (mels, C): frames t - shift - r
            g = nn.functional.gelu(y, approximate="tanh")
            ins_out.append(seq[self.mels:])
            if j == 0:
                h = g
            else:
                raw = torch.cat([res[j], h])                                     # (r + mels, C)
                h = raw[:self.mels] + g
                res_out.append(raw[self.mels:])
            shift += r
        o = h @ self.head_w.T + self.head_b                                     # frames t - RIGHT
        seq = torch.cat([head_state, o])                                        # from t0 - RIGHT - 2 SMOOTH
        index = frame.double() - RIGHT - 2 * SMOOTH + torch.arange(seq.shape[0], dtype=torch.float64)
        p = torch.softmax(seq[:, :len(CLASSES)].double(), -1)
        opening = seq[:, -1].double().clamp(0, 1)
        vis, ope = [], []
        for f in range(self.frames):
            c = self.first_pos + f * self.every
            lo, hi = c - SMOOTH, c + SMOOTH + 1
            kk = self.triangle * (index[lo:hi] >= 0).double()
            kk = kk / kk.sum().clamp(min=1e-12)
            vis.append(kk @ p[lo:hi])
            ope.append(kk @ opening[lo:hi])
        return (torch.stack(vis).float(), torch.stack(ope).clamp(0, 1).float(), x[None, -self.tail:].float(), m,
                *ins_out, *res_out, seq[-2 * SMOOTH:])


def export_face(out: Path, fps: int, frames: int, weights: str | None = None) -> Path:
    """out/face_step.onnx and out/face_manifest.json: the face's listener for calls of `frames` frames."""
    import onnx

    step = FaceStep(fps, frames, weights).eval()
    state = step.initial_state()
    names = list(state)
    example = (torch.zeros(1, step.samples), torch.zeros(1, dtype=torch.int64), *state.values())
    out = Path(out)
    with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(step, example, input_names=["samples", "frame", *names],
                                    output_names=["visemes", "opening", *(f"{n}_out" for n in names)],
                                    opset_version=OPSET, dynamo=True, external_data=False, optimize=False, verbose=False)
    program.save(str(out / FACE_GRAPH))
    onnx.checker.check_model(str(out / FACE_GRAPH))
    manifest = {
        "format": 1, "graph": FACE_GRAPH, "opset": OPSET, "fps": step.fps, "frames_per_call": step.frames,
        "samples_per_call": step.samples, "sample_rate": RATE, "visemes": list(CLASSES),
        "frame": {"per_call": step.mels, "offset": step.offset,
                  "rule": "call n: frame = n * per_call + offset (int64, shape (1,))"},
        "face_frames": {"first": step.first_frame,
                        "rule": "call n gives face frames first + n * frames_per_call, ...: drop those below 0; "
                                "after the audio's end, call with zeros until the last frame is given"},
        "state": [{"input": n, "output": f"{n}_out", "shape": list(t.shape),
                   "dtype": str(t.dtype).removeprefix("torch."),
                   "init": step.prior.tolist() if n == "mean" else 0.0} for n, t in state.items()],
        "weights": json.loads(json.dumps(weights_meta(weights)))}
    (out / FACE_MANIFEST).write_text(json.dumps(manifest, indent=1))
    return out
