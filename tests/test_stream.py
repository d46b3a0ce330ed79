import numpy as np
import pytest
import torch

from dimgestor.config import get_preset
from dimgestor.model.diffusion import Diffusion
from dimgestor.model.network import DiMGestor
from dimgestor.streaming.stream import GestureStream, generate_offline
from helpers.stream import noise_audio as _audio, random_tiny_model as _model, stream_in_pieces as _stream


@pytest.fixture(scope="module")
def model():
    return _model()


@pytest.mark.parametrize("chunk", [160, 1000, 3333])
def test_streaming_equals_offline(model, chunk):
    audio = _audio(2.0 + 123 / 16000)
    offline = generate_offline(model, audio, steps=8, seed=5)
    assert offline.shape == (40, 12) and np.abs(offline).max() > 0.1
    sizes = [chunk] * (len(audio) // chunk) + [len(audio) % chunk]
    streamed = _stream(model, audio, sizes, steps=8, seed=5)
    assert np.abs(streamed - offline).max() < 1e-4


def test_streaming_with_odd_splits_and_eta(model):
    audio = _audio(1.3)
    rng = np.random.default_rng(3)
    sizes = []
    while sum(sizes) < len(audio):
        sizes.append(int(rng.choice([1, 2, 799, 801, 1601])))
    sizes[-1] -= sum(sizes) - len(audio)
    offline = generate_offline(model, audio, steps=5, seed=9, eta=0.7)
    assert np.abs(_stream(model, audio, sizes, steps=5, seed=9, eta=0.7) - offline).max() < 1e-4
    assert not np.allclose(offline, generate_offline(model, audio, steps=5, seed=9, eta=0.0))


def test_ddpm_streaming_equals_offline():
    model = _model(n_steps=40)
    audio = _audio(0.8)
    offline = generate_offline(model, audio, sampler="ddpm", seed=2)
    assert offline.shape == (16, 12)
    assert np.abs(_stream(model, audio, [1000] * 12 + [800], sampler="ddpm", seed=2) - offline).max() < 1e-4


def test_seed_changes_the_frames_and_frames_follow_the_audio(model):
    a = _audio(1.0)
    assert not np.allclose(generate_offline(model, a, seed=0), generate_offline(model, a, seed=1))
    b = a.copy()
    b[8000:] = 0  # silence after 0.5 s: the first frames (before 0.5 s - lookahead) are unchanged
    fa, fb = generate_offline(model, a), generate_offline(model, b)
    assert np.allclose(fa[:9], fb[:9], atol=1e-6) and not np.allclose(fa[10:], fb[10:])


def test_length_latency_and_edges(model):
    s = GestureStream(model)
    assert s.lookahead_s == pytest.approx(0.08)
    assert len(s.push(np.zeros(1279, np.float32))) == 0  # frame 0 needs 800 + 480 samples
    assert len(s.push(np.zeros(1, np.float32))) == 1
    assert len(s.finish()) == 0 and s.frames_out == 1  # 1280 samples -> T = 1
    with pytest.raises(RuntimeError):
        s.push(np.zeros(10, np.float32))
    assert generate_offline(model, np.zeros(799, np.float32)).shape == (0, 12)
    with pytest.raises(ValueError, match="mono"):
        generate_offline(model, np.zeros((2, 800), np.float32))
    with pytest.raises(ValueError, match="float"):
        GestureStream(model).push(np.zeros(800, np.int16))


def test_loss_goes_down_on_synthetic_data():
    """A tiny model learns a loudness -> motion link: the loss on fixed held-out noise falls clearly."""
    torch.manual_seed(0)
    model = DiMGestor(get_preset("tiny"))
    diffusion = Diffusion(model.config)
    B, T = 8, 24
    audio = torch.stack([torch.from_numpy(_audio(T / 20 + 0.03, seed=s)) for s in range(B)])
    feats, _ = model.frontend(audio, model.frontend.init_state(B))
    loud = feats.mean(-1)[:, : T * 5].reshape(B, T, 5).mean(-1)  # (B, T)
    x0 = torch.stack([torch.sin(torch.cumsum(loud, 1) * (k + 1)) for k in range(12)], -1)  # motion from loudness
    g = torch.Generator().manual_seed(0)
    t_eval, n_eval = torch.randint(0, 1000, (B,), generator=g), torch.randn(x0.shape, generator=g)

    def eval_loss():
        with torch.no_grad():
            return diffusion.training_loss(model, x0, feats, t_eval, n_eval).item()

    before = eval_loss()
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    for _ in range(150):
        loss = diffusion.training_loss(model, x0, feats, torch.randint(0, 1000, (B,)), torch.randn_like(x0))
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert eval_loss() < 0.5 * before


def test_pretrained_front_end_streams_like_offline(tmp_path):
    transformers = pytest.importorskip("transformers", reason="optional extra `pretrained` not installed")
    torch.manual_seed(0)
    w2v = transformers.Wav2Vec2Config(hidden_size=16, num_hidden_layers=1, num_attention_heads=2, intermediate_size=32,
                                      conv_dim=(8,) * 7, num_conv_pos_embeddings=16, num_conv_pos_embedding_groups=2)
    transformers.Wav2Vec2Model(w2v).save_pretrained(tmp_path)
    model = _model(frontend="pretrained", pretrained_path=str(tmp_path), pretrained_block_ms=200,
                   pretrained_left_ms=200, pretrained_right_ms=100)
    assert model.lookahead_s == pytest.approx(0.3)  # frame 0 needs the first 200 ms block + 100 ms right context
    audio = _audio(1.5)
    offline = generate_offline(model, audio, steps=3, seed=1)
    assert offline.shape == (30, 12)
    assert np.abs(_stream(model, audio, [1111] * 21 + [669], steps=3, seed=1) - offline).max() < 1e-4


@pytest.mark.parametrize("taps", [1, 5])
def test_streaming_recipe_streams_exactly(taps):
    """The default training recipe (short cosine chain, x0, correlated noise) streams like any other."""
    model = _model(n_steps=8, schedule="cosine", prediction="x0", noise_taps=taps)
    audio = _audio(2.1 + 77 / 16000, seed=4)
    for K in (2, 8):
        offline = generate_offline(model, audio, steps=K, seed=3)
        assert offline.shape == (42, 12) and np.isfinite(offline).all()
        for sizes in ([1, 2, 799, 801] * 12 + [len(audio)], [3333] * 11):
            sizes = list(sizes)
            total = 0
            for i, n in enumerate(sizes):
                if total + n >= len(audio):
                    sizes = sizes[:i] + [len(audio) - total]
                    break
                total += n
            else:
                sizes.append(len(audio) - total)
            assert np.abs(_stream(model, audio, sizes, steps=K, seed=3) - offline).max() < 1e-4
    assert not np.allclose(generate_offline(model, audio, steps=8, seed=3), generate_offline(model, audio, steps=8, seed=4))


def _snapshot(state):
    """Copies of everything a StreamState holds (tensors and arrays cloned, counters as they are)."""
    def copy(v):
        if isinstance(v, torch.Tensor):
            return v.clone()
        if isinstance(v, np.ndarray):
            return v.copy()
        if isinstance(v, tuple):
            return type(v)(*map(copy, v)) if hasattr(v, "_fields") else tuple(map(copy, v))
        return v
    return [copy(getattr(state, f)) for f in state.__dataclass_fields__]


def _same(a, b):
    if isinstance(a, torch.Tensor):
        return torch.equal(a, b)
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    if isinstance(a, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


@pytest.mark.parametrize("guidance,smoothing,frontend", [(1.0, None, "logmel"), (2.0, (3.0, 0.5), "logmel"),
                                                        (1.0, 2.0, "speech")])
def test_a_step_only_reads_its_state(model, guidance, smoothing, frontend):
    """step(state, audio) -> (frames, state): the state given stays as it was, so stepping it again gives the
    same frames (front end, extractor, every denoiser step, the output filter and the counters are all in it)."""
    if frontend != model.config.frontend:
        model = _model(frontend=frontend)
    audio = _audio(1.6)
    s = GestureStream(model, steps=3, seed=4, smoothing=smoothing, guidance=guidance)
    _, s1 = s.step(s.state, audio[:7001])
    kept = _snapshot(s1)
    a, s2 = s.step(s1, audio[7001:19000])
    b, s3 = s.step(s1, audio[7001:19000])
    assert len(a) > 0 and np.array_equal(a, b)
    assert all(_same(x, y) for x, y in zip(kept, _snapshot(s1)))  # s1 untouched by two steps from it
    assert (s2.samples_in, s2.frames_out) == (19000, s1.frames_out + len(a))
    assert (s2.smoother is not None) == (smoothing is not None)  # the output filter's state is in the state too
    end, done = s.finish_step(s2)
    assert done.finished and not s2.finished and done.frames_out == len(audio[:19000]) * 20 // 16000
    with pytest.raises(RuntimeError, match="after finish"):
        s.step(done, audio[:10])
    want = generate_offline(model, audio[:19000], steps=3, seed=4, smoothing=smoothing, guidance=guidance)
    got = np.concatenate([s.step(s.initial_state(), audio[:7001])[0], a, end])
    assert np.abs(got - want).max() < 1e-4
