"""WAV reading in every common encoding, anti-aliased resampling, streaming parity, alignment."""

import math
import struct
import warnings

import numpy as np
import pytest
from scipy.signal import firwin, resample_poly

from dimgestor.audio import (AudioError, StreamingResampler, align, kaiser_lowpass, load_wav, read_wav, resample,
                             save_wav)

EXTENSIBLE_GUID_TAIL = b"\x00\x00\x00\x00\x10\x00\x80\x00\x00\xaa\x00\x38\x9b\x71"


def write_riff(path, samples, rate, encoding, extensible=False, extra_chunk=True):
    """A WAV written by hand, so the reader is tested against the format, not against itself."""
    x = np.asarray(samples, dtype=np.float64)
    x = x[:, None] if x.ndim == 1 else x
    channels = x.shape[1]
    if encoding == "pcm16":
        tag, bits, data = 1, 16, np.round(x * 32767).astype("<i2").tobytes()
    elif encoding == "pcm24":
        v = np.round(x * (2**23 - 1)).astype(np.int64) & 0xFFFFFF
        tag, bits = 1, 24
        data = np.stack([v & 0xFF, (v >> 8) & 0xFF, (v >> 16) & 0xFF], -1).astype(np.uint8).tobytes()
    elif encoding == "pcm32":
        tag, bits, data = 1, 32, np.round(x * (2**31 - 1)).astype("<i4").tobytes()
    elif encoding == "float32":
        tag, bits, data = 3, 32, x.astype("<f4").tobytes()
    elif encoding == "pcm8":
        tag, bits, data = 1, 8, np.round(x * 127 + 128).astype(np.uint8).tobytes()
    block = channels * bits // 8
    if extensible:
        fmt = struct.pack("<HHIIHHHHI", 0xFFFE, channels, rate, rate * block, block, bits, 22, bits, 0)
        fmt += struct.pack("<H", tag) + EXTENSIBLE_GUID_TAIL
    else:
        fmt = struct.pack("<HHIIHH", tag, channels, rate, rate * block, block, bits)
    chunks = b"fmt " + struct.pack("<I", len(fmt)) + fmt
    if extra_chunk:  # an odd-sized LIST chunk before the data exercises chunk walking and padding
        chunks += b"LIST" + struct.pack("<I", 5) + b"INFOx" + b"\x00"
    chunks += b"data" + struct.pack("<I", len(data)) + data
    path.write_bytes(b"RIFF" + struct.pack("<I", 4 + len(chunks)) + b"WAVE" + chunks)
    return path


def tone(freq, rate, seconds=0.5, amp=0.5):
    t = np.arange(int(rate * seconds)) / rate
    return amp * np.sin(2 * np.pi * freq * t)


@pytest.mark.parametrize(
    "encoding, extensible, tol",
    [("pcm16", False, 1e-4), ("pcm24", False, 1e-6), ("pcm32", False, 1e-7), ("float32", False, 1e-7),
     ("pcm8", False, 1e-2), ("pcm24", True, 1e-6), ("float32", True, 1e-7)],
)
def test_reads_every_encoding(tmp_path, encoding, extensible, tol):
    x = tone(440.0, 16000)
    path = write_riff(tmp_path / "a.wav", x, 16000, encoding, extensible)
    y = load_wav(path)
    assert y.dtype == np.float32 and y.shape == x.shape
    np.testing.assert_allclose(y, x, atol=tol)


def test_stereo_is_averaged_and_channels_are_kept_by_read_wav(tmp_path):
    left, right = tone(300.0, 16000), tone(500.0, 16000, amp=0.25)
    path = write_riff(tmp_path / "s.wav", np.stack([left, right], -1), 16000, "pcm24")
    raw, rate = read_wav(path)
    assert raw.shape == (len(left), 2) and rate == 16000
    np.testing.assert_allclose(load_wav(path), (left + right) / 2, atol=1e-6)


def test_other_rates_are_resampled_to_16k_keeping_pitch(tmp_path):
    path = write_riff(tmp_path / "cd.wav", tone(440.0, 44100, seconds=1.0), 44100, "pcm16")
    y = load_wav(path)
    assert len(y) == 16000
    spectrum = np.abs(np.fft.rfft(y * np.hanning(len(y))))
    assert np.argmax(spectrum) == 440  # 1 s of audio: bin k is k Hz
    assert load_wav(path, target_rate=None).shape == (44100,)


def test_save_wav_round_trip(tmp_path):
    x = tone(220.0, 22050)
    save_wav(tmp_path / "o.wav", x, 22050)
    raw, rate = read_wav(tmp_path / "o.wav")
    assert rate == 22050
    np.testing.assert_allclose(raw[:, 0], x, atol=1 / 32767)


def test_bad_files_raise_audio_error_naming_the_file(tmp_path):
    text = tmp_path / "notes.wav"
    text.write_text("these are meeting notes, not audio")
    with pytest.raises(AudioError, match=r"notes\.wav: not a WAV file"):
        load_wav(text)
    good = write_riff(tmp_path / "cut.wav", tone(440.0, 16000), 16000, "pcm16", extra_chunk=False)
    good.write_bytes(good.read_bytes()[:-1000])
    with pytest.raises(AudioError, match=r"cut\.wav: truncated"):
        load_wav(good)
    header_only = tmp_path / "header.wav"
    header_only.write_bytes(good.read_bytes()[:30])
    with pytest.raises(AudioError, match=r"header\.wav"):
        load_wav(header_only)
    with pytest.raises(AudioError, match=r"missing\.wav: cannot read"):
        load_wav(tmp_path / "missing.wav")


@pytest.mark.parametrize("src, dst", [(44100, 16000), (48000, 16000), (8000, 16000), (22050, 16000), (16000, 24000)])
def test_resample_equals_scipy_polyphase_reference(src, dst):
    x = np.random.default_rng(0).normal(size=5001)
    g = math.gcd(src, dst)
    ref = resample_poly(x, dst // g, src // g)
    y = resample(x, src, dst)
    assert len(y) == math.ceil(len(x) * dst / src) == len(ref)
    np.testing.assert_allclose(y, ref, atol=1e-6)


def test_resampling_removes_what_would_alias_and_keeps_the_passband():
    rate = 48000
    passed = resample(tone(1000.0, rate, 1.0), rate, 16000)[2000:-2000]
    blocked = resample(tone(10000.0, rate, 1.0), rate, 16000)[2000:-2000]  # above the new Nyquist (8 kHz)
    assert abs(np.sqrt(2) * passed.std() - 0.5) < 0.005
    assert 20 * np.log10(blocked.std() / passed.std()) < -50


@pytest.mark.parametrize("src, dst", [(44100, 16000), (8000, 16000), (48000, 16000), (16000, 16000)])
def test_streaming_resampler_equals_one_shot_for_any_chunking(src, dst):
    x = np.random.default_rng(1).normal(size=9000).astype(np.float32)
    whole = resample(x, src, dst)
    for sizes in ([1] * 50 + [8950], [0, 7, 13, 441, 1, 160, 8378], [9000]):
        r = StreamingResampler(src, dst)
        parts, i = [], 0
        for n in sizes:
            parts.append(r.process(x[i:i + n]))
            i += n
        parts.append(r.flush())
        np.testing.assert_array_equal(np.concatenate(parts), whole)


def test_align_trims_to_the_shorter_and_warns_on_a_large_mismatch():
    audio = np.zeros(16000 * 10, dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seconds, trimmed = align(9.8, audio, name="close")
    assert seconds == 9.8 and len(trimmed) == 156800
    with pytest.warns(UserWarning, match=r"far: motion is 12\.00 s but audio is 10\.00 s"):
        seconds, trimmed = align(12.0, audio, name="far")
    assert seconds == 10.0 and len(trimmed) == len(audio)


def test_a_resampler_state_carried_to_another_resampler_goes_on_exactly():
    """StreamingResampler.get_state / set_state (a session handed over at 48 kHz): a new resampler given the
    state after the first part makes exactly the outputs the first one would have made."""
    import json

    from dimgestor.audio import StreamingResampler

    x = np.random.default_rng(3).standard_normal(48000).astype(np.float32) * 0.3
    whole = StreamingResampler(48000, 16000)
    expected = np.concatenate([whole.process(x[:17011]), whole.process(x[17011:])])
    first = StreamingResampler(48000, 16000)
    part = first.process(x[:17011])
    state = json.loads(json.dumps(first.get_state()))  # (it travels as JSON)
    second = StreamingResampler(48000, 16000)
    second.set_state(state)
    assert second.inputs == 17011 and second.outputs == len(part)
    assert np.array_equal(np.concatenate([part, second.process(x[17011:])]), expected)
    with pytest.raises(ValueError, match="does not fit"):
        StreamingResampler(44100, 16000).set_state(state)


@pytest.mark.parametrize("up, down", [(160, 441), (1, 3), (2, 3), (147, 160), (160, 147), (1, 12), (4, 1)])
def test_the_resamplers_filter_is_scipys_firwin(up, down):
    """The resampler designs its filter with numpy (no scipy.signal import: ~1 s of CPU at a server's start or its
    first resampling client): scipy.signal.firwin's Kaiser-windowed sinc to float64 rounding."""
    half = 10 * max(up, down)
    want = firwin(2 * half + 1, 1.0 / max(up, down), window=("kaiser", 5.0))
    np.testing.assert_allclose(kaiser_lowpass(2 * half + 1, 1.0 / max(up, down), 5.0), want, rtol=0, atol=1e-15)


@pytest.mark.parametrize("rate,channels,block_s", [(16000, 1, 0.37), (44100, 2, 1.0), (48000, 1, 0.01),
                                                   (8000, 2, 5.0), (22050, 1, 100.0)])
def test_a_wav_read_in_blocks_is_load_wav_sample_for_sample(tmp_path, rate, channels, block_s):
    """wav_stream (generate's long recordings): the blocks of the file, mixed and resampled as they come, concatenate
    to exactly load_wav's samples, and the count it gives up front is theirs."""
    from dimgestor.audio import wav_stream

    x = np.random.default_rng(rate).uniform(-0.9, 0.9, (rate * 2 + 17, channels))
    save_wav(tmp_path / "a.wav", x, rate)
    total, blocks = wav_stream(tmp_path / "a.wav", block_s=block_s)
    parts = list(blocks)
    whole = load_wav(tmp_path / "a.wav")
    assert total == len(whole) and np.array_equal(np.concatenate(parts), whole)
    assert all(p.dtype == np.float32 for p in parts) and len(parts) >= min(3, 2 / block_s)
