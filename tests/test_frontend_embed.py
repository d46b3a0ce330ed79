"""The embedding front end (`frontend=embedding`, issue "real voices"): the speech front end plus Google's speech
embedding from openWakeWord's wheel. It streams exactly, is causal, hears a quiet and a telephone microphone
nearly as a loud wideband one, and its streams save, resume and batch like any other."""
import copy
import dataclasses

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime", reason="the embedding runs on ONNX Runtime (pip install 'dimgestor[embedding]')")

from dimgestor.audio import SAMPLE_RATE, load_wav  # noqa: E402
from dimgestor.config import get_preset  # noqa: E402
from dimgestor.frontend.base import build_frontend  # noqa: E402
from dimgestor.frontend.embed import EMBED_DIM, EMBED_FRAMES, EMBED_STEP, EmbeddingFrontEnd  # noqa: E402
from dimgestor.streaming import savestate  # noqa: E402
from dimgestor.streaming.stream import GestureStream, generate_offline  # noqa: E402
from dimgestor.training.augment import active_level, band_limit  # noqa: E402
from helpers.stream import noise_audio, random_tiny_model  # noqa: E402

try:
    from dimgestor.frontend.embed import model_files
    model_files()
except (ImportError, OSError, ValueError) as e:  # (`make test` installs it: pip install --no-deps openwakeword==0.5.1)
    pytest.skip(f"the embedding's ONNX files are not here: {e}", allow_module_level=True)

DEMO = load_wav(__import__("pathlib").Path(__file__).resolve().parents[1] / "dimgestor" / "assets" / "demo_en.wav")


@pytest.fixture(scope="module")
def fe() -> EmbeddingFrontEnd:
    return build_frontend(get_preset("realtime").model_copy(update={"frontend": "embedding"}))


def _run(fe, audio, chunks=None):
    state, out = fe.init_state(1), []
    with torch.no_grad():
        if chunks is None:
            return fe(torch.from_numpy(np.ascontiguousarray(audio, np.float32))[None], state)[0][0]
        at = 0
        for n in chunks:
            f, state = fe(torch.from_numpy(np.ascontiguousarray(audio[at:at + n], np.float32))[None], state)
            out.append(f[0])
            at += n
    return torch.cat(out)


@pytest.mark.parametrize("seed", [0, 1])
def test_streamed_equals_whole_for_awkward_chunks(fe, seed):
    audio = DEMO[: 6 * SAMPLE_RATE]
    rng = np.random.default_rng(seed)
    sizes = [1, 159, 161, 1279, 1281, 0, 12511] + list(rng.integers(1, 4000, size=200))
    sizes = sizes[: np.searchsorted(np.cumsum(sizes), len(audio))] + [len(audio)]
    whole, parts = _run(fe, audio), _run(fe, audio, sizes)
    assert parts.shape == whole.shape == (len(audio) // 160, fe.speech.dim + EMBED_DIM)
    s = fe.speech.dim
    assert torch.equal(parts[:, s:], whole[:, s:])  # the embedding: bit for bit
    assert torch.allclose(parts[:, :s], whole[:, :s], atol=1e-5)  # the speech front end's own tolerance


def test_the_embedding_is_causal_and_held_for_80_ms(fe):
    audio = DEMO[: 4 * SAMPLE_RATE]
    f = _run(fe, audio)[:, fe.speech.dim:]
    changed = np.flatnonzero((f[1:] != f[:-1]).any(-1).numpy()) + 1
    assert set(changed) <= set(range(EMBED_STEP - 1, len(f), EMBED_STEP)) and len(changed) > len(f) // EMBED_STEP // 2
    # changing the audio after frame i's end leaves frames <= i alone
    i = 200
    later = audio.copy()
    later[(i + 1) * 160:] = np.random.default_rng(0).normal(0, 0.3, len(later) - (i + 1) * 160)
    g = _run(fe, later)[:, fe.speech.dim:]
    assert torch.equal(f[: i + 1], g[: i + 1]) and not torch.equal(f[i + EMBED_STEP:], g[i + EMBED_STEP:])
    assert EMBED_FRAMES == 76  # 775 ms of look-back per embedding


def _level(x, dbfs):
    """x at an active speech level of `dbfs` (`active_level` is a mean power)."""
    return (x * 10 ** ((dbfs - 10 * np.log10(active_level(x, SAMPLE_RATE))) / 20)).astype(np.float32)


def _nmse(a, b):
    return float(((a - b) ** 2).mean() / b.var(0).mean())


def test_a_quiet_or_a_telephone_microphone_reads_nearly_the_same(fe):
    """The same speech at -35 and -10 dBFS, and through a 300-3400 Hz telephone band: the embedding moves by
    under 5 % and 15 % of its variance (measured 1 % and 4 % on the ZEGGS clip, `benchmarks/speaker_shift.py`)."""
    s = fe.speech.dim
    loud = _level(DEMO, -10.0)
    ref = _run(fe, loud)[:, s:].double().numpy()
    quiet = _run(fe, _level(DEMO, -35.0))[:, s:].double().numpy()
    phone = _run(fe, band_limit(loud, 300.0, 3400.0, SAMPLE_RATE))[:, s:].double().numpy()
    assert _nmse(quiet, ref) < 0.05, _nmse(quiet, ref)
    assert _nmse(phone, ref) < 0.15, _nmse(phone, ref)


@pytest.fixture(scope="module")
def model():
    return random_tiny_model(frontend="embedding")


def test_a_stream_resumes_exactly_from_its_saved_state(model):
    audio = noise_audio(2.4)
    whole = GestureStream(model, steps=4, seed=7)
    before = whole.push(audio[:13001])
    data = savestate.dumps(whole)
    after = np.concatenate([whole.push(audio[13001:30000]), whole.push(audio[30000:]), whole.finish()])
    resumed = GestureStream(copy.deepcopy(model), steps=4, seed=7)
    state, _ = savestate.loads(resumed, data)
    resumed.state = state
    again = np.concatenate([resumed.push(audio[13001:30000]), resumed.push(audio[30000:]), resumed.finish()])
    assert len(again) == len(after) > 10 and np.array_equal(again, after)
    offline = generate_offline(model, audio, steps=4, seed=7)
    assert np.abs(np.concatenate([before, again]) - offline).max() < 1e-4


def test_a_saved_state_whose_two_front_ends_disagree_is_refused(model):
    s = GestureStream(model, steps=4, seed=1)
    s.push(noise_audio(1.0)[:5000])
    fe = s.state.frontend
    bad = dataclasses.replace(s.state, frontend=fe._replace(speech=fe.speech._replace(consumed=fe.speech.consumed + 1)))
    savestate.loads(GestureStream(model, steps=4, seed=1), savestate.dumps(s))  # the true one resumes
    with pytest.raises(savestate.StateError, match="state.frontend.speech"):
        savestate.loads(GestureStream(model, steps=4, seed=1), savestate.dumps(s, state=bad))


def test_streams_batched_together_hear_what_they_hear_alone(model):
    from dimgestor.model.conditioning import condition, condition_group

    a, b = noise_audio(1.0, seed=1), noise_audio(1.0, seed=2)
    fes = [model.frontend.init_state(1) for _ in range(2)]
    exs = [model.extractor.init_state(1) for _ in range(2)]
    both = condition_group(model, fes, exs, [a, b])
    for got, audio in zip(both, (a, b)):
        alone = condition(model, model.frontend.init_state(1), model.extractor.init_state(1), audio)
        assert torch.allclose(got.cond, alone.cond, atol=1e-5)
        assert torch.equal(got.frontend.emb, alone.frontend.emb) and got.frontend.consumed == alone.frontend.consumed


def test_onnx_export_says_it_cannot_take_it(model):
    from dimgestor.export.onnx_export import state_specs

    with pytest.raises(ValueError, match="not 'embedding'"):
        state_specs(model, steps=4, rows=1)


def test_without_openwakeword_the_error_says_what_to_install(monkeypatch):
    import sys

    from dimgestor.frontend import embed as frontend_embed

    monkeypatch.setitem(sys.modules, "openwakeword", None)  # `import openwakeword` now fails
    with pytest.raises(ImportError, match=r"pip install --no-deps openwakeword==0.5.1"):
        frontend_embed.model_files()


def test_a_file_that_is_not_the_one_shipped_is_refused(monkeypatch, tmp_path):
    import sys

    from dimgestor.frontend import embed as frontend_embed

    mel, emb = frontend_embed.model_files()
    models = tmp_path / "openwakeword" / "resources" / "models"
    models.mkdir(parents=True)
    (models / mel.name).write_bytes(mel.read_bytes())
    (models / emb.name).write_bytes(emb.read_bytes()[:-1])  # cut short by one byte
    (tmp_path / "openwakeword" / "__init__.py").write_text("raise ImportError('never imported')\n")
    monkeypatch.delitem(sys.modules, "openwakeword", raising=False)
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ValueError, match=r"embedding_model.onnx is not the file openwakeword 0.5.1 ships"):
        frontend_embed.model_files()
