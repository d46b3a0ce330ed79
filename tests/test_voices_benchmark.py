"""benchmarks/voices.py: the espeak voices it makes, the tables it prints, and a --quick run's JSON."""

import json
import math
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
import voices  # noqa: E402

from helpers import warm

needs_espeak = pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="espeak-ng not installed")


def _row(coupling, shifted=0.0, sd=0.05, onset=0.8, shuffled=0.7, ratio=3.0, jerk=2e4):
    return {"coupling": coupling, "coupling_shifted": shifted, "coupling_shifted_sd": sd,
            "coupling_above": coupling > shifted + 2 * sd, "onset_align": onset, "onset_shuffled": shuffled,
            "contrast": 2.0, "silence_ratio": ratio, "hand_jerk": jerk}


def _result(couplings: dict, variety: float = 0.8) -> dict:
    groups = {"lawrence_a": "lawrence", "scott_b": "scott", "espeak_x": "espeak", "demo_en": "demo"}
    rows = {n: {**_row(c), "jerk_ratio": 1.2, "nearest": 5.0 * variety, "variety": variety}
            for n, c in couplings.items()}
    model = {"checkpoint": "ck", "steps": 4, "rows": rows, "reference": {}, "summary": voices.summarize(rows, groups)}
    return {"settings": {"seeds": 2, "steps": 4}, "models": {"m": model}}


def test_summary_keeps_real_and_synthetic_voices_apart():
    s = _result({"lawrence_a": 0.4, "scott_b": 0.2, "espeak_x": 0.1, "demo_en": -0.5})["models"]["m"]["summary"]
    assert s["real"]["voices"] == 2 and s["real"]["coupling"] == pytest.approx(0.3)  # lawrence + scott
    assert s["synthetic"]["voices"] == 1 and s["synthetic"]["coupling"] == pytest.approx(0.1)
    assert s["unseen"]["voices"] == 3 and s["unseen"]["coupling"] == pytest.approx(0.7 / 3)  # the demo clip is not unseen
    assert s["unseen"]["above_chance"] == 2 and s["unseen"]["coupling_min"] == pytest.approx(0.1)  # 0.1 is not > 0 + 0.1
    assert s["real"]["onset_margin"] == pytest.approx(0.1) and s["real"]["variety"] == pytest.approx(0.8)
    assert s["real"]["jerk_ratio_max"] == pytest.approx(1.2) and s["real"]["silence_ratio_min"] == pytest.approx(3.0)


def test_compare_table_puts_old_beside_new(tmp_path):
    old, new = tmp_path / "old.json", tmp_path / "new.json"
    old.write_text(json.dumps(_result({"lawrence_a": 0.21, "scott_b": 0.31, "espeak_x": 0.05, "demo_en": 0.1}, 0.7)))
    new.write_text(json.dumps(_result({"lawrence_a": 0.52, "scott_b": 0.48, "espeak_x": 0.47, "demo_en": 0.3}, 0.9)))
    table = voices.compare_table(voices.labelled_models([str(old), str(new)]))
    lines = {line.split("|")[1].strip(): line for line in table.splitlines() if line.startswith("| ")}
    assert "coupling (shifted) old:m" in lines["voice"] and "variety new:m" in lines["voice"]
    assert "+0.21 (+0.00) |" in lines["lawrence_a"] and "+0.52 (+0.00) |" in lines["lawrence_a"]
    assert "+0.05 (+0.00) ~" in lines["espeak_x"]  # not above its shifted baseline + 2 sd: marked
    real = lines["**real unseen mean (lawrence + scott + realworld)**"]
    assert "+0.26 (2/2 above)" in real and "+0.50 (2/2 above)" in real and "| 0.70 | 0.90 |" in real
    assert "+0.05 (0/1 above)" in lines["**synthetic unseen mean (espeak)**"]
    for total in (real, lines["**all unseen mean**"]):
        assert total.count("|") == lines["voice"].count("|")  # one cell per column
    md = voices.model_table(_result({"lawrence_a": 0.4, "espeak_x": 0.1, "demo_en": 0.0}), "m")
    assert "| lawrence_a | +0.40 | +0.00 | 0.05 | yes |" in md and "real unseen mean (1 voices)" in md


def test_results_of_the_first_schema_still_compare(tmp_path):
    """Files written before real and synthetic voices were apart (flat unseen_* keys over lawrence + espeak)."""
    old = _result({"lawrence_a": 0.2, "espeak_x": 0.4})
    old["models"]["m"]["summary"] = {"unseen_voices": 2, "unseen_coupling": 0.3, "unseen_above_chance": 2,
                                     "unseen_onset_margin": 0.1, "unseen_silence_ratio": 3.5, "unseen_hand_jerk": 2e4}
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old))
    table = voices.compare_table(voices.labelled_models([str(path), str(path)]))
    assert "| **all unseen mean** | +0.30 (2/2 above) | +0.30 (2/2 above) |" in table
    assert "real unseen mean" not in table


@needs_espeak
def test_espeak_clips_are_deterministic_with_pauses_and_long_enough(tmp_path):
    for name, voice, pitch, wpm, lang in voices.ESPEAK_VOICES:
        a = voices.espeak_clip(voice, pitch, wpm, voices.TEXTS[lang], tmp_path)
        assert 35 <= len(a) / voices.SAMPLE_RATE <= 70, (name, len(a) / voices.SAMPLE_RATE)
        assert np.abs(a).max() == pytest.approx(10 ** (-1 / 20), rel=1e-4)
        # the fixed pauses between sentences are digital silence: at least one run of zeros >= 1.5 s
        zero = np.concatenate([[0], (a == 0).astype(np.int8), [0]])
        runs = np.diff(np.flatnonzero(np.diff(zero)))[::2]
        assert runs.max() >= 1.5 * voices.SAMPLE_RATE, name
    again = voices.espeak_clip(*voices.ESPEAK_VOICES[0][1:4], voices.TEXTS["en"], tmp_path)
    first = voices.espeak_clip(*voices.ESPEAK_VOICES[0][1:4], voices.TEXTS["en"], tmp_path)
    np.testing.assert_array_equal(again, first)


@pytest.mark.slow
@needs_espeak
def test_quick_run_writes_the_per_voice_json(tmp_path):
    out = tmp_path / "v.json"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    proc = warm.run([sys.executable, str(REPO / "benchmarks" / "voices.py"), "--quick", "--out", str(out)],
                    cwd=REPO, env=env, capture_output=True, text=True, timeout=500)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(out.read_text())
    assert out.with_suffix(".png").stat().st_size > 10_000
    assert r["schema"] == voices.SCHEMA and r["code_version"] and r["torch"] and r["device"].startswith("CPU")
    m = r["models"]["default"]
    espeak = [n for n in m["rows"] if n.startswith("espeak_")]
    assert len(espeak) == 3 and {"demo_en", "demo_zh"} <= set(m["rows"])
    for name, row in m["rows"].items():
        assert math.isfinite(row["coupling"]) and row["coupling_shifted_sd"] > 0, name
        assert 0 <= row["onset_shuffled"] <= 1 and row["silence_ratio"] > 0, name
    if voices.ZEGGS.is_dir():  # the real capture as reference, on the held-out stretch
        assert m["reference"]["zeggs_heldout_real"]["coupling"] > 0.3
        assert 14 < r["voices"]["zeggs_heldout"]["seconds"] < 16
    else:
        assert "zeggs_heldout" in r["skipped"]
    real = sum(n.startswith(("lawrence", "scott", "realworld")) for n in m["rows"])
    assert m["summary"]["synthetic"]["voices"] == 3 and m["summary"]["unseen"]["voices"] == 3 + real
    assert (m["summary"].get("real") or {}).get("voices", 0) == real
    if voices.ZEGGS.is_dir():  # variety: against the training stretch, over the actor's own held-out figure
        assert m["reference"]["zeggs_heldout_real"]["variety"] == 1.0
        assert 3.0 < m["reference"]["zeggs_heldout_real"]["nearest"] < 10.0  # cm (6.0 measured)
        assert all(0.2 < row["variety"] < 2.0 for row in m["rows"].values())
    compared = warm.run([sys.executable, str(REPO / "benchmarks" / "voices.py"), "--compare", str(out), str(out)],
                        cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert compared.returncode == 0 and "espeak_de_p40_s150" in compared.stdout
