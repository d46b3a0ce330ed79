"""Mamba-2 mixer in pure PyTorch that continues any window from a carried state.

Notation (Dao & Gu 2024, "Transformers are SSMs", eq. for the SSD recurrence):
    h_t = exp(dt_t * A) * h_{t-1} + dt_t * B_t x_t^T        (per head: h is (headdim, d_state))
    y_t = h_t C_t + D * x_t
with A = -exp(A_log) a scalar per head, dt_t = softplus(dt_raw_t + dt_bias), and B_t, C_t shared by the
heads of a group. The parameter names and the packed `in_proj` layout follow the reference implementation
(state-spaces/mamba `Mamba2Simple`/`Mamba2`, and the transformers `Mamba2Mixer`), so their state_dicts load.

Three CPU forms of the same scan, picked by length in `Mamba2._run`, each with a parity test against
`ssd_naive` (the per-step recurrence) and against `ssd_chunked` (the whole-sequence chunked
state-space-duality scan, kept as the reference of the chunk algebra):
  - `ssd_steps`: the recurrence itself (`ssd_step`, also what `ssd_naive` and the runner's written-out
    block in `dimgestor.model.sampler` call), for windows of up to `STEP_MAX` frames (a streaming window at
    20 fps is 1-10 frames, where the number of ops per call, not their arithmetic, is the cost);
  - `ssd_one_chunk`: one chunk of the SSD algebra as a few batched matmuls, for windows up to a chunk
    (`ssd_window`: the same algebra for a batch of streams' windows in the runner, its state written in place);
  - `ssd_scan`: the lean long-sequence scan, a loop over chunks carrying the state, so its working memory
    is one chunk's (O(h Q^2 + h p n)) whatever the length; only the output grows with L.
On CUDA, the fused `mamba_ssm` kernel is used when importable.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

try:  # optional fused kernel, CUDA only
    from mamba_ssm.ops.triton.ssd_combined import mamba_chunk_scan_combined
except Exception:  # pragma: no cover - absent on CPU machines
    mamba_chunk_scan_combined = None


@dataclass(frozen=True)
class Mamba2State:
    """Everything a Mamba-2 layer needs to continue a sequence: a value, never mutated in place."""

    conv: torch.Tensor  # (B, conv_dim, d_conv - 1): the last inputs of the causal depthwise conv
    ssm: torch.Tensor  # (B, nheads, headdim, d_state): h after the last processed step

    def nbytes(self) -> int:
        return self.conv.numel() * self.conv.element_size() + self.ssm.numel() * self.ssm.element_size()

    def detach(self) -> "Mamba2State":
        return Mamba2State(self.conv.detach(), self.ssm.detach())


def segsum(x: torch.Tensor) -> torch.Tensor:
    """Stable segment sums: out[..., i, j] = sum(x[..., j+1 : i+1]) for j <= i, -inf above the diagonal."""
    T = x.size(-1)
    x = x[..., None].expand(*x.shape, T)  # (..., T, T): x[..., k, j] = x_k
    below = torch.tril(torch.ones(T, T, dtype=torch.bool, device=x.device), diagonal=-1)
    x = x.masked_fill(~below, 0)
    out = torch.cumsum(x, dim=-2)
    keep = torch.tril(torch.ones(T, T, dtype=torch.bool, device=x.device), diagonal=0)
    return out.masked_fill(~keep, -torch.inf)


def ssd_chunked(x, dt, A, B, C, chunk_size, initial_state=None):
    """Chunked SSD scan for any length L (padded internally to a multiple of the chunk).

    x: (b, L, h, p), dt: (b, L, h) (already softplus'ed), A: (h,), B, C: (b, L, h, n),
    initial_state: (b, h, p, n) or None. Returns y: (b, L, h, p) without the D skip, final state (b, h, p, n).
    """
    b, L, h, p = x.shape
    n = B.shape[-1]
    Q = min(chunk_size, L)
    pad = (-L) % Q
    if pad:  # dt = 0 on padded steps: decay 1 and no input, so the final state is unchanged
        x, dt, B, C = (F.pad(t, (0, 0) * (t.dim() - 2) + (0, pad)) for t in (x, dt, B, C))
    c = x.shape[1] // Q
    X = (x * dt[..., None]).reshape(b, c, Q, h, p)  # discretised input dt * x
    Adt = (A * dt).reshape(b, c, Q, h).permute(0, 3, 1, 2)  # (b, h, c, Q)
    B = B.reshape(b, c, Q, h, n)
    C = C.reshape(b, c, Q, h, n)
    A_cum = torch.cumsum(Adt, dim=-1)  # (b, h, c, Q)

    # 1. within each chunk: the quadratic (attention-like) form
    Lmat = torch.exp(segsum(Adt))  # (b, h, c, Q, Q)
    y_diag = torch.einsum("bclhn,bcshn,bhcls,bcshp->bclhp", C, B, Lmat, X)
    # 2. the state each chunk leaves behind, from its own inputs
    decay_states = torch.exp(A_cum[..., -1:] - A_cum)  # (b, h, c, Q)
    states = torch.einsum("bclhn,bhcl,bclhp->bchpn", B, decay_states, X)
    # 3. carry states across chunks (a short recurrence over c + 1 chunk boundaries)
    if initial_state is None:
        initial_state = torch.zeros(b, h, p, n, dtype=x.dtype, device=x.device)
    states = torch.cat([initial_state[:, None].to(states.dtype), states], dim=1)  # (b, c+1, h, p, n)
    decay_chunk = torch.exp(segsum(F.pad(A_cum[..., -1], (1, 0))))  # (b, h, c+1, c+1)
    new_states = torch.einsum("bhzc,bchpn->bzhpn", decay_chunk, states)
    states, final_state = new_states[:, :-1], new_states[:, -1]
    # 4. contribution of the carried-in state to each position
    y_off = torch.einsum("bclhn,bchpn,bhcl->bclhp", C, states, torch.exp(A_cum))
    y = (y_diag + y_off).reshape(b, c * Q, h, p)[:, :L]
    return y, final_state


def ssd_one_chunk(x, dt, A, B, C, initial_state):
    """The SSD scan of a sequence that fits in one chunk, with B and C per group (b, L, g, n).

    The same algebra as one chunk of `ssd_chunked`, written as a few batched matmuls instead of einsums:
    streaming windows are a handful of frames, where the cost of each op, not its arithmetic, dominates.
    Returns y (b, L, h, p) without the D skip and the final state (b, h, p, n).
    """
    b, L, h, p = x.shape
    g, n = B.shape[2], B.shape[3]
    r = h // g  # heads per group
    A_cum = torch.cumsum(dt * A, dim=1).transpose(1, 2)  # (b, h, L)
    seg = A_cum[:, :, :, None] - A_cum[:, :, None, :]  # (b, h, L, L): log decay from step s to step l
    causal = torch.ones(L, L, dtype=torch.bool, device=x.device).tril()
    decay = torch.exp(seg.masked_fill(~causal, -torch.inf))
    Cg, Bg = C.transpose(1, 2), B.transpose(1, 2)  # (b, g, L, n)
    scores = (Cg @ Bg.transpose(2, 3))[:, :, None] * decay.view(b, g, r, L, L)  # (b, g, r, L, L)
    Xdt = (x * dt[..., None]).permute(0, 2, 1, 3)  # (b, h, L, p)
    y = scores.view(b, h, L, L) @ Xdt  # within the window
    h0 = initial_state.reshape(b, g, r * p, n)
    y_off = (Cg @ h0.transpose(2, 3)).view(b, g, L, r, p).permute(0, 1, 3, 2, 4).reshape(b, h, L, p)
    y = y + y_off * torch.exp(A_cum)[..., None]  # the carried-in state, decayed to each step
    w = torch.exp(A_cum[:, :, -1:] - A_cum)  # (b, h, L): decay from each step to the end
    Xw = (Xdt * w[..., None]).reshape(b, g, r, L, p).permute(0, 1, 2, 4, 3).reshape(b, g, r * p, L)
    final = initial_state * torch.exp(A_cum[:, :, -1])[..., None, None] + (Xw @ Bg).reshape(b, h, p, n)
    return y.transpose(1, 2), final


STEP_MAX = 4  # windows of up to this many frames run the recurrence (`ssd_steps`; 2 for a batch of streams)


def ssd_scan(x, dt, A, B, C, chunk_size, initial_state):
    """The SSD scan of any length as a loop over chunks carrying the state, B and C per group (b, L, g, n).

    Each chunk is `ssd_one_chunk` on that chunk alone; nothing of a finished chunk but its output and its
    final state is kept, so peak working memory is one chunk's, not the whole sequence's chunk tensors
    (which `ssd_chunked` materialises at once). Returns y (b, L, h, p) without the D skip and the final state.
    """
    b, L, h, p = x.shape
    y = x.new_empty(b, L, h, p)
    state = initial_state
    for a in range(0, L, chunk_size):
        e = min(a + chunk_size, L)
        y[:, a:e], state = ssd_one_chunk(x[:, a:e], dt[:, a:e], A, B[:, a:e], C[:, a:e], state)
    return y, state


def ssd_step(h, dA, Xdt, B, C, out=None):
    """One step of the recurrence, the one place it is written (every step-by-step form calls it):

        h_t = exp(dt_t A) h_{t-1} + (dt_t x_t) B_t^T,    y_t = h_t C_t

    with a head's p channels as rows of the state. One sequence: h (r, n), dA and Xdt (r, 1) (each row's decay
    exp(dt A) and discretised input dt x), B (1, n), C (n, 1) -> y (r, 1), as plain 2-D matmuls (torch's CPU
    `bmm`/`baddbmm` loop over their batch one small matmul at a time). A batch: h (..., r, n), dA and Xdt
    broadcastable to (..., r, 1), B and C (..., 1, n) -> y (..., r), as broadcast multiply-adds.
    Returns (y, new state); out: write the new state there (a runner's buffer, may be h itself).
    """
    if h.dim() == 2:
        new = torch.addmm(h * dA, Xdt, B, out=out)
        return torch.mm(new, C), new
    new = torch.addcmul(h * dA, Xdt, B, out=out)
    return torch.linalg.vecdot(new, C), new


def ssd_window(h, dtA, Xdt, B, C, out=None):
    """A batch's window of a few frames at once, one group: the recurrence of `ssd_step` in the closed form of
    one SSD chunk, so each state is read twice and written once a window, not read and written every frame
    (a batch's states outgrow the caches, and those passes were most of the recurrence's cost).

    h (b, h, p, n); dtA (b, L, h): each frame's log decay dt A; Xdt (b, L, h, p); B, C (b, L, n)
    -> y (b, L, h, p), the new state (written into `out` where given, which may be h itself). A row whose dt is
    0 keeps its state exactly (its decay exp(0) = 1, its input 0).
    """
    b, L, nh, p = Xdt.shape
    n = h.shape[-1]
    la = dtA.transpose(1, 2).cumsum(-1)  # (b, h, L): log decay from the state before the window to frame t
    X = Xdt.transpose(1, 2)  # (b, h, L, p)
    carried = torch.bmm(h.reshape(b, nh * p, n), C.transpose(1, 2)).view(b, nh, p, L).transpose(2, 3)
    seg = la[..., :, None] - la[..., None, :]  # (b, h, L, L): log decay from frame s to frame t
    causal = torch.ones(L, L, dtype=torch.bool, device=h.device).tril()
    scores = torch.exp(seg.masked_fill(~causal, -torch.inf)) * (C @ B.transpose(1, 2))[:, None]
    y = torch.addcmul(scores @ X, carried, la.exp()[..., None])  # (b, h, L, p)
    Xw = (X * torch.exp(la[..., -1:] - la)[..., None]).transpose(2, 3).reshape(b, nh * p, L)  # decayed to the end
    new = torch.mul(h, la[..., -1].exp()[..., None, None], out=out)
    new.view(b, nh * p, n).baddbmm_(Xw, B)
    return y.transpose(1, 2), new


def ssd_steps(x, dt, A, B, C, initial_state):
    """The recurrence step by step with B and C per group (b, L, g, n): fewest ops for a window of a few frames.

    The heads of a group sit side by side as r rows of the state (row j * p + i: head j, channel i).
    Returns y (b, L, h, p) without the D skip and the final state (b, h, p, n).
    """
    b, L, h, p = x.shape
    g, n = B.shape[2], B.shape[3]
    r = (h // g) * p
    dA = torch.exp(dt * A).repeat_interleave(p, dim=-1)  # (b, L, h p): each head's decay on its p rows
    Xdt = x * dt[..., None]
    ys = []
    if b * g == 1:  # one sequence, one group: 2-D matmuls
        dA, Xdt, B, C = dA.view(L, r, 1), Xdt.reshape(L, r, 1), B.reshape(L, 1, n), C.reshape(L, n, 1)
        state = initial_state.reshape(r, n)
        for t in range(L):
            y, state = ssd_step(state, dA[t], Xdt[t], B[t], C[t])
            ys.append(y)  # (r, 1)
        y = torch.stack(ys) if L > 1 else ys[0][None]  # (L, r, 1)
    else:
        dA, Xdt, B, C = dA.view(b, L, g, r, 1), Xdt.reshape(b, L, g, r, 1), B[:, :, :, None], C[:, :, :, None]
        state = initial_state.reshape(b, g, r, n)
        for t in range(L):
            y, state = ssd_step(state, dA[:, t], Xdt[:, t], B[:, t], C[:, t])
            ys.append(y)  # (b, g, r)
        y = torch.stack(ys, 1) if L > 1 else ys[0][:, None]  # (b, L, g, r)
    return y.reshape(b, L, h, p), state.reshape(b, h, p, n)


def ssd_naive(x, dt, A, B, C, initial_state=None):
    """The recurrence with B and C per head (b, L, h, n), from zeros by default: the reference the chunked
    scans are tested against. Same shapes as ssd_chunked."""
    b, L, h, p = x.shape
    state = initial_state if initial_state is not None else x.new_zeros(b, h, p, B.shape[-1])
    return ssd_steps(x, dt, A, B, C, state)  # one group per head


class RMSNormGated(nn.Module):
    """RMSNorm(y * silu(z)) * weight, normalised per group of `group_size` channels (reference `RMSNormGated`)."""

    def __init__(self, d: int, eps: float = 1e-5, group_size: int | None = None, norm_before_gate: bool = False,
                 device=None, dtype=None):
        super().__init__()
        self.eps = eps
        self.group_size = group_size or d
        self.norm_before_gate = norm_before_gate
        self.weight = nn.Parameter(torch.ones(d, device=device, dtype=dtype))

    def forward(self, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        if not self.norm_before_gate and self.group_size == y.shape[-1]:  # one group: the fused kernel
            return F.rms_norm(y * F.silu(z), (self.group_size,), self.weight, self.eps)
        if not self.norm_before_gate:
            y = y * F.silu(z)
        shape = y.shape
        g = y.reshape(*shape[:-1], -1, self.group_size)
        g = g * torch.rsqrt(g.pow(2).mean(-1, keepdim=True) + self.eps)
        y = g.reshape(shape) * self.weight
        if self.norm_before_gate:
            y = y * F.silu(z)
        return y


class Mamba2(nn.Module):
    """Mamba-2 mixer: `forward(x, state) -> (y, state)` for any length, window by window equal to the whole."""

    def __init__(self, d_model: int, d_state: int = 128, d_conv: int = 4, expand: int = 2, headdim: int = 64,
                 ngroups: int = 1, chunk_size: int = 64, rmsnorm: bool = True, norm_before_gate: bool = False,
                 bias: bool = False, conv_bias: bool = True, dt_min: float = 0.001, dt_max: float = 0.1,
                 dt_init_floor: float = 1e-4, dt_limit: tuple[float, float] = (0.0, float("inf")),
                 A_init_range: tuple[float, float] = (1.0, 16.0), D_has_hdim: bool = False, device=None, dtype=None):
        super().__init__()
        kw = {"device": device, "dtype": dtype}
        self.d_model, self.d_state, self.d_conv, self.expand = d_model, d_state, d_conv, expand
        self.d_inner = expand * d_model
        if self.d_inner % headdim:
            raise ValueError(f"expand * d_model = {self.d_inner} is not a multiple of headdim = {headdim}")
        self.headdim, self.ngroups, self.chunk_size = headdim, ngroups, chunk_size
        self.nheads = self.d_inner // headdim
        if self.nheads % ngroups:
            raise ValueError(f"nheads = {self.nheads} is not a multiple of ngroups = {ngroups}")
        self.dt_limit, self.rmsnorm = tuple(dt_limit), rmsnorm
        self.conv_dim = self.d_inner + 2 * ngroups * d_state

        # in_proj packs [z (d_inner), xBC (d_inner + 2 * ngroups * d_state), dt (nheads)] in this order.
        self.in_proj = nn.Linear(d_model, 2 * self.d_inner + 2 * ngroups * d_state + self.nheads, bias=bias, **kw)
        self.conv1d = nn.Conv1d(self.conv_dim, self.conv_dim, d_conv, groups=self.conv_dim, padding=d_conv - 1,
                                bias=conv_bias, **kw)
        # dt initialised log-uniformly in [dt_min, dt_max]; dt_bias is its softplus inverse.
        dt = torch.exp(torch.rand(self.nheads, **kw) * (math.log(dt_max) - math.log(dt_min)) + math.log(dt_min))
        dt = dt.clamp(min=dt_init_floor)
        self.dt_bias = nn.Parameter(dt + torch.log(-torch.expm1(-dt)))
        self.A_log = nn.Parameter(torch.log(torch.empty(self.nheads, **kw).uniform_(*A_init_range)))
        self.D = nn.Parameter(torch.ones(self.d_inner if D_has_hdim else self.nheads, **kw))
        if rmsnorm:
            self.norm = RMSNormGated(self.d_inner, eps=1e-5, group_size=self.d_inner // ngroups,
                                     norm_before_gate=norm_before_gate, **kw)
        self.out_proj = nn.Linear(self.d_inner, d_model, bias=bias, **kw)

    def zero_state(self, batch: int, device=None, dtype=None) -> Mamba2State:
        device = device if device is not None else self.A_log.device
        dtype = dtype if dtype is not None else self.in_proj.weight.dtype
        return Mamba2State(torch.zeros(batch, self.conv_dim, self.d_conv - 1, device=device, dtype=dtype),
                           torch.zeros(batch, self.nheads, self.headdim, self.d_state, device=device, dtype=dtype))

    def state_nbytes(self, batch: int = 1, bytes_per_value: int = 4) -> int:
        return batch * bytes_per_value * (self.conv_dim * (self.d_conv - 1) + self.nheads * self.headdim * self.d_state)

    def forward(self, x: torch.Tensor, state: Mamba2State | None = None) -> tuple[torch.Tensor, Mamba2State]:
        return self._run(x, state, reference=False)

    def step_reference(self, x: torch.Tensor, state: Mamba2State | None = None) -> tuple[torch.Tensor, Mamba2State]:
        """Same as forward, but with the naive per-step recurrence: the reference the tests compare against."""
        return self._run(x, state, reference=True)

    def _depthwise_conv(self, xs: torch.Tensor, L: int) -> torch.Tensor:
        """The depthwise conv as d_conv shifted multiply-adds: exact, and far faster on CPU than the
        grouped conv1d, whose backward pass dominated a training step."""
        w = self.conv1d.weight[:, 0, :, None]  # (conv_dim, d_conv, 1)
        bias = self.conv1d.bias
        y = xs[:, :, 0:L] * w[:, 0] if bias is None else torch.addcmul(bias[:, None], xs[:, :, 0:L], w[:, 0])
        for k in range(1, self.d_conv):  # y += x shifted by k * w_k, one fused op per tap
            y = torch.addcmul(y, xs[:, :, k:k + L], w[:, k])
        return y

    def _run(self, u, state, reference):
        b, L, _ = u.shape
        if state is None:
            state = self.zero_state(b, u.device, u.dtype)
        z, xBC, dt = torch.split(self.in_proj(u), [self.d_inner, self.conv_dim, self.nheads], dim=-1)

        # causal depthwise conv, continued from the carried tail of the previous window
        xBC_t = torch.cat([state.conv, xBC.transpose(1, 2)], dim=2)  # (b, conv_dim, d_conv - 1 + L)
        # the tail as its own small tensor: a view would keep this whole window's xBC alive with the state
        new_conv = xBC_t[:, :, xBC_t.shape[2] - (self.d_conv - 1):].clone()
        xBC = F.silu(self._depthwise_conv(xBC_t, L).transpose(1, 2))

        x, B, C = torch.split(xBC, [self.d_inner, self.ngroups * self.d_state, self.ngroups * self.d_state], dim=-1)
        x = x.reshape(b, L, self.nheads, self.headdim)
        dt = F.softplus(dt + self.dt_bias)  # (b, L, h)
        if self.dt_limit != (0.0, float("inf")):
            dt = dt.clamp(*self.dt_limit)
        A = -torch.exp(self.A_log.float())
        Bg = B.reshape(b, L, self.ngroups, self.d_state)
        Cg = C.reshape(b, L, self.ngroups, self.d_state)

        if reference:
            y, ssm = ssd_naive(x, dt, A, *(t.repeat_interleave(self.nheads // self.ngroups, 2) for t in (Bg, Cg)),
                                state.ssm)
        elif u.is_cuda and mamba_chunk_scan_combined is not None:  # pragma: no cover - needs CUDA
            y, ssm = mamba_chunk_scan_combined(x, dt, A, Bg, Cg, chunk_size=self.chunk_size, D=None,
                                               initial_states=state.ssm, return_final_states=True)
        elif L <= (STEP_MAX if b == 1 else 2):  # a streaming window of a few frames: the recurrence has the fewest ops
            y, ssm = ssd_steps(x, dt, A, Bg, Cg, state.ssm)
        elif L <= self.chunk_size:  # a window that fits one chunk
            y, ssm = ssd_one_chunk(x, dt, A, Bg, Cg, state.ssm)
        else:  # a long sequence: chunk by chunk, working memory of one chunk
            y, ssm = ssd_scan(x, dt, A, Bg, Cg, self.chunk_size, state.ssm)

        D = self.D.reshape(self.nheads, -1) if self.D.numel() == self.d_inner else self.D[:, None]
        y = torch.addcmul(y, x, D).reshape(b, L, self.d_inner)  # y + D x
        y = self.norm(y, z) if self.rmsnorm else y * F.silu(z)
        return self.out_proj(y), Mamba2State(new_conv, ssm.to(state.ssm.dtype))
