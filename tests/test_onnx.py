"""`dimgestor export-onnx` and its ONNX Runtime stream: the graph loads, the manifest is the graph's, the state
shapes are the torch stream's, and ORT frames equal torch frames streamed in odd chunks with the state carried."""
import json
from dataclasses import replace

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime", reason="the `onnx` extra is not installed")
pytest.importorskip("onnxscript", reason="the `onnx` extra is not installed")

from dimgestor.audio import SAMPLE_RATE  # noqa: E402
from dimgestor.checkpoint import load_checkpoint  # noqa: E402
from dimgestor.cli import main, model_info  # noqa: E402
from dimgestor.onnx_export import FrameStep  # noqa: E402
from dimgestor.onnx_stream import FrameStepStream, load_manifest, ort_runner, ort_stream, torch_runner  # noqa: E402
from dimgestor.synthetic import synthetic_speech  # noqa: E402

STEPS, FRAMES, SEED = 2, 2, 7  # a small graph: exporting it takes ~15 s


@pytest.fixture(scope="module")
def bundle():
    return load_checkpoint(None)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The embedded default model exported through the command line."""
    out = tmp_path_factory.mktemp("onnx")
    assert main(["export-onnx", "--out", str(out), "--steps", str(STEPS), "--frames", str(FRAMES)]) == 0
    return out


@pytest.fixture(scope="module")
def audio():
    """Digital silence (log10 of a zero frame's energy needs its + 1e-12), then speech-like sound; 3.2 s."""
    return np.concatenate([np.zeros(SAMPLE_RATE // 4, np.float32), synthetic_speech(2.95, seed=3)]).astype(np.float32)


def pieces(audio, sizes):
    i, k = 0, 0
    while i < len(audio):
        yield audio[i:i + sizes[k % len(sizes)]]
        i += sizes[k % len(sizes)]
        k += 1


def streamed(stream, audio, sizes):
    return np.concatenate([stream.push(c) for c in pieces(audio, sizes)] + [stream.finish()])


def test_manifest_is_the_graph(exported):
    m = load_manifest(exported)
    session = ort.InferenceSession(str(exported / m["graph"]), providers=["CPUExecutionProvider"])
    onnx_type = {"float32": "tensor(float)", "float64": "tensor(double)", "int64": "tensor(int64)"}
    for entries, values in ((m["inputs"], session.get_inputs()), (m["outputs"], session.get_outputs())):
        assert [(e["name"], e["shape"], onnx_type[e["dtype"]]) for e in entries] == [
            (v.name, v.shape, v.type) for v in values]
    names_in, names_out = {e["name"] for e in m["inputs"]}, {e["name"] for e in m["outputs"]}
    assert names_in - {s["input"] for s in m["state"]} == {"samples", "seed", "frame"}
    assert names_out - {s["output"] for s in m["state"]} == {"frames"}
    assert m["opset"] >= 17 and m["call"] == {**m["call"], "samples_per_call": 800 * FRAMES, "frames_per_call": FRAMES,
                                              "warmup_calls": 6 // FRAMES}
    json.loads((exported / "manifest.json").read_text())  # strict JSON: NaN is written "nan"


def test_onnx_runtime_fuses_each_blocks_gelu_and_rmsnorm_and_reads_each_state_once(exported, bundle, tmp_path):
    """The graph is written in the forms ONNX Runtime fuses (a tanh GELU and an RMSNorm a block and step become
    one node each), and each stacked denoiser state is cut by one node (beside the warm-up gate), not per step."""
    import collections

    import onnx

    m = load_manifest(exported)
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.optimized_model_filepath = str(tmp_path / "optimized.onnx")
    ort.InferenceSession(str(exported / m["graph"]), opts, providers=["CPUExecutionProvider"])
    ops = collections.Counter(n.op_type for n in onnx.load(opts.optimized_model_filepath).graph.node)
    blocks = bundle.config.n_blocks
    assert ops["FastGelu"] == STEPS * blocks
    assert ops["SimplifiedLayerNormalization"] >= STEPS * blocks
    written = onnx.load(str(exported / m["graph"])).graph.node
    for name in ("denoiser_enc", "denoiser_conv", "denoiser_ssm"):
        assert sorted(n.op_type for n in written if name in n.input) == ["Reshape", "Where"]


def test_state_shapes_are_the_torch_streams(exported, bundle):
    m = load_manifest(exported)
    shapes = {s["input"]: tuple(s["shape"]) for s in m["state"]}
    torch_state = bundle.stream(steps=STEPS).state  # guided (the default model's 1.25): 2 denoiser rows
    assert m["sampler"]["guidance"] == bundle.config.guidance != 1 and m["sampler"]["rows"] == 2
    assert [shapes[f"denoiser_{k}"] for k in ("enc", "conv", "ssm")] == [tuple(t.shape) for t in torch_state.denoiser]
    assert shapes["extractor_style_ssm"] == tuple(torch_state.extractor.style.ssm.shape)
    info = model_info(bundle.config, STEPS)["stream_state_bytes"]
    per_row_step = sum(4 * np.prod(shapes[f"denoiser_{k}"]) // (STEPS * 2) for k in ("enc", "conv", "ssm"))
    assert per_row_step == info["denoiser_per_step"]


def test_ort_frames_equal_torch_frames_in_odd_chunks(exported, bundle, audio):
    torch_frames = streamed(bundle.stream(steps=STEPS, seed=SEED), audio, [1, 799, 1601, 333])
    ort_frames = streamed(ort_stream(exported, seed=SEED), audio, [777, 5, 2001, 1600])
    assert ort_frames.shape == torch_frames.shape == (len(audio) * 20 // SAMPLE_RATE, bundle.config.motion_dim)
    assert np.abs(torch_frames).max() > 0.5  # real motion, not a constant
    assert np.abs(ort_frames - torch_frames).max() < 1e-4
    other_seed = streamed(ort_stream(exported, seed=SEED + 1), audio, [4000])
    assert np.abs(other_seed - torch_frames).max() > 0.1  # the seed input reaches the graph's noise


def test_state_must_be_carried(exported, bundle, audio):
    """Every call from a fresh state (the audio clock kept) gives other frames: the equality above needs the
    carried state, not just the graph."""
    stream = ort_stream(exported, seed=SEED)
    carried = streamed(stream, audio[:SAMPLE_RATE * 2], [800 * FRAMES])
    fresh, state = [], stream.initial_state()
    for i, chunk in enumerate(pieces(audio[:SAMPLE_RATE * 2], [800 * FRAMES])):
        frames, _ = stream.step(replace(stream.initial_state(), calls=i, frames_out=len(fresh)), chunk)
        fresh.extend(frames)
    assert len(fresh) == len(carried) - stream.warmup * FRAMES
    assert np.abs(np.array(fresh) - carried[:len(fresh)]).max() > 0.1


def test_a_state_on_onnx_runtime_is_a_value(exported, audio):
    """The ONNX Runtime runner keeps the states as its own values between calls (no copy); stepping twice from
    one state gives the same frames and state, so a call never writes into the state it was given."""
    stream = ort_stream(exported, seed=SEED)
    _, state = stream.step(stream.initial_state(), audio[:SAMPLE_RATE])
    a, after_a = stream.step(state, audio[SAMPLE_RATE:SAMPLE_RATE * 2])
    b, after_b = stream.step(state, audio[SAMPLE_RATE:SAMPLE_RATE * 2])
    assert len(a) > 0 and np.array_equal(a, b)
    for name in after_a.tensors:
        assert np.array_equal(np.asarray(after_a.tensors[name].numpy()), np.asarray(after_b.tensors[name].numpy()))


def test_streams_sharing_one_session_from_two_threads_equal_streams_alone(exported, audio):
    """`streamer serve --backend onnxruntime` loads the graph once (`OnnxModel`) and its inference threads run
    several clients' streams on it at once: each stream's frames are those it makes alone."""
    from concurrent.futures import ThreadPoolExecutor

    from dimgestor.onnx_stream import OnnxModel

    model = OnnxModel.load(exported)
    alone = [streamed(ort_stream(exported, seed=s), audio[:SAMPLE_RATE * 2], [1600]) for s in (1, 2)]
    with ThreadPoolExecutor(2) as pool:
        shared = list(pool.map(lambda s: streamed(model.stream(seed=s), audio[:SAMPLE_RATE * 2], [1600]), (1, 2)))
    for a, b in zip(alone, shared):
        assert len(a) > 0 and np.array_equal(a, b)


def test_frame_step_in_torch_equals_the_graph(exported, bundle, audio):
    """The traced module run in torch is the graph's reference: same driver, same frames."""
    step = FrameStep(bundle.model, STEPS, bundle.config.guidance, FRAMES).eval()
    m = load_manifest(exported)
    a = streamed(FrameStepStream(m, torch_runner(step), seed=SEED), audio[:SAMPLE_RATE], [1234])
    b = streamed(FrameStepStream(m, ort_runner(exported), seed=SEED), audio[:SAMPLE_RATE], [1234])
    assert np.abs(a - b).max() < 1e-4


def test_frames_per_call_must_divide_the_warmup(bundle):
    with pytest.raises(ValueError, match="divide"):
        FrameStep(bundle.model, 1, 1.0, frames=4)


def test_push_after_finish_raises(exported):
    s = ort_stream(exported)
    s.push(np.zeros(100, np.float32))
    assert len(s.finish()) == 0  # 100 samples: no whole frame
    with pytest.raises(RuntimeError):
        s.push(np.zeros(10, np.float32))


def test_generate_backend_onnxruntime_writes_the_torch_backends_bvh(exported, audio, tmp_path, capsys):
    from dimgestor.audio import save_wav
    from dimgestor.bvh import read_bvh

    save_wav(tmp_path / "speech.wav", audio, SAMPLE_RATE)
    common = ["generate", "--audio", str(tmp_path / "speech.wav"), "--seed", str(SEED)]
    assert main([*common, "--steps", str(STEPS), "--out", str(tmp_path / "torch.bvh")]) == 0
    assert main([*common, "--backend", "onnxruntime", "--onnx", str(exported), "--out", str(tmp_path / "ort.bvh")]) == 0
    a, b = read_bvh(tmp_path / "torch.bvh").values, read_bvh(tmp_path / "ort.bvh").values
    assert a.shape == b.shape and a.shape[0] == len(audio) * 20 // SAMPLE_RATE
    # < 1e-4 on the normalized features; in the BVH's degrees and centimetres the Euler conversion amplifies that
    # (0.013 degrees on one channel of an espeak-ng clip at K = 4, the root within 3e-5 cm)
    assert np.abs(a - b).max() < 0.05


def test_generate_refuses_another_models_export(exported, tiny_checkpoint, audio, tmp_path, capsys):
    from dimgestor.audio import save_wav

    save_wav(tmp_path / "speech.wav", audio, SAMPLE_RATE)
    assert main(["generate", "--checkpoint", str(tiny_checkpoint), "--audio", str(tmp_path / "speech.wav"),
                 "--backend", "onnxruntime", "--onnx", str(exported), "--out", str(tmp_path / "o.bvh")]) == 2
    assert "export this checkpoint" in capsys.readouterr().err
    assert main(["generate", "--audio", str(tmp_path / "speech.wav"), "--backend", "onnxruntime", "--eta", "0.5",
                 "--onnx", str(exported), "--out", str(tmp_path / "o.bvh")]) == 2


def test_warmup_calls_keep_the_denoiser_state(exported):
    """frame < 0 (a warm-up call): the graph returns the denoiser states it was given; from frame 0 on, new ones."""
    m = load_manifest(exported)
    session = ort.InferenceSession(str(exported / m["graph"]), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    states = {s["input"]: rng.standard_normal(s["shape"]).astype(s["dtype"]) for s in m["state"]}
    names = [o.name for o in session.get_outputs()]
    for frame, kept in ((-FRAMES, True), (0, False)):
        feeds = {"samples": rng.standard_normal((1, 800 * FRAMES)).astype(np.float32), "seed": np.array([1]),
                 "frame": np.array([frame]), **states}
        out = dict(zip(names, session.run(names, feeds)))
        for k in ("denoiser_enc", "denoiser_conv", "denoiser_ssm"):
            assert np.array_equal(out[k + "_out"], states[k]) == kept
        assert not np.array_equal(out["extractor_style_ssm_out"], states["extractor_style_ssm"])


def test_serve_on_onnxruntime_records_what_the_torch_backend_records(exported, audio, tmp_path):
    """`streamer serve --backend onnxruntime --onnx DIR` (the export's K and guidance) records the same motion as
    the torch backend with the same settings: every joint within 1e-3 cm."""
    import subprocess
    import sys

    from dimgestor.audio import save_wav
    from dimgestor.bvh import forward_kinematics, read_bvh

    wav = tmp_path / "speech.wav"
    save_wav(wav, audio, SAMPLE_RATE)
    guidance = load_manifest(exported)["sampler"]["guidance"]
    out = {}
    for backend in ("torch", "onnxruntime"):
        out[backend] = tmp_path / f"{backend}.bvh"
        extra = ["--onnx", str(exported)] if backend == "onnxruntime" else ["--guidance", str(guidance)]
        r = subprocess.run([sys.executable, "-m", "streamer.cli", "serve", "--source", str(wav), "--fast", "--no-ws",
                            "--record", str(out[backend]), "--steps", str(STEPS), "--seed", str(SEED), "--backend",
                            backend, "--window-ms", "100", *extra], capture_output=True, text=True, timeout=180,
                           env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})
        assert r.returncode == 0, r.stderr[-2000:]
    assert "backend onnxruntime" in r.stderr
    a, b = read_bvh(out["torch"]), read_bvh(out["onnxruntime"])
    assert a.num_frames == b.num_frames == len(audio) * 20 // SAMPLE_RATE
    assert np.abs(forward_kinematics(a) - forward_kinematics(b)).max() < 1e-3


def test_serve_refuses_an_onnx_export_with_other_settings_or_a_state_store(exported):
    from streamer.options import ServeError, ServeOptions

    with pytest.raises(ServeError, match="--state-store saves torch stream states"):
        ServeOptions.parse(backend="onnxruntime", state_store="memory")
    with pytest.raises(ServeError, match="--onnx is an export for --backend onnxruntime"):
        ServeOptions.parse(onnx=str(exported))
    from streamer.server import build

    with pytest.raises(ServeError, match=f"exported with K={STEPS}"):
        build(ServeOptions.parse(backend="onnxruntime", onnx=str(exported), steps=STEPS + 1, source="ws"))


def test_onnx_runtime_benchmark_runs_end_to_end_at_tiny_size(exported, tmp_path):
    """benchmarks/onnx_runtime.py on this module's export (K = 2, 100 ms windows): per-window times of both
    backends with their frames compared, and the streams-per-process section for all three executors."""
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    shutil.copytree(exported, tmp_path / "exports" / f"default_k{STEPS}_f{FRAMES}")
    out = tmp_path / "onnx_runtime.json"
    proc = subprocess.run([sys.executable, str(repo / "benchmarks" / "onnx_runtime.py"), "--steps", str(STEPS),
                           "--audio-s", "1.5", "--rounds", "2", "--streams", str(STEPS), "--streams-s", "1.5",
                           "--streams-max", "2", "--exports", str(tmp_path / "exports"), "--out", str(out)],
                          cwd=repo, env={**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"},
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(out.read_text())
    (row,) = r["results"]
    assert row["steps"] == STEPS and row["max_abs_diff"] < 1e-4 and row["ratio_p50"] > 0
    assert row["torch"]["windows"] == row["onnxruntime"]["windows"] > 0
    (s,) = r["streams"]
    for name, backend in (("torch_batched", "torch"), ("torch_unbatched", "torch"), ("onnxruntime", "onnxruntime")):
        m = s[name]
        assert m["backend"] == backend and 0 <= m["max_realtime_streams"] <= 2 and m["trials"]
        assert all(t["frames"] > 0 and t["backend"] == backend for t in m["trials"])
        assert s["max_realtime_streams"][name] == m["max_realtime_streams"]
    assert out.with_suffix(".png").is_file()
