"""The AdaLN-Transformer baseline: same condition path as DiM-Gestor, attention over the whole sequence."""

import numpy as np
import pytest
import torch

from dimgestor.config import get_preset
from dimgestor.model.baselines import AdaLNAttentionBlock, AdaLNTransformer, SelfAttention, denoiser_params, rotary
from dimgestor.model.network import DiMGestor, FuzzyFeatureExtractor
from dimgestor.streaming.stream import generate_offline


def _randomize(model: torch.nn.Module, seed: int = 0) -> None:
    """Give zero-initialised (adaLN-Zero) weights random values so the blocks do something."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g))


def test_same_condition_path_and_width_only_blocks_differ():
    cfg = get_preset("tiny")
    mamba, transformer = DiMGestor(cfg), AdaLNTransformer(cfg, n_blocks=3)
    assert isinstance(transformer.extractor, FuzzyFeatureExtractor)
    assert len(transformer.blocks) == 3 and all(isinstance(b, AdaLNAttentionBlock) for b in transformer.blocks)
    counts_m, counts_t = mamba.param_counts(), transformer.param_counts()
    for part in ("frontend", "style_extractor", "downsampler", "step_embedder", "encoder_decoder"):
        assert counts_m[part] == counts_t[part], part
    assert denoiser_params(transformer) == sum(counts_t[k] for k in ("step_embedder", "denoiser_blocks", "encoder_decoder"))


def test_blocks_are_the_identity_at_init_adaln_zero():
    cfg = get_preset("tiny")
    block = AdaLNTransformer(cfg, n_blocks=1).blocks[0]
    x, c = torch.randn(2, 9, cfg.hidden), torch.randn(2, 9, cfg.hidden)
    y, state = block(x, c)
    torch.testing.assert_close(y, x)
    assert state is None


def test_attention_sees_the_whole_sequence():
    # Unlike the causal Mamba-2 denoiser, a change in the last frame moves the first frame's output.
    cfg = get_preset("tiny")
    model = AdaLNTransformer(cfg, n_blocks=2).eval()
    _randomize(model)
    x, cond = torch.randn(1, 12, cfg.motion_dim), torch.randn(1, 12, cfg.hidden)
    x2 = x.clone()
    x2[:, -1] += 1.0
    with torch.no_grad():
        y1, _ = model(x, 500, cond)
        y2, _ = model(x2, 500, cond)
    assert (y1[:, 0] - y2[:, 0]).abs().max() > 1e-5


def test_sdpa_and_naive_attention_agree():
    torch.manual_seed(0)
    sdpa = SelfAttention(64, 4, "sdpa")
    naive = SelfAttention(64, 4, "naive")
    naive.load_state_dict(sdpa.state_dict())
    x = torch.randn(2, 37, 64)
    torch.testing.assert_close(sdpa(x), naive(x), atol=1e-5, rtol=1e-5)


def test_rotary_scores_depend_only_on_relative_position():
    torch.manual_seed(1)
    q, k = torch.randn(1, 1, 1, 16), torch.randn(1, 1, 1, 16)
    seq_q, seq_k = q.expand(1, 1, 20, 16), k.expand(1, 1, 20, 16)
    scores = rotary(seq_q) @ rotary(seq_k).transpose(-2, -1)  # (1, 1, 20, 20)
    torch.testing.assert_close(scores[0, 0, 3, 1], scores[0, 0, 15, 13])
    torch.testing.assert_close(scores[0, 0, 0, 0], (q @ k.transpose(-2, -1))[0, 0, 0, 0])


def test_generate_offline_samples_from_the_baseline():
    cfg = get_preset("tiny")
    model = AdaLNTransformer(cfg, n_blocks=2).eval()
    _randomize(model)
    audio = np.random.default_rng(0).normal(scale=0.1, size=16000).astype(np.float32)
    frames = generate_offline(model, audio, steps=2)
    assert frames.shape == (cfg.fps, cfg.motion_dim) and np.isfinite(frames).all()


def test_refuses_to_continue_from_a_state():
    cfg = get_preset("tiny")
    model = AdaLNTransformer(cfg, n_blocks=1)
    with pytest.raises(ValueError, match="whole sequence"):
        model(torch.zeros(1, 3, cfg.motion_dim), 0, torch.zeros(1, 3, cfg.hidden), state=object())


# ---------------------------------------------------------------- the benchmarks that use the baseline

import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from helpers import warm

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def test_seam_ratio_sees_a_jump_at_window_boundaries():
    sys.path.insert(0, str(BENCH))
    from seams import seam_ratio

    t = np.arange(200) / 20.0
    smooth = np.stack([np.sin(2 * t), np.cos(3 * t)], axis=1)
    boundaries = list(range(10, 200, 10))
    assert seam_ratio(smooth, boundaries, 20.0)["ratio"] == pytest.approx(1.0, abs=0.1)
    jumpy = smooth.copy()
    for b in boundaries:  # every window shifted a little: a seam at each boundary
        jumpy[b:] += 0.05
    assert seam_ratio(jumpy, boundaries, 20.0)["ratio"] > 5


@pytest.mark.slow
def test_paper_table_runs_and_writes_the_issue_schema(tmp_path):
    out = tmp_path / "pt.json"
    cmd = [sys.executable, str(BENCH / "paper_table.py"), "--preset", "tiny", "--hidden", "0", "--lengths", "2",
           "--repeats", "1", "--out", str(out)]
    proc = warm.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(out.read_text())
    assert result["lengths_s"] == [2.0] and isinstance(result["device"], str)
    assert set(result["models"]) == {"mamba2_6", "transformer_6", "transformer_12"}
    for m in result["models"].values():
        assert m["params"] > 0 and len(m["time_s"]) == 1 and len(m["peak_mem_mb"]) == 1
        assert all(x > 0 for x in m["time_s"])
        assert 0 < m["weights_mb"][0] < m["tensor_mem_mb"][0] and m["work_mem_mb"][0] > 0
    assert result["models"]["transformer_12"]["params"] > result["models"]["transformer_6"]["params"]
    ratios = result["ratios"]["mamba2_6 / transformer_12"]
    assert all(len(ratios[k]) == 1 and ratios[k][0] > 0 for k in ("time_s", "tensor_mem_mb", "work_mem_mb", "peak_mem_mb"))
    assert out.with_suffix(".png").is_file()
    assert "mamba2_6 / transformer_12 at 2 s" in proc.stdout


@pytest.mark.slow
def test_streaming_benchmark_runs_and_writes_the_issue_schema(tmp_path):
    out = tmp_path / "st.json"
    cmd = [sys.executable, str(BENCH / "streaming.py"), "--sections", "sweep", "hour", "streams", "--presets", "tiny",
           "--steps", "1", "--windows-ms", "500", "--audio-s", "1", "--hour-preset", "tiny", "--hour-steps", "1",
           "--hour-s", "20", "--streams-preset", "tiny", "--streams-steps", "1", "--streams-window-ms", "500",
           "--streams-s", "1", "--streams-max", "1", "--streams-aligned", "--out", str(out)]
    proc = warm.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(out.read_text())
    keys = {"preset", "steps", "window_ms", "lookahead_ms", "rtf", "latency_ms_p50", "latency_ms_p95",
            "e2e_latency_ms", "rss_mb_start", "rss_mb_after_1h"}
    (row,) = result["results"]
    assert keys <= set(row) and row["preset"] == "tiny" and row["rtf"] > 0
    assert row["e2e_latency_ms"] >= row["lookahead_ms"]  # a frame cannot be ready before its audio exists
    assert result["hour_run"]["audio_s"] == 20 and len(result["hour_run"]["rss_trace_mb"]) == 0
    assert result["max_realtime_streams"]["tiny"] in (0, 1) and result["streams"]["by_k"]["1"]["batched"]["trials"]
    assert out.with_suffix(".png").is_file()


def test_the_transformer_baseline_refuses_to_stream():
    # it carries no state, so a stream would silently restart every window
    from dimgestor.streaming.stream import GestureStream
    with pytest.raises(ValueError, match="cannot stream"):
        GestureStream(AdaLNTransformer(get_preset("tiny"), n_blocks=1))
