"""A front end that hears speech rather than a speaker: level-free spectra and prosody, streamed with state.

Log-mel (`LogMelFrontEnd`) carries the microphone's gain and colour and the speaker's timbre in every
number, and a model trained on one voice learns those instead of the rhythm. Every channel here is
relative to the stream's own running statistics, so a quiet and a loud microphone, or two voices,
give features that differ only in what was said and how it was stressed:

    bands     n_mels log-mel bands minus their running mean over speech (cepstral mean normalization:
              removes gain, microphone EQ and the average timbre), floored 30 dB below it so that
              silence reads the same at any gain
    loudness  frame energy minus the running speech level (a per-stream AGC), in [-45, +20] dB
    flux      onset strength: mean rise of the bands since the previous frame
    voicing   periodicity (normalized autocorrelation peak, 80-400 Hz), 0 outside speech
    pitch     log2 f0 minus its running mean over voiced frames (octaves, [-1, 1]), 0 when unvoiced
    pause     time since the last speech frame, 0..1 over `PAUSE_S` (a breath between phrases and a long
              silence look alike in every other channel; speakers keep gesturing through the first, not the second)

The running statistics are means over the frames that count as speech (within 25 dB of the current
level), with a count-based start (the plain mean of the first frames, then an exponential one with time
constant `tau_s`), and they hold through silence: a long pause neither raises the noise to speech level
nor forgets the speaker. They are updated frame by frame, so any chunking gives the same numbers.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from ..config import ModelConfig
from .mel import mel_filterbank

__all__ = ["SpeechFrontEnd", "SpeechState", "SPEECH_CHANNELS"]

SPEECH_CHANNELS = ("loudness", "flux", "voicing", "pitch", "pause")  # after the n_mels bands

FLOOR_DBFS = -100.0  # nothing quieter than this is speech, whatever the gain
SNR_DB = 15.0  # a speech frame stands this far above the running noise floor ...
GATE_DB = 25.0  # ... and within this much of the running speech level
FLOOR_RISE_DB_S = 3.0  # the noise floor falls to any quieter frame at once and rises this fast (dB/s): a
# fixed rate, not a fraction of the gap to the current frame, so that the gain of the input does not matter
BAND_RANGE = (-30.0, 30.0)  # band dB relative to the band's running mean, clipped: room noise and digital
# silence both read as the floor
LOUD_RANGE = (-45.0, 20.0)  # frame dB relative to the running speech level, clipped (pauses in a quiet
# room sit at -40..-50 dB: below -45 a pause reads the same whatever the room)
DB_SCALE = 20.0  # dB per feature unit
F0_RANGE = (80.0, 400.0)  # Hz searched for a pitch period inside one 25 ms window
VOICED = 0.45  # periodicity above which a frame is voiced
PAUSE_S = 2.0  # the pause channel rises from 0 to 1 over this long a silence


class SpeechState(NamedTuple):
    tail: torch.Tensor  # (B, m) samples received but not yet consumed by a complete frame
    consumed: int  # frames emitted
    floor: torch.Tensor  # (B,) float64: running noise floor, dBFS (NaN before the first frame)
    count: torch.Tensor  # (B,) float64: speech frames seen (for the count-based start of the means)
    level: torch.Tensor  # (B,) float64: running speech level, dBFS
    mean: torch.Tensor  # (B, n_mels) float64: running band means over speech, dB
    voiced: torch.Tensor  # (B,) float64: voiced frames seen
    pitch: torch.Tensor  # (B,) float64: running mean log2 f0 over voiced frames
    quiet: torch.Tensor  # (B,) float64: frames since the last speech frame
    prev: torch.Tensor  # (B, n_mels) float32: the previous frame's relative bands (for the flux)

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.tail, self.floor, self.count, self.level, self.mean,
                                                            self.voiced, self.pitch, self.quiet, self.prev))


def running_stats(energy, bands, periodicity, logf0, carried, tau: float, pitch_tau: float, floor_rise: float,
                  xp=np):
    """The running statistics over n new frames, frame by frame in float64 (any chunking gives the same numbers).

    energy, periodicity, logf0 (B, n), bands (B, n, M); carried: (floor, count, level, mean, voiced, pitch,
    quiet) as `SpeechState` holds them. xp: numpy (at run time: the fewest ops per frame) or torch (while
    exporting: a graph cannot hold numpy); the body uses only what both share, `where` and `isnan`, so the
    two give the same float64 numbers. -> (the carried statistics after the last frame; level (B, n),
    mean (B, n, M), pitch (B, n), frames since speech (B, n) and `speech started` (B, n) after each frame).
    """
    if xp is np and energy.shape[0] == 1:
        return _running_stats_one(energy, bands, periodicity, logf0, carried, tau, pitch_tau, floor_rise)
    floor, count, level, mean, nv, pitch, quiet = carried
    levels, means, pitches, quiets, started = [], [], [], [], []
    for i in range(energy.shape[1]):
        e = energy[:, i]
        floor = xp.where(xp.isnan(floor), e, xp.where(e < floor + floor_rise, e, floor + floor_rise))
        active = (e > floor + SNR_DB) & (e > FLOOR_DBFS) & ((count == 0) | (e > level - GATE_DB))
        count = count + active
        a = xp.where(active, _at_least(1.0 / _at_least(count, 1.0, xp), 1.0 / tau, xp), 0.0)
        level = level + a * (e - level)
        mean = mean + a[:, None] * (bands[:, i] - mean)
        voiced = active & (periodicity[:, i] > VOICED)
        nv = nv + voiced
        ap = xp.where(voiced, _at_least(1.0 / _at_least(nv, 1.0, xp), 1.0 / pitch_tau, xp), 0.0)
        pitch = pitch + ap * (logf0[:, i] - pitch)
        quiet = xp.where(active, 0.0, quiet + 1.0)
        levels.append(level), means.append(mean), pitches.append(pitch), quiets.append(quiet), started.append(count > 0)
    return ((floor, count, level, mean, nv, pitch, quiet),
            *(xp.stack(v, 1) for v in (levels, means, pitches, quiets, started)))


def _running_stats_one(energy, bands, periodicity, logf0, carried, tau: float, pitch_tau: float, floor_rise: float):
    """`running_stats` of one stream in numpy: the same float64 operations in the same order, on Python floats (each
    an IEEE double, as numpy's elements) instead of 1-element arrays, so the same numbers ~10x faster (a window of
    speech frames was ~20 numpy calls a frame: 24 of the 35 s a small training spent before its first step)."""
    floor, count, level = (float(carried[k][0]) for k in range(3))
    mean = carried[3][0]
    nv, pitch, quiet = (float(carried[k][0]) for k in range(4, 7))
    e_all, f0_all = energy[0].tolist(), logf0[0].tolist()
    voiced_all = (periodicity[0] > VOICED).tolist()  # (compared as before: a float32 measure against VOICED)
    rows = bands[0]
    lo_a, lo_p = 1.0 / tau, 1.0 / pitch_tau
    n = len(e_all)
    levels, pitches, quiets, started = [0.0] * n, [0.0] * n, [0.0] * n, [False] * n
    means = np.empty((1, n, rows.shape[1]), dtype=np.float64)
    for i, e in enumerate(e_all):
        if math.isnan(floor):
            floor = e
        else:
            risen = floor + floor_rise
            floor = e if e < risen else risen
        active = (e > floor + SNR_DB) and (e > FLOOR_DBFS) and (count == 0 or e > level - GATE_DB)
        count = count + active
        a = 0.0
        if active:
            r = 1.0 / (count if count > 1.0 else 1.0)
            a = r if r > lo_a else lo_a
        level = level + a * (e - level)
        mean = mean + a * (rows[i] - mean)
        means[0, i] = mean
        voiced = active and voiced_all[i]
        nv = nv + voiced
        ap = 0.0
        if voiced:
            r = 1.0 / (nv if nv > 1.0 else 1.0)
            ap = r if r > lo_p else lo_p
        pitch = pitch + ap * (f0_all[i] - pitch)
        quiet = 0.0 if active else quiet + 1.0
        levels[i], pitches[i], quiets[i], started[i] = level, pitch, quiet, count > 0
    one = lambda x: np.array([x], dtype=np.float64)  # noqa: E731
    return ((one(floor), one(count), one(level), mean[None], one(nv), one(pitch), one(quiet)), np.array([levels]), means, np.array([pitches]), np.array([quiets]), np.array([started]))


def _at_least(x, lo: float, xp):
    """max(x, lo) elementwise with `where` (numpy's and torch's maximum differ on a scalar bound)."""
    return xp.where(x > lo, x, lo)


class SpeechFrontEnd(nn.Module):
    """Streaming level-free bands + prosody at `feature_rate`; frame i ends at sample (i+1)*hop (no lookahead)."""

    def __init__(self, config: ModelConfig, tau_s: float = 3.0, pitch_tau_s: float = 5.0):
        super().__init__()
        self.hop, self.win, self.n_fft, self.sr = config.hop_length, config.win_length, config.n_fft, config.sample_rate
        self.n_mels = config.n_mels
        self.dim = config.n_mels + len(SPEECH_CHANNELS)
        self.tau = tau_s * config.feature_rate  # frames
        self.pitch_tau = pitch_tau_s * config.feature_rate
        self.floor_rise = FLOOR_RISE_DB_S / config.feature_rate  # dB per frame
        self.pause_frames = PAUSE_S * config.feature_rate
        self.register_buffer("window", torch.hann_window(self.win, periodic=True), persistent=False)
        self.register_buffer("fb", mel_filterbank(config.n_mels, config.n_fft, config.sample_rate), persistent=False)
        # autocorrelation through a zero-padded FFT (no wrap-around), normalized by the window's own (Boersma)
        self.ac_fft = 1 << (2 * self.win - 1).bit_length()
        w_ac = torch.fft.irfft(torch.fft.rfft(self.window, n=self.ac_fft).abs().square(), n=self.ac_fft)
        self.lag_lo = int(self.sr // F0_RANGE[1])
        self.lag_hi = min(int(math.ceil(self.sr / F0_RANGE[0])), self.win // 2)
        self.register_buffer("w_ac", (w_ac[self.lag_lo:self.lag_hi + 1] / w_ac[0]).clamp_min(1e-3), persistent=False)
        self.register_buffer("w_power", self.window.square().mean(), persistent=False)

    def init_state(self, batch: int, device=None) -> SpeechState:
        z = lambda *shape: torch.zeros(*shape, dtype=torch.float64, device=device)  # noqa: E731
        return SpeechState(torch.zeros(batch, self.win - self.hop, device=device), 0,
                           torch.full((batch,), float("nan"), dtype=torch.float64, device=device), z(batch), z(batch),
                           z(batch, self.n_mels), z(batch), z(batch), z(batch),
                           torch.full((batch, self.n_mels), BAND_RANGE[0] / DB_SCALE, device=device))

    def samples_needed(self, n_feats: int) -> int:
        return n_feats * self.hop

    def _stats(self, energy, bands, periodicity, logf0, state: SpeechState):
        """`running_stats` on the frames' measures -> torch tensors: in numpy at run time, in torch while exporting."""
        carried = (state.floor, state.count, state.level, state.mean, state.voiced, state.pitch, state.quiet)
        measures = (energy.double(), bands.double(), periodicity, logf0.double())
        if torch.compiler.is_exporting():
            return running_stats(*measures, carried, self.tau, self.pitch_tau, self.floor_rise, torch)
        # (on a GPU the statistics go through the host: one small copy each way per window, not ~20 kernels a frame)
        carried, *per_frame = running_stats(*(t.cpu().numpy() for t in measures),
                                            tuple(t.cpu().numpy() for t in carried), self.tau, self.pitch_tau,
                                            self.floor_rise)
        dev = energy.device
        return tuple(torch.from_numpy(a).to(dev) for a in carried), *(torch.from_numpy(a).to(dev) for a in per_frame)

    def frame_measures(self, frames: torch.Tensor):
        """Windowed frames (B, n, win) -> (band dB (B, n, M), frame dBFS (B, n), periodicity (B, n), log2 f0 (B, n)).
        One zero-padded transform gives both the bands' spectrum and the autocorrelation where win <= n_fft and
        n_fft divides its size (as `_spectra_as_matmuls` says)."""
        x = frames * self.window
        if torch.compiler.is_exporting():
            power, ac0, ac = self._spectra_as_matmuls(x)
        else:
            spec = torch.fft.rfft(x, n=self.ac_fft)
            power_ac = spec.real.square() + spec.imag.square()  # (B, n, ac_fft//2+1)
            if self.ac_fft % self.n_fft == 0 and self.win <= self.n_fft:  # (one transform serves both: below)
                power = power_ac[..., ::self.ac_fft // self.n_fft]  # (B, n, n_fft//2+1)
            else:
                spec = torch.fft.rfft(x, n=self.n_fft)
                power = spec.real.square() + spec.imag.square()
            ac = torch.fft.irfft(power_ac, n=self.ac_fft)  # (B, n, ac_fft)
            ac0, ac = ac[..., :1], ac[..., self.lag_lo:self.lag_hi + 1]
        bands = 10.0 * torch.log10((power @ self.fb).clamp_min(1e-12))  # (B, n, M)
        energy = 10.0 * torch.log10(x.square().mean(-1) / self.w_power + 1e-12)  # dBFS: a full-scale sine is -3
        r = ac / ac0.clamp_min(1e-12) / self.w_ac  # normalized
        periodicity, k = r.max(dim=-1)
        f0 = self.sr / (k + self.lag_lo).to(x.dtype)
        return bands, energy, periodicity.clamp(0.0, 1.0), torch.log2(f0)

    def _spectra_as_matmuls(self, x: torch.Tensor):
        """`frame_measures`' transforms as two matrix products, for an exported graph: ONNX Runtime's DFT costs
        more than the rest of the front end together (0.64 of its 1.07 ms a 100 ms window, 10 frames), and a
        matrix product of the frames with the DFT's cosines and sines is one small GEMM. One zero-padded
        ac_fft-point spectrum serves both: its every (ac_fft / n_fft)-th bin is the n_fft-point spectrum
        (win <= n_fft), and the autocorrelation is only needed at lag 0 and lag_lo..lag_hi, the inverse
        transform of the power at those lags (a cosine sum). Same numbers as torch.fft up to float32 rounding.
        x (B, n, win) -> (power (B, n, n_fft//2+1), autocorrelation at lag 0 (B, n, 1), at the lags (B, n, L))."""
        if self.ac_fft % self.n_fft or self.win > self.n_fft:
            raise ValueError("the exported front end needs win <= n_fft and n_fft dividing the autocorrelation's "
                             f"{self.ac_fft}-point transform, got win {self.win}, n_fft {self.n_fft}")
        bins = self.ac_fft // 2 + 1
        t = torch.arange(self.win, dtype=torch.float64)[:, None]
        k = torch.arange(bins, dtype=torch.float64)[None, :]
        angle = 2.0 * math.pi * ((t * k) % self.ac_fft) / self.ac_fft  # (win, bins); the remainder keeps it exact
        dft = torch.cat([angle.cos(), angle.sin()], 1).float()  # (win, 2 bins): real part, minus the imaginary
        lags = torch.cat([torch.zeros(1, dtype=torch.float64),
                          torch.arange(self.lag_lo, self.lag_hi + 1, dtype=torch.float64)])[None, :]
        weight = torch.full((bins, 1), 2.0, dtype=torch.float64)  # a one-sided spectrum: inner bins count twice
        weight[0], weight[-1] = 1.0, 1.0
        inverse = (weight * torch.cos(2.0 * math.pi * ((k.T * lags) % self.ac_fft) / self.ac_fft)
                   / self.ac_fft).float()  # (bins, 1 + L)
        re, im = (x @ dft).split(bins, -1)
        power_ac = re.square() + im.square()  # (B, n, bins): |rfft(x, n=ac_fft)|^2
        ac = power_ac @ inverse  # (B, n, 1 + L)
        return power_ac[..., ::self.ac_fft // self.n_fft], ac[..., :1], ac[..., 1:]

    def forward(self, samples: torch.Tensor, state: SpeechState) -> tuple[torch.Tensor, SpeechState]:
        """samples (B, N) -> (feats (B, n, n_mels + 5), state)."""
        buf = torch.cat([state.tail, samples.to(state.tail)], dim=1)  # (B, m + N)
        n = max((buf.shape[1] - (self.win - self.hop)) // self.hop, 0)
        if n == 0:
            return buf.new_zeros(buf.shape[0], 0, self.dim), state._replace(tail=buf)
        bands, energy, periodicity, logf0 = self.frame_measures(buf.unfold(1, self.win, self.hop)[:, :n])
        carried, *per_frame = self._stats(energy, bands, periodicity, logf0, state)
        floor, count, level, mean, nv, pitch, quiet = carried
        levels, means, pitches, quiets, speech = per_frame
        level_t, mean_t, pitch_t, started = levels.float(), means.float(), pitches.float(), speech  # (B, n), (B, n, M)
        rel = ((bands - mean_t).clamp(*BAND_RANGE) / DB_SCALE).where(started[..., None], BAND_RANGE[0] / DB_SCALE)  # (B, n, M)
        loud_db = (energy - level_t).clamp(*LOUD_RANGE)
        loud = (loud_db / DB_SCALE).where(started, LOUD_RANGE[0] / DB_SCALE)
        flux = (rel - torch.cat([state.prev[:, None], rel[:, :-1]], 1)).clamp_min(0.0).mean(-1)  # (B, n)
        in_speech = started & (loud_db > -GATE_DB)
        voicing = periodicity.where(in_speech, 0.0)
        pitch_rel = (logf0 - pitch_t).clamp(-1.0, 1.0).where(in_speech & (periodicity > VOICED), 0.0)
        pause = (quiets.float() / self.pause_frames).clamp(max=1.0).where(started, 1.0)
        feats = torch.cat([rel, torch.stack([loud, flux, voicing, pitch_rel, pause], -1)], -1)  # (B, n, M + 5)
        return feats, SpeechState(buf[:, n * self.hop:], state.consumed + n, floor, count, level, mean, nv, pitch,
                                  quiet, rel[:, -1].clone())
