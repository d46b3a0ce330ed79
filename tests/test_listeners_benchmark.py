"""benchmarks/listeners.py: each candidate is the default model's recipe with its one change, and the table."""
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
import listeners  # noqa: E402


def test_candidates_are_the_default_recipe_with_one_change(tmp_path):
    base = listeners.train_config("default", tmp_path)
    assert base.overrides == {"frontend": "speech", "lookahead_ms": 300, "down_kernel": 41}
    assert (base.max_steps, base.cond_drop, base.seed, base.speeds, base.mirror) == (1200, 0.15, 0, (0.9, 1.1), True)
    embed = listeners.train_config("embed_mel8", tmp_path)
    assert embed.overrides == {**base.overrides, "frontend": "embedding", "n_mels": 8}
    assert embed.model_dump(exclude={"overrides", "out"}) == base.model_dump(exclude={"overrides", "out"})
    aug = listeners.train_config("voice_aug", tmp_path)
    assert aug.augment and aug.aug_config["p_formant"] == 0.8 and aug.out == str(tmp_path / "voice_aug")
    assert listeners.train_config("default_seed2", tmp_path).seed == 2
    for name in listeners.CANDIDATES:  # every candidate validates (a bad field would fail only after training)
        listeners.train_config(name, tmp_path)


def test_table_has_a_row_per_candidate():
    row = {"coupling": 0.3, "coupling_min": 0.2, "above_chance": 4, "voices": 4, "silence_ratio": 5.0,
           "silence_ratio_min": 4.0, "jerk_ratio": 1.2, "jerk_ratio_max": 1.4, "variety": 0.8}
    result = {"candidates": {"default": {"rows": {"zeggs_heldout": {"coupling": 0.56}}, "summary": {"real": row}},
                             "embed": {"rows": {}, "summary": {}}}}
    lines = listeners.table(result).splitlines()
    assert lines[2] == "| default | +0.56 | +0.30 (+0.20) | 4/4 | 5.00 (4.00) | 1.20 (1.40) | 0.80 |"
    assert lines[3].startswith("| embed | - |") and len(lines) == 4


@pytest.mark.skipif(listeners.ZEGGS.is_dir(), reason="checks the message given where ../shared is absent")
def test_without_the_shared_data_it_says_so(capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["listeners.py", "--runs", "/nonexistent"])
    assert listeners.main() == 0 and "skipped" in capsys.readouterr().out
