"""`dimgestor export-onnx` and its ONNX Runtime stream: the graph loads, the manifest is the graph's, the state
shapes are the torch stream's, and ORT frames equal torch frames streamed in odd chunks with the state carried."""
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime", reason="the `onnx` extra is not installed")
pytest.importorskip("onnxscript", reason="the `onnx` extra is not installed")

from dimgestor.audio import SAMPLE_RATE  # noqa: E402
from dimgestor.export.onnx_export import FrameStep  # noqa: E402
from dimgestor.export.onnx_stream import FrameStepStream, load_manifest, ort_runner, ort_stream, torch_runner  # noqa: E402
from dimgestor.streaming.checkpoint import load_checkpoint  # noqa: E402
from dimgestor.training.synthetic import synthetic_speech  # noqa: E402
from dimgestor_app.cli import main, model_info  # noqa: E402

from helpers import warm

STEPS, FRAMES, SEED, BATCH = 2, 2, 7, 3  # small graphs: exporting each takes ~15 s


@pytest.fixture(scope="module")
def bundle():
    return load_checkpoint(None)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The embedded default model exported through the command line, with a graph of BATCH streams a call and a
    Triton model repository."""
    out = tmp_path_factory.mktemp("onnx")
    assert main(["export-onnx", "--out", str(out), "--steps", str(STEPS), "--frames", str(FRAMES),
                 "--batch", str(BATCH), "--triton", "2"]) == 0
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
    face = json.loads((exported / "face_manifest.json").read_text())  # the face's listener beside it
    assert (exported / face["graph"]).is_file() and face["frames_per_call"] == FRAMES and face["fps"] == 20


def test_onnx_runtime_fuses_each_blocks_gelu_and_rmsnorm_and_reads_each_state_once(exported, bundle, tmp_path):
    """The graph is written in the forms ONNX Runtime fuses (a tanh GELU and an RMSNorm a block and step become
    one node each), each stacked denoiser state is read by one node that cuts it (the warm-up holds a stream's
    state inside the steps, with no pass over the whole state), and the front end's transforms are matrix
    products (ONNX Runtime's DFT cost more than the rest of the front end)."""
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
    assert ops["DFT"] == 0
    written = onnx.load(str(exported / m["graph"])).graph.node
    for name in ("denoiser_enc", "denoiser_conv", "denoiser_ssm"):
        assert [n.op_type for n in written if name in n.input] == ["Reshape"]


def test_triton_repository_keeps_every_state_as_implicit_state(exported, audio):
    """The Triton repository's config.pbtxt parses as Triton's own ModelConfig and declares exactly the graph's
    inputs and outputs (samples, seed, frame -> frames; every state pair as the sequence batcher's implicit state,
    with its start value), and a client that sends only samples, seed and frame, its states carried the way the
    config says, gets the frames of the Python ONNX Runtime stream."""
    mc = pytest.importorskip("tritonclient.grpc.model_config_pb2", reason="the test extra's tritonclient is absent")
    from google.protobuf import text_format

    model = exported / "triton" / "dimgestor"
    config = text_format.Parse((model / "config.pbtxt").read_text(), mc.ModelConfig())
    assert config.backend == "onnxruntime" and config.max_batch_size == 0
    assert [(g.count, g.kind) for g in config.instance_group] == [(2, mc.ModelInstanceGroup.KIND_CPU)]
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    session = ort.InferenceSession(str(model / "1" / "model.onnx"), opts, providers=["CPUExecutionProvider"])
    onnx_type = {mc.TYPE_FP32: "tensor(float)", mc.TYPE_FP64: "tensor(double)", mc.TYPE_INT64: "tensor(int64)"}
    numpy_type = {mc.TYPE_FP32: np.float32, mc.TYPE_FP64: np.float64, mc.TYPE_INT64: np.int64}
    states = config.sequence_batching.state
    declared_in = [(t.name, list(t.dims), onnx_type[t.data_type]) for t in config.input]
    declared_out = [(t.name, list(t.dims), onnx_type[t.data_type]) for t in config.output]
    assert [n for n, *_ in declared_in] == ["samples", "seed", "frame"] and [n for n, *_ in declared_out] == ["frames"]
    assert sorted(declared_in + [(s.input_name, list(s.dims), onnx_type[s.data_type]) for s in states]) == sorted(
        (v.name, v.shape, v.type) for v in session.get_inputs())
    assert sorted(declared_out + [(s.output_name, list(s.dims), onnx_type[s.data_type]) for s in states]) == sorted(
        (v.name, v.shape, v.type) for v in session.get_outputs())

    carried = {}  # what Triton holds for a new sequence: each state's initial_state
    for s in states:
        assert len(s.initial_state) == 1  # (a repeated field in Triton's schema)
        init = s.initial_state[0]
        assert list(init.dims) == list(s.dims) and init.data_type == s.data_type
        dtype = numpy_type[init.data_type]
        carried[s.input_name] = (np.zeros(list(init.dims), dtype) if init.zero_data else np.fromfile(
            model / "initial_state" / init.data_file, dtype).reshape(list(init.dims)))
    assert np.isnan(carried["frontend_floor"]).all()  # the one start value that is not zeros
    m = load_manifest(exported)
    call, warmup = m["call"]["samples_per_call"], m["call"]["warmup_calls"]
    calls = len(audio) // call
    got = []
    for j in range(calls):  # a Triton client's requests: samples, seed, frame; states stay in the server
        result = dict(zip([o.name for o in session.get_outputs()], session.run(None, {
            "samples": audio[None, j * call:(j + 1) * call], "seed": np.array([SEED], np.int64),
            "frame": np.array([(j - warmup) * FRAMES], np.int64), **carried})))
        carried = {s.input_name: result[s.output_name] for s in states}
        if j >= warmup:
            got.append(result["frames"])
    want = ort_stream(exported, seed=SEED, smoothing=None).push(audio[:calls * call])
    assert len(want) == (calls - warmup) * FRAMES
    np.testing.assert_array_equal(np.concatenate(got), want)


def test_triton_without_an_instance_is_refused_before_exporting(tmp_path):
    """`--triton 0` is a clear error at once, not after minutes of exporting, and writes nothing."""
    with pytest.raises(SystemExit, match="--triton needs at least 1 instance, got 0"):
        main(["export-onnx", "--out", str(tmp_path / "out"), "--steps", str(STEPS), "--triton", "0"])
    assert not (tmp_path / "out").exists()


def test_state_shapes_are_the_torch_streams(exported, bundle):
    m = load_manifest(exported)
    shapes = {s["input"]: tuple(s["shape"]) for s in m["state"]}
    torch_state = bundle.stream(steps=STEPS).state  # (the default model's guidance is folded in: one denoiser row)
    rows = 1 if bundle.config.guidance == 1 else 2  # (a guided model's export: tests/test_onnx_cache.py)
    assert m["sampler"]["guidance"] == bundle.config.guidance and m["sampler"]["rows"] == rows
    assert [shapes[f"denoiser_{k}"] for k in ("enc", "conv", "ssm")] == [tuple(t.shape) for t in torch_state.denoiser]
    assert shapes["extractor_style_ssm"] == tuple(torch_state.extractor.style.ssm.shape)
    info = model_info(bundle.config, STEPS)["stream_state_bytes"]
    per_row_step = sum(4 * np.prod(shapes[f"denoiser_{k}"]) // (STEPS * rows) for k in ("enc", "conv", "ssm"))
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
    fresh = []
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

    from dimgestor.export.onnx_stream import OnnxModel

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
        r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "serve", "--source", str(wav), "--fast", "--no-ws",
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
    backends with their frames compared, the streams-per-process section for all four executors (ONNX Runtime
    batched among them), each searched twice (the count their median), and the per-call table of 1 and BATCH
    streams a call."""
    import os
    import shutil
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    shutil.copytree(exported, tmp_path / "exports" / f"default_k{STEPS}_f{FRAMES}")
    out = tmp_path / "onnx_runtime.json"
    proc = warm.run([sys.executable, str(repo / "benchmarks" / "onnx_runtime.py"), "--steps", str(STEPS),
                     "--audio-s", "1.5", "--rounds", "2", "--streams", str(STEPS), "--streams-s", "1.5",
                     "--streams-max", "2", "--streams-repeats", "2", "--batches", str(BATCH), "--call-batches", "1", str(BATCH),
                     "--call-reps", "2", "--exports", str(tmp_path / "exports"), "--out", str(out)],
                    cwd=repo, env={**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"},
                    capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(out.read_text())
    (row,) = r["results"]
    assert row["steps"] == STEPS and row["max_abs_diff"] < 1e-4 and row["ratio_p50"] > 0
    assert row["torch"]["windows"] == row["onnxruntime"]["windows"] > 0
    (s,) = r["streams"]
    for name, backend in (("torch_batched", "torch"), ("torch_unbatched", "torch"), ("onnxruntime", "onnxruntime"),
                          ("onnxruntime_batched", "onnxruntime")):
        m = s[name]
        assert m["backend"] == backend and 0 <= m["max_realtime_streams"] <= 2 and m["trials"]
        assert all(t["frames"] > 0 and t["backend"] == backend for t in m["trials"])
        assert s["max_realtime_streams"][name] == m["max_realtime_streams"] == int(np.median(m["searches"]))
        assert len(m["searches"]) == 2
    assert len(s["ratio_by_search"]) == 2
    assert s["graph_batches"] == [1, BATCH] and all(t["executor"] == "BatcherPool" and t["graph_batches"] == [
        1, BATCH] for t in s["onnxruntime_batched"]["trials"])
    (c,) = r["calls"]
    assert [row["batch"] for row in c["rows"]] == [1, BATCH] and c["state_bytes_per_stream"] > 0
    assert all(row["ms_per_call"] > 0 and row["ms_per_stream"] == row["ms_per_call"] / row["batch"] for row in c["rows"])
    assert out.with_suffix(".png").is_file()


def test_gpu_benchmark_runs_end_to_end_on_the_cpu_at_tiny_size(exported, tmp_path):
    """benchmarks/onnx_cuda.py's code path with `--device cpu` (no GPU here): both backends stream 1 and BATCH
    streams in lockstep with every input and output bound once to a fixed buffer, their frames agree, the CUDA
    graph row is recorded as not possible, and one profiled call says where the nodes ran."""
    import os
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    out = tmp_path / "onnx_cuda.json"
    proc = warm.run([sys.executable, str(repo / "benchmarks" / "onnx_cuda.py"), "--exports", str(exported),
                     "--device", "cpu", "--rounds", "3", "--warmup-rounds", "1", "--out", str(out)],
                    cwd=repo, env={**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"},
                    capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(out.read_text())
    assert r["steps"] == STEPS and [row["batch"] for row in r["rows"]] == [1, BATCH]
    for row in r["rows"]:
        for name in ("torch", "onnxruntime"):
            assert row[name]["rounds"] == 3 and row[name]["ms_p50"] > 0
    assert "onnxruntime_graph" in r["errors"]  # CUDA graphs need the CUDA provider
    assert len(r["compare"]) == 2 and all(c["frames"] > 0 and c["max_abs_diff"] < 1e-4 for c in r["compare"])
    placement = r["onnxruntime_nodes_by_provider"]
    assert list(placement) == ["CPUExecutionProvider"] and placement["CPUExecutionProvider"]["nodes"] > 100
    assert out.with_suffix(".png").is_file()


# ---- many streams a call: the batched graph and `streamer serve --backend onnxruntime`'s batches ----------------

def test_batched_graph_is_its_manifest_entry(exported):
    """The graph of B streams: every input and output the single-stream graph's with each state's rows times B on
    its `batch_dim`, the other inputs' first dim B and frames (B, M, D)."""
    m = load_manifest(exported)
    assert m["batched"] == [{"batch": BATCH, "graph": f"frame_step_b{BATCH}.onnx"}]
    session = ort.InferenceSession(str(exported / m["batched"][0]["graph"]), providers=["CPUExecutionProvider"])
    dims = {s["input"]: s["batch_dim"] for s in m["state"]} | {s["output"]: s["batch_dim"] for s in m["state"]}
    for entries, values in ((m["inputs"], session.get_inputs()), (m["outputs"], session.get_outputs())):
        want = []
        for e in entries:
            shape = list(e["shape"])
            if e["name"] == "frames":
                shape = [BATCH, *shape]
            else:
                shape[dims.get(e["name"], 0)] *= BATCH
            want.append((e["name"], shape))
        assert want == [(v.name, v.shape) for v in values]


def test_batched_graph_rows_equal_single_stream_calls(exported):
    """Row b of one call of the B-stream graph is stream b's own call of the single-stream graph: different seeds,
    frame indices and states, one row in its warm-up (frame < 0: it keeps its denoiser state) beside others that
    are not, one at the start state (NaN noise floor). Frames and every state within 1e-5."""
    m = load_manifest(exported)
    single = ort.InferenceSession(str(exported / m["graph"]), providers=["CPUExecutionProvider"])
    batched = ort.InferenceSession(str(exported / f"frame_step_b{BATCH}.onnx"), providers=["CPUExecutionProvider"])
    names = [o.name for o in single.get_outputs()]
    rng = np.random.default_rng(5)
    start = {s["input"]: np.full(s["shape"], float(s["init"]), s["dtype"]) for s in m["state"]}
    states = [start] + [{s["input"]: (0.3 * rng.standard_normal(s["shape"])).astype(s["dtype"]) for s in m["state"]}
                        for _ in range(BATCH - 1)]
    samples = (0.1 * rng.standard_normal((BATCH, 800 * FRAMES))).astype(np.float32)
    seed, frame = np.array([3, 11, 2**40 + 5]), np.array([-FRAMES, 14, 0])
    alone = [dict(zip(names, single.run(names, {"samples": samples[b:b + 1], "seed": seed[b:b + 1],
                                                "frame": frame[b:b + 1], **states[b]}))) for b in range(BATCH)]
    feeds = {"samples": samples, "seed": seed, "frame": frame}
    feeds |= {s["input"]: np.concatenate([st[s["input"]] for st in states], s["batch_dim"]) for s in m["state"]}
    together = dict(zip(names, batched.run(names, feeds)))
    assert together["frames"].shape == (BATCH, FRAMES, alone[0]["frames"].shape[-1])
    for b in range(BATCH):
        assert np.abs(together["frames"][b] - alone[b]["frames"]).max() < 1e-5
        for s in m["state"]:
            k = s["shape"][s["batch_dim"]]
            row = np.take(together[s["output"]], range(b * k, (b + 1) * k), axis=s["batch_dim"])
            assert row.shape == alone[b][s["output"]].shape
            np.testing.assert_allclose(row, alone[b][s["output"]], rtol=0, atol=1e-5, equal_nan=True)
    rows = list(range(m["sampler"]["rows"]))  # row 0 in its warm-up keeps its rows (a guided model's 2 branches)
    kept = np.take(together["denoiser_ssm_out"], rows, axis=2)
    assert np.array_equal(kept, np.take(feeds["denoiser_ssm"], rows, axis=2))


def test_plan_mixes_graph_sizes_at_the_least_cost(exported):
    from dimgestor.export.onnx_batch import BatchRunner

    m = load_manifest(exported)
    runner = BatchRunner(exported, m, cost={1: 1.0, BATCH: 1.2})
    assert [runner.plan(n) for n in (1, 2, 3, 4, 5, 7)] == [[1], [3], [3], [3, 1], [3, 3], [3, 3, 1]]
    dear = BatchRunner(exported, m, cost={1: 1.0, BATCH: 3.5})  # a batch dearer than its calls alone: never used
    assert dear.plan(4) == [1, 1, 1, 1]
    measured = BatchRunner(exported, m)  # measured at load: each graph's seconds per call
    assert set(measured.cost) == {1, BATCH} and all(t > 0 for t in measured.cost.values())


def test_streams_pushed_together_equal_streams_alone(exported, audio):
    """`dimgestor.export.onnx_batch.push_many` (each push's calls of all its streams as batched calls, padded with idle
    rows or mixed with single calls by `plan`) gives each stream the frames it makes alone: different seeds and
    audio, awkward chunks (a window that is no call, several calls at once), streams joining late and missing
    cycles, one pushed alone before it joins, one stream finished mid-way (its exception in its place, the others
    go on)."""
    from dimgestor.export.onnx_batch import BatchRunner, push_many
    from dimgestor.export.onnx_stream import OnnxModel

    model = OnnxModel.load(exported)
    runner = BatchRunner(exported, model.manifest, cost={1: 1.0, BATCH: 1.2})  # pads 2 to 3, 4 as 3 + 1
    n = 5
    clips = [np.roll(audio, 3000 * k)[: len(audio) - 1000 * k] for k in range(n)]
    alone = [streamed(ort_stream(exported, seed=SEED + k), clips[k], [len(clips[k])]) for k in range(n)]
    streams = [model.stream(seed=SEED + k) for k in range(n)]
    got, pos, joins = [[] for _ in range(n)], [0] * n, [0, 0, 2, 5, 1]
    rng = np.random.default_rng(1)
    got[1].append(streams[1].push(clips[1][:4000]))  # its first calls alone: its state ONNX Runtime's own values
    pos[1] = 4000
    cycle = 0
    while any(p < len(c) for p, c in zip(pos, clips)):
        if cycle == 6:  # stream 4 finishes early: a push into it still comes, and fails alone
            heard = streams[4].state.samples_in
            got[4].append(streams[4].finish())
            pos[4] = len(clips[4])
        idx = [k for k in range(n) if cycle >= joins[k] and pos[k] < len(clips[k]) and rng.random() < 0.85]
        chunks = []
        for k in idx:
            size = int(rng.choice([1, 799, 1600, 3200, 2001, 5000]))
            chunks.append(clips[k][pos[k]:pos[k] + size])
            pos[k] += size
        if cycle == 6:
            idx, chunks = idx + [4], chunks + [np.zeros(1600, np.float32)]
        outs = push_many(runner, [streams[k] for k in idx], chunks, return_exceptions=True)
        for k, f in zip(idx, outs):
            if k == 4 and cycle == 6:
                assert isinstance(f, RuntimeError)
            else:
                got[k].append(f)
        cycle += 1
    assert cycle > 6
    for k in range(n):
        if k != 4:
            got[k].append(streams[k].finish())
        frames = np.concatenate(got[k])
        want = alone[k]
        if k == 4:  # the audio it had when it finished, alone
            want = streamed(ort_stream(exported, seed=SEED + 4), clips[4][:heard], [heard])
        assert frames.shape == want.shape and len(frames) > 0
        assert np.abs(frames - want).max() < 1e-5
    st = runner.stats
    assert st.calls.get(BATCH, 0) > 0 and st.calls.get(1, 0) > 0 and st.padded > 0
    assert st.gathers < sum(st.calls.values())  # the same streams together again: the last outputs fed back


def test_serve_on_onnxruntime_batches_clients_and_each_gets_what_it_gets_alone(exported, audio):
    """`streamer serve --backend onnxruntime --source ws`: three clients talking at once (different audio, each sent
    as fast as the socket takes it, so that their windows wait together whatever the machine's speed: paced in
    real time on a quiet machine each window was done before the next client's came, and nothing batched) share
    the batched calls (the status line's batch peaks at 2 or more), and each gets the frames it gets talking
    alone to the same server (root and rotations as sent, to the JSON's rounding)."""
    import asyncio
    import re
    import time

    from helpers.serve import Serve
    from websockets.asyncio.client import connect

    clips = [np.round(np.roll(audio, 4000 * k)[:SAMPLE_RATE * 2] * 32767 * 0.8).astype("<i2") for k in range(3)]

    async def talk(url, clip, delay):
        await asyncio.sleep(delay)
        async with connect(url) as c:
            json.loads(await asyncio.wait_for(c.recv(), 30))
            await c.send(json.dumps({"type": "hello", "protocol": 1,
                                     "audio": {"rate": 16000, "format": "pcm16", "channels": 1}}))
            for i in range(0, len(clip), 1600):
                await c.send(clip[i:i + 1600].tobytes())
            await c.send(json.dumps({"type": "audio_end"}))
            frames = []
            while True:
                m = json.loads(await asyncio.wait_for(c.recv(), 60))
                if m["type"] == "frame":
                    frames.append([*m["root"], *np.ravel(m["rotations"])])
                elif m["type"] == "end":
                    return np.array(frames)

    s = Serve("--backend", "onnxruntime", "--onnx", str(exported), "--steps", str(STEPS), "--source", "ws",
              "--ws", "127.0.0.1:0", "--window-ms", "100", "--status-every", "0.3")
    try:
        url = s.wait_for(r"WebSocket\s+(ws://\S+)", 120).group(1)

        async def together():
            return await asyncio.gather(*(talk(url, clip, 0.01 * k) for k, clip in enumerate(clips)))

        shared = asyncio.run(together())
        status, seen = r"batch [\d.]+ streams \(max (\d+)\)", len(s.lines)
        deadline = time.monotonic() + 10  # a status line (every 0.3 s) printed after those batches
        while not any(re.search(status, line) for line in s.lines[seen:]) and time.monotonic() < deadline:
            time.sleep(0.05)
        peak = max([int(m) for m in re.findall(status, s.output)] or [0])
        alone = [asyncio.run(talk(url, clip, 0)) for clip in clips]
    finally:
        s.proc.terminate()
        s.finish()
    assert peak >= 2, s.output[-2000:]
    for a, b in zip(shared, alone):
        assert a.shape == b.shape == (len(clips[0]) * 20 // SAMPLE_RATE, a.shape[1])
        assert np.abs(a - b).max() <= 2e-5  # rounded to 5 decimals (root) and 6 (rotations) in the JSON


def test_the_window_profile_splits_an_export_by_the_models_parts(exported, audio, tmp_path):
    """benchmarks/window_profile.py's ONNX Runtime arm on an export: the window as serve runs it, and the profiler's
    node times by the part the exporter recorded for each node."""
    import argparse
    import sys

    bench = str(Path(__file__).resolve().parents[1] / "benchmarks")
    sys.path.insert(0, bench)
    try:
        import window_profile
    finally:
        sys.path.remove(bench)
    args = argparse.Namespace(window_ms=100, windows=4, warmup=2, out=tmp_path / "wp.json")
    r = window_profile.onnx_arm(exported, audio, args)
    assert r["steps"] == STEPS and r["window_ms_mean"] > 0 and r["profiled_window_ms_mean"] > r["window_ms_mean"]
    assert {"front end", "style", "sampler (K steps)", "states"} <= set(r["parts_ms"]), r["parts_ms"]
    assert all(v > 0 for v in r["parts_ms"].values()) and r["nodes_run_per_window"]["sampler (K steps)"] > 100
    assert not list(tmp_path.glob("wp_ort*"))  # the profiler's trace is read and removed


def test_a_calibrated_students_export_scales_its_motion_as_torch_does(bundle, audio, tmp_path):
    """A distilled student's calibration (`DiMGestor.calibrate`, buffers in its weights) is in its graph: ONNX
    Runtime's frames equal the torch stream's, which are not the frames without it."""
    import torch

    from dimgestor.model.network import DiMGestor
    from dimgestor.streaming.checkpoint import save_checkpoint

    b = bundle  # (the default model, made a student by its calibration only)
    model = DiMGestor(b.config.model_copy(update={"calibrated": True}))
    model.load_state_dict(b.model.state_dict(), strict=False)
    g = torch.Generator().manual_seed(0)
    model.out_gain.copy_(0.5 + torch.rand(b.config.motion_dim, generator=g))
    model.out_shift.copy_(0.2 * torch.randn(b.config.motion_dim, generator=g))
    folder = save_checkpoint(tmp_path / "student", model, b.feature_spec, b.skeleton, b.mean, b.std)
    assert main(["export-onnx", "--checkpoint", str(folder), "--out", str(tmp_path / "onnx"), "--steps", "1",
                 "--frames", str(FRAMES)]) == 0
    student = load_checkpoint(folder)
    torch_frames = streamed(student.stream(steps=1, seed=SEED), audio, [1601, 333])
    ort_frames = streamed(ort_stream(tmp_path / "onnx", seed=SEED), audio, [777, 2001])
    plain = streamed(b.stream(steps=1, seed=SEED), audio, [4000])
    assert np.abs(ort_frames - torch_frames).max() < 1e-4
    assert np.abs(torch_frames - (plain * model.out_gain.numpy() + model.out_shift.numpy())).max() < 1e-4
