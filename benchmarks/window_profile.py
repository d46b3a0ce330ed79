"""Where one window goes (issue 50): a `streamer.sessions.Session` window of the embedded default model cut into
its parts, so that every change to the window's cost is measured against it.

torch    `Session.infer` of `--window-ms` windows of speech, one thread, with the face, `--windows` timed after a
         warm-up; each part timed where it runs (wall and this thread's CPU, summed over the timed windows):
           front end       the speech front end (`model.frontend`)
           style           the style extractor's Mamba-2 (with its in and out projections)
           extractor rest  the rest of the fuzzy feature extractor: the Conv1D downsampler to the motion rate
                           (stepped on its state) and the glue between them
           modulations     every adaLN output of the window, all steps at once (`DenoiseRunner.modulations`)
           encoder         the Conv1D encoder, each sampler step
           blocks          the AdaLN Mamba-2 blocks, each sampler step
           final           the final layer, each sampler step
           noise           the seeded noise of each step
           sampler rest    the rest of the denoiser's loop (the DDIM update, guidance's combination, state copies)
           stream rest     the stream's own work around the model (buffers, smoothing, states)
           decoder         features -> the skeleton's pose (`PoseDecoder.decode`)
           face            the face (`FaceStream.push_many`: listener, mouth, blinks, brows)
           framing         the rest of `Session.frames_of` (denormalizing, channels, checks, `Frame`s)
           encoding        the frames as a WebSocket client gets them (`protocol.encode_frames`, JSON and binary),
                           outside the window (the connection's thread)
         and once more with guidance 1 (the model unguided: one denoiser row a stream instead of two), so the
         difference is what guidance costs. (The embedded default model has its guided teacher's scale folded in and
         runs one row: its guided arm runs it at that scale, 1.25, for what a second row costs.)
onnxruntime  with `--onnx DIR` (an export of the same model, `dimgestor export-onnx --out DIR`): the window as
         `serve --backend onnxruntime` runs it (one thread), then again with ONNX Runtime's profiler on, each node's
         time summed by the part of the model it belongs to (the module scope the exporter records with it; the
         sampler's K steps are one part). The profiler adds a few microseconds to each of the ~2,400
         nodes a window runs, so its parts are shares of a slower window: read them beside each part's nodes run.

    .venv/bin/python benchmarks/window_profile.py                    # writes results/window_profile.json, .png
    .venv/bin/python benchmarks/window_profile.py --onnx /tmp/k4     # with ONNX Runtime's parts
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, test_audio, utc_now, write_json

RATE = 16000
MODEL_PARTS = ("front end", "style", "extractor rest", "modulations", "encoder", "blocks", "final", "noise",
               "sampler rest", "stream rest")
PARTS = (*MODEL_PARTS, "decoder", "face", "framing")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=4, help="DDIM steps K")
    p.add_argument("--window-ms", type=int, default=100)
    p.add_argument("--windows", type=int, default=200, help="timed windows per arm")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--onnx", type=Path, default=None, help="an export of the embedded default model (its K)")
    p.add_argument("--out", type=Path, default=RESULTS / "window_profile.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


class Clock:
    """Wall and thread CPU seconds by part, while `on`; a part inside another is taken out of the outer one's."""

    def __init__(self):
        self.on, self.wall, self.cpu, self.calls = False, defaultdict(float), defaultdict(float), defaultdict(int)
        self._stack: list[list] = []  # [name, t0, c0, inner wall, inner cpu]

    def enter(self, name: str) -> None:
        if self.on:
            self._stack.append([name, time.perf_counter(), time.thread_time(), 0.0, 0.0])

    def leave(self, name: str) -> None:
        if not (self._stack and self._stack[-1][0] == name):
            return  # (entered while off)
        frame = self._stack.pop()
        wall, cpu = time.perf_counter() - frame[1], time.thread_time() - frame[2]
        self.wall[name] += wall - frame[3]
        self.cpu[name] += cpu - frame[4]
        self.calls[name] += 1
        if self._stack:
            self._stack[-1][3] += wall
            self._stack[-1][4] += cpu

    @contextmanager
    def part(self, name: str):
        self.enter(name)
        try:
            yield
        finally:
            self.leave(name)


def instrument(bundle, clock: Clock) -> list:
    """Wrap each part where it runs; returns the undo list."""
    import dimgestor.model.sampler as sampler
    from dimgestor.face.stream import FaceStream
    from dimgestor.features import PoseDecoder
    from dimgestor.streaming.stream import GestureStream
    from streamer.sessions import Session

    undo = []

    def wrap(owner, attr: str, name: str, static: bool = False):
        raw = owner.__dict__[attr] if isinstance(owner, type) else getattr(owner, attr)
        fn = raw.__func__ if static else raw

        def timed(*a, **k):
            with clock.part(name):
                return fn(*a, **k)
        setattr(owner, attr, staticmethod(timed) if static else timed)
        undo.append(lambda: setattr(owner, attr, raw))

    def hook(module, name: str):
        pre = module.register_forward_pre_hook(lambda m, a: clock.enter(name))
        post = module.register_forward_hook(lambda m, a, o: clock.leave(name))
        undo.extend([pre.remove, post.remove])

    m = bundle.model
    hook(m.frontend, "front end")
    hook(m.extractor, "extractor rest")
    for child in ("style_in", "style", "style_out"):
        hook(getattr(m.extractor, child), "style")
    hook(m.encoder, "encoder")
    wrap(sampler.DenoiseRunner, "modulations", "modulations")
    wrap(sampler.DenoiseRunner, "sample", "sampler rest")
    wrap(sampler._FastBlock, "__call__", "blocks")
    wrap(sampler, "_modulated_block", "blocks")
    wrap(sampler, "_modulated_final", "final")
    wrap(sampler, "motion_noise_rows", "noise")
    wrap(GestureStream, "push", "stream rest")
    wrap(GestureStream, "finish", "stream rest")
    wrap(PoseDecoder, "decode", "decoder")
    wrap(FaceStream, "push_many", "face", static=True)
    wrap(Session, "frames_of", "framing")
    return undo


def torch_arm(bundle, audio: np.ndarray, guidance: float | None, args) -> dict:
    """The window's parts on torch (the Session a `serve` client gets, with the face)."""
    import torch

    from dimgestor.face import FaceOptions
    from streamer import protocol
    from streamer.sessions import Session

    clock = Clock()
    undo = instrument(bundle, clock)
    window = RATE * args.window_ms // 1000
    session = Session.from_bundle(bundle, steps=args.steps, seed=0, guidance=guidance, face=FaceOptions())
    whole, whole_cpu, frames, enc = [], [], 0, {"json": 0.0, "binary": 0.0}
    try:
        with torch.inference_mode():
            for k in range(args.warmup + args.windows):
                x = audio[k * window:(k + 1) * window]
                clock.on = k >= args.warmup
                t0, c0 = time.perf_counter(), time.thread_time()
                out = session.infer(x)
                if clock.on:
                    whole.append(time.perf_counter() - t0)
                    whole_cpu.append(time.thread_time() - c0)
                    frames += len(out)
                    for encoding in enc:
                        t = time.perf_counter()
                        protocol.encode_frames(out, encoding)
                        enc[encoding] += time.perf_counter() - t
    finally:
        for u in reversed(undo):
            u()
    n = args.windows
    parts = {p: {"ms": 1000 * clock.wall[p] / n, "cpu_ms": 1000 * clock.cpu[p] / n, "calls_per_window": clock.calls[p] / n}
             for p in PARTS}
    window_ms, window_cpu = 1000 * float(np.sum(whole)) / n, 1000 * float(np.sum(whole_cpu)) / n
    parts["other"] = {"ms": window_ms - sum(v["ms"] for v in parts.values()),
                      "cpu_ms": window_cpu - sum(v["cpu_ms"] for v in parts.values()), "calls_per_window": 0.0}
    return {"guidance": session.stream.guidance, "window_ms_mean": window_ms, "window_cpu_ms_mean": window_cpu,
            "window_ms_p50": 1000 * float(np.median(whole)), "frames_per_window": frames / n, "parts": parts,
            "encoding_ms_per_window": {k: 1000 * v / n for k, v in enc.items()}}


def onnx_arm(folder: Path, audio: np.ndarray, args) -> dict:
    """The window on ONNX Runtime, one thread, its profiler's node times summed by the model's part."""
    import onnxruntime as ort

    from dimgestor.export.onnx_stream import FrameStepStream, load_manifest, ort_runner

    manifest = load_manifest(folder)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads, opts.inter_op_num_threads = 1, 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.enable_profiling = True
    opts.profile_file_prefix = str(args.out.with_suffix("")) + "_ort"
    session = ort.InferenceSession(str(folder / manifest["graph"]), opts, providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]

    def run(feeds):
        return dict(zip(names, session.run(None, {k: np.ascontiguousarray(v) for k, v in feeds.items()})))

    profiled = _pushes(FrameStepStream(manifest, run, seed=0), audio, args)
    whole = _pushes(FrameStepStream(manifest, ort_runner(folder, 1), seed=0), audio, args)  # as serve runs it
    scopes = node_scopes(folder / manifest["graph"])
    trace = Path(session.end_profiling())
    events = json.loads(trace.read_text())
    trace.unlink()
    runs = [e for e in events if e.get("cat") == "Session" and e.get("name") == "model_run"]
    timed = runs[-args.windows * max(1, len(runs) // (args.warmup + args.windows)):] if runs else []
    start = min((e["ts"] for e in timed), default=0)
    by_part: dict[str, float] = defaultdict(float)
    nodes: dict[str, int] = defaultdict(int)
    for e in events:
        if e.get("cat") == "Node" and e.get("ts", 0) >= start and e["name"].endswith("_kernel_time"):
            part = scopes.get(e["name"].removesuffix("_kernel_time"), "fused by the optimizer")
            by_part[part] += e["dur"] / 1e3
            nodes[part] += 1
    n = args.windows
    parts = {k: v / n for k, v in sorted(by_part.items(), key=lambda kv: -kv[1])}
    return {"folder": str(folder), "steps": manifest["sampler"]["steps"], "guidance": manifest["sampler"]["guidance"],
            "window_ms_mean": 1000 * float(np.mean(whole)), "window_ms_p50": 1000 * float(np.median(whole)),
            "profiled_window_ms_mean": 1000 * float(np.mean(profiled)),
            "session_run_ms_per_window": sum(e["dur"] for e in timed) / 1e3 / n, "parts_ms": parts,
            "nodes_run_per_window": {k: nodes[k] / n for k in parts}}


def _pushes(stream, audio: np.ndarray, args) -> list[float]:
    """Seconds of each window's push after the warm-up."""
    window, out = RATE * args.window_ms // 1000, []
    for k in range(args.warmup + args.windows):
        t0 = time.perf_counter()
        stream.push(audio[k * window:(k + 1) * window])
        if k >= args.warmup:
            out.append(time.perf_counter() - t0)
    return out


ONNX_SCOPES = (("model.frontend", "front end"), ("model.extractor.style", "style"), ("model.extractor", "extractor rest"),
               ("model.t_embedder", "modulations"), ("model.encoder", "encoder"), ("model.blocks", "blocks"),
               ("model.final", "final"))


def node_scopes(graph: Path) -> dict[str, str]:
    """Each node of the exported graph -> the model's part, from the module scope the exporter records with it
    (`pkg.torch.onnx.name_scopes`). The sampler's K steps are written out in the frame step, so the exporter
    records no module of theirs: its modulations, encoder, blocks, final layer and update are one part here."""
    import onnx

    out = {}
    for node in onnx.load(str(graph), load_external_data=False).graph.node:
        meta = {p.key: p.value for p in node.metadata_props}
        names = json.loads(meta.get("pkg.torch.onnx.name_scopes", "[]").replace("'", '"'))
        scope = names[-2] if len(names) >= 2 else ""
        part = next((part for key, part in ONNX_SCOPES if scope.startswith(key)), None)
        if part is None:  # the frame step's own: the sampler's K steps (written out in it) or the states
            part = "sampler (K steps)" if "runner.sample(" in meta.get("pkg.torch.onnx.stack_trace", "") else "states"
        out[node.name] = part
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arms = [a for a in ("guided", "unguided") if a in result["torch"]]
    fig, ax = plt.subplots(figsize=(9, 3.8))
    for i, arm in enumerate(arms):
        left = 0.0
        for j, (part, v) in enumerate(result["torch"][arm]["parts"].items()):
            ax.barh(i, v["cpu_ms"], left=left, color=f"C{j % 10}", hatch="//" if j >= 10 else None,
                    label=part if i == 0 else None)
            left += max(v["cpu_ms"], 0.0)
    ax.set_yticks(range(len(arms)), [f"torch, {a} ({result['torch'][a]['guidance']:g})" for a in arms])
    ax.set_xlabel("CPU ms a window (mean)")
    ax.legend(fontsize=7, ncol=5, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    ax.set_title(f"window_profile: K={result['steps']}, {result['window_ms']} ms windows, one thread "
                 f"({result['code_version']}, {result['device'][:40]})", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    args = parse_args(argv)
    import torch

    from dimgestor.streaming.checkpoint import load_checkpoint

    torch.set_num_threads(1)
    bundle = load_checkpoint(None)
    need = (args.warmup + args.windows + 2) * RATE * args.window_ms // 1000
    audio = test_audio(need / RATE, RATE)[:need]
    result = {"benchmark": "window_profile", "code_version": code_version(), "device": describe_device("cpu"),
              "utc": utc_now(), "argv": args.argv, "note": args.note, "load_average_before": load_average(),
              "steps": args.steps, "window_ms": args.window_ms, "windows": args.windows, "torch": {}}
    guided = None  # (the model's own guidance) where it guides; a student at the first guided scale in its lineage
    if bundle.config.guidance == 1:
        teacher, guided = bundle.info.get("teacher", {}), 1.25  # (the shipped recipe's, where none is recorded)
        while teacher:
            if teacher.get("guidance", 1) > 1:
                guided = teacher["guidance"]
                break
            teacher = teacher.get("teacher", {})
    for arm, guidance in (("guided", guided), ("unguided", 1.0)):
        result["torch"][arm] = r = torch_arm(bundle, audio, guidance, args)
        top = sorted(r["parts"].items(), key=lambda kv: -kv[1]["cpu_ms"])[:5]
        print(f"torch {arm} (guidance {r['guidance']:g}): {r['window_cpu_ms_mean']:.2f} ms CPU a window: "
              + ", ".join(f"{p} {v['cpu_ms']:.2f}" for p, v in top), flush=True)
    g, u = result["torch"]["guided"], result["torch"]["unguided"]
    result["torch"]["guidance_cpu_ms"] = g["window_cpu_ms_mean"] - u["window_cpu_ms_mean"]
    if args.onnx is not None:
        result["onnxruntime"] = o = onnx_arm(args.onnx, audio, args)
        print(f"onnxruntime: {o['window_ms_mean']:.2f} ms a window ({o['profiled_window_ms_mean']:.2f} profiled): "
              + ", ".join(f"{p} {v:.2f}" for p, v in list(o["parts_ms"].items())[:6]), flush=True)
    result["load_average_after"] = load_average()
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
