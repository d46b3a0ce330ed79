"""The K-step sampler every stream runs, alone or batched: a window's cost is reading the weights once a step, so
all its adaLN modulations come from one matmul and B streams' windows share each forward (`sample_frames` is its
reference)."""
from __future__ import annotations

import threading
import weakref
from typing import NamedTuple, Sequence

import torch
import torch.nn.functional as F

from .diffusion import Diffusion, guide, motion_noise_rows
from .mamba2 import STEP_MAX, Mamba2State, ssd_step, ssd_window
from .network import DenoiserState, DiMGestor

__all__ = ["StepStates", "StateBuffers", "Window", "DenoiseRunner", "runner_for", "denoise"]


class StepStates(NamedTuple):
    """The denoiser's carried state for every sampler step of B stream rows, stacked."""

    enc: torch.Tensor  # (K, B, motion_dim, 2): the causal encoder's tail
    conv: torch.Tensor  # (K, blocks, B, d_conv - 1, conv_dim), time-major: the fast block appends without a transpose
    ssm: torch.Tensor  # (K, blocks, B, heads, headdim, d_state)

    @property
    def batch(self) -> int:
        return self.enc.shape[1]

    @staticmethod
    def zeros(model: DiMGestor, steps: int, batch: int = 1, device=None, dtype=None) -> "StepStates":
        s = model.init_state(batch, device, dtype)
        return StepStates(s.enc[None].repeat(steps, 1, 1, 1),
                          torch.stack([b.conv.transpose(1, 2) for b in s.blocks])[None].repeat(steps, 1, 1, 1, 1),
                          torch.stack([b.ssm for b in s.blocks])[None].repeat(steps, 1, 1, 1, 1, 1))

    @staticmethod
    def cat(states: Sequence["StepStates"], out: "StepStates | None" = None) -> "StepStates":
        """The states' rows in turn, in one new buffer (or written into `out`, shaped for them)."""
        if len(states) == 1 and out is None:
            return states[0]
        return StepStates(*(torch.cat([s[f] for s in states], dim, out=None if out is None else out[f])
                            for f, dim in enumerate(_BATCH_DIMS)))

    def step(self, k: int) -> DenoiserState:
        """Step k as the model's own DenoiserState (what `DiMGestor.forward` takes)."""
        return DenoiserState(self.enc[k], tuple(Mamba2State(c.transpose(1, 2), s) for c, s in zip(self.conv[k], self.ssm[k])))

    @staticmethod
    def from_steps(steps: Sequence[DenoiserState]) -> "StepStates":
        return StepStates(torch.stack([s.enc for s in steps]),
                          torch.stack([torch.stack([b.conv.transpose(1, 2) for b in s.blocks]) for s in steps]),
                          torch.stack([torch.stack([b.ssm for b in s.blocks]) for s in steps]))

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in self)


_BATCH_DIMS = (1, 2, 2)  # the batch (stream row) dimension of StepStates' enc, conv and ssm
_USE_COUNT = getattr(torch._C, "_storage_Use_Count", None)  # (how torch's CUDA graph trees tell a storage is free)


class StateBuffers:
    """The buffers a runner's batches write their states into (`denoise`), used again once nothing holds them.

    A batch of many streams' states is tens of MB. A fresh one each window is memory the allocator hands back to
    the system when freed, so every window paid the first touch of each of its pages again: at 48 streams a
    quarter of the batch's time (benchmarks/README.md, "The batch's buffers"). A buffer is free when no tensor but
    its own refers to its storage (the storage's use count; where torch lacks it, nothing is kept). A taken
    buffer is its first `rows` rows, so batches of other sizes share it; at most `keep` free ones are kept."""

    def __init__(self, keep: int = 4):
        self.keep = keep
        self._lock = threading.Lock()
        self._bufs: list[tuple[tuple, int, StepStates, tuple[int, ...]]] = []  # (shape key, rows, buffer, free counts)
        self.made = 0  # buffers allocated (tests)

    def __len__(self) -> int:
        """Buffers kept, in use or free."""
        return len(self._bufs)

    @staticmethod
    def _uses(t: torch.Tensor) -> int:
        return _USE_COUNT(t.untyped_storage()._cdata)

    def _free(self, entry) -> bool:
        return all(self._uses(t) == n for t, n in zip(entry[2], entry[3]))

    def take(self, like: StepStates, rows: int) -> StepStates:
        """A state of `rows` rows shaped as `like`'s (contents undefined) that nothing else refers to."""
        shapes = [(t.shape[:d], t.shape[d + 1:]) for t, d in zip(like, _BATCH_DIMS)]
        if _USE_COUNT is None:
            return StepStates(*(torch.empty(a + (rows,) + b, dtype=t.dtype, device=t.device)
                                for (a, b), t in zip(shapes, like)))
        key = (tuple(shapes), like.enc.dtype, like.enc.device)
        with self._lock:  # (a runner is shared by every stream of its model, on any thread)
            fits = [e for e in self._bufs if e[0] == key and rows <= e[1] <= 2 * rows + 8 and self._free(e)]
            if fits:
                entry = min(fits, key=lambda e: e[1])
            else:
                cap = rows if rows <= 8 else -(-rows // 8) * 8  # a few rows to spare, for the next batch's size
                buf = StepStates(*(torch.empty(a + (cap,) + b, dtype=t.dtype, device=t.device)
                                   for (a, b), t in zip(shapes, like)))
                entry = (key, cap, buf, tuple(self._uses(t) for t in buf))
                self.made += 1
                spare = [e for e in self._bufs if self._free(e)]
                drop = {id(e) for e in spare[:max(0, len(spare) - self.keep)]}  # the longest unused first
                self._bufs = [e for e in self._bufs if id(e) not in drop]
            self._bufs = [e for e in self._bufs if e is not entry] + [entry]  # (the most recently used last)
            buf = entry[2]
            return StepStates(buf.enc[:, :rows], buf.conv[:, :, :rows], buf.ssm[:, :, :rows])


class Window(NamedTuple):
    """What denoising one stream's window needs: its condition, its carried state, and where its noise comes from."""

    cond: torch.Tensor  # (1, n, H): the condition of the window's n frames
    state: StepStates  # the stream's denoiser state before the window (only read)
    frame_start: int  # the index of the window's first frame in its stream (the noise's position)
    seed: int  # the stream's noise seed
    guidance: float = 1.0  # its classifier-free guidance scale (!= 1: `state` has the unconditional row too)


class _Guidance(NamedTuple):
    """Where the rows of a guided batch sit. The network runs on R = B + G rows: each window's conditional
    row, directly followed by its unconditional row when the window is guided (the rows of one stream's state
    are adjacent, so a stream's state is one slice of the batch's buffer)."""

    rows: torch.Tensor  # (R,) the window each network row belongs to
    sources: torch.Tensor  # (R,) where each row's modulations come from: its window b, or B (the null condition)
    cond_rows: torch.Tensor  # (B,) each window's conditional row
    null_rows: torch.Tensor  # (G,) each guided window's unconditional row
    guided: torch.Tensor  # (G,) the guided windows
    scale: torch.Tensor  # (G, 1, 1) their guidance scales
    all_guided: bool

    @staticmethod
    def plan(guidance: Sequence[float] | None, device, dtype) -> "_Guidance | None":
        """None where no window is guided (scale 1): then the batch runs exactly the unguided ops."""
        if guidance is None or all(s == 1.0 for s in guidance):
            return None
        rows, sources, cond_rows, null_rows, guided, scale = [], [], [], [], [], []
        for b, s in enumerate(guidance):
            cond_rows.append(len(rows))
            rows.append(b)
            sources.append(b)
            if s != 1.0:
                null_rows.append(len(rows))
                rows.append(b)
                sources.append(len(guidance))
                guided.append(b)
                scale.append(float(s))
        idx = lambda v: torch.tensor(v, dtype=torch.long, device=device)  # noqa: E731
        return _Guidance(idx(rows), idx(sources), idx(cond_rows), idx(null_rows), idx(guided),
                         torch.tensor(scale, dtype=dtype, device=device)[:, None, None], len(guided) == len(guidance))

    def modulations(self, mods: torch.Tensor, null: torch.Tensor) -> torch.Tensor:
        """The windows' modulations (K, B, n, W) and the null condition's (K, W) -> every row's (K, R, n, W).

        The unconditional rows' condition is zeros, so their modulations are the same every window (the step
        embedding's alone): made once, not half of every window's largest matrix product."""
        K, B, n, W = mods.shape
        null = null[:, None, None].expand(K, 1, n, W)
        if self.all_guided:  # each window's row, then its null row
            return torch.stack([mods, null.expand(K, B, n, W)], 2).view(K, 2 * B, n, W)
        return torch.cat([mods, null], 1).index_select(1, self.sources)

    def combine(self, out: torch.Tensor) -> torch.Tensor:
        """The network output on the R rows -> the guided output (B, n, D) of the B windows."""
        out_c, out_u = out.index_select(0, self.cond_rows), out.index_select(0, self.null_rows)
        if self.all_guided:
            return guide(out_c, out_u, self.scale)
        return out_c.index_copy(0, self.guided, guide(out_c.index_select(0, self.guided), out_u, self.scale))


class DenoiseRunner:
    """The K-step sampler of one model and schedule (`runner_for`); its stacked adaLN weights and step embeddings
    are rebuilt when the model's parameters change."""

    def __init__(self, model: DiMGestor, pairs: Sequence[tuple[int, int]], sampler: str = "ddim", eta: float = 0.0):
        self.model, self.pairs, self.sampler, self.eta = model, list(pairs), sampler, float(eta)
        self.diffusion = Diffusion(model.config)
        self._version: tuple | None = None
        self.buffers = StateBuffers()  # where `denoise` writes its batches' states

    def _params(self) -> list[torch.nn.Parameter]:
        m = self.model
        return [p for part in (m.t_embedder, m.encoder, m.blocks, m.final) for p in part.parameters()]

    def _prepare(self) -> None:
        if self._version is not None and torch.compiler.is_exporting():
            return  # traced (the ONNX export, after a first eager call): the prepared tensors are constants
        params = self._params()
        version = tuple(p._version for p in params) + tuple(p.data_ptr() for p in params)
        if version == self._version:
            return
        m = self.model
        mods = [b.adaLN_modulation[-1] for b in m.blocks] + [m.final.adaLN_modulation[-1]]
        with torch.inference_mode():
            self._w = torch.cat([lin.weight for lin in mods]).detach().clone()  # (blocks * 6H + 2H, H)
            self._b = torch.cat([lin.bias for lin in mods]).detach().clone()
            H = m.config.hidden
            for j in range(len(m.blocks)):  # the blocks take 1 + scale: fold the 1 into the bias
                self._b[6 * H * j + H: 6 * H * j + 2 * H] += 1  # scale1
                self._b[6 * H * j + 4 * H: 6 * H * j + 5 * H] += 1  # scale2
            self._b[6 * H * len(m.blocks) + H:] += 1  # the final layer's scale
            t = torch.tensor([t for t, _ in self.pairs], device=self._w.device)
            self._temb = m.t_embedder(t).detach().clone()  # (K, H)
            self._null = F.linear(F.silu(self._temb), self._w, self._b)  # (K, W): the null condition's (zeros)
            self._blocks = [_FastBlock.of(b) for b in m.blocks]
        self._version = version

    def modulations(self, cond: torch.Tensor) -> torch.Tensor:
        """cond (B, n, H) -> (K, B, n, blocks * 6H + 2H): every adaLN output of the window, all steps (scales + 1)."""
        self._prepare()
        c = cond[None] + self._temb[:, None, None, :]  # (K, B, n, H): the condition plus each step's embedding
        return F.linear(F.silu(c), self._w, self._b)

    def sample(self, cond: torch.Tensor, frame_starts: Sequence[int], seeds: Sequence[int], states: StepStates,
               guidance: Sequence[float] | None = None, out: StepStates | None = None,
               hold: torch.Tensor | None = None) -> torch.Tensor:
        """B windows: cond (B, n, H), row b's frames start at frame_starts[b] of the stream seeded seeds[b] -> x0
        (B, n, motion_dim); under torch.inference_mode(). The new states go into `out` step by step (None: into
        `states`, in place). guidance: each window's scale (None: all 1); a guided window has two rows in `states`
        (conditional, unconditional: `_Guidance`). hold: (B + G,) bool, rows whose states stay as they were (an
        exported stream's warm-up; their frames mean nothing), in the fast blocks as a zero step size."""
        m, d = self.model, self.diffusion
        n = cond.shape[1]
        D, L, H = m.config.motion_dim, m.config.noise_taps, m.config.hidden
        nb = len(m.blocks)
        plan = _Guidance.plan(guidance, cond.device, cond.dtype)
        x = motion_noise_rows(seeds, frame_starts, n, 0, D, L, cond.device).to(cond.dtype)  # x_T, (B, n, D)
        mods = self.modulations(cond)  # (K, B windows, n, W)
        if plan is not None:
            mods = plan.modulations(mods, self._null)  # (K, R, n, W)
        B = mods.shape[1]  # network rows
        if states.batch != B:
            raise ValueError(f"states hold {states.batch} rows, the windows (with their guided rows) need {B}")
        out = states if out is None else out
        fast = n <= STEP_MAX and all(b is not None for b in self._blocks)
        for k, (t, t_prev) in enumerate(self.pairs):
            h, tail = m.encoder(x if plan is None else x.index_select(0, plan.rows), states.enc[k])
            out.enc[k].copy_(tail if hold is None else torch.where(_rows(hold, tail), states.enc[k], tail))
            if fast:  # rows (B n, H), the blocks' ops written out for a window of a few frames
                h = h.reshape(B * n, H)
                mk = mods[k].reshape(B * n, -1).split(H, -1)  # every block's 6 chunks (H each) cut at once
                for j, fb in enumerate(self._blocks):
                    h = fb(h, mk[6 * j: 6 * (j + 1)], (states.conv[k, j], states.ssm[k, j]),
                           (out.conv[k, j], out.ssm[k, j]), B, n, hold)
                h = h.view(B, n, H)
            else:  # a long window (a backlog): the block's modules, the scan picked by length
                for j, block in enumerate(m.blocks):
                    h = _modulated_block(block, h, mods[k, :, :, 6 * H * j: 6 * H * (j + 1)],
                                         (states.conv[k, j], states.ssm[k, j]), (out.conv[k, j], out.ssm[k, j]))
                    if hold is not None:
                        for old, new in ((states.conv[k, j], out.conv[k, j]), (states.ssm[k, j], out.ssm[k, j])):
                            new.copy_(torch.where(_rows(hold, new), old, new))
            y = _modulated_final(m.final, h, mods[k, :, :, 6 * H * nb:])
            if plan is not None:
                y = plan.combine(y)  # (B windows, n, D)
            eps, x0 = d.split(y, x, t)
            noisy = d.needs_noise(self.sampler, t, t_prev, self.eta)
            noise = motion_noise_rows(seeds, frame_starts, n, k + 1, D, L, cond.device).to(x.dtype) if noisy else None
            x = d.sample_step(self.sampler, x, eps, x0, t, t_prev, self.eta, noise)
        return m.calibrate(x)


def _rows(mask: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """A (rows,) mask shaped to broadcast over `like` (rows, ...)."""
    return mask.view(-1, *[1] * (like.dim() - 1))


def _modulated_block(block, h, mod, state, out):
    """`AdaLNMamba2Block.forward` with its adaLN output `mod` (B, n, 6H) computed beforehand (1 added to the
    scales); state: the (conv (B, d_conv - 1, C), ssm) it continues; the new one is written into `out`'s."""
    shift1, scale1, gate1, shift2, scale2, gate2 = mod.chunk(6, dim=-1)
    y, new = block.mixer(torch.addcmul(shift1, block.norm1(h), scale1), Mamba2State(state[0].transpose(1, 2), state[1]))
    out[0].copy_(new.conv.transpose(1, 2))
    out[1].copy_(new.ssm)
    h = torch.addcmul(h, gate1, y)
    return torch.addcmul(h, gate2, block.mlp(torch.addcmul(shift2, block.norm2(h), scale2)))


def _modulated_final(final, h, mod):
    """`FinalLayer.forward` with its adaLN output `mod` (B, n, 2H) computed beforehand (1 added to the scale)."""
    shift, scale = mod.chunk(2, dim=-1)
    return F.linear(torch.addcmul(shift, final.norm(h), scale), final.decoder.weight[:, :, 0], final.decoder.bias)


class _FastBlock:
    """`AdaLNMamba2Block.forward` on a window of a few frames with its ops written out on rows (B n, H): there each
    op's fixed cost is the cost, so no module calls or layout changes (the tests hold it equal to the modules)."""

    def __init__(self, block, H: int):
        mx = block.mixer
        self.H, self.di, self.C, self.h, self.p, self.n, self.dc = (
            H, mx.d_inner, mx.conv_dim, mx.nheads, mx.headdim, mx.d_state, mx.d_conv)
        self.w_in, self.w_out = mx.in_proj.weight, mx.out_proj.weight
        self.taps = mx.conv1d.weight[:, 0].detach().clone()  # (C, d_conv)
        self.conv_bias = mx.conv1d.bias
        self.dt_bias, self.A = mx.dt_bias, -torch.exp(mx.A_log.detach().float())
        self.D = mx.D.detach().repeat_interleave(mx.headdim) if mx.D.numel() == mx.nheads else mx.D.detach()
        self.norm_w, self.eps = mx.norm.weight, mx.norm.eps
        self.fc1, self.fc2 = block.mlp.fc1, block.mlp.fc2

    @staticmethod
    def of(block) -> "_FastBlock | None":
        """The fast form, or None where the block is not the plain one it writes out (the modules run then)."""
        mx = block.mixer
        plain = (mx.ngroups == 1 and mx.rmsnorm and not mx.norm.norm_before_gate and mx.in_proj.bias is None
                 and mx.out_proj.bias is None and mx.conv1d.bias is not None and mx.dt_limit == (0.0, float("inf"))
                 and isinstance(block.mlp.act, torch.nn.GELU) and block.mlp.act.approximate == "tanh")
        return _FastBlock(block, block.norm1.normalized_shape[0]) if plain else None

    def __call__(self, h, mod, state, out, B: int, L: int, hold=None):
        """h (B L, H); mod: its 6 adaLN chunks (B L, H) each, 1 added to the scales; state: the (conv (B, d_conv - 1,
        C), ssm (B, h, p, n)) it continues; the new one is written into `out`'s (may be the same tensors);
        hold: None or (B,) bool, rows whose state `out` gets unchanged (`DenoiseRunner.sample`)."""
        H, h_, p, n = self.H, self.h, self.p, self.n
        (conv, ssm), (conv_out, ssm_out) = state, out
        shift1, scale1, gate1, shift2, scale2, gate2 = mod
        u = torch.addcmul(shift1, F.layer_norm(h, (H,), eps=1e-6), scale1)
        z, xBC, dt = F.linear(u, self.w_in).split([self.di, self.C, h_], -1)
        xs = torch.cat([conv, xBC.view(B, L, self.C)], 1)  # (B, d_conv - 1 + L, C): the conv's window, time-major
        conv_out.copy_(xs[:, L:] if hold is None else torch.where(_rows(hold, conv), conv, xs[:, L:]))
        # each frame's d_conv inputs as a view (B, L, C, d_conv), weighed and summed (exported: a few nodes, not 3 a tap)
        y = (xs.unfold(1, self.dc, 1) * self.taps).sum(-1) + self.conv_bias
        x, Bm, Cm = F.silu(y).split([self.di, n, n], -1)  # (B, L, .)
        dt = F.softplus(dt + self.dt_bias).view(B, L, h_)
        if hold is not None:  # dt = 0: dA = exp(0) = 1 and Xdt = 0, so the recurrence returns the state as it was
            dt = torch.where(_rows(hold, dt), 0.0, dt)
        dtA = dt * self.A  # (B, L, h)
        Xdt = x.view(B, L, h_, p) * dt[..., None]  # (B, L, h, p)
        if B == 1:  # 2-D matmuls on the state's rows (a head's p channels each), written into the buffer
            flat, flat_out = ssm.view(h_ * p, n), ssm_out.view(h_ * p, n)
            dA = torch.exp(dtA)[0, :, :, None].expand(L, h_, p).reshape(L, h_ * p, 1)
            Xdt, Bm, Cm = Xdt.view(L, h_ * p, 1), Bm.view(L, 1, n), Cm.view(L, n, 1)
            ys = [ssd_step(flat if t == 0 else flat_out, dA[t], Xdt[t], Bm[t], Cm[t], out=flat_out)[0]
                  for t in range(L)]  # (h p, 1) each
            y = torch.cat(ys, 1).t() if L > 1 else ys[0].view(1, h_ * p)
        else:  # the window's frames at once: each row's state read twice and written once
            y, _ = ssd_window(ssm, dtA, Xdt, Bm, Cm, out=ssm_out)
        y = torch.addcmul(y.reshape(B * L, self.di), x.reshape(B * L, self.di), self.D)  # + D x
        g = F.rms_norm(y * F.silu(z), (self.di,), self.norm_w, self.eps)
        h = torch.addcmul(h, gate1, F.linear(g, self.w_out))
        f = F.gelu(F.linear(torch.addcmul(shift2, F.layer_norm(h, (H,), eps=1e-6), scale2), self.fc1.weight,
                            self.fc1.bias), approximate="tanh")
        return torch.addcmul(h, gate2, F.linear(f, self.fc2.weight, self.fc2.bias))


_RUNNERS: "weakref.WeakKeyDictionary[DiMGestor, dict]" = weakref.WeakKeyDictionary()


def runner_for(model: DiMGestor, pairs: Sequence[tuple[int, int]], sampler: str, eta: float) -> DenoiseRunner:
    """The shared runner of this model and schedule: streams with the same one can share a batch."""
    runners = _RUNNERS.setdefault(model, {})
    key = (tuple(pairs), sampler, float(eta))
    if key not in runners:
        runners[key] = DenoiseRunner(model, pairs, sampler, eta)
    return runners[key]


def denoise(runner: DenoiseRunner, windows: Sequence[Window]) -> tuple[list[torch.Tensor], list[StepStates]]:
    """Windows of one frame count, one sampler run -> each one's x0 (n, D) and new state (the given ones are only
    read; the new ones are rows of one buffer, read in place when the same streams come back together: `_join`)."""
    with torch.inference_mode():
        buf = _join([w.state for w in windows], runner.buffers)
        new = runner.buffers.take(buf, buf.batch)
        x = runner.sample(torch.cat([w.cond for w in windows]), [w.frame_start for w in windows],
                          [w.seed for w in windows], buf, [w.guidance for w in windows], out=new)
    return list(x), _split(new, [w.state.batch for w in windows])


def _join(states: Sequence[StepStates], buffers: StateBuffers) -> StepStates:
    """Streams' states as one buffer of their rows in turn: without a copy where they already lie so (the rows
    of the buffer `denoise` wrote them into last time), else copied together into one of `buffers`."""
    if len(states) == 1:
        return states[0]
    joined = [_adjacent([s[f] for s in states], dim) for f, dim in enumerate(_BATCH_DIMS)]
    if all(t is not None for t in joined):
        return StepStates(*joined)
    return StepStates.cat(states, out=buffers.take(states[0], sum(s.batch for s in states)))


def _adjacent(parts: Sequence[torch.Tensor], dim: int) -> torch.Tensor | None:
    """The tensor whose slices along `dim` are `parts` in turn, as a view, when they lie so in one storage."""
    first = parts[0]
    storage, strides, offset = first.untyped_storage().data_ptr(), first.stride(), first.storage_offset()
    others = lambda t: t.shape[:dim] + t.shape[dim + 1:]  # noqa: E731
    for t in parts:
        if (t.untyped_storage().data_ptr() != storage or t.stride() != strides or t.storage_offset() != offset
                or others(t) != others(first)):
            return None
        offset += t.shape[dim] * strides[dim]
    shape = list(first.shape)
    shape[dim] = sum(t.shape[dim] for t in parts)
    return first.as_strided(shape, strides, first.storage_offset())


def _split(buf: StepStates, rows: Sequence[int]) -> list[StepStates]:
    """A batch's buffer -> each stream's state: its rows (views, in order)."""
    if len(rows) == 1:
        return [buf]
    out, r = [], 0
    for n in rows:
        out.append(StepStates(buf.enc[:, r:r + n], buf.conv[:, :, r:r + n], buf.ssm[:, :, r:r + n]))
        r += n
    return out
