"""Gesture quality metrics: Fréchet gesture distance (raw and learned feature space), BeatAlign, jerk.

Notation: motion features are (T, D) arrays at `fps`; joint world positions are (T, J, 3) arrays (from
forward kinematics); audio is float32 mono at `sr`. Times are in seconds.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from dimgestor.audio import SAMPLE_RATE

# --------------------------------------------------------------------------------------------------
# Fréchet distance
# --------------------------------------------------------------------------------------------------


def gaussian_stats(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and covariance (D, D) of samples x (N, D)."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"need samples of shape (N >= 2, D), got {x.shape}")
    return x.mean(axis=0), np.cov(x, rowvar=False).reshape(x.shape[1], x.shape[1])


def _sqrtm_product(sigma1: np.ndarray, sigma2: np.ndarray, eps: float) -> np.ndarray:
    """sqrt(sigma1 @ sigma2), retried with eps * I added to both when the product is near singular."""
    import scipy.linalg  # (scipy here and below, not at the top: every `dimgestor` command imports this module)

    with warnings.catch_warnings(record=True) as caught:  # scipy warns when the product is singular
        warnings.simplefilter("always", scipy.linalg.LinAlgWarning)
        covmean = scipy.linalg.sqrtm(sigma1 @ sigma2)
    if caught or not np.isfinite(covmean).all():
        offset = np.eye(sigma1.shape[0]) * eps
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", scipy.linalg.LinAlgWarning)
            covmean = scipy.linalg.sqrtm((sigma1 + offset) @ (sigma2 + offset))
    if np.iscomplexobj(covmean):
        # Round-off gives tiny imaginary parts on a PSD product; large ones mean the input is broken.
        if np.abs(covmean.imag).max() > 1e-3 * max(1.0, np.abs(covmean.real).max()):
            raise ValueError(f"matrix square root has a large imaginary part ({np.abs(covmean.imag).max():.3g})")
        covmean = covmean.real
    return covmean


def frechet_distance(mu1, sigma1, mu2, sigma2, eps: float = 1e-6) -> float:
    """||mu1 - mu2||^2 + Tr(sigma1 + sigma2 - 2 sqrt(sigma1 sigma2)) between two Gaussians."""
    mu1, mu2 = np.atleast_1d(mu1).astype(np.float64), np.atleast_1d(mu2).astype(np.float64)
    sigma1, sigma2 = np.atleast_2d(sigma1).astype(np.float64), np.atleast_2d(sigma2).astype(np.float64)
    if mu1.shape != mu2.shape or sigma1.shape != sigma2.shape or sigma1.shape != (mu1.size, mu1.size):
        raise ValueError(f"shape mismatch: mu {mu1.shape} vs {mu2.shape}, sigma {sigma1.shape} vs {sigma2.shape}")
    covmean = _sqrtm_product(sigma1, sigma2, eps)
    diff = mu1 - mu2
    value = diff @ diff + np.trace(sigma1) + np.trace(sigma2) - 2.0 * np.trace(covmean)
    return float(max(value, 0.0))  # a true distance; round-off can give -1e-12


def fgd(real: np.ndarray, generated: np.ndarray) -> float:
    """Fréchet distance between the Gaussians fitted to two sample sets (N, D) and (M, D)."""
    return frechet_distance(*gaussian_stats(real), *gaussian_stats(generated))


# --------------------------------------------------------------------------------------------------
# Learned feature space (GENEA numerical evaluations: conv autoencoder on fixed-length chunks)
# --------------------------------------------------------------------------------------------------


def motion_chunks(motion: np.ndarray, chunk: int = 34, stride: int | None = None) -> np.ndarray:
    """Cut (T, D) motion into (n, chunk, D) windows, `stride` apart (default chunk // 2)."""
    stride = stride or max(1, chunk // 2)
    motion = np.asarray(motion, dtype=np.float32)
    if motion.shape[0] < chunk:
        return np.zeros((0, chunk, motion.shape[1]), dtype=np.float32)
    starts = range(0, motion.shape[0] - chunk + 1, stride)
    return np.stack([motion[s : s + chunk] for s in starts])


class MotionAutoencoder(nn.Module):
    """1D-conv encoder of a (chunk, D) motion window to a `latent` vector, with a conv decoder to train it."""

    def __init__(self, dim: int, chunk: int = 34, latent: int = 32, width: int = 64):
        super().__init__()
        self.dim, self.chunk, self.latent, self.width = dim, chunk, latent, width
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))
        self.encoder = nn.Sequential(
            nn.Conv1d(dim, width, 3, padding=1), nn.LeakyReLU(0.2),
            nn.Conv1d(width, width, 4, stride=2, padding=1), nn.LeakyReLU(0.2),  # chunk -> chunk // 2
            nn.Conv1d(width, width, 4, stride=2, padding=1), nn.LeakyReLU(0.2),  # -> chunk // 4
        )
        self.n_low = chunk // 4
        if self.n_low < 1:
            raise ValueError(f"chunk must be at least 4 frames, got {chunk}")
        self.to_latent = nn.Linear(width * self.n_low, latent)
        self.from_latent = nn.Linear(latent, width * self.n_low)
        self.decoder = nn.Sequential(
            nn.Conv1d(width, width, 3, padding=1), nn.LeakyReLU(0.2),
            nn.Conv1d(width, width, 3, padding=1), nn.LeakyReLU(0.2),
            nn.Conv1d(width, dim, 3, padding=1),
        )

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Raw chunks (B, chunk, D) -> latent (B, latent)."""
        h = self.encoder(self.normalize(x).transpose(1, 2))  # (B, width, chunk // 4)
        return self.to_latent(h.flatten(1))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latent (B, latent) -> normalized chunks (B, chunk, D)."""
        h = self.from_latent(z).view(-1, self.width, self.n_low)
        h = F.interpolate(h, size=self.chunk, mode="linear", align_corners=False)
        return self.decoder(h).transpose(1, 2)

    def loss(self, x: torch.Tensor) -> torch.Tensor:
        """L1 reconstruction + L1 of frame-to-frame velocity, in normalized units."""
        target = self.normalize(x)
        recon = self.decode(self.encode(x))
        velocity = F.l1_loss(recon.diff(dim=1), target.diff(dim=1))
        return F.l1_loss(recon, target) + velocity

    @torch.no_grad()
    def embed(self, chunks: np.ndarray, batch: int = 256) -> np.ndarray:
        """Latent features (n, latent) of raw chunks (n, chunk, D)."""
        self.eval()
        x = torch.as_tensor(np.asarray(chunks, dtype=np.float32))
        if x.ndim != 3 or x.shape[1:] != (self.chunk, self.dim):
            raise ValueError(f"expected chunks (n, {self.chunk}, {self.dim}), got {tuple(x.shape)}")
        return torch.cat([self.encode(x[i : i + batch]) for i in range(0, len(x), batch)]).numpy()

    def save(self, folder: str | Path) -> None:
        from safetensors.torch import save_file

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        save_file({k: v.contiguous() for k, v in self.state_dict().items()}, folder / "fgd_autoencoder.safetensors")
        hparams = dict(dim=self.dim, chunk=self.chunk, latent=self.latent, width=self.width)
        (folder / "fgd_autoencoder.json").write_text(json.dumps(hparams, indent=2))

    @classmethod
    def load(cls, folder: str | Path) -> "MotionAutoencoder":
        from safetensors.torch import load_file

        folder = Path(folder)
        ae = cls(**json.loads((folder / "fgd_autoencoder.json").read_text()))
        ae.load_state_dict(load_file(folder / "fgd_autoencoder.safetensors"))
        return ae.eval()


def train_motion_autoencoder(
    chunks: np.ndarray, latent: int = 32, width: int = 64, steps: int = 1500, batch: int = 64,
    lr: float = 1e-3, seed: int = 0, log_every: int = 0,
) -> MotionAutoencoder:
    """Fit a MotionAutoencoder on raw chunks (n, chunk, D); normalization statistics come from the chunks."""
    chunks = np.asarray(chunks, dtype=np.float32)
    if chunks.ndim != 3 or len(chunks) < 2:
        raise ValueError(f"need at least 2 chunks of shape (chunk, D), got {chunks.shape}")
    torch.manual_seed(seed)
    ae = MotionAutoencoder(chunks.shape[2], chunks.shape[1], latent, width)
    flat = chunks.reshape(-1, chunks.shape[2])
    ae.mean.copy_(torch.from_numpy(flat.mean(0)))
    ae.std.copy_(torch.from_numpy(flat.std(0)).clamp_min(1e-4))  # constant channels stay finite
    data = torch.from_numpy(chunks)
    opt = torch.optim.AdamW(ae.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    gen = torch.Generator().manual_seed(seed)
    ae.train()
    for step in range(steps):
        idx = torch.randint(len(data), (min(batch, len(data)),), generator=gen)
        loss = ae.loss(data[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if log_every and (step % log_every == 0 or step == steps - 1):
            print(f"fgd autoencoder step {step}: loss {loss.item():.4f}")
    return ae.eval()


def feature_fgd(ae: MotionAutoencoder, real_chunks: np.ndarray, generated_chunks: np.ndarray) -> float:
    """FGD between real and generated chunks in the autoencoder's latent space."""
    return fgd(ae.embed(real_chunks), ae.embed(generated_chunks))


# --------------------------------------------------------------------------------------------------
# BeatAlign (speech version used with BEAT)
# --------------------------------------------------------------------------------------------------


def _mel_filterbank(sr: int, n_fft: int, n_mels: int) -> np.ndarray:
    """Triangular HTK-mel filters (n_mels, n_fft // 2 + 1)."""
    mel = lambda f: 2595.0 * np.log10(1.0 + f / 700.0)  # noqa: E731
    hz = lambda m: 700.0 * (10.0 ** (m / 2595.0) - 1.0)  # noqa: E731
    edges = hz(np.linspace(mel(0.0), mel(sr / 2), n_mels + 2))
    freqs = np.linspace(0.0, sr / 2, n_fft // 2 + 1)
    lower, centre, upper = edges[:-2, None], edges[1:-1, None], edges[2:, None]
    up = (freqs - lower) / np.maximum(centre - lower, 1e-9)
    down = (upper - freqs) / np.maximum(upper - centre, 1e-9)
    return np.maximum(0.0, np.minimum(up, down))


def onset_strength(audio: np.ndarray, sr: int = SAMPLE_RATE, hop: int = 160, n_fft: int = 1024, n_mels: int = 64):
    """Spectral flux of the log-mel spectrogram -> (envelope (F,), frames per second); frame f is at f * hop / sr."""
    y = np.asarray(audio, dtype=np.float64).reshape(-1)
    y = np.pad(y, n_fft // 2, mode="constant")  # centred frames, as librosa
    n_frames = 1 + (len(y) - n_fft) // hop
    if n_frames < 2:
        raise ValueError(f"audio too short for onset detection: {len(audio)} samples")
    frames = np.lib.stride_tricks.sliding_window_view(y, n_fft)[::hop][:n_frames] * np.hanning(n_fft)
    power = np.abs(np.fft.rfft(frames, axis=1)) ** 2  # (F, n_fft // 2 + 1)
    log_mel = 10.0 * np.log10(np.maximum(power @ _mel_filterbank(sr, n_fft, n_mels).T, 1e-10))
    log_mel = np.maximum(log_mel, log_mel.max() - 80.0)  # 80 dB floor so silence does not make flux
    flux = np.maximum(0.0, np.diff(log_mel, axis=0)).mean(axis=1)
    return np.concatenate([[0.0], flux]), sr / hop


def peak_pick(x: np.ndarray, pre_max: int, post_max: int, pre_avg: int, post_avg: int, delta: float, wait: int):
    """Indices n with x[n] the max of x[n-pre_max : n+post_max+1], above its local mean + delta, >= wait apart."""
    peaks, last = [], -np.inf
    for n in range(len(x)):
        lo_m, hi_m = max(0, n - pre_max), min(len(x), n + post_max + 1)
        lo_a, hi_a = max(0, n - pre_avg), min(len(x), n + post_avg + 1)
        if x[n] == x[lo_m:hi_m].max() and x[n] >= x[lo_a:hi_a].mean() + delta and n - last > wait:
            peaks.append(n)
            last = n
    return np.asarray(peaks, dtype=np.int64)


def audio_onsets(audio: np.ndarray, sr: int = SAMPLE_RATE, delta: float = 0.07) -> np.ndarray:
    """Onset times (s): peaks of the normalized onset-strength envelope (librosa's default peak picking)."""
    env, rate = onset_strength(audio, sr)
    env = env - env.min()
    if env.max() <= 0:
        return np.zeros(0)
    env = env / env.max()
    s = lambda seconds: int(round(seconds * rate))  # noqa: E731
    peaks = peak_pick(env, s(0.03), 0, s(0.10), s(0.10), delta, s(0.03))
    return peaks / rate


def joint_speed(positions: np.ndarray, fps: float) -> np.ndarray:
    """Speed (T, J) of joint positions (T, J, 3), central differences inside, one-sided at the ends."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3 or p.shape[0] < 2:
        raise ValueError(f"expected positions (T >= 2, J, 3), got {p.shape}")
    return np.linalg.norm(np.gradient(p, 1.0 / fps, axis=0), axis=2)


def motion_beats(positions: np.ndarray, fps: float, threshold: float = 0.1, min_gap_s: float = 0.1) -> np.ndarray:
    """Beat times (s): local minima of the joints' mean speed, normalized by its clip mean, above `threshold`.

    Normalizing by the clip mean makes the threshold unit-free (cm or m); it drops the near-zero minima
    of a body at rest, which are jitter rather than beats (as BEAT's velocity mask does).
    """
    from scipy.signal import argrelextrema

    speed = joint_speed(positions, fps).mean(axis=1)
    if speed.mean() <= 1e-12:
        return np.zeros(0)  # a still body has no beats
    speed = speed / speed.mean()
    order = max(1, int(round(min_gap_s * fps)))
    minima = argrelextrema(speed, np.less, order=order)[0]
    return minima[speed[minima] > threshold] / fps


def beat_align(onsets_s: np.ndarray, beats_s: np.ndarray, sigma: float = 0.3) -> float:
    """Mean over audio onsets of exp(-d^2 / (2 sigma^2)), d = distance to the nearest motion beat."""
    onsets_s, beats_s = np.asarray(onsets_s, dtype=np.float64), np.sort(np.asarray(beats_s, dtype=np.float64))
    if onsets_s.size == 0:
        return float("nan")  # undefined without audio onsets
    if beats_s.size == 0:
        return 0.0
    d = np.abs(onsets_s[:, None] - beats_s[None, :]).min(axis=1)
    return float(np.exp(-(d**2) / (2.0 * sigma**2)).mean())


def beat_align_score(audio: np.ndarray, sr: int, positions: np.ndarray, fps: float, sigma: float = 0.3) -> float:
    """BeatAlign of joint positions (T, J, 3) against the audio they were made for."""
    return beat_align(audio_onsets(audio, sr), motion_beats(positions, fps), sigma)


# --------------------------------------------------------------------------------------------------
# Smoothness
# --------------------------------------------------------------------------------------------------


def jerk_magnitude(positions: np.ndarray, fps: float) -> np.ndarray:
    """|d^3 p / dt^3| (T - 3, J) by third finite differences (exact for cubic motion)."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[0] < 4:
        raise ValueError(f"expected positions (T >= 4, J, 3), got {p.shape}")
    return np.linalg.norm(np.diff(p, n=3, axis=0) * fps**3, axis=2)


def jerk(positions: np.ndarray, fps: float) -> float:
    """Mean jerk magnitude over frames and joints, in position units / s^3."""
    return float(jerk_magnitude(positions, fps).mean())


def upper_body_joints(names: list[str]) -> list[int]:
    """Indices of spine, neck, head, shoulders, arms and wrists (no fingers, legs or end sites)."""
    keep = ("spine", "neck", "head", "shoulder", "arm", "hand")
    drop = ("thumb", "index", "middle", "ring", "pinky", "end", "leg", "foot", "toe", "upleg")
    picked = [i for i, n in enumerate(names) if any(k in n.lower() for k in keep) and not any(d in n.lower() for d in drop)]
    return picked or list(range(len(names)))


def area_under_jerk(positions: np.ndarray, fps: float) -> float:
    """Area under the peak-jerk curve (the largest joint jerk of each frame, as FlowMDM's PJ/AUJ), per second
    of motion so that clips of any length compare: units / s^3."""
    return float(jerk_magnitude(positions, fps).max(axis=1).mean())


def hand_joints(names: list[str]) -> list[int]:
    """Indices of the two wrists (LeftHand/RightHand, Hand_L, ...): no fingers, no end sites."""
    drop = ("thumb", "index", "middle", "ring", "pinky", "finger", "end")
    picked = [i for i, n in enumerate(names) if "hand" in n.lower() and not any(d in n.lower() for d in drop)]
    return picked or upper_body_joints(names)


# --------------------------------------------------------------------------------------------------
# Speech-driven: does the body move more while the person speaks?
# --------------------------------------------------------------------------------------------------


def speech_mask(audio: np.ndarray, sr: int, fps: float, n_frames: int, rel_db: float = -30.0) -> np.ndarray:
    """(n_frames,) +1 speech, -1 silence, 0 in between (within 0.75 s of speech): a loudness gate.

    A frame is speech when its 100 ms RMS is within `rel_db` of the clip's 95th-percentile RMS; silence
    starts 0.75 s after speech ends (a gesture's retraction) and ends 0.75 s before it resumes (preparation).
    """
    a = np.asarray(audio, dtype=np.float64)
    hop = sr / fps
    centre = (np.arange(n_frames) + 0.5) * hop
    cum = np.concatenate([[0.0], np.cumsum(a * a)])
    lo = np.clip((centre - hop).astype(int), 0, len(a))
    hi = np.clip((centre + hop).astype(int), 0, len(a))
    rms = np.sqrt((cum[hi] - cum[lo]) / np.maximum(hi - lo, 1))
    ref = np.percentile(rms, 95) if n_frames else 0.0
    if ref <= 1e-6:
        return -np.ones(n_frames, dtype=int)
    speech = rms > ref * 10 ** (rel_db / 20)
    guard = int(round(0.75 * fps))
    near = np.convolve(speech.astype(float), np.ones(2 * guard + 1), mode="same") > 0
    return np.where(speech, 1, np.where(near, 0, -1))


def speech_contrast(speed: np.ndarray, mask: np.ndarray) -> float:
    """Mean speed in speech frames over mean speed in silence frames (nan without either; see speech_mask)."""
    speech, silence = speed[mask[: len(speed)] == 1], speed[mask[: len(speed)] == -1]
    if len(speech) == 0 or len(silence) == 0:
        return float("nan")
    return float(speech.mean() / max(silence.mean(), 1e-9))



# --------------------------------------------------------------------------------------------------
# Speech-drivenness: does hand motion follow this voice? (each measure beside its chance level)
#
# hand speed: mean speed of the two wrists relative to the hips, per motion frame (see `hand_speed`).
# loudness: RMS of each motion frame's audio in dB. Correlations use Pearson's r.
# --------------------------------------------------------------------------------------------------

LOUDNESS_FLOOR_DB = -100.0  # digital silence reads as this rather than -inf


def hand_speed(positions: np.ndarray, hands: list[int], fps: float) -> np.ndarray:
    """(T,) mean speed of the `hands` joints (metrics.hand_joints) of hip-relative positions (T, J, 3)."""
    return joint_speed(np.asarray(positions)[:, hands], fps).mean(axis=1)


def loudness_db(audio: np.ndarray, sr: int, fps: float, n_frames: int | None = None) -> np.ndarray:
    """(n_frames,) RMS of each motion frame's samples ([i, i+1) / fps s) in dB re full scale, floored at -100.

    n_frames defaults to the whole frames the audio holds; frames past its end read as the floor.
    """
    a = np.asarray(audio, dtype=np.float64).reshape(-1)
    hop = sr / fps
    n = int(len(a) // hop) if n_frames is None else int(n_frames)
    edges = np.clip(np.round(np.arange(n + 1) * hop).astype(np.int64), 0, len(a))
    cum = np.concatenate([[0.0], np.cumsum(a * a)])
    power = (cum[edges[1:]] - cum[edges[:-1]]) / np.maximum(edges[1:] - edges[:-1], 1)
    floor = 10.0 ** (LOUDNESS_FLOOR_DB / 10.0)
    return 10.0 * np.log10(np.maximum(power, floor))


def boxcar(x: np.ndarray, width: int) -> np.ndarray:
    """Running mean over `width` frames, 'valid' part only (len(x) - width + 1 values)."""
    x = np.asarray(x, dtype=np.float64)
    width = max(1, min(int(width), len(x)))
    cum = np.concatenate([[0.0], np.cumsum(x)])
    return (cum[width:] - cum[:-width]) / width


def lagged_correlation(x: np.ndarray, y: np.ndarray, max_lag: int) -> tuple[float, int]:
    """Best Pearson r of x[t + lag] against y[t] over |lag| <= max_lag frames, and that lag (nan if undefined).

    A positive lag means x follows y (the hands move after the sound).
    """
    n = min(len(x), len(y))
    x, y = np.asarray(x[:n], np.float64), np.asarray(y[:n], np.float64)
    best, best_lag = -np.inf, 0
    for lag in range(-max_lag, max_lag + 1):
        a, b = (x[lag:], y[: n - lag]) if lag >= 0 else (x[: n + lag], y[-lag:])
        if len(a) < 3 or a.std() < 1e-12 or b.std() < 1e-12:
            continue
        r = float(np.corrcoef(a, b)[0, 1])
        if r > best:
            best, best_lag = r, lag
    return (best, best_lag) if np.isfinite(best) else (float("nan"), 0)


def _coupling(speed: np.ndarray, loud: np.ndarray, fps: float, smooth_s: float, max_lag_s: float) -> float:
    width = max(1, int(round(smooth_s * fps)))
    return lagged_correlation(boxcar(speed, width), boxcar(loud, width), int(round(max_lag_s * fps)))[0]


def speech_coupling(hand_speed: np.ndarray, audio: np.ndarray, sr: int, fps: float, smooth_s: float = 0.5,
                    max_lag_s: float = 0.2) -> float:
    """Pearson r between hand speed (T,) and loudness_db, both boxcar-averaged over `smooth_s`, at the best lag
    within +-`max_lag_s` (motion may lead or follow speech). nan for a still body or a constant signal.

    Read it beside `shifted_coupling` (the same statistic against unrelated stretches of the same audio):
    the best of several lags of two slow signals is above 0 by chance.
    """
    speed = np.asarray(hand_speed, dtype=np.float64)
    return _coupling(speed, loudness_db(audio, sr, fps, len(speed)), fps, smooth_s, max_lag_s)


def shift_offsets(n_frames: int, n: int = 20, lo: float = 0.1, hi: float = 0.9) -> np.ndarray:
    """n circular shifts (frames) evenly spaced from lo to hi of the clip: far from 0 at both ends."""
    return np.unique(np.round(np.linspace(lo, hi, n) * n_frames).astype(np.int64))


def shifted_coupling(hand_speed: np.ndarray, audio: np.ndarray, sr: int, fps: float, n: int = 20,
                     smooth_s: float = 0.5, max_lag_s: float = 0.2, lo: float = 0.1,
                     hi: float = 0.9) -> tuple[float, float]:
    """Chance level of speech_coupling: mean and sd of it against the audio circularly shifted by n offsets
    spread over lo..hi of the clip (the loudness track rolled by whole frames, which is the audio rolled by
    whole frames). The same voice, the same motion, no relation in time.
    """
    speed = np.asarray(hand_speed, dtype=np.float64)
    loud = loudness_db(audio, sr, fps, len(speed))
    values = [_coupling(speed, np.roll(loud, int(k)), fps, smooth_s, max_lag_s)
              for k in shift_offsets(len(speed), n, lo, hi)]
    values = np.asarray([v for v in values if np.isfinite(v)])
    if values.size == 0:
        return float("nan"), float("nan")
    return float(values.mean()), float(values.std(ddof=1)) if values.size > 1 else 0.0


# Strokes coincide with or follow the stressed syllable by up to ~300 ms (McNeill's phonological synchrony
# rule; Loehr 2004 measured apexes within about 0.3 s of pitch accents). 100 ms before the onset allows for
# the 50 ms motion frames and the onset detector's smearing.
ONSET_WINDOW_S = (-0.1, 0.3)


def stressed_onsets(audio: np.ndarray, sr: int = SAMPLE_RATE, keep: float = 0.4) -> np.ndarray:
    """The strongest `keep` fraction of audio_onsets (by onset strength), in time order: a stand-in for the
    stressed syllables that beat gestures land on.

    Every syllable makes an onset, and at ~4 syllables/s busy hands have a speed peak near almost any of
    them; on the synthetic world (a stroke on each stressed syllable, ~40% of them) the rule's own motion
    aligns no better with all onsets than with shuffled ones, and 0.2 better with the strongest 40%.
    """
    onsets = audio_onsets(audio, sr)
    if onsets.size == 0:
        return onsets
    env, rate = onset_strength(audio, sr)
    strength = env[np.clip(np.round(onsets * rate).astype(np.int64), 0, len(env) - 1)]
    n = max(1, int(round(keep * onsets.size)))
    return np.sort(onsets[np.argsort(-strength, kind="stable")[:n]])


def speed_peaks(speed: np.ndarray, threshold: float | None = None) -> np.ndarray:
    """Frames where speed is a local maximum (above the frame before, not below the one after) and above
    `threshold` (default: the clip mean, so the small wobbles of a resting hand do not count)."""
    s = np.asarray(speed, dtype=np.float64)
    if len(s) < 3:
        return np.zeros(0, dtype=np.int64)
    threshold = s.mean() if threshold is None else threshold
    i = np.arange(1, len(s) - 1)
    return i[(s[i] > s[i - 1]) & (s[i] >= s[i + 1]) & (s[i] > threshold)]


def onset_hits(onsets_s: np.ndarray, hand_speed: np.ndarray, fps: float,
               window_s: tuple[float, float] = ONSET_WINDOW_S) -> np.ndarray:
    """(n_onsets,) bool: a hand-speed peak (speed_peaks) lies within onset + window_s[0] .. onset + window_s[1]."""
    onsets = np.asarray(onsets_s, dtype=np.float64).reshape(-1)
    peaks = speed_peaks(hand_speed) / fps
    if onsets.size == 0 or peaks.size == 0:
        return np.zeros(onsets.size, dtype=bool)
    d = peaks[None, :] - onsets[:, None]  # peak time after each onset
    return ((d >= window_s[0]) & (d <= window_s[1])).any(axis=1)


def onset_alignment(onsets_s: np.ndarray, hand_speed: np.ndarray, fps: float,
                    window_s: tuple[float, float] = ONSET_WINDOW_S) -> float:
    """Fraction of speech onsets (audio_onsets) with a hand-speed peak within window_s of them (nan without
    onsets). Read it beside shuffled_onset_alignment: busy hands hit many windows by chance."""
    hits = onset_hits(onsets_s, hand_speed, fps, window_s)
    return float(hits.mean()) if hits.size else float("nan")


def onset_locked_speed(onsets_s: np.ndarray, hand_speed: np.ndarray, fps: float, speech: np.ndarray,
                       window_s: tuple[float, float] = (0.0, 0.35)) -> float:
    """Mean hand speed from onset + window_s[0] to onset + window_s[1], over the onsets, relative to the mean
    speed in speech (speech: (T,) bool): an event-locked average, the size of the movement that follows an
    onset, where onset_alignment only asks whether some peak is near. Busy hands with many small peaks hit
    most windows by chance but score ~1 here; strokes that start on the onsets score well above 1 (the voice
    world's rule: 1.7). nan without onsets or speech."""
    s = np.asarray(hand_speed, dtype=np.float64)
    onsets = np.asarray(onsets_s, dtype=np.float64).reshape(-1)
    if onsets.size == 0 or not np.any(speech):
        return float("nan")
    a, b = int(round(window_s[0] * fps)), int(round(window_s[1] * fps))
    start = np.round(onsets * fps).astype(np.int64)
    start = start[(start + a >= 0) & (start + b < len(s))]
    if start.size == 0:
        return float("nan")
    return float(s[start[:, None] + np.arange(a, b + 1)].mean() / s[speech].mean())


def shuffled_onsets(n_onsets: int, speech: np.ndarray, fps: float, rng: np.random.Generator) -> np.ndarray:
    """n_onsets times (s) drawn uniformly inside the speech frames (speech: (T,) bool), sorted."""
    frames = np.flatnonzero(speech)
    if frames.size == 0 or n_onsets == 0:
        return np.zeros(0)
    return np.sort((rng.choice(frames, n_onsets) + rng.random(n_onsets)) / fps)


def shuffled_onset_alignment(n_onsets: int, hand_speed: np.ndarray, fps: float, speech: np.ndarray,
                             window_s: tuple[float, float] = ONSET_WINDOW_S, draws: int = 10,
                             seed: int = 0) -> float:
    """Chance level of onset_alignment: the same number of onsets relocated at random inside speech
    (speech: (T,) bool, e.g. speech_mask(...) == 1), averaged over `draws` seeded draws. Inside speech,
    so that a model that merely moves more while speaking does not score above it."""
    if n_onsets == 0 or not np.any(speech):
        return float("nan")
    rng = np.random.default_rng(seed)
    return float(np.mean([onset_hits(shuffled_onsets(n_onsets, speech, fps, rng), hand_speed, fps, window_s).mean()
                          for _ in range(draws)]))


# --------------------------------------------------------------------------------------------------
# Rest: hands calm down when the speech stops (natural pauses: speech_mask / speech_contrast above)
# --------------------------------------------------------------------------------------------------


def insert_silence(audio: np.ndarray, sr: int, at_s: float, seconds: float, noise_dbfs: float | None = None,
                   seed: int = 0) -> np.ndarray:
    """The audio with `seconds` of digital silence (exact zeros) inserted at `at_s`; with noise_dbfs, white
    noise of that RMS (dB re full scale, seeded) instead, as a quiet room would give."""
    a = np.asarray(audio, dtype=np.float32).reshape(-1)
    at, n = int(round(at_s * sr)), int(round(seconds * sr))
    if not 0 <= at <= len(a):
        raise ValueError(f"at_s {at_s} is outside the audio (0..{len(a) / sr:g} s)")
    gap = np.zeros(n, dtype=np.float32)
    if noise_dbfs is not None:
        gap = (10.0 ** (noise_dbfs / 20.0) * np.random.default_rng(seed).standard_normal(n)).astype(np.float32)
    return np.concatenate([a[:at], gap, a[at:]])


def quietest_point(audio: np.ndarray, sr: int, lo_s: float, hi_s: float, fps: float = 20.0) -> float:
    """Start time (s) of the quietest motion frame between lo_s and hi_s: where a pause can be lengthened
    without cutting a word."""
    loud = loudness_db(audio, sr, fps)
    lo, hi = int(lo_s * fps), max(int(lo_s * fps) + 1, min(int(hi_s * fps), len(loud)))
    return float((lo + int(np.argmin(loud[lo:hi]))) / fps)


def inserted_silence_speeds(hand_speed: np.ndarray, audio: np.ndarray, sr: int, fps: float, at_s: float,
                            seconds: float, guard_s: float = 0.75) -> tuple[float, float]:
    """(mean hand speed in speech, mean hand speed inside an inserted silence) for motion made from
    `audio` = insert_silence(..., at_s, seconds). Speech frames are speech_mask's; the silence excludes
    `guard_s` at both of its ends (the stroke retracting, the next one preparing), as speech_mask does."""
    speed = np.asarray(hand_speed, dtype=np.float64)
    mask = speech_mask(audio, sr, fps, len(speed))
    a, b = int(np.ceil((at_s + guard_s) * fps)), int(np.floor((at_s + seconds - guard_s) * fps))
    inside = speed[max(a, 0):min(b, len(speed))]
    speaking = speed[mask == 1]
    if inside.size == 0 or speaking.size == 0:
        return float("nan"), float("nan")
    return float(speaking.mean()), float(inside.mean())


def window_stack(positions: np.ndarray, length: int, hop: int) -> np.ndarray:
    """(T, J, 3) -> (N, length, J, 3): the windows of `length` frames starting every `hop` frames."""
    starts = range(0, len(positions) - length + 1, hop)
    return np.stack([positions[s:s + length] for s in starts]) if len(positions) >= length else \
        np.zeros((0, length) + positions.shape[1:], positions.dtype)


def nearest_window_distances(query: np.ndarray, reference: np.ndarray, fps: float, window_s: float = 1.0,
                             query_hop_s: float = 0.25, chunk: int = 512) -> np.ndarray:
    """For each `window_s` window of `query` (every `query_hop_s`), the distance to the nearest window of
    `reference` (every frame): the mean over the window's frames and joints of the joints' Euclidean distance.

    query, reference: joint positions (T, J, 3) in the same frame (e.g. `eval.joint_positions`' body frame), file
    units; reference may be a list of such stretches (no window spans two of them). A small distance means the motion replays a stretch of the reference: motion made for new speech that
    sits closer to its training stretch than the real actor's own unseen motion does repeats what it saw.
    -> (N,) distances in file units."""
    # Windows overlap, so rather than comparing every pair of windows frame by frame ((Nq, Nr, n, J, 3)), compare
    # every query frame with every reference frame once (e[t, u]: the mean joint distance) and sum e along the
    # diagonals: window (s, a) is sum_f e[s + f, a + f] / n. Reference windows `chunk` at a time bound the memory.
    n = int(round(window_s * fps))
    hop = max(1, int(round(query_hop_s * fps)))
    query = np.asarray(query, np.float64)
    stretches = [np.asarray(x, np.float64) for x in (reference if isinstance(reference, (list, tuple)) else [reference])]
    starts = np.arange(0, len(query) - n + 1, hop)
    if not len(starts) or not any(len(x) >= n for x in stretches):
        raise ValueError(f"need at least {n} frames in both the query ({len(query)}) and a reference stretch "
                         f"({', '.join(str(len(x)) for x in stretches)})")
    q = query[:starts[-1] + n]  # the frames some window covers
    best = np.full(len(starts), np.inf)
    for x in stretches:
        for a in range(0, len(x) - n + 1, chunk):
            b = min(a + chunk, len(x) - n + 1)  # windows a..b-1 use frames a..b+n-2
            r = x[a:b + n - 1]
            e, sq, diff = (np.zeros((len(q), len(r))) for _ in range(3))  # (Tq, Tr)
            for j in range(q.shape[1]):
                sq[:] = 0.0
                for c in range(q.shape[2]):  # one coordinate at a time: no (Tq, Tr, 3) temporary
                    np.subtract.outer(q[:, j, c], r[:, j, c], out=diff)
                    sq += np.square(diff, out=diff)
                e += np.sqrt(sq, out=sq)
            d = np.zeros((len(starts), b - a))
            for f in range(n):
                d += e[starts + f, f:f + b - a]
            best = np.minimum(best, d.min(axis=1) / (n * q.shape[1]))
    return best
