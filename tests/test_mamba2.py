"""The Mamba-2 mixer: chunked scan == recurrence, windows == whole, reference layout loads."""
import pytest
import torch

from dimgestor.model import mamba2
from dimgestor.model.mamba2 import Mamba2, Mamba2State, ssd_chunked, ssd_naive, ssd_one_chunk, ssd_scan, ssd_steps

@pytest.fixture(autouse=True)
def float64():
    """Exactness checks: keep float32 rounding out of the way, and restore the default afterwards."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def random_ssd_inputs(b, L, h, p, n, seed):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(b, L, h, p, generator=g)
    dt = torch.nn.functional.softplus(torch.randn(b, L, h, generator=g))
    A = -torch.rand(h, generator=g) * 4 - 0.1
    B = torch.randn(b, L, h, n, generator=g)
    C = torch.randn(b, L, h, n, generator=g)
    h0 = torch.randn(b, h, p, n, generator=g)
    return x, dt, A, B, C, h0


@pytest.mark.parametrize("L", [1, 7, 64, 257])
@pytest.mark.parametrize("chunk", [1, 5, 16, 64])
def test_chunked_scan_equals_recurrence(L, chunk):
    x, dt, A, B, C, h0 = random_ssd_inputs(2, L, 3, 4, 5, seed=L * 100 + chunk)
    for init in (None, h0):
        y_ref, s_ref = ssd_naive(x, dt, A, B, C, init)
        y, s = ssd_chunked(x, dt, A, B, C, chunk, init)
        torch.testing.assert_close(y, y_ref, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(s, s_ref, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("L", [1, 2, 7, 33])
@pytest.mark.parametrize("groups", [1, 3])
def test_one_chunk_scan_equals_recurrence(L, groups):
    x, dt, A, B, C, h0 = random_ssd_inputs(2, L, 6, 4, 5, seed=L + 10 * groups)
    Bg, Cg = B[:, :, :groups], C[:, :, :groups]  # one B and C per group of 6 / groups heads
    rep = 6 // groups
    y_ref, s_ref = ssd_naive(x, dt, A, Bg.repeat_interleave(rep, 2), Cg.repeat_interleave(rep, 2), h0)
    y, s = ssd_one_chunk(x, dt, A, Bg, Cg, h0)
    torch.testing.assert_close(y, y_ref, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(s, s_ref, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("L", [1, 2, 3, 16, 17, 63, 130])
@pytest.mark.parametrize("chunk", [1, 4, 16])
@pytest.mark.parametrize("groups", [1, 3])
def test_lean_scan_equals_chunked_scan_and_recurrence(L, chunk, groups):
    """The chunk loop carrying the state == the whole-sequence chunked scan == the recurrence, for lengths
    that are and are not a multiple of the chunk, from zero and from a carried state."""
    x, dt, A, B, C, h0 = random_ssd_inputs(2, L, 6, 4, 5, seed=1000 + L * 10 + chunk + groups)
    Bg, Cg = B[:, :, :groups], C[:, :, :groups]
    Bh, Ch = (t.repeat_interleave(6 // groups, 2) for t in (Bg, Cg))
    for init in (torch.zeros_like(h0), h0):
        y_ref, s_ref = ssd_naive(x, dt, A, Bh, Ch, init)
        y_chk, s_chk = ssd_chunked(x, dt, A, Bh, Ch, chunk, init)
        y, s = ssd_scan(x, dt, A, Bg, Cg, chunk, init)
        for got, want in ((y, y_ref), (s, s_ref), (y, y_chk), (s, s_chk)):
            torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("L", [1, 2, 3, 9])
@pytest.mark.parametrize("groups", [1, 2, 6])
@pytest.mark.parametrize("batch", [1, 3])  # one stream (batched matmuls) and a batch of streams (broadcasts)
def test_step_form_equals_chunked_scan_and_recurrence(L, groups, batch):
    x, dt, A, B, C, h0 = random_ssd_inputs(batch, L, 6, 4, 5, seed=2000 + L * 10 + groups)
    Bg, Cg = B[:, :, :groups], C[:, :, :groups]
    Bh, Ch = (t.repeat_interleave(6 // groups, 2) for t in (Bg, Cg))
    y_ref, s_ref = ssd_naive(x, dt, A, Bh, Ch, h0)
    y_chk, s_chk = ssd_chunked(x, dt, A, Bh, Ch, 4, h0)
    y, s = ssd_steps(x, dt, A, Bg, Cg, h0)
    for got, want in ((y, y_ref), (s, s_ref), (y, y_chk), (s, s_chk)):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)


def test_scan_memory_does_not_grow_with_chunk_tensors():
    """The lean scan's largest intermediate is one chunk's, whatever the length (float64 bytes here)."""

    def biggest(L):
        x, dt, A, B, C, h0 = random_ssd_inputs(1, L, 4, 8, 16, seed=L)
        peak = 0
        real = mamba2.ssd_one_chunk

        def spy(*args):
            nonlocal peak
            y, s = real(*args)
            peak = max(peak, max(a.numel() for a in args if torch.is_tensor(a)))
            return y, s

        mamba2.ssd_one_chunk = spy
        try:
            ssd_scan(x, dt, A, B[:, :, :1], C[:, :, :1], 16, h0)
        finally:
            mamba2.ssd_one_chunk = real
        return peak

    sizes = [biggest(L) for L in (64, 1024)]
    assert sizes[0] == sizes[1], "each chunk call sees one chunk's inputs, not the whole sequence"


@pytest.mark.parametrize("L", [1, 2, 3, 8, 9, 30])
def test_forward_picks_each_form_and_each_equals_the_recurrence(L):
    """Mamba2.forward chooses step form / one chunk / chunk loop by length (chunk 8): all equal the reference."""
    m = make_mixer(3)
    x = torch.randn(2, L, 16)
    s0 = Mamba2State(torch.randn(2, m.conv_dim, m.d_conv - 1), torch.randn(2, m.nheads, m.headdim, m.d_state))
    y, s = m(x, s0)
    y_ref, s_ref = m.step_reference(x, s0)
    torch.testing.assert_close(y, y_ref)
    torch.testing.assert_close(s.ssm, s_ref.ssm)
    torch.testing.assert_close(s.conv, s_ref.conv)


def make_mixer(seed=0, **kw):
    torch.manual_seed(seed)
    args = dict(d_model=16, d_state=8, d_conv=4, expand=2, headdim=8, ngroups=2, chunk_size=8)
    args.update(kw)
    m = Mamba2(**args)
    with torch.no_grad():  # non-trivial norm and skip weights so every parameter matters
        m.norm.weight.uniform_(0.5, 1.5)
        m.D.uniform_(-1, 1)
    return m


def test_forward_equals_naive_recurrence():
    m = make_mixer()
    x = torch.randn(2, 37, 16)
    y, s = m(x)
    y_ref, s_ref = m.step_reference(x)
    torch.testing.assert_close(y, y_ref)
    torch.testing.assert_close(s.ssm, s_ref.ssm)
    torch.testing.assert_close(s.conv, s_ref.conv)


@pytest.mark.parametrize("seed", range(5))
def test_window_by_window_equals_whole_sequence(seed):
    m = make_mixer(seed)
    g = torch.Generator().manual_seed(seed)
    L = 50 + seed * 13
    x = torch.randn(2, L, 16, generator=g)
    y_full, s_full = m(x)
    cuts = sorted(torch.randperm(L - 1, generator=g)[:4].add(1).tolist())
    if seed == 0:
        cuts = list(range(1, L))  # one frame at a time
    state, ys = None, []
    for a, b in zip([0] + cuts, cuts + [L]):
        y, state = m(x[:, a:b], state)
        ys.append(y)
    torch.testing.assert_close(torch.cat(ys, 1), y_full)
    torch.testing.assert_close(state.ssm, s_full.ssm)
    torch.testing.assert_close(state.conv, s_full.conv)


def test_state_is_a_value_and_shapes_match_contract():
    m = make_mixer()
    s0 = m.zero_state(3)
    assert isinstance(s0, Mamba2State)
    assert s0.conv.shape == (3, m.conv_dim, m.d_conv - 1)
    assert s0.ssm.shape == (3, m.nheads, m.headdim, m.d_state)
    before = s0.ssm.clone()
    _, s1 = m(torch.randn(3, 5, 16), s0)
    assert torch.equal(s0.ssm, before), "forward must not mutate the state it was given"
    assert s1.nbytes() == m.state_nbytes(3, bytes_per_value=8)


def test_reference_parameter_layout():
    m = Mamba2(d_model=32, d_state=16, d_conv=4, expand=2, headdim=16, ngroups=1)
    shapes = {k: tuple(v.shape) for k, v in m.state_dict().items()}
    nheads, d_inner = 4, 64
    conv_dim = d_inner + 2 * 16
    assert shapes == {
        "dt_bias": (nheads,), "A_log": (nheads,), "D": (nheads,),
        "in_proj.weight": (2 * d_inner + 2 * 16 + nheads, 32),
        "conv1d.weight": (conv_dim, 1, 4), "conv1d.bias": (conv_dim,),
        "norm.weight": (d_inner,), "out_proj.weight": (32, d_inner),
    }


def test_bad_sizes_raise_clear_errors():
    with pytest.raises(ValueError, match="headdim"):
        Mamba2(d_model=10, headdim=8)
    with pytest.raises(ValueError, match="ngroups"):
        Mamba2(d_model=16, expand=2, headdim=8, ngroups=3)


def test_matches_transformers_mamba2_mixer():
    """A state_dict of the transformers Mamba2Mixer (a peer implementation) loads unchanged and agrees."""
    transformers = pytest.importorskip("transformers", reason="transformers not installed (extra 'pretrained')")
    from transformers.models.mamba2.modeling_mamba2 import Mamba2Mixer

    cfg = transformers.Mamba2Config(hidden_size=32, state_size=16, conv_kernel=4, expand=2, head_dim=16,
                                    num_heads=4, n_groups=1, chunk_size=8, use_bias=False, use_conv_bias=True,
                                    time_step_limit=(0.0, float("inf")), rms_norm=True)
    torch.manual_seed(0)
    peer = Mamba2Mixer(cfg, layer_idx=0).double().eval()
    with torch.no_grad():
        for p in peer.parameters():
            p.add_(0.1 * torch.randn_like(p))
    ours = Mamba2(d_model=32, d_state=16, d_conv=4, expand=2, headdim=16, ngroups=1, chunk_size=8)
    missing, unexpected = ours.load_state_dict(peer.state_dict(), strict=True)
    assert not missing and not unexpected
    x = torch.randn(2, 21, 32)
    with torch.no_grad():
        y_peer = peer(x)
        y_ours, _ = ours(x)
    torch.testing.assert_close(y_ours, y_peer, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("batch", [(), (3, 2)])
def test_a_step_written_into_a_buffer_equals_the_step_as_a_value(batch):
    """`ssd_step` is the recurrence, in its 2-D form (one sequence) and broadcast over a batch, and
    `out=h` (how the runner updates its state buffers) gives the same y and state as the value form."""
    gen = torch.Generator().manual_seed(len(batch))
    r, n = 6, 5
    h0, dA, Xdt = (torch.randn(*batch, r, k, generator=gen) for k in (n, 1, 1))
    B, C = torch.randn(*batch, 1, n, generator=gen), torch.randn(*batch, 1, n, generator=gen)
    C_in = C.transpose(-1, -2) if not batch else C  # one sequence takes C as a column
    y, h1 = mamba2.ssd_step(h0, dA, Xdt, B, C_in)
    torch.testing.assert_close(h1, h0 * dA + Xdt * B)  # exp(dt A) h + (dt x) B^T
    torch.testing.assert_close(y.reshape(*batch, r), (h1 * C).sum(-1))  # h C
    buf = h0.clone()
    y2, h2 = mamba2.ssd_step(buf, dA, Xdt, B, C_in, out=buf)
    assert h2 is buf
    torch.testing.assert_close(y2, y)
    torch.testing.assert_close(buf, h1)


@pytest.mark.parametrize("L", [1, 2, 4])
def test_a_batchs_window_at_once_equals_its_frames_step_by_step_and_a_held_row_keeps_its_state(L):
    """`ssd_window` (the runner's form for a batch of streams) gives the recurrence's y and state, written into
    the state's own buffer; a row whose dt is 0 (a held row) gets its state back bit for bit."""
    gen = torch.Generator().manual_seed(L)
    b, h, p, n = 3, 4, 5, 6
    x, h0 = torch.randn(b, L, h, p, generator=gen), torch.randn(b, h, p, n, generator=gen)
    dt = torch.rand(b, L, h, generator=gen) * 0.5 + 0.01
    dt[1] = 0.0  # the held row
    A = -torch.rand(h, generator=gen) - 0.1
    B, C = torch.randn(b, L, n, generator=gen), torch.randn(b, L, n, generator=gen)
    y_ref, h_ref = ssd_steps(x, dt, A, B[:, :, None], C[:, :, None], h0)
    buf = h0.clone()
    y, new = mamba2.ssd_window(buf, dt * A, x * dt[..., None], B, C, out=buf)
    assert new is buf
    torch.testing.assert_close(y, y_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(buf, h_ref, rtol=1e-5, atol=1e-5)
    assert torch.equal(buf[1], h0[1]) and not torch.equal(buf[0], h0[0])
