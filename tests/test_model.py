import pytest
import torch

from dimgestor.config import get_preset
from dimgestor.model.network import AdaLNMamba2Block, DiMGestor, modulate


def _randomize(model, scale=0.05):
    """Perturb every weight so the zero-initialised parts do not make a parity test trivial."""
    torch.manual_seed(1)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p) * scale)
    return model


def test_modulate():
    x = torch.ones(1, 2, 3)
    assert torch.equal(modulate(x, torch.full_like(x, 2.0), torch.full_like(x, 1.0)), torch.full_like(x, 4.0))


def test_block_is_identity_at_init():
    torch.manual_seed(0)
    model = DiMGestor(get_preset("tiny"))
    x, c = torch.randn(2, 9, 32), torch.randn(2, 9, 32)
    for block in model.blocks:
        y, _ = block(x, c)
        assert torch.equal(y, x)
    out, _ = model(torch.randn(2, 9, 12), 500, c)
    assert torch.equal(out, torch.zeros_like(out))  # zeroed final layer


def test_a_trained_like_block_is_not_identity():
    torch.manual_seed(0)
    block = AdaLNMamba2Block(get_preset("tiny"))
    x, c = torch.randn(1, 5, 32), torch.randn(1, 5, 32)
    assert not torch.allclose(block(x, c)[0], x)


def test_denoiser_window_by_window_equals_whole():
    model = _randomize(DiMGestor(get_preset("tiny")))
    x, c = torch.randn(1, 37, 12), torch.randn(1, 37, 32)
    whole, _ = model(x, 321, c)
    state, parts = None, []
    for a, b in [(0, 1), (1, 17), (17, 18), (18, 37)]:
        y, state = model(x[:, a:b], 321, c[:, a:b], state)
        parts.append(y)
    assert torch.allclose(whole, torch.cat(parts, 1), atol=1e-5)


def test_denoiser_is_causal():
    model = _randomize(DiMGestor(get_preset("tiny")))
    x, c = torch.randn(1, 20, 12), torch.randn(1, 20, 32)
    y, _ = model(x, 10, c)
    x2, c2 = x.clone(), c.clone()
    x2[:, 12:] += 1
    c2[:, 12:] -= 1
    y2, _ = model(x2, 10, c2)
    assert torch.allclose(y[:, :12], y2[:, :12], atol=1e-6) and not torch.allclose(y[:, 12], y2[:, 12])


def test_extractor_windows_equal_whole_and_respect_lookahead():
    cfg = get_preset("tiny")  # kernel 11, lookahead 3 feature frames
    model = _randomize(DiMGestor(cfg))
    feats = torch.randn(1, 103, cfg.n_mels)
    whole, _ = model.condition(feats)
    assert whole.shape == (1, (103 - 3) // 5, 32)
    state, parts = None, []
    for a, b in [(0, 1), (1, 8), (8, 9), (9, 60), (60, 103)]:
        cnd, state = model.condition(feats[:, a:b], state)
        parts.append(cnd)
    assert torch.allclose(whole, torch.cat(parts, 1), atol=1e-5)
    # frame 4 (features 20..24) may see features up to 27, not 28
    f2 = feats.clone()
    f2[:, 28:] += 1
    changed, _ = model.condition(f2)
    assert torch.allclose(whole[:, :5], changed[:, :5], atol=1e-6) and not torch.allclose(whole[:, 5], changed[:, 5])


def test_latency_and_sample_bookkeeping():
    model = DiMGestor(get_preset("tiny"))
    assert model.samples_needed(1) == (5 + 3) * 160  # one frame + 30 ms lookahead
    assert model.lookahead_s == pytest.approx(0.08)
    counts = model.param_counts()
    assert set(counts) >= {"frontend", "style_extractor", "downsampler", "denoiser_blocks", "encoder_decoder"}
    assert sum(counts.values()) == sum(p.numel() for p in model.parameters())
    sizes = model.stream_state_nbytes(8)
    assert sizes["total"] == sizes["frontend"] + sizes["extractor"] + 8 * sizes["denoiser_per_step"]


@pytest.mark.parametrize("T", [129, 300])
def test_long_sequences_run_in_segments_equal_one_pass(T):
    """forward splits sequences longer than segment_frames (2 chunks) and carries the state: same frames."""
    model = _randomize(DiMGestor(get_preset("tiny")))
    assert model.segment_frames == 2 * model.config.chunk_size == 32
    x, c = torch.randn(2, T, 12), torch.randn(2, T, 32)
    s0 = model.init_state(2)
    y_seg, s_seg = model(x, 77, c, s0)
    model.segment_frames = 10 ** 6  # one pass over the whole sequence
    y_one, s_one = model(x, 77, c, s0)
    torch.testing.assert_close(y_seg, y_one, rtol=1e-5, atol=1e-5)
    for a, b in zip(s_seg.blocks, s_one.blocks):
        torch.testing.assert_close(a.ssm, b.ssm, rtol=1e-5, atol=1e-5)


def test_batch_rows_are_independent_streams():
    """Each batch row carries its own state and step: a row run in a batch equals the row run alone."""
    model = _randomize(DiMGestor(get_preset("tiny")))
    torch.manual_seed(3)
    x, c = torch.randn(3, 4, 12), torch.randn(3, 4, 32)
    _, state = model(torch.randn(3, 5, 12), 500, torch.randn(3, 5, 32))  # a different past per row
    t = torch.tensor([999, 500, 1])
    y, s = model(x, t, c, state)
    for i in range(3):
        row = type(state)(state.enc[i:i + 1], tuple(type(b)(b.conv[i:i + 1], b.ssm[i:i + 1]) for b in state.blocks))
        yi, si = model(x[i:i + 1], t[i:i + 1], c[i:i + 1], row)
        torch.testing.assert_close(y[i:i + 1], yi, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(s.blocks[-1].ssm[i:i + 1], si.blocks[-1].ssm, rtol=1e-5, atol=1e-5)


def test_carried_states_do_not_keep_a_windows_tensors_alive():
    """The tails a forward returns own their small storage: a view would keep the whole window's
    activations (xBC, the feature buffer) alive for as long as the state is carried."""
    model = _randomize(DiMGestor(get_preset("tiny")))
    T = 300
    with torch.inference_mode():
        _, s = model(torch.randn(1, T, 12), 5, torch.randn(1, T, 32))
        feats = torch.randn(1, T * 5, model.frontend.dim)
        _, ex = model.condition(feats)
    tails = [s.enc] + [b.conv for b in s.blocks] + [b.ssm for b in s.blocks] + [ex.buf]
    for t in tails:
        assert t.untyped_storage().nbytes() == t.numel() * t.element_size()
