import numpy as np
import pytest
import torch

from dimgestor.config import get_preset
from dimgestor.frontend.base import LogMelFrontEnd, PretrainedFrontEnd
from dimgestor.frontend.mel import mel_filterbank


def _chunked(fe, audio, sizes):
    state, out, i = fe.init_state(1), [], 0
    for n in sizes:
        f, state = fe(audio[:, i:i + n], state)
        out.append(f)
        i += n
    return torch.cat(out, dim=1)


def _splits(total, rng):
    sizes = []
    while sum(sizes) < total:
        sizes.append(int(rng.choice([1, 7, 159, 160, 161, 1000, 3333])))
    sizes[-1] -= sum(sizes) - total
    return sizes


def test_logmel_chunked_equals_one_shot():
    fe = LogMelFrontEnd(get_preset("tiny"))
    rng = np.random.default_rng(0)
    audio = torch.from_numpy(rng.standard_normal((1, 16000 + 77)).astype(np.float32) * 0.1)
    whole, _ = fe(audio, fe.init_state(1))
    assert whole.shape == (1, (16000 + 77) // 160, 20)
    for _ in range(3):
        parts = _chunked(fe, audio, _splits(audio.shape[1], rng))
        assert torch.allclose(whole, parts, atol=1e-5)


def test_logmel_is_causal_and_needs_no_lookahead():
    fe = LogMelFrontEnd(get_preset("tiny"))
    audio = torch.randn(1, 1600) * 0.1
    f, _ = fe(audio, fe.init_state(1))
    audio2 = audio.clone()
    audio2[:, 800:] = 0.5  # change the future after frame 4
    f2, _ = fe(audio2, fe.init_state(1))
    assert torch.equal(f[:, :5], f2[:, :5]) and not torch.equal(f[:, 5], f2[:, 5])
    assert fe.samples_needed(5) == 800


def test_logmel_sees_a_tone_in_the_right_band():
    c = get_preset("tiny")
    fe = LogMelFrontEnd(c)
    t = torch.arange(16000) / 16000
    f, _ = fe(torch.sin(2 * torch.pi * 1000 * t)[None] * 0.5, fe.init_state(1))
    peak = f[0, 10:].mean(0).argmax().item()
    fb = mel_filterbank(c.n_mels, c.n_fft, c.sample_rate)
    assert peak == fb[round(1000 / 8000 * (c.n_fft // 2))].argmax().item()
    silence, _ = fe(torch.zeros(1, 1600), fe.init_state(1))
    assert torch.allclose(silence, torch.full_like(silence, -1.0))


def test_pretrained_requires_a_local_folder(tmp_path):
    cfg = get_preset("tiny", frontend="pretrained", pretrained_path=str(tmp_path / "missing"))
    with pytest.raises(FileNotFoundError, match="not a local model folder"):
        PretrainedFrontEnd(cfg)


@pytest.fixture
def tiny_wav2vec2(tmp_path):
    transformers = pytest.importorskip("transformers", reason="optional extra `pretrained` not installed")
    torch.manual_seed(0)
    cfg = transformers.Wav2Vec2Config(hidden_size=16, num_hidden_layers=2, num_attention_heads=2,
                                      intermediate_size=32, conv_dim=(8, 8, 8, 8, 8, 8, 8),
                                      num_conv_pos_embeddings=16, num_conv_pos_embedding_groups=2,
                                      feat_extract_norm="layer")
    transformers.Wav2Vec2Model(cfg).save_pretrained(tmp_path)
    return tmp_path


def test_pretrained_streaming_equals_offline(tiny_wav2vec2):
    cfg = get_preset("tiny", frontend="pretrained", pretrained_path=str(tiny_wav2vec2),
                     pretrained_block_ms=200, pretrained_left_ms=400, pretrained_right_ms=100)
    fe = PretrainedFrontEnd(cfg)
    assert fe.dim == 16
    rng = np.random.default_rng(1)
    audio = torch.from_numpy(rng.standard_normal((1, 16000)).astype(np.float32) * 0.1)
    whole, _ = fe(audio, fe.init_state(1))
    # 16000 samples: blocks of 3200 need 1600 samples beyond them -> 4 complete blocks of 20 frames
    assert whole.shape == (1, 80, 16) and fe.samples_needed(80) == 4 * 3200 + 1600
    parts = _chunked(fe, audio, _splits(16000, rng))
    assert torch.allclose(whole, parts, atol=1e-5)
