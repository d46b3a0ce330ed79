"""WAV loading and saving, anti-aliased rational resampling (one-shot and streaming), alignment, the mel filters.

The resampler is a polyphase FIR, the same filter and output alignment as
scipy.signal.resample_poly (Kaiser-windowed sinc, beta 5, 10 zero crossings per side at the
lower rate), written out so that a streaming resampler with an explicit input history gives
exactly the one-shot output for any chunking.
"""

from __future__ import annotations

import math
import struct
import warnings
import wave
from pathlib import Path
from typing import Iterator, NamedTuple

import numpy as np

SAMPLE_RATE = 16000  # what the model consumes

_PCM, _FLOAT, _EXTENSIBLE = 1, 3, 0xFFFE


class AudioError(ValueError):
    """A file that is not readable audio; the message names the file."""


def check_audio(audio) -> np.ndarray:
    """Samples a stream takes (mono, float, in [-1, 1]) as float32; anything else is a ValueError saying why."""
    a = np.asarray(audio)
    if a.ndim != 1:
        raise ValueError(f"audio must be mono 1-D samples, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"audio must be float samples in [-1, 1], got dtype {a.dtype}")
    return a.astype(np.float32, copy=False)


# ---- reading -------------------------------------------------------------------------------------


class WavLayout(NamedTuple):
    """Where a WAV file's samples are and how they are encoded (`wav_layout`)."""

    path: str
    tag: int  # _PCM or _FLOAT (WAVE_FORMAT_EXTENSIBLE resolved)
    channels: int
    rate: int
    bits: int
    block_align: int  # bytes per sample frame
    data_at: int  # the first sample's byte in the file
    frames: int  # whole sample frames in the data chunk

    @property
    def seconds(self) -> float:
        return self.frames / self.rate


def wav_layout(path: str | Path) -> WavLayout:
    """The RIFF chunks of a WAV file, walked without reading its samples (a file of any length): AudioError naming
    the file for anything that is not a readable WAV. PCM 8/16/24/32-bit, IEEE float 32/64-bit, and
    WAVE_FORMAT_EXTENSIBLE wrapping either."""
    path = str(path)
    try:
        with open(path, "rb") as f:
            size_of_file = f.seek(0, 2)
            f.seek(0)
            head = f.read(12)
            if len(head) < 12 or head[:4] != b"RIFF" or head[8:12] != b"WAVE":
                raise AudioError(f"{path}: not a WAV file (no RIFF/WAVE header)")
            fmt = data = None
            pos = 12
            while pos + 8 <= size_of_file:
                f.seek(pos)
                cid, size = struct.unpack("<4sI", f.read(8))
                present = min(size, size_of_file - pos - 8)
                if cid == b"data":
                    if present < size and size not in (0, 0xFFFFFFFF):  # 0 / -1: size unknown to a streaming writer
                        raise AudioError(f"{path}: truncated: the data chunk declares {size} bytes but {present} are "
                                         "present")
                    data = (pos + 8, size if size not in (0, 0xFFFFFFFF) else size_of_file - pos - 8)
                elif cid == b"fmt ":
                    if present < 16:
                        raise AudioError(f"{path}: truncated or malformed 'fmt ' chunk ({present} bytes)")
                    fmt = f.read(min(size, 64))
                pos += 8 + size + (size & 1)  # chunks are word aligned
    except OSError as e:
        raise AudioError(f"{path}: cannot read: {e.strerror or e}") from None
    if fmt is None or data is None:
        raise AudioError(f"{path}: not a usable WAV file: missing the {'fmt ' if fmt is None else 'data'} chunk (truncated?)")
    tag, channels, rate, _, block_align, bits = struct.unpack("<HHIIHH", fmt[:16])
    if tag == _EXTENSIBLE:
        if len(fmt) < 26:
            raise AudioError(f"{path}: WAVE_FORMAT_EXTENSIBLE header too short")
        tag = struct.unpack("<H", fmt[24:26])[0]  # first two bytes of the SubFormat GUID
    if channels < 1 or rate < 1 or block_align < 1:
        raise AudioError(f"{path}: invalid format: {channels} channels, {rate} Hz, block align {block_align}")
    layout = WavLayout(path, tag, channels, rate, bits, block_align, data[0], data[1] // block_align)
    _decode(path, tag, bits, np.zeros((0, channels, block_align // channels), np.uint8))  # (an unsupported encoding)
    return layout


def read_wav(path: str | Path) -> tuple[np.ndarray, int]:
    """Samples (n, channels) float32 in [-1, 1] and the sample rate, at the file's own rate (`wav_layout`)."""
    layout = wav_layout(path)
    (x,) = wav_blocks(layout, max(layout.frames, 1))
    return x, layout.rate


def wav_blocks(layout: WavLayout, frames: int):
    """The samples of a WAV file (`wav_layout`), (n, channels) float32 in [-1, 1], in blocks of `frames` sample
    frames (the last one shorter; one empty block for a file without samples): a file of any length in the memory
    of one block."""
    width = layout.block_align // layout.channels
    try:
        with open(layout.path, "rb") as f:
            f.seek(layout.data_at)
            done = 0
            while True:
                n = min(frames, layout.frames - done)
                raw = f.read(n * layout.block_align)
                n = len(raw) // layout.block_align
                block = np.frombuffer(raw[:n * layout.block_align], dtype=np.uint8).reshape(-1, layout.channels, width)
                yield _decode(layout.path, layout.tag, layout.bits, block)
                done += n
                if done >= layout.frames or n == 0:
                    return
    except OSError as e:
        raise AudioError(f"{layout.path}: cannot read: {e.strerror or e}") from None


def _decode(path: str, tag: int, bits: int, frames: np.ndarray) -> np.ndarray:
    """(n, channels, width) bytes -> (n, channels) float32."""
    n, ch, width = frames.shape
    flat = np.ascontiguousarray(frames).reshape(-1)
    if tag == _FLOAT and width in (4, 8):
        x = flat.view("<f4" if width == 4 else "<f8").astype(np.float32)
    elif tag == _PCM and width == 1:
        x = (flat.astype(np.float32) - 128.0) / 128.0
    elif tag == _PCM and width == 2:
        x = flat.view("<i2").astype(np.float32) / 32768.0
    elif tag == _PCM and width == 3:
        b = flat.reshape(-1, 3).astype(np.int32)
        v = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
        x = (np.where(v >= 1 << 23, v - (1 << 24), v) / float(1 << 23)).astype(np.float32)
    elif tag == _PCM and width == 4:
        x = (flat.view("<i4").astype(np.float64) / 2.0**31).astype(np.float32)
    else:
        raise AudioError(f"{path}: unsupported WAV encoding (format tag {tag}, {bits} bits)")
    return x.reshape(n, ch)


def load_wav(path: str | Path, target_rate: int | None = SAMPLE_RATE) -> np.ndarray:
    """Mono float32 samples (channels averaged), resampled to target_rate (None keeps the file rate)."""
    x, rate = read_wav(path)
    mono = x.mean(axis=1, dtype=np.float64) if x.shape[1] > 1 else x[:, 0].astype(np.float64)
    if target_rate is not None and rate != target_rate:
        mono = resample(mono, rate, target_rate)
    return mono.astype(np.float32)


def wav_stream(path: str | Path, target_rate: int = SAMPLE_RATE, block_s: float = 10.0
               ) -> tuple[int, Iterator[np.ndarray]]:
    """`load_wav` in pieces, for a file of any length: (how many samples there are at `target_rate`, an iterator of
    mono float32 blocks of about `block_s` seconds whose concatenation is `load_wav(path, target_rate)`)."""
    layout = wav_layout(path)
    if layout.rate == target_rate:
        total = layout.frames
    else:
        g = math.gcd(layout.rate, target_rate)
        total = -(-layout.frames * (target_rate // g) // (layout.rate // g))  # resample's ceil(n * dst / src)

    def blocks() -> Iterator[np.ndarray]:
        r = None if layout.rate == target_rate else StreamingResampler(layout.rate, target_rate, block=8192)
        for x in wav_blocks(layout, max(1, int(block_s * layout.rate))):
            mono = x.mean(axis=1, dtype=np.float64) if x.shape[1] > 1 else x[:, 0].astype(np.float64)
            yield (mono if r is None else r.process(mono)).astype(np.float32)
        if r is not None:
            yield r.flush().astype(np.float32)
    return total, blocks()


def save_wav(path: str | Path, x: np.ndarray, rate: int) -> None:
    """Write PCM16: x is (n,) mono or (n, channels), float in [-1, 1] (clipped)."""
    x = np.asarray(x, dtype=np.float64)
    x = x[:, None] if x.ndim == 1 else x
    pcm = np.round(np.clip(x, -1.0, 1.0) * 32767.0).astype("<i2")
    with wave.open(str(path), "wb") as w:
        w.setnchannels(x.shape[1])
        w.setsampwidth(2)
        w.setframerate(int(rate))
        w.writeframes(pcm.tobytes())


# ---- the mel filters ------------------------------------------------------------------------------


def mel_weights(n_mels: int, n_fft: int, sample_rate: int, f_min: float = 0.0, f_max: float | None = None
                ) -> np.ndarray:
    """(n_fft//2+1, n_mels) float32 triangular HTK-mel filters, area-normalised (Slaney): the front ends' (as a
    tensor: `dimgestor.frontend.mel`) and the face's, in numpy so that the face's own process needs no torch."""
    f_max = sample_rate / 2 if f_max is None else f_max
    hz_to_mel = lambda f: 2595.0 * math.log10(1.0 + f / 700.0)  # noqa: E731
    mels = np.linspace(hz_to_mel(f_min), hz_to_mel(f_max), n_mels + 2, dtype=np.float64)
    hz = 700.0 * (10.0 ** (mels / 2595.0) - 1.0)  # (n_mels + 2,) band edges
    freqs = np.linspace(0, sample_rate / 2, n_fft // 2 + 1, dtype=np.float64)
    lower, centre, upper = hz[:-2], hz[1:-1], hz[2:]
    up = (freqs[:, None] - lower) / (centre - lower)
    down = (upper - freqs[:, None]) / (upper - centre)
    fb = np.maximum(np.minimum(up, down), 0.0)
    fb = fb * (2.0 / (upper - lower))  # equal area per band, so wide high bands do not dominate
    return fb.astype(np.float32)


# ---- resampling ----------------------------------------------------------------------------------


def kaiser_lowpass(numtaps: int, cutoff: float, beta: float) -> np.ndarray:
    """A linear-phase low-pass FIR: a sinc cut at `cutoff` (a fraction of the Nyquist frequency) under a Kaiser
    window of `beta`, scaled to unit gain at 0 Hz. It is scipy.signal.firwin(numtaps, cutoff, window=("kaiser",
    beta)) to float64 rounding (tests/test_audio.py compares them), written out so that making a resampler does not
    import scipy.signal (~1 s of CPU: every server start and every client at another sample rate paid it)."""
    m = np.arange(numtaps) - 0.5 * (numtaps - 1)
    h = cutoff * np.sinc(cutoff * m) * np.kaiser(numtaps, beta)
    return h / h.sum()


class StreamingResampler:
    """Rational-ratio resampler fed in chunks; the concatenated output equals resample() exactly.

    Output sample m is y[m] = sum_n x[n] h[m*down + D - n*up] (D = filter centre); it is emitted as
    soon as every input it needs has arrived. flush() ends the stream with zeros, as one-shot does.
    """

    def __init__(self, src_rate: int, dst_rate: int, block: int = 4096):
        if int(src_rate) != src_rate or int(dst_rate) != dst_rate or src_rate <= 0 or dst_rate <= 0:
            raise ValueError(f"sample rates must be positive integers, got {src_rate} -> {dst_rate}")
        g = math.gcd(int(src_rate), int(dst_rate))
        self.up, self.down = int(dst_rate) // g, int(src_rate) // g
        self.block = block
        if self.up == self.down:
            self.delay, self.taps = 0, 1
            self.hpoly = np.ones((1, 1))
        else:
            half_len = 10 * max(self.up, self.down)
            h = kaiser_lowpass(2 * half_len + 1, 1.0 / max(self.up, self.down), 5.0) * self.up
            self.delay = half_len
            self.taps = (len(h) - 1) // self.up + 1
            h = np.concatenate([h, np.zeros(self.taps * self.up - len(h))])
            self.hpoly = h.reshape(self.taps, self.up).T  # (up, taps): phase p uses h[p + j*up]
        self.reset()

    def reset(self) -> None:
        self._buf = np.zeros(0)
        self._buf_start = 0  # absolute index of _buf[0]
        self._n_in = 0
        self._m_out = 0

    def _input_index(self, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = m * self.down + self.delay
        return t // self.up, t % self.up  # newest input used, filter phase

    def _outputs(self, m0: int, m1: int) -> np.ndarray:
        out = []
        padded = np.concatenate([self._buf, [0.0]])  # the extra zero stands for every index outside
        for a in range(m0, m1, self.block):
            m = np.arange(a, min(a + self.block, m1))
            n_hi, phase = self._input_index(m)
            idx = n_hi[:, None] - np.arange(self.taps)[None, :] - self._buf_start
            # Indices outside the buffer are before the signal start or after its end: zeros.
            xs = padded[np.where((idx >= 0) & (idx < len(self._buf)), idx, len(self._buf))]
            out.append(np.sum(self.hpoly[phase] * xs, axis=1))
        return np.concatenate(out) if out else np.zeros(0)

    def process(self, chunk: np.ndarray) -> np.ndarray:
        chunk = np.asarray(chunk, dtype=np.float64).reshape(-1)
        self._buf = np.concatenate([self._buf, chunk])
        self._n_in += len(chunk)
        m_end = max(self._m_out, -((self.delay - self._n_in * self.up) // self.down))  # ceil((n_in*up - D)/down)
        y = self._outputs(self._m_out, m_end)
        self._m_out = m_end
        keep_from = self._input_index(np.array(self._m_out))[0] - (self.taps - 1)
        drop = int(min(max(keep_from - self._buf_start, 0), len(self._buf)))
        self._buf, self._buf_start = self._buf[drop:], self._buf_start + drop
        return y.astype(np.float32)

    @property
    def inputs(self) -> int:
        """Input samples taken so far."""
        return self._n_in

    @property
    def outputs(self) -> int:
        """Output samples given so far."""
        return self._m_out

    def get_state(self) -> dict:
        """What the next outputs depend on besides the filter: JSON-ready (the input history as float64 hex)."""
        return {"up": self.up, "down": self.down, "buf": self._buf.astype("<f8").tobytes().hex(),
                "buf_start": int(self._buf_start), "n_in": int(self._n_in), "m_out": int(self._m_out)}

    def set_state(self, state: dict) -> None:
        """A state from `get_state` of a resampler with the same rates: it goes on exactly as that one would.
        ValueError, saying why, for any other (`check_state`); the resampler is then unchanged."""
        self.check_state(state)
        self._buf = np.frombuffer(bytes.fromhex(state["buf"]), "<f8").astype(np.float64)
        self._buf_start, self._n_in, self._m_out = state["buf_start"], state["n_in"], state["m_out"]

    def check_state(self, state) -> None:
        """ValueError unless `state` is one `get_state` of this resampler could give (a stored state is untrusted):
        the same rates, the counts it keeps consistent, the input history it keeps, finite."""
        keys = {"up", "down", "buf", "buf_start", "n_in", "m_out"}
        if not isinstance(state, dict) or set(state) != keys:
            raise ValueError(f"a resampler state is an object of {sorted(keys)}")
        bad = sorted(k for k in keys - {"buf"} if not isinstance(state[k], int) or isinstance(state[k], bool)
                     or state[k] < 0)
        if bad:
            raise ValueError(f"a resampler state's counts are integers >= 0, not its {', '.join(bad)}")
        if (state["up"], state["down"]) != (self.up, self.down):
            raise ValueError(f"a resampler state for {state['down']} -> {state['up']} does not fit "
                             f"{self.down} -> {self.up}")
        n_in, m_out, start = state["n_in"], state["m_out"], state["buf_start"]
        if m_out != max(0, -((self.delay - n_in * self.up) // self.down)):
            raise ValueError(f"a resampler state with {n_in} inputs gave {m_out} outputs")
        keep_from = (m_out * self.down + self.delay) // self.up - (self.taps - 1)
        if start != min(max(keep_from, 0), n_in):
            raise ValueError(f"a resampler state keeps its inputs from {start}, not {min(max(keep_from, 0), n_in)}")
        buf = state["buf"]
        if not isinstance(buf, str) or len(buf) != 16 * (n_in - start):
            raise ValueError(f"a resampler state holds {n_in - start} inputs: {16 * (n_in - start)} hex digits")
        try:
            x = np.frombuffer(bytes.fromhex(buf), "<f8")
        except ValueError:
            raise ValueError("a resampler state's inputs are not hex digits") from None
        if not np.isfinite(x).all():
            raise ValueError("a resampler state's inputs hold NaN or infinite values")

    def flush(self) -> np.ndarray:
        """The remaining outputs (input padded with zeros); total length ceil(n_in * up / down)."""
        total = -((-self._n_in * self.up) // self.down)
        y = self._outputs(self._m_out, total)
        self.reset()
        return y.astype(np.float32)


def resample(x: np.ndarray, src_rate: int, dst_rate: int) -> np.ndarray:
    """Anti-aliased resampling of a 1-D signal; output length ceil(len(x) * dst / src)."""
    if src_rate == dst_rate:
        return np.asarray(x, dtype=np.float32).copy()
    r = StreamingResampler(src_rate, dst_rate, block=8192)
    return np.concatenate([r.process(x), r.flush()])


# ---- alignment -----------------------------------------------------------------------------------


def align(motion_seconds: float, audio: np.ndarray, rate: int = SAMPLE_RATE, name: str = "",
          tolerance_s: float = 0.5) -> tuple[float, np.ndarray]:
    """Trim motion and audio to the shorter of the two; warn when they differ by more than tolerance_s.

    Returns (seconds kept, audio trimmed to that length).
    """
    audio_seconds = len(audio) / rate
    if abs(audio_seconds - motion_seconds) > tolerance_s:
        warnings.warn(
            f"{name or 'pair'}: motion is {motion_seconds:.2f} s but audio is {audio_seconds:.2f} s; "
            "trimming both to the shorter", stacklevel=2,
        )
    seconds = min(motion_seconds, audio_seconds)
    return seconds, audio[: int(round(seconds * rate))]
