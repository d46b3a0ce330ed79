"""`dimgestor serve --device`: where the model runs (cpu, cuda, cuda:N), checked before anything loads, refused in
one line where there is no such GPU, and handed to what loads the model (torch) or runs the export (ONNX Runtime's
providers). On a machine with a GPU, `benchmarks/` measures serving on it; these run anywhere."""

import asyncio
import sys

import pytest
import torch

from dimgestor.export.onnx_stream import providers
from helpers import warm
from helpers.serve import REPO
from streamer.options import ServeError, ServeOptions
from streamer.server import serve


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")
@pytest.mark.parametrize("args, message", [
    (["--device", "cuda"], "--device cuda: no NVIDIA GPU here (torch "),
    (["--device", "cuda:1", "--backend", "onnxruntime"], "--device cuda:1: no NVIDIA GPU here"),
    (["--device", "2"], "--device '2': the device the model runs on (cpu, cuda or cuda:N); a microphone is "
                        "--input-device (--input-device 2)"),
])
def test_a_gpu_that_is_not_there_is_one_line_and_exit_2(args, message):
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "serve", "--no-ws", *args],
                 cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.startswith("dimgestor: ") and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


class Loaded(Exception):
    pass


@pytest.fixture
def two_gpus(monkeypatch):
    """torch says two CUDA GPUs are here; the model's load records the device it is asked for, then stops."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    asked = []

    def load(checkpoint=None, device="cpu"):
        asked.append(str(device))
        raise Loaded(device)

    import dimgestor.streaming.checkpoint as checkpoint

    monkeypatch.setattr(checkpoint, "load_checkpoint", load)
    return asked


def test_the_device_reaches_the_model_and_a_gpu_past_the_last_is_refused(two_gpus):
    for device in ("cuda", "cuda:1", "cpu"):
        with pytest.raises(Loaded):
            asyncio.run(serve(ServeOptions(compute_device=device, no_ws=True, source="demo")))
    assert two_gpus == ["cuda", "cuda:1", "cpu"]
    with pytest.raises(ServeError, match=r"^--device cuda:2: this machine has 2 GPUs \(cuda:0\.\.cuda:1\)$"):
        asyncio.run(serve(ServeOptions(compute_device="cuda:2", no_ws=True, source="demo")))
    assert len(two_gpus) == 3  # refused before the model loads


def test_onnxruntime_on_a_gpu_needs_its_cuda_provider_and_loads_the_model_on_the_cpu(two_gpus, monkeypatch):
    """The export runs on ONNX Runtime's CUDA provider (the onnxruntime-gpu package): without it, one line; with
    it, the checkpoint loads on the CPU (the export is made and read there) and the sessions get the GPU."""
    ort = pytest.importorskip("onnxruntime")
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    with pytest.raises(ServeError, match="no CUDA provider .*install onnxruntime-gpu"):
        asyncio.run(serve(ServeOptions(compute_device="cuda:1", backend="onnxruntime", no_ws=True)))
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    with pytest.raises(Loaded):
        asyncio.run(serve(ServeOptions(compute_device="cuda:1", backend="onnxruntime", no_ws=True)))
    assert two_gpus == ["cpu"]
    assert providers("cuda:1") == [("CUDAExecutionProvider", {"device_id": 1}), "CPUExecutionProvider"]
    assert providers("cuda") == [("CUDAExecutionProvider", {"device_id": 0}), "CPUExecutionProvider"]
    assert providers() == ["CPUExecutionProvider"]
