"""A Triton model repository for the exported step (`dimgestor export-onnx --triton`): implicit state.

Triton's sequence batcher can keep a sequence's state inside the server: every `<state>` / `<state>_out`
pair of the manifest becomes one `state` entry of `sequence_batching`, started from its `init` (Triton's
`zero_data`, or a file of the fill under `initial_state/`: the speech front end's noise floor starts at NaN).
A client then sends only `samples`, `seed` and `frame` with a sequence id (start flag on its first call),
and reads `frames`:

    frame = (call - warmup_calls) * frames_per_call     (below 0: a warm-up call, its frames are dropped)

The graph of one stream (batch 1) keeps each state's rows on the dim its torch layout has (the denoiser's on
dim 1 or 2, `batch_dim`), while Triton batches implicit states on a leading batch dim, so the model declares
`max_batch_size: 0`: each call runs alone, and concurrent sequences run on the `instance_group`'s instances
(one ONNX Runtime thread each).

    <repo>/<name>/config.pbtxt
    <repo>/<name>/1/model.onnx                the export's frame_step.onnx
    <repo>/<name>/initial_state/<state>       raw start values of the states that do not start at zero
"""
from __future__ import annotations

import shutil
from pathlib import Path

from .onnx_stream import initial_tensor, load_manifest

__all__ = ["triton_config", "write_triton_repository", "TRITON_TYPES"]

TRITON_TYPES = {"float32": "TYPE_FP32", "float64": "TYPE_FP64", "int64": "TYPE_INT64"}
IDLE_S = 60.0  # a sequence silent this long is dropped by Triton (its state freed)


def _dims(shape) -> str:
    return "[ " + ", ".join(str(int(d)) for d in shape) + " ]"


def _tensor(entry: dict) -> str:
    return (f'  {{ name: "{entry["name"]}" data_type: {TRITON_TYPES[entry["dtype"]]} '
            f'dims: {_dims(entry["shape"])} }}')


def _fill(state: dict) -> float:
    return float(state["init"])  # "nan" reads as NaN


def triton_config(manifest: dict, name: str = "dimgestor", instances: int = 1, idle_s: float = IDLE_S) -> str:
    """The model's config.pbtxt (protobuf text of Triton's ModelConfig) for an export's manifest."""
    states = {s["input"] for s in manifest["state"]}
    outs = {s["output"] for s in manifest["state"]}
    inputs = [e for e in manifest["inputs"] if e["name"] not in states]
    outputs = [e for e in manifest["outputs"] if e["name"] not in outs]
    entries = []
    for s in manifest["state"]:
        kind = TRITON_TYPES[s["dtype"]]
        start = "zero_data: true" if _fill(s) == 0.0 else f'data_file: "{s["input"]}"'
        entries.append(
            f'    {{\n      input_name: "{s["input"]}"\n      output_name: "{s["output"]}"\n'
            f'      data_type: {kind}\n      dims: {_dims(s["shape"])}\n'
            f'      initial_state: {{ data_type: {kind} dims: {_dims(s["shape"])} {start} name: "{s["input"]}" }}\n'
            f'    }}')
    call = manifest["call"]
    return "\n".join([
        f"# dimgestor's streaming step: {call['frames_per_call']} motion frames ({call['samples_per_call']} samples at "
        f"{call['sample_rate']} Hz) a call, K = {manifest['sampler']['steps']}, guidance "
        f"{manifest['sampler']['guidance']:g}; the first {call['warmup_calls']} calls of a sequence are warm-up.",
        "# Send samples, seed (the stream's, constant) and frame = (call - warm-up calls) * frames per call.",
        f'name: "{name}"',
        'backend: "onnxruntime"',
        "max_batch_size: 0",
        "input [", ",\n".join(_tensor(e) for e in inputs), "]",
        "output [", ",\n".join(_tensor(e) for e in outputs), "]",
        "sequence_batching {",
        f"  max_sequence_idle_microseconds: {int(idle_s * 1e6)}",
        "  state [", ",\n".join(entries), "  ]",
        "}",
        f"instance_group [ {{ count: {int(instances)} kind: KIND_CPU }} ]",
        'parameters { key: "intra_op_thread_count" value: { string_value: "1" } }',
        'parameters { key: "inter_op_thread_count" value: { string_value: "1" } }',
        "",
    ])


def write_triton_repository(export_dir: str | Path, repo: str | Path, name: str = "dimgestor",
                            instances: int = 1) -> Path:
    """An export folder (frame_step.onnx + manifest.json) -> repo/name/{config.pbtxt, 1/model.onnx,
    initial_state/...}; returns the model's folder."""
    export_dir = Path(export_dir)
    manifest = load_manifest(export_dir)
    model = Path(repo) / name
    (model / "1").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(export_dir / manifest["graph"], model / "1" / "model.onnx")
    for s in manifest["state"]:
        if _fill(s) != 0.0:
            (model / "initial_state").mkdir(exist_ok=True)
            (model / "initial_state" / s["input"]).write_bytes(initial_tensor(s).tobytes())  # raw row-major, as Triton reads it
    (model / "config.pbtxt").write_text(triton_config(manifest, name, instances))
    return model
