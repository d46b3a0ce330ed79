"""The torch stream on a GPU: the same frames as on the CPU, streamed and batched. Skips where torch sees no
CUDA device (CI and the developers' machines have none; run it where one is)."""
import numpy as np
import pytest
import torch

from dimgestor.streaming.batch import push_many
from dimgestor.streaming.checkpoint import load_checkpoint

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: torch.cuda.is_available() is False")

WINDOW = 1600  # 100 ms


@pytest.fixture(scope="module", autouse=True)
def full_precision():
    """TF32 off (cuDNN's convolutions use it by default): what is compared is the algebra, not TF32's rounding."""
    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


def speech(seconds: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * 16000)) / 16000
    voiced = np.sin(2 * np.pi * (130 + 20 * np.sin(2 * np.pi * 0.7 * t)) * t) * (0.5 + 0.5 * np.sin(2 * np.pi * 3.5 * t))
    return (0.3 * voiced + 0.01 * rng.standard_normal(t.size)).astype(np.float32)


def test_cuda_stream_gives_the_cpu_streams_frames():
    audio = speech(3.0, 0)
    frames = {}
    for device in ("cpu", "cuda"):
        bundle = load_checkpoint(None, device=device)
        stream = bundle.stream(steps=4, seed=3)
        frames[device] = np.concatenate([stream.push(audio[a:a + 1234]) for a in range(0, len(audio), 1234)]
                                        + [stream.finish()])
    assert frames["cuda"].shape == frames["cpu"].shape == (60, frames["cpu"].shape[1])
    np.testing.assert_allclose(frames["cuda"], frames["cpu"], atol=1e-3)


def test_cuda_batched_streams_give_their_own_frames():
    bundle = load_checkpoint(None, device="cuda")
    audios = [speech(2.0, s) for s in range(3)]
    alone = []
    for i, a in enumerate(audios):
        s = bundle.stream(steps=4, seed=i)
        alone.append(np.concatenate([s.push(a[k:k + WINDOW]) for k in range(0, len(a), WINDOW)]))
    streams = [bundle.stream(steps=4, seed=i) for i in range(3)]
    together = [[] for _ in audios]
    for k in range(0, len(audios[0]), WINDOW):
        for i, out in enumerate(push_many(streams, [a[k:k + WINDOW] for a in audios])):
            together[i].append(out)
    for want, got in zip(alone, together):
        np.testing.assert_allclose(np.concatenate(got), want, atol=1e-4)
