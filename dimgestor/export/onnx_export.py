"""The streaming step as one ONNX graph with explicit state: `dimgestor export-onnx`.

The graph (`FrameStep`) is M motion frames of one stream (M = `--frames`, 2 by default: a 100 ms window):
their 800 M new audio samples, the stream's seed and the index of the call's first frame in, the M denoised
frames (normalized features) out, and every carried state in and out beside them:

    samples (1, 800 M), seed (1,), frame (1,), <state>...  ->  frames (M, D), <state>_out...

    front end    its tail of samples and, for the speech front end, the running statistics (float64, as in torch)
    extractor    the style extractor's Mamba-2 state and the downsampler's buffer of k - stride columns
    denoiser     `StepStates`, the torch stream's own layout: for every sampler step the encoder tail and each
                 block's Mamba-2 conv and SSM state, stacked (K, ...), a row per branch (2 when guided)

Why this boundary (one graph for the whole window step, fixed shapes):
- fixed shapes: a frame's audio is exactly 5 feature frames and one downsampler output, so the speech front
  end's per-frame running statistics unroll into the graph and nothing in it loops over a length (a variable
  window would need an ONNX Loop for them); fixed shapes are also what Unity Sentis, Unreal NNE, Triton and
  the browser run best;
- one call a window: the K sampler steps (with guidance and the DDIM updates, the schedule's numbers as
  constants) are unrolled inside, so a window costs one runtime call, not K: on CPU a model this small pays
  for the number of ops and calls, not for arithmetic. A graph per step (the DDIM loop in Python) would cost
  K calls and K copies of the state a window;
- the noise is made in the graph: x_T is `motion_noise(seed, frame)`, the counter-based hash the torch stream
  draws (int64 ops, then Box-Muller in float64), so the frames equal torch's and an engine feeds two integers.
  Only deterministic DDIM (eta = 0) is exported;
- warm-up by the frame index: the downsampler's buffer always holds k - stride columns, so the first
  lookahead / M calls (6 frames for the default model) make conditions from the zeros before the start. The
  caller numbers those calls' frames below 0 (`frame` = (call - warm-up calls) M); the graph then returns
  the denoiser state it was given (zeros), which is exactly the torch stream's start, and the caller drops
  their frames. Every state is carried on every call, so an engine's implicit state (Triton) needs no
  special case. M must divide the lookahead's frames (1, 2, 3 or 6 for the default model).

It is traced from what the torch stream runs (`DiMGestor.frontend`, `.condition`, and the stream's sampler
`DenoiseRunner.sample` with its written-out blocks; run eagerly, `FrameStep` is the graph's reference), so
there is no second model. Where ONNX Runtime pays for a form that torch does not, the traced code takes another
form of the same math while exporting (`torch.compiler.is_exporting()`): the speech front end's spectra as matrix
products instead of DFT nodes, its running statistics in torch instead of numpy. The exporter is torch.onnx's
dynamo one (`torch.export`, then onnxscript), which handles what the model's code does in torch.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, Sequence

import torch
from torch import nn

from ..model.diffusion import Diffusion, check_guidance
from ..model.mamba2 import Mamba2State
from ..model.network import DiMGestor, ExtractorState
from ..model.sampler import StepStates, runner_for
from .onnx_stream import MANIFEST

if TYPE_CHECKING:
    from ..streaming.checkpoint import Bundle

__all__ = ["FrameStep", "StateSpec", "check_export", "export_bundle", "export_onnx", "state_specs", "manifest_of",
           "weights_sha256", "OPSET", "register"]

OPSET = 18
GRAPH = "frame_step.onnx"


class StateSpec(NamedTuple):
    """One carried tensor: fed as input `name`, returned as output `name + "_out"`, starting at `init`."""

    name: str
    init: torch.Tensor  # its value before the first call (the graph's batch of streams)
    dim: int = 0  # the dimension the streams' rows stack on (a stream has `init.shape[dim] // batch` rows)

    @property
    def out(self) -> str:
        return self.name + "_out"


def _fill(t: torch.Tensor) -> float:
    """The one value a state starts with (every initial state is a constant fill: zeros, NaN, a floor)."""
    flat = t.flatten()
    v = flat[:1]
    if not (torch.equal(flat, v.expand_as(flat)) or bool(torch.isnan(flat).all())):
        raise ValueError("an initial state that is not one constant cannot be written as a fill")
    return float(v)


def _warmup(model: DiMGestor) -> int:
    c = model.config
    if c.lookahead_feats % c.feats_per_frame:
        raise ValueError(f"ONNX export needs a lookahead of whole motion frames: {c.lookahead_feats} feature frames "
                         f"is not a multiple of {c.feats_per_frame}")
    return c.lookahead_feats // c.feats_per_frame


def state_specs(model: DiMGestor, steps: int, rows: int, batch: int = 1) -> list[StateSpec]:
    """The graph's carried tensors in input order: front end, extractor, denoiser (K steps, `rows` branches), for
    `batch` streams (their rows stacked on each spec's `dim`: the batch dim of the torch layouts)."""
    if model.config.frontend in ("pretrained", "embedding"):
        raise ValueError(f"ONNX export supports the logmel and speech front ends, not '{model.config.frontend}' "
                         "(a pretrained encoder runs outside the graph)")
    fe = model.frontend.init_state(batch)
    specs = [StateSpec(f"frontend_{k}", v) for k, v in fe._asdict().items() if torch.is_tensor(v)]
    ex = model.extractor
    style = ex.style.zero_state(batch)
    specs += [StateSpec("extractor_style_conv", style.conv), StateSpec("extractor_style_ssm", style.ssm),
              StateSpec("extractor_buf", torch.zeros(batch, ex.feat_dim + ex.S, ex.k - ex.stride))]
    d = StepStates.zeros(model, steps, rows * batch)  # the torch stream's own layout (`StreamState.denoiser`)
    return specs + [StateSpec("denoiser_enc", d.enc, 1), StateSpec("denoiser_conv", d.conv, 2),
                    StateSpec("denoiser_ssm", d.ssm, 2)]


class _Slots:
    """A `StepStates` field as the runner's `out=` sees it: `slots[k]` or `slots[k, j]` is its own new tensor.

    The runner writes each step's and block's new state into `out.conv[k, j]` (copy_, out=); traced into
    one stacked tensor, every such write becomes a scatter that copies the whole (K, blocks, ...) state (2 MB
    at K = 8, ~2 ms each in ONNX Runtime). Written into separate tensors and stacked once at the end (one
    concatenation of all K * blocks parts, not a stack of stacks: each level copies the whole state), the
    graph holds plain values."""

    def __init__(self, like: torch.Tensor):
        self.like, self.parts = like, {}

    def __getitem__(self, index) -> torch.Tensor:
        if index not in self.parts:
            self.parts[index] = torch.empty_like(self.like[index])
        return self.parts[index]

    def stacked(self) -> torch.Tensor:
        depth = max(1 if isinstance(k, int) else len(k) for k in self.parts)
        order = sorted(self.parts) if depth > 1 else range(self.like.shape[0])
        if depth > 1 and len(order) != math.prod(self.like.shape[:depth]):
            raise ValueError("the runner left a state slot unwritten")
        return torch.stack([self.parts[i] for i in order]).view(self.like.shape)


class _Parts:
    """A `StepStates` field as the runner reads it: `parts[k]` or `parts[k, j]`, all cut by one split of the
    input (two nested selects copy the state twice in ONNX Runtime, where a slice is a copy)."""

    def __init__(self, t: torch.Tensor, depth: int):
        self.shape, self.depth = t.shape, depth
        self.parts = t.reshape(-1, *t.shape[depth:]).unbind(0)

    def __getitem__(self, index) -> torch.Tensor:
        index = (index,) if isinstance(index, int) else index
        if len(index) != self.depth:
            raise IndexError(f"state parts are indexed by {self.depth} numbers, got {index}")
        flat = 0
        for i, n in zip(index, self.shape):
            flat = flat * n + i
        return self.parts[flat]


class FrameStep(nn.Module):
    """M motion frames of `batch` streams as a function of explicit tensors: what the ONNX graph is traced from,
    and, run in torch, the graph's reference (`forward(samples, seed, frame, *state) -> (frames, *state)`).

    batch 1 is the engines' graph (frames (M, D)); a batch of B streams (frames (B, M, D)) takes each stream's
    samples, seed, frame index and states as its rows: the streams are independent (own seeds, own frame
    indices, some in their warm-up while others are not), and a row's frames are the ones it makes alone."""

    def __init__(self, model: DiMGestor, steps: int, guidance: float, frames: int = 2, batch: int = 1):
        super().__init__()
        if frames < 1 or _warmup(model) % frames:
            raise ValueError(f"frames per call must divide the {_warmup(model)} warm-up frames (the lookahead), "
                             f"got {frames}")
        if batch < 1:
            raise ValueError(f"a batch is at least one stream, got {batch}")
        self.model, self.guidance, self.frames, self.batch = model, check_guidance(guidance), frames, batch
        self.pairs = Diffusion(model.config).sampling_pairs("ddim", steps)
        self.runner = runner_for(model, self.pairs, "ddim", 0.0)  # the torch stream's sampler, shared with it
        self.rows = 1 if self.guidance == 1.0 else 2
        self.specs = state_specs(model, len(self.pairs), self.rows, batch)
        self._fe_type, self._fe_fixed = type(model.frontend.init_state(1)), model.frontend.init_state(1)._asdict()

    def forward(self, samples: torch.Tensor, seed: torch.Tensor, frame: torch.Tensor, *state: torch.Tensor):
        m, named = self.model, dict(zip((s.name for s in self.specs), state))
        fe = self._fe_type(**{k: named.get(f"frontend_{k}", v) for k, v in self._fe_fixed.items()})
        ex = ExtractorState(Mamba2State(named["extractor_style_conv"], named["extractor_style_ssm"]),
                            named["extractor_buf"])
        feats, fe = m.frontend(samples, fe)  # (B, 5 M, F)
        cond, ex = m.condition(feats, ex)  # (B, M, H)
        states = StepStates(named["denoiser_enc"], named["denoiser_conv"], named["denoiser_ssm"])
        out = StepStates(*(_Slots(t) for t in states))
        parts = StepStates(*(_Parts(t, depth) for t, depth in zip(states, (1, 2, 2))))
        # a warm-up call (frame < 0): its condition is not real yet, so that stream's denoiser rows keep their
        # start state (the runner holds them: no pass over the whole stacked state to choose old or new)
        warm = (frame < 0).repeat_interleave(self.rows)  # (B rows,)
        frames = self.runner.sample(cond, frame, seed, parts, [self.guidance] * self.batch, out=out,
                                    hold=warm)  # (B, M, D)
        new = {f"frontend_{k}": v for k, v in fe._asdict().items() if torch.is_tensor(v)}
        new |= {"extractor_style_conv": ex.style.conv, "extractor_style_ssm": ex.style.ssm, "extractor_buf": ex.buf}
        new |= {spec.name: slots.stacked() for spec, slots in zip(self.specs[-3:], out)}
        return (frames[0] if self.batch == 1 else frames, *(new[s.name] for s in self.specs))

    def example_inputs(self) -> tuple[torch.Tensor, ...]:
        c, B = self.model.config, self.batch
        seed, frame = torch.zeros(B, dtype=torch.int64), torch.zeros(B, dtype=torch.int64)  # distinct: not aliased
        return (torch.zeros(B, c.samples_per_frame * self.frames), seed, frame, *(s.init for s in self.specs))


def _tensor_entry(name: str, t: torch.Tensor) -> dict:
    return {"name": name, "shape": list(t.shape), "dtype": str(t.dtype).removeprefix("torch.")}


def manifest_of(step: FrameStep, checkpoint: dict, batches: Sequence[int] = ()) -> dict:
    """What an engine needs to drive the graph: every input, output and state (shape, dtype, start value), and
    the graphs of `batches` streams a call beside it (their shapes: each state's rows times the batch on its
    `batch_dim`, the other inputs' first dim the batch, frames (B, M, D))."""
    c = step.model.config
    inputs = step.example_inputs()
    frame = torch.zeros(step.frames, c.motion_dim)
    return {
        "format": 1, "graph": GRAPH, "opset": OPSET,
        "call": {"samples_per_call": c.samples_per_frame * step.frames, "sample_rate": c.sample_rate, "fps": c.fps,
                 "frames_per_call": step.frames, "warmup_calls": _warmup(step.model) // step.frames,
                 "finish": "pad with zeros to whole calls until frame T - 1 is made, T = samples_in * fps // "
                           "sample_rate; keep frames < T"},
        "sampler": {"name": "ddim", "eta": 0.0, "steps": len(step.pairs), "pairs": step.pairs,
                    "guidance": step.guidance, "rows": step.rows},
        "noise": "counter-based, in the graph: x_T of frame f is motion_noise(seed, f); `frame` is the index of the "
                 "call's first frame, (call - warmup_calls) * frames_per_call: below 0 during the warm-up, whose "
                 "frames are dropped (the graph keeps the denoiser state)",
        "inputs": [_tensor_entry("samples", inputs[0]), _tensor_entry("seed", inputs[1]),
                   _tensor_entry("frame", inputs[2]),
                   *(_tensor_entry(s.name, s.init) for s in step.specs)],
        "outputs": [_tensor_entry("frames", frame), *(_tensor_entry(s.out, s.init) for s in step.specs)],
        "state": [{"input": s.name, "output": s.out, "shape": list(s.init.shape),
                   "dtype": str(s.init.dtype).removeprefix("torch."), "init": _fill(s.init), "batch_dim": s.dim}
                  for s in step.specs],
        "batched": [{"batch": b, "graph": batch_graph(b)} for b in sorted(set(batches))],
        "checkpoint": checkpoint,
    }


def batch_graph(batch: int) -> str:
    return GRAPH if batch == 1 else f"frame_step_b{batch}.onnx"


def export_onnx(checkpoint: str | None, out: str | Path, steps: int | None = None,
                guidance: float | None = None, frames: int = 2, batches: Sequence[int] = (),
                speaker: str | None = None) -> Path:
    """A checkpoint (None: the embedded default) -> out/frame_step.onnx and out/manifest.json; returns out.
    batches: also a graph of B streams a call for each B (out/frame_step_bB.onnx), for a server's batches.
    speaker: the speaker the graph plays, of a model trained with --speaker-condition (its vector is baked in)."""
    from ..streaming.checkpoint import load_checkpoint

    bundle = load_checkpoint(checkpoint)
    bundle.model.use_speaker(speaker)
    return export_bundle(bundle, out, steps, guidance, frames, batches)


def export_bundle(bundle: Bundle, out: str | Path, steps: int | None = None, guidance: float | None = None,
                  frames: int = 2, batches: Sequence[int] = ()) -> Path:
    """`export_onnx` of a loaded checkpoint."""
    model = bundle.model.eval()
    c = model.config
    steps = steps or c.sample_steps
    if not 1 <= steps <= c.n_steps:
        raise ValueError(f"--steps must be in 1..{c.n_steps}, got {steps}")
    guidance = c.guidance if guidance is None else guidance
    if any(b < 1 for b in batches):
        raise ValueError(f"--batch sizes must be at least 1, got {list(batches)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    step = FrameStep(model, steps, guidance, frames).eval()
    _export_graph(step, out / GRAPH)
    for b in sorted(set(batches) - {1}):
        _export_graph(FrameStep(model, steps, guidance, frames, batch=b).eval(), out / batch_graph(b))
    checkpoint = {"path": str(bundle.path), "weights_sha256": weights_sha256(bundle.path),
                  "config": c.model_dump(mode="json"), "mean": bundle.mean.tolist(), "std": bundle.std.tolist(),
                  "speaker": model.speaker}  # (the speaker the graph plays: its vector is a constant in it)
    (out / MANIFEST).write_text(json.dumps(_json_safe(manifest_of(step, checkpoint, batches)), indent=1))
    return out


def _export_graph(step: FrameStep, path: Path) -> None:
    import onnx

    names_in = ["samples", "seed", "frame", *(s.name for s in step.specs)]
    names_out = ["frames", *(s.out for s in step.specs)]
    with torch.inference_mode(False), torch.no_grad(), _quiet():
        step(*step.example_inputs())  # the runner prepares its stacked weights eagerly; traced, they are constants
        program = torch.onnx.export(step, step.example_inputs(), input_names=names_in, output_names=names_out,
                                    opset_version=OPSET, dynamo=True, external_data=False, optimize=False,
                                    verbose=False)
    _optimize(program.model)
    program.save(str(path))
    onnx.checker.check_model(str(path))


@contextlib.contextmanager
def _quiet():
    """The exporter's warnings and log lines (deprecations inside torch, torchvision absent) off the console."""
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        logger.setLevel(level)


def _optimize(model) -> None:
    """torch.onnx's own graph optimization (onnxscript's `optimize_ir`: constant folding, rewrites, clean-up;
    without it ORT runs a frame 2.8x slower) minus its no-op rules: their `x + 0` matches any scalar within
    1e-8 of 0, which removed the front end's `+ 1e-12` and made digital silence log10(0) = -inf. Plus rules of
    ours (`_fusable_rules`) that let ONNX Runtime fuse each block's RMSNorm and GELU into one node each."""
    import onnx_ir as ir
    import onnx_ir.passes.common as common
    from onnxscript import rewriter
    from onnxscript.optimizer import _constant_folding
    from onnxscript.rewriter.rules.common import _no_op

    # SlicesSplit (several Slices of one value -> one Split) never matches this model's graphs and its matcher
    # took a third of each graph's export (18 of 52 s for the default model's): left out, the graphs are the same
    rules = [r for r in rewriter._DEFAULT_REWRITE_RULES if r not in _no_op.rules and r.name != "SlicesSplit"]
    rules += _fusable_rules()
    ir.passes.Sequential(
        common.InlinePass(),
        ir.passes.PassManager([_constant_folding.FoldConstantsPass(
            shape_inference=True, input_size_limit=_constant_folding.DEFAULT_CONSTANT_FOLD_INPUT_SIZE_LIMIT,
            output_size_limit=_constant_folding.DEFAULT_CONSTANT_FOLD_OUTPUT_SIZE_LIMIT),
            rewriter.RewritePass(rules), common.RemoveUnusedNodesPass(), common.RemoveUnusedFunctionsPass(),
            common.RemoveUnusedOpsetsPass()], steps=2, early_stop=True),
        common.RemoveUnusedNodesPass(),
        common.LiftConstantsToInitializersPass(lift_all_constants=True, size_limit=0),
        common.DeduplicateInitializersPass(),
        common.CommonSubexpressionEliminationPass(),
        common.NameFixPass(),
    )(model)


def _fusable_rules() -> list:
    """Two traced forms ONNX Runtime's fusions do not match, rewritten into the forms they do (same math; the
    fused kernels round their own way, the frames move by < 1e-6):

    - RMSNorm's `x * Reciprocal(Sqrt(s))` -> `x / Sqrt(s)` (the Reciprocal used there only):
      SimplifiedLayerNormalization, 7 nodes -> 1;
    - tanh GELU's `x * (0.5 * (1 + tanh(u)))` -> `(x * 0.5) * (1 + tanh(u))` (exact: multiplying by 0.5 is):
      FastGelu, 8 nodes -> 1."""
    from onnxscript.rewriter import pattern

    def rms(op, x, s):
        return op.Mul(x, op.Reciprocal(op.Sqrt(s)))

    def rms_div(op, x, s):
        return op.Div(x, op.Sqrt(s))

    def gelu(op, x, u, half, one):
        return op.Mul(x, op.Mul(half, op.Add(op.Tanh(u), one)))

    def gelu_half_first(op, x, u, half, one):
        return op.Mul(op.Mul(x, half), op.Add(op.Tanh(u), one))

    def constants(context, half, one, **_):
        value = lambda v: None if v.const_value is None or v.const_value.size != 1 else float(  # noqa: E731
            v.const_value.numpy().reshape(()))
        return value(half) == 0.5 and value(one) == 1.0

    return [*pattern.RewriteRule(rms, rms_div).commute(),
            *pattern.RewriteRule(gelu, gelu_half_first, constants).commute()]


def weights_sha256(checkpoint: Path) -> str:
    """The checkpoint's weights file hash: which model an export was made from."""
    return hashlib.sha256((Path(checkpoint) / "model.safetensors").read_bytes()).hexdigest()


def check_export(manifest: dict, bundle: Bundle) -> None:
    """An ONNX export must be of this checkpoint's weights (`export-onnx --checkpoint` the same folder)."""
    if manifest["checkpoint"]["weights_sha256"] != weights_sha256(bundle.path):
        raise ValueError(f"the ONNX export was made from {manifest['checkpoint']['path']}, not from "
                         f"{bundle.path}: export this checkpoint (dimgestor export-onnx --checkpoint ...)")
    wanted = bundle.model.speaker
    if (played := manifest["checkpoint"].get("speaker")) != wanted:
        how = f"with --speaker {wanted}" if wanted else "without --speaker"
        raise ValueError(f"the ONNX export plays {_who(played)}, not {_who(wanted)}: export it {how}")


def _who(speaker: str | None) -> str:
    return f"speaker {speaker!r}" if speaker else "no speaker in particular"


def _json_safe(v):
    """NaN as the string "nan" (strict JSON has no NaN; the speech front end's noise floor starts there)."""
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    return v


def register(subparsers) -> None:
    from ..cli_help import examples

    p = subparsers.add_parser(
        "export-onnx", help="the streaming step as an ONNX graph with explicit state",
        description="Export the model's streaming step (one window of frames, every state explicit) as an ONNX "
                    "graph with a manifest: for `dimgestor serve --backend onnxruntime`, `dimgestor web`, Triton "
                    "or your own runtime.",
        epilog=examples("dimgestor export-onnx --out onnx_model",
                        "dimgestor export-onnx --checkpoint live --out onnx_live --steps 4 --batch 4 8",
                        "dimgestor export-onnx --out onnx_model --triton 2"))
    g = p.add_argument_group("model and sampling")
    g.add_argument("--checkpoint", default=None, help="checkpoint or run folder (default: the embedded model)")
    g.add_argument("--steps", type=int, default=None, metavar="K",
                   help="DDIM steps K in the graph (default: the checkpoint's)")
    g.add_argument("--guidance", type=float, default=None, metavar="S",
                   help="classifier-free guidance scale baked into the graph (default: the checkpoint's)")
    g.add_argument("--speaker", default=None, metavar="NAME",
                   help="the speaker the graph plays, for a model trained with --speaker-condition (`dimgestor info` "
                        "lists them) (default: no speaker in particular)")
    g.add_argument("--frames", type=int, default=2, metavar="N",
                   help="motion frames per call, 50 ms each (2: 100 ms windows); a divisor of the lookahead's frames "
                        "(1, 2, 3 or 6 for the default model)")
    g = p.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="DIR", help="folder for frame_step.onnx and manifest.json")
    g.add_argument("--batch", type=int, nargs="*", default=[], metavar="B",
                   help="also export graphs of B streams a call (frame_step_bB.onnx): `dimgestor serve --backend "
                        "onnxruntime` runs the due windows of many clients as one call")
    g.add_argument("--triton", type=int, default=None, metavar="INSTANCES",
                   help="also write a Triton model repository (OUT/triton/dimgestor: config.pbtxt with the states "
                        "as the sequence batcher's implicit state, 1/model.onnx) with this many CPU instances")
    g.add_argument("--no-face", action="store_true",
                   help="leave out the face's listener (face_step.onnx and face_manifest.json: what the face's "
                        "network hears, called like frame_step.onnx; docs/face.md)")
    p.set_defaults(func=_run)


def _run(args) -> int:
    if args.triton is not None and args.triton < 1:  # before minutes of exporting
        raise SystemExit(f"--triton needs at least 1 instance, got {args.triton}")
    out = export_onnx(args.checkpoint, args.out, args.steps, args.guidance, args.frames, args.batch, args.speaker)
    m = json.loads((out / MANIFEST).read_text())
    print(f"wrote {out / GRAPH} (opset {OPSET}, K={m['sampler']['steps']}, guidance {m['sampler']['guidance']:g}, "
          f"{len(m['state'])} state tensors) and {out / MANIFEST}")
    if not args.no_face:
        from .onnx_face import FACE_GRAPH, FACE_MANIFEST, export_face

        fps = m["call"]["fps"]
        if round(100 / fps) * fps == 100:
            export_face(out, int(fps), args.frames)
            print(f"wrote {out / FACE_GRAPH} (the face's listener, {args.frames} frames a call) and "
                  f"{out / FACE_MANIFEST}")
        else:
            print(f"no face graph: the face's graph needs a frame rate that divides 100 ({fps:g} fps)")
    if args.triton is not None:
        from .onnx_triton import write_triton_repository

        model = write_triton_repository(out, out / "triton", instances=args.triton)
        print(f"wrote the Triton model repository {model.parent} (model {model.name}, {args.triton} CPU instances)")
    return 0
