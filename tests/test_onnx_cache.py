"""The per-user cache of ONNX exports (`dimgestor.export.onnx_cache`): a second `serve --backend onnxruntime` reuses the
first one's export and makes the same frames; an entry cut short, altered, missing a file or of another model is
rebuilt, never served; a changed K is another export; concurrent starts export once.

One real export (a tiny model, K = 1, no batched graphs: what the first `serve` makes); the other tests work on
copies of that cache with an exporter that copies the real export's files, counting its calls."""
import json
import os
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime", reason="the `onnx` extra is not installed")
pytest.importorskip("onnxscript", reason="the `onnx` extra is not installed")

from dimgestor.export import onnx_cache, onnx_export  # noqa: E402
from dimgestor.export.onnx_cache import CACHE_FILE, cache_root, cached_export, entry_name, export_key, problem  # noqa: E402
from dimgestor.streaming.checkpoint import load_checkpoint  # noqa: E402
from helpers import warm
from helpers.checkpoint import make_tiny_checkpoint  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
STEPS, SEED = 1, 3
EXPORTING, REUSING = "exporting the model for ONNX Runtime", "using cached ONNX export"


@pytest.fixture(scope="module")
def exportable(tmp_path_factory):
    """A tiny model whose lookahead is whole calls of 2 frames (what the export needs: 100 ms)."""
    return make_tiny_checkpoint(tmp_path_factory.mktemp("ckpt"), lookahead_ms=100, down_kernel=15)


@pytest.fixture(scope="module")
def tiny_bundle(exportable):
    return load_checkpoint(exportable)


def serve(checkpoint, cache: Path, wav, record: Path, *more: str) -> str:
    """`dimgestor serve --backend onnxruntime` on the WAV, recorded; its output (it must succeed)."""
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "serve", "--checkpoint", str(checkpoint),
                  "--backend", "onnxruntime", "--onnx-cache", str(cache), "--no-batch", "--steps", str(STEPS),
                  "--seed", str(SEED), "--source", str(wav), "--fast", "--no-ws", "--record", str(record),
                  *more], cwd=REPO, capture_output=True, text=True, timeout=600,
                 env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stderr


@pytest.fixture(scope="module")
def first(exportable, wav, tmp_path_factory):
    """The first start: an empty cache, the model exported into it; (cache, recording, output)."""
    folder = tmp_path_factory.mktemp("first")
    out = serve(exportable, folder / "cache", wav, folder / "first.bvh")
    return folder / "cache", folder / "first.bvh", out


@pytest.fixture
def entry(first, tiny_bundle, tmp_path):
    """A copy of the first start's cache; the path of its entry (the pristine one stays as it was)."""
    cache = shutil.copytree(first[0], tmp_path / "cache")
    (e,) = [p for p in cache.iterdir() if p.is_dir()]
    return e


@pytest.fixture
def exports(first, monkeypatch):
    """The exporter replaced by a copy of the first start's files (graphs already as ONNX Runtime optimized them);
    the list of (steps, batches) it was asked for."""
    (pristine,) = [p for p in first[0].iterdir() if p.is_dir()]
    calls = []

    def export_bundle(bundle, out, steps, guidance, frames, batches):
        calls.append((steps, list(batches)))
        for p in pristine.iterdir():
            if p.name != CACHE_FILE:
                shutil.copy(p, Path(out) / p.name)
        return Path(out)

    monkeypatch.setattr(onnx_export, "export_bundle", export_bundle)
    monkeypatch.setattr(onnx_cache, "_ort_optimized", lambda graph: None)  # (the copies are optimized already)
    return calls


def key_of(bundle, steps: int = STEPS) -> dict:
    return export_key(bundle, steps, bundle.config.guidance)


def ask(bundle, entry: Path, steps: int = STEPS):
    """cached_export for `bundle` in `entry`'s cache: (the folder it returns, its log lines)."""
    lines = []
    return cached_export(bundle, steps, bundle.config.guidance, root=entry.parent, log=lines.append), lines


def test_first_start_exports_into_the_cache_and_says_so(first, tiny_bundle):
    cache, _, out = first
    (e,) = [p for p in cache.iterdir() if p.is_dir()]
    assert f"{EXPORTING} (first start with this model and settings, ~1 min) into {e}" in out
    assert REUSING not in out
    assert problem(e, export_key(tiny_bundle, STEPS, tiny_bundle.config.guidance)) is None
    assert not [p for p in cache.iterdir() if p.name.startswith(".")]  # no partial export left beside it


def test_a_second_serve_reuses_the_export_and_makes_the_first_ones_frames(first, exportable, wav, tmp_path):
    from dimgestor.bvh import read_bvh

    cache, first_bvh, _ = first
    before = {p: p.stat().st_mtime_ns for p in cache.rglob("*")}
    out = serve(exportable, cache, wav, tmp_path / "second.bvh")
    assert REUSING in out and EXPORTING not in out
    assert {p: p.stat().st_mtime_ns for p in cache.rglob("*") if not p.name.endswith(".lock")} == {
        p: t for p, t in before.items() if not p.name.endswith(".lock")}
    a, b = read_bvh(first_bvh).values, read_bvh(tmp_path / "second.bvh").values
    assert a.shape == b.shape and a.shape[0] > 0 and np.array_equal(a, b)


def test_an_entry_cut_short_is_exported_again_not_served(entry, tiny_bundle, exports):
    graph = entry / "frame_step.onnx"
    whole = graph.read_bytes()
    graph.write_bytes(whole[: len(whole) // 2])
    folder, lines = ask(tiny_bundle, entry)
    assert exports == [(STEPS, [])] and folder == entry
    assert any("is damaged (frame_step.onnx is" in ln for ln in lines) and any(EXPORTING in ln for ln in lines)
    assert graph.read_bytes() == whole and problem(entry, key_of(tiny_bundle)) is None


@pytest.mark.parametrize("damage", ["flip a byte", "delete the manifest", "cache.json cut short"])
def test_an_altered_or_incomplete_entry_is_exported_again(entry, tiny_bundle, exports, damage):
    if damage == "flip a byte":
        data = bytearray((entry / "frame_step.onnx").read_bytes())
        data[len(data) // 2] ^= 1
        (entry / "frame_step.onnx").write_bytes(bytes(data))
    elif damage == "delete the manifest":
        (entry / "manifest.json").unlink()
    else:
        (entry / CACHE_FILE).write_text((entry / CACHE_FILE).read_text()[:40])
    folder, lines = ask(tiny_bundle, entry)
    assert len(exports) == 1 and any("is damaged" in ln for ln in lines)
    assert problem(folder, key_of(tiny_bundle)) is None


def test_another_models_entry_is_never_served(entry, tiny_bundle, exports, tmp_path):
    other = load_checkpoint(make_tiny_checkpoint(tmp_path / "other", seed=5, lookahead_ms=100, down_kernel=15))
    key, other_key = (key_of(b) for b in (tiny_bundle, other))
    assert other_key["model"] != key["model"] and entry_name(other_key) != entry.name  # its own entry
    # this model's entry under the other model's name (files and cache.json moved whole): another model's
    shutil.copytree(entry, entry.with_name(entry_name(other_key)))
    folder, lines = ask(other, entry)
    assert folder.name == entry_name(other_key) and exports == [(STEPS, [])]
    assert any("of another model or other settings" in ln for ln in lines)
    # cache.json's fingerprint swapped for the other model's, the files left
    record = json.loads((entry / CACHE_FILE).read_text())
    (entry / CACHE_FILE).write_text(json.dumps({**record, "key": {**record["key"], "model": other_key["model"]}}))
    assert ask(tiny_bundle, entry)[0] == entry and len(exports) == 2


def test_a_killed_starts_partial_export_is_cleared_by_the_next(entry, tiny_bundle, exports):
    shutil.rmtree(entry)
    partial = entry.with_name(f".partial-{entry.name}-killed")
    partial.mkdir()
    (partial / "frame_step.onnx").write_bytes(b"half")
    assert ask(tiny_bundle, entry)[0] == entry and len(exports) == 1 and not partial.exists()


def test_a_changed_k_is_another_export_and_the_first_stays(entry, tiny_bundle, exports):
    folder, lines = ask(tiny_bundle, entry, steps=2)
    assert exports == [(2, [])] and folder != entry and folder.name.startswith("k2-")
    assert problem(entry, key_of(tiny_bundle)) is None  # the K = 1 entry still whole
    assert ask(tiny_bundle, entry)[1] == [f"{REUSING} {entry}"] and len(exports) == 1


def test_the_key_holds_every_setting_and_version(tiny_bundle):
    key = export_key(tiny_bundle, 4, 1.5, batches=(8, 1, 4))
    assert key["steps"] == 4 and key["guidance"] == 1.5 and key["batches"] == [4, 8] and key["frames"] == 2
    assert set(key["versions"]) >= {"torch", "onnx", "onnxscript", "onnxruntime", "dimgestor"}
    assert all(key["versions"][p] for p in ("torch", "onnx", "onnxscript", "onnxruntime"))
    names = {entry_name(export_key(tiny_bundle, *a, batches=b)) for a, b in
             [((4, 1.5), (4, 8)), ((4, 1.5), ()), ((2, 1.5), (4, 8)), ((4, 2.0), (4, 8))]}
    assert len(names) == 4


def test_the_traced_code_is_in_the_key_and_loading_code_is_not():
    mods = onnx_cache.traced_modules()
    assert {"export.onnx_export", "model.network", "model.sampler", "model.diffusion", "model.mamba2",
            "frontend.base", "frontend.speech", "frontend.mel", "config"} <= set(mods)
    assert not {"streaming.checkpoint", "export.onnx_stream", "streaming.stream", "cli_help", "export.onnx_cache"} & set(mods)


def test_concurrent_starts_export_once(entry, tiny_bundle, exports, monkeypatch):
    shutil.rmtree(entry)
    slow = onnx_export.export_bundle

    def export_bundle(*args):
        time.sleep(0.5)  # the second start arrives while the first exports
        return slow(*args)

    monkeypatch.setattr(onnx_export, "export_bundle", export_bundle)
    results, logs = [], [[], []]
    threads = [threading.Thread(target=lambda i=i: results.append(cached_export(
        tiny_bundle, STEPS, tiny_bundle.config.guidance, root=entry.parent, log=logs[i].append))) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert results == [entry, entry] and len(exports) == 1
    assert sorted(any(EXPORTING in ln for ln in log) for log in logs) == [False, True]
    assert problem(entry, key_of(tiny_bundle)) is None


def test_cache_root_flag_then_environment_then_platform(monkeypatch, tmp_path):
    monkeypatch.delenv("DIMGESTOR_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform != "win32":
        assert cache_root() == tmp_path / "xdg" / "dimgestor" / "onnx"
    monkeypatch.setenv("DIMGESTOR_CACHE", str(tmp_path / "mine"))
    assert cache_root() == tmp_path / "mine" / "onnx"
    assert cache_root(tmp_path / "flag") == tmp_path / "flag"


def test_onnx_cache_needs_the_onnxruntime_backend_without_onnx():
    from streamer.options import ServeError, ServeOptions

    assert ServeOptions.parse(backend="onnxruntime", onnx_cache="c").onnx_cache == "c"
    for bad in ({"onnx_cache": "c"}, {"backend": "onnxruntime", "onnx": "e", "onnx_cache": "c"}):
        with pytest.raises(ServeError, match="--onnx-cache is where --backend onnxruntime keeps"):
            ServeOptions.parse(**bad)


def test_generate_on_onnxruntime_reuses_the_same_cache(entry, exportable, wav, exports, tmp_path, capsys):
    """`dimgestor generate --backend onnxruntime` without --onnx asks the same cache: serve's export is reused."""
    from dimgestor_app.cli import main

    assert main(["generate", "--checkpoint", str(exportable), "--audio", str(wav), "--steps", str(STEPS),
                 "--backend", "onnxruntime", "--onnx-cache", str(entry.parent), "--out",
                 str(tmp_path / "g.bvh")]) == 0
    err = capsys.readouterr().err
    assert f"{REUSING} {entry}" in err and EXPORTING not in err and exports == []


def test_the_start_benchmark_runs_end_to_end_at_tiny_size(first, exportable, tmp_path):
    """benchmarks/onnx_start.py on a copy of the first start's cache: one cached start, one torch start."""
    cache = shutil.copytree(first[0], tmp_path / "cache")
    out = tmp_path / "onnx_start.json"
    r = warm.run([sys.executable, str(REPO / "benchmarks" / "onnx_start.py"), "--checkpoint", str(exportable),
                  "--steps", str(STEPS), "--no-batch", "--warm", "0", "--torch", "1", "--cache", str(cache),
                  "--timeout", "300", "--out", str(out)], cwd=REPO, capture_output=True, text=True,
                 timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"})
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(out.read_text())
    (run,), (base,) = result["runs"], result["torch_runs"]
    assert not run["exported"] and result["first_start_export_s"] is None
    assert 0 < run["cache_line_s"] <= run["ws_address_s"] <= run["first_frame_s"] == result["cached_start_s_median"]
    assert base["backend"] == "torch" and base["first_frame_s"] > 0 and result["code"] and result["machine"]
    assert out.with_suffix(".png").is_file()


def test_the_cached_graphs_make_the_torch_frame_steps_frames(first, tiny_bundle):
    """The entry's graphs (as ONNX Runtime optimized them) against the module they were traced from, in torch."""
    from dimgestor.export.onnx_export import FrameStep
    from dimgestor.export.onnx_stream import FrameStepStream, load_manifest, ort_stream, torch_runner
    from dimgestor.training.synthetic import synthetic_speech

    (e,) = [p for p in first[0].iterdir() if p.is_dir()]
    audio = synthetic_speech(1.5, seed=2).astype(np.float32)
    step = FrameStep(tiny_bundle.model.eval(), STEPS, tiny_bundle.config.guidance).eval()
    reference = FrameStepStream(load_manifest(e), torch_runner(step), seed=SEED)
    stream = ort_stream(e, seed=SEED)
    a = np.concatenate([reference.push(audio), reference.finish()])
    b = np.concatenate([stream.push(audio), stream.finish()])
    assert a.shape == b.shape and len(a) > 0 and np.abs(a - b).max() < 1e-4


def test_serve_says_which_flag_to_use_when_the_cache_cannot_be_written(tmp_path):
    from streamer.options import ServeError, ServeOptions
    from streamer.server import build

    blocker = tmp_path / "a file"
    blocker.write_text("")
    with pytest.raises(ServeError, match="a writable folder: --onnx-cache DIR"):
        build(ServeOptions.parse(backend="onnxruntime", onnx_cache=str(blocker / "cache"), source="ws"))
