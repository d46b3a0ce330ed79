"""I/O-free streaming generation, and the offline path it must equal.

`GestureStream.push(samples)` takes audio in chunks of any size and returns the motion frames whose
condition became complete, each denoised through all sampler steps at once (batched over the new
frames). For every step it carries the denoiser's state (encoder tail + each block's Mamba-2 state);
the front end and the feature extractor carry theirs. Noise is `motion_noise(seed, frame, step)`, so
the frames equal those of `generate_offline` on the whole recording. With classifier-free guidance
(scale != 1) the unconditional branch carries its own per-step states beside the conditional one's.

All of that is one value, `StreamState`; `GestureStream.step(state, samples) -> (frames, state)` is the
stream as a function (it never writes into the state it is given), and `push` / `finish` step the state
the stream holds. `dimgestor.streaming.batch.step_many` maps the step over the states of many streams at once; the
step's parts (`dimgestor.model.conditioning`, then `dimgestor.model.sampler`) are functions of states, shared by both.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from ..audio import check_audio
from ..config import ModelConfig
from ..model.conditioning import Conditioned, condition
from ..model.diffusion import Diffusion, check_guidance, guide, motion_noise
from ..model.network import DenoiserState, DiMGestor, ExtractorState
from ..model.sampler import StepStates, Window, denoise, runner_for
from ..smoothing import OneEuroFilter, OneEuroState

__all__ = ["MODEL_SPEAKER", "GestureStream", "StreamState", "generate_offline", "make_smoother", "sample_frames"]


def sample_frames(model: DiMGestor, diffusion: Diffusion, cond: torch.Tensor, frame_start: int,
                  states: list[DenoiserState | None], pairs: list[tuple[int, int]], seed: int,
                  sampler: str, eta: float, guidance: float = 1.0) -> tuple[torch.Tensor, list[DenoiserState]]:
    """Denoise frames [frame_start, frame_start + n) given cond (1, n, H); one carried state per step.

    guidance != 1: classifier-free guidance; the unconditional branch (the condition zeroed) is row 1 of
    every step's state and of the network's batch, beside the conditional row 0. At 1 it does not exist.
    """
    n, D, dev = cond.shape[1], model.config.motion_dim, cond.device
    L = model.config.noise_taps
    guided = guidance != 1.0
    if guided:
        cond = torch.cat([cond, torch.zeros_like(cond)])  # (2, n, H): conditional, unconditional
    x = motion_noise(seed, frame_start, n, 0, D, L, dev)[None]  # x_T, (1, n, D)
    new_states = []
    for i, ((t, t_prev), state) in enumerate(zip(pairs, states)):
        out, state = model(x.expand(2, -1, -1) if guided else x, t, cond, state)
        if guided:
            out = guide(out[:1], out[1:], guidance)
        new_states.append(state)
        eps, x0 = diffusion.split(out, x, t)
        noisy = diffusion.needs_noise(sampler, t, t_prev, eta)
        noise = motion_noise(seed, frame_start, n, i + 1, D, L, dev)[None] if noisy else None
        x = diffusion.sample_step(sampler, x, eps, x0, t, t_prev, eta, noise)
    return model.calibrate(x[0]), new_states


def make_smoother(config: ModelConfig, smoothing="config") -> OneEuroFilter | None:
    """The output filter: "config" (the model config's smooth_hz/smooth_beta), None or 0 (off), a cutoff
    in Hz (with the config's beta), or a (cutoff_hz, beta) pair. A config, not a model: the ONNX Runtime
    stream (`dimgestor.export.onnx_stream`) has no torch model."""
    c = config
    if isinstance(smoothing, str):
        if smoothing != "config":
            raise ValueError(f"smoothing must be 'config', None, a cutoff in Hz or (cutoff_hz, beta), got {smoothing!r}")
        hz, beta = c.smooth_hz, c.smooth_beta
    elif smoothing is None:
        return None
    elif isinstance(smoothing, (tuple, list)):
        hz, beta = smoothing
    else:
        hz, beta = float(smoothing), c.smooth_beta
    return OneEuroFilter(c.fps, hz, beta) if hz else None


MODEL_SPEAKER = object()  # GestureStream's default speaker: the model's own (`DiMGestor.use_speaker`)


def _device(model: torch.nn.Module) -> torch.device:
    return next(model.parameters()).device


@dataclass(frozen=True)
class StreamState:
    """Everything a stream carries from one push to the next: a value. `GestureStream.step` returns a new one
    and never writes into the one it was given, so a state can be kept, compared or stepped again."""

    frontend: Any  # the audio front end's state (`AudioFrontEnd.init_state`)
    extractor: ExtractorState  # the feature extractor's
    denoiser: StepStates  # every sampler step's denoiser state; 2 rows when guided (conditional, unconditional)
    smoother: OneEuroState | None = None  # the output filter's (None: no frame filtered yet, or no filter)
    samples_in: int = 0  # audio samples received (the audio clock)
    frames_out: int = 0  # frames returned; frame i is presented at i / fps on the audio clock
    finished: bool = False

    def conditioned(self, c: Conditioned, samples: int) -> "StreamState":
        """This state with its front end and extractor moved on to `c` by `samples` more samples heard."""
        return replace(self, frontend=c.frontend, extractor=c.extractor, samples_in=self.samples_in + samples)


class GestureStream:
    """Audio chunks in, final motion frames (normalized features) out; no I/O, no threads.

    The stream's settings (model, schedule, seed, guidance, output filter, speaker) and its `state`. `step(state,
    samples) -> (frames, state)` is the stream as a function; `push` and `finish` step the state it holds.
    """

    def __init__(self, model: DiMGestor, steps: int | None = None, seed: int = 0, sampler: str = "ddim",
                 eta: float = 0.0, smoothing="config", guidance: float | None = None,
                 speaker: str | None | object = MODEL_SPEAKER):
        if not getattr(model, "streams", True):
            raise ValueError(f"{type(model).__name__} cannot stream: it carries no state between windows "
                             "(use generate_offline on the whole recording)")
        self.model, self.seed, self.sampler, self.eta = model, int(seed), sampler, float(eta)
        # the speaker it plays, of a model trained with a speaker condition: a name, None for none in particular,
        # MODEL_SPEAKER for the model's own (`DiMGestor.use_speaker`) as it is now; fixed for the stream's life
        self.speaker = model.speaker if speaker is MODEL_SPEAKER else speaker
        self.speaker_index = model.speaker_number(self.speaker)  # (ValueError for a name the model does not know)
        # classifier-free guidance scale (None: the config's); != 1 adds an unconditional row to the state
        self.guidance = check_guidance(model.config.guidance if guidance is None else guidance)
        self.diffusion = Diffusion(model.config)
        self.pairs = self.diffusion.sampling_pairs(sampler, steps or model.config.sample_steps)
        self.smoother = make_smoother(model.config, smoothing)
        self.runner = runner_for(model, self.pairs, sampler, eta)  # shared: streams of one runner batch together
        self.state = self.initial_state()

    def initial_state(self) -> StreamState:
        m, dev = self.model, _device(self.model)
        rows = 1 if self.guidance == 1.0 else 2
        return StreamState(m.frontend.init_state(1, dev), m.extractor.init_state(1, dev),
                           StepStates.zeros(m, len(self.pairs), rows, dev))

    @property
    def lookahead_s(self) -> float:
        """Algorithmic latency: audio needed after a frame's start before that frame is final."""
        return self.model.lookahead_s

    @property
    def samples_in(self) -> int:
        return self.state.samples_in

    @property
    def frames_out(self) -> int:
        return self.state.frames_out

    @property
    def finished(self) -> bool:
        return self.state.finished

    def begin_step(self, state: StreamState, samples) -> tuple[torch.Tensor, StreamState]:
        """`step`'s first half: checks, the audio clock, and the condition (1, n, H) of the n frames the samples
        complete (`dimgestor.streaming.batch.begin_many` does it for many streams, conditioned in groups)."""
        samples = self.check_step(state, samples)
        c = condition(self.model, state.frontend, state.extractor, samples, self.speaker_index)
        return c.cond, state.conditioned(c, len(samples))

    def check_step(self, state: StreamState, samples) -> np.ndarray:
        """`begin_step`'s checks: the samples as mono float32, or the error of a finished stream or bad audio."""
        if state.finished:
            raise RuntimeError("push() after finish(): start a new GestureStream")
        return check_audio(samples)

    def end_step(self, state: StreamState, frames: torch.Tensor | None, denoiser: StepStates
                 ) -> tuple[np.ndarray, StreamState]:
        """`step`'s last half: the denoised frames (n, D) (None: no new frame) and the denoiser state after them
        -> the returned frames (output filter applied) and the state; the frame clock moves on."""
        if frames is None:
            return np.zeros((0, self.model.config.motion_dim), np.float32), replace(state, denoiser=denoiser)
        out, smoothed = frames.float().cpu().numpy(), state.smoother
        if self.smoother is not None:
            out, smoothed = self.smoother.step(smoothed, out)
        return out, replace(state, denoiser=denoiser, smoother=smoothed, frames_out=state.frames_out + len(out))

    def window(self, state: StreamState, cond: torch.Tensor) -> Window:
        """What the sampler needs to denoise the frames of `cond` (1, n, H) after `state` (`dimgestor.model.sampler`)."""
        return Window(cond, state.denoiser, state.frames_out, self.seed, self.guidance)

    def _denoise(self, state: StreamState, cond: torch.Tensor) -> tuple[np.ndarray, StreamState]:
        if not cond.shape[1]:
            return self.end_step(state, None, state.denoiser)
        (x,), (denoiser,) = denoise(self.runner, [self.window(state, cond)])
        return self.end_step(state, x, denoiser)

    def step(self, state: StreamState, samples) -> tuple[np.ndarray, StreamState]:
        """The stream as a function: mono float32 16 kHz samples (any length) after `state` -> the (n, motion_dim)
        frames that became final and the state after them. `state` is only read."""
        cond, state = self.begin_step(state, samples)
        return self._denoise(state, cond)

    def finish_step(self, state: StreamState) -> tuple[np.ndarray, StreamState]:
        """The end of the audio after `state`: pad with silence exactly as `generate_offline` does -> the
        remaining frames and the finished state."""
        if state.finished:
            return np.zeros((0, self.model.config.motion_dim), np.float32), state
        c = self.model.config
        T = state.samples_in * c.fps // c.sample_rate
        pad = max(self.model.samples_needed(T) - state.samples_in, 0)
        padded = condition(self.model, state.frontend, state.extractor, np.zeros(pad, np.float32), self.speaker_index)
        frames, end = self._denoise(replace(state.conditioned(padded, 0), finished=True), padded.cond)
        out = frames[: max(T - state.frames_out, 0)]
        return out, replace(end, frames_out=state.frames_out + len(out))

    def push(self, samples) -> np.ndarray:
        """Feed mono float32 16 kHz samples (any length) -> (n, motion_dim) frames that became final."""
        frames, self.state = self.step(self.state, samples)
        return frames

    def finish(self) -> np.ndarray:
        """Pad with silence exactly as `generate_offline` does and return the remaining frames."""
        frames, self.state = self.finish_step(self.state)
        return frames


def generate_offline(model: DiMGestor, audio, steps: int | None = None, seed: int = 0, sampler: str = "ddim",
                     eta: float = 0.0, smoothing="config", guidance: float | None = None) -> np.ndarray:
    """Whole-recording generation: (T, motion_dim) normalized features, T = len(audio) * fps // SAMPLE_RATE.

    steps None: the config's sample_steps; smoothing: see make_smoother; guidance None: the config's scale.
    """
    audio = check_audio(audio)
    c = model.config
    guidance = check_guidance(c.guidance if guidance is None else guidance)
    T = len(audio) * c.fps // c.sample_rate
    diffusion = Diffusion(c)
    pairs = diffusion.sampling_pairs(sampler, steps or c.sample_steps)
    if T == 0:
        return np.zeros((0, c.motion_dim), np.float32)
    pad = max(model.samples_needed(T) - len(audio), 0)  # the same silence GestureStream.finish appends
    dev = _device(model)
    with torch.inference_mode():
        x = torch.from_numpy(np.concatenate([audio, np.zeros(pad, np.float32)])).to(dev)[None]
        feats, _ = model.frontend(x, model.frontend.init_state(1, dev))
        cond, _ = model.condition(feats)
        frames, _ = sample_frames(model, diffusion, cond[:, :T], 0, [None] * len(pairs), pairs, seed, sampler, eta,
                                  guidance)
    out = frames.float().cpu().numpy()
    smoother = make_smoother(c, smoothing)
    return smoother(out) if smoother is not None else out
