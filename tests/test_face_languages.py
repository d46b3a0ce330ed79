"""Speech of many languages with every phone's time (espeak-ng's own phoneme events), each phone mapped onto a
mouth by its articulation (`dimgestor.face.ipa`), and the face scored on it per language
(benchmarks/face_languages.py)."""

import ctypes.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dimgestor.face.ipa import arpabet
from dimgestor.face.visemes import VOWEL_CLASS, canonical_phone

REPO = Path(__file__).resolve().parents[1]
needs_espeak = pytest.mark.skipif(ctypes.util.find_library("espeak-ng") is None,
                                  reason="libespeak-ng is not installed (Debian: apt-get install espeak-ng)")


@pytest.mark.parametrize("ipa, language, phone", [
    ("", "en-us", "SIL"), ("aɪ", "en-us", "AA"), ("eɪ", "en-us", "EY"), ("əʊ", "en-gb", "OW"), ("ɚ", "en-us", "ER"),
    ("iː", "de", "IY"), ("ɔ̃", "fr-fr", "AO"), ("y", "fr-fr", "UW"), ("øː", "de", "OW"), ("e", "de", "EY"),
    ("e", "es", "EH"), ("e̞", "ja", "EH"), ("ɯᵝ", "ja", "UW"), ("ä", "ja", "AA"), ("ɛː", "sv", "EH"),
    ("tʃ", "en-us", "CH"), ("dʒ", "it", "JH"), ("ts", "de", "S"), ("tɕ", "ja", "CH"), ("ç", "de", "SH"),
    ("m", "yue", "M"), ("b", "es", "B"), ("p", "pl", "P"), ("f", "de", "F"), ("ɸ", "ja", "F"), ("θ", "es", "TH"),
    ("ɾ", "es", "D"), ("ʁ", "fr-fr", "R"), ("ɴ", "ja", "NG"), ("ɲ", "es", "N"), ("ʎ", "it", "L"), ("j", "de", "Y"),
    ("w", "en-us", "W"), ("ˈa1", "yue", "AA"), ("ou2", "yue", "OW"),
])
def test_ipa_phones_take_the_mouth_of_the_arpabet_phone_articulated_alike(ipa, language, phone):
    assert arpabet(ipa, language) == phone
    assert canonical_phone(phone) == phone  # a phone of the face's own tables


def test_a_symbol_without_a_known_mouth_is_named():
    with pytest.raises(ValueError, match=r"'ʘ'.*U\+0298"):
        arpabet("ʘ")


@needs_espeak
def test_every_language_speaks_with_phone_times_that_match_its_audio():
    """Each language's sentences: every phone has a mouth, the phones tile the audio, pauses are silent where
    vowels are loud (the times are where the sounds are), and at least four of the five vowel shapes occur."""
    from dimgestor.evaluation.phone_timed import LANGUAGES, TEXTS, speak

    assert len(LANGUAGES) >= 6 and {"en-us", "de", "es", "fr-fr", "ja", "yue"} <= set(LANGUAGES)
    for lang in LANGUAGES:
        shapes, pause_rms, vowel_rms = set(), [], []
        for text in TEXTS[lang][:4]:
            s = speak(text, lang)
            assert s.rate == 16000 and s.audio.dtype == np.float32 and s.seconds > 0.5, (lang, text)
            starts, ends = np.array([a for a, _, _ in s.phones]), np.array([b for _, b, _ in s.phones])
            assert starts[0] == 0 and np.all(ends > starts) and np.allclose(starts[1:], ends[:-1]), (lang, text)
            assert abs(ends[-1] - s.seconds) < 2 / 16000 + 1 / 22050, (lang, ends[-1], s.seconds)
            for a, b, ipa in s.phones:
                phone = arpabet(ipa, lang)  # raises on a phone without a mouth
                x = s.audio[int(a * s.rate):int(b * s.rate)]
                if phone in VOWEL_CLASS:
                    shapes.add(VOWEL_CLASS[phone])
                    if b - a >= 0.04:
                        vowel_rms.append(float(np.sqrt(np.mean(x ** 2))))
                elif phone == "SIL" and b - a >= 0.1:
                    pause_rms.append(float(np.sqrt(np.mean(x ** 2))))
        assert len(shapes) >= 4, (lang, shapes)
        assert pause_rms and np.median(pause_rms) < np.median(vowel_rms) / 100, (lang, pause_rms[:5], vowel_rms[:5])


@needs_espeak
def test_a_passage_keeps_every_phone_at_its_place_across_sentences_and_pauses():
    """Each sentence of a passage is its own utterance (the rate and pitch drawn for it) placed after the pauses
    before it: its audio and its phones, shifted by where it starts."""
    from dimgestor.evaluation.phone_timed import TEXTS, alignment, passage, speak

    p = passage("es", "f2", seed=3, sentences=3)
    assert p.voice == "es+f2" and p.phones[0] == (0.0, 0.5, "")
    assert abs(p.phones[-1][1] - p.seconds) < 1e-9 and np.all(np.diff([a for a, _, _ in p.phones]) >= 0)
    rng, at = np.random.default_rng(3), 8000
    for text in TEXTS["es"][:3]:
        one = speak(text, "es+f2", rate=int(rng.integers(140, 191)), pitch=int(rng.integers(30, 71)))
        assert np.array_equal(p.audio[at:at + len(one.audio)], one.audio)
        t = at / 16000
        assert [(round(a + t, 6), ipa) for a, _, ipa in one.phones] == [
            (round(a, 6), ipa) for a, _, ipa in p.phones if t - 1e-9 <= a < t + one.seconds - 1e-9][:len(one.phones)]
        gap = int(round(float(rng.uniform(0.4, 1.0)) * 16000))
        assert not p.audio[at + len(one.audio):at + len(one.audio) + gap].any()
        at += len(one.audio) + gap
    assert at == len(p.audio)
    again = passage("es", "f2", seed=3, sentences=3)
    assert np.array_equal(again.audio, p.audio) and again.phones == p.phones  # deterministic
    assert all(label == "" or canonical_phone(label) == label for _, _, label in alignment(p))


@needs_espeak
def test_the_languages_benchmark_writes_its_schema(tmp_path):
    out = tmp_path / "face_languages.json"
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "face_languages.py"), "--languages", "de", "ja",
                        "--variants", "f2", "--sentences", "3", "--out", str(out)], cwd=REPO, capture_output=True,
                       text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"})
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(out.read_text())
    assert out.with_suffix(".png").stat().st_size > 10_000
    assert res["code_version"] and res["device"].startswith("CPU") and len(res["load_average_before"]) == 3
    assert [row["voice"] for row in res["rows"]] == ["de+f2", "ja+f2"]
    for row in res["rows"]:
        assert row["seconds"] > 3 and row["phones"] > 20
        assert -1 <= row["face"]["openness_r"] <= 1 and 0 <= row["face"]["vowel_top1"] <= 1
        assert -1 <= row["loudness_jaw"]["openness_r"] <= 1
    assert set(res["per_language"]) == {"de", "ja"}
    assert all(v["voices"] == 1 for v in res["per_language"].values())


@needs_espeak
def test_the_listener_probe_writes_its_schema(tmp_path):
    """benchmarks/face_net.py at its smallest: one voice of one language and one real clip labelled by the
    teacher, a few steps, one real clip scored."""
    data = REPO.parent / "shared" / "data" / "phone_aligned_speech"
    if not data.is_dir():
        pytest.skip(f"the phone-aligned clips are not at {data} (only beside the dev checkout)")
    out = tmp_path / "face_net.json"
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "face_net.py"), "--languages", "ja",
                        "--train-variants", "f1", "--held-variants", "f2", "--sentences", "2", "--steps", "3",
                        "--batch", "2", "--clips", "clip000070_lskPN47Lo8o", "--real-repeat", "1",
                        "--teacher", str(data / "clip000028_tCAkv4ggPgI.wav"), "--out", str(out)], cwd=REPO,
                       capture_output=True, text=True, timeout=300,
                       env={**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"})
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(out.read_text())
    assert res["code_version"] and res["params"] > 10_000 and res["data_minutes"] > 0
    [taught] = res["teacher"]  # pocketsphinx's phones over the whole recording: a phone every 50-200 ms of speech
    assert taught["file"] == "clip000028_tCAkv4ggPgI.wav" and 5 * taught["seconds"] < taught["phones"] < 25 * taught["seconds"]
    [(name, clip)] = res["real"].items()
    assert name == "clip000070_lskPN47Lo8o" and clip["held_out"]
    assert set(clip["net"]) >= {"openness_r", "vowel_top1", "closures"} and set(clip["pocketsphinx"]) == set(clip["net"])
    assert [v["voice"] for v in res["espeak_held_out"]["voices"]] == ["ja+f2"]
