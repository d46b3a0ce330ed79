"""docs/training.md documents every model config field (`--set` keys) with each preset's value, every recipe's
settings, and only `dimgestor train` flags that exist."""

import json
import re
import shlex
from pathlib import Path

import pytest

from dimgestor.config import PRESETS, ModelConfig, get_preset
from dimgestor.training.train import RECIPES
from dimgestor_app.cli import build_parser

DOC = Path(__file__).resolve().parents[1] / "docs" / "training.md"


def cell(value) -> str:
    """A value as the table writes it: what `--set KEY=VALUE` takes."""
    return "null" if value is None else value if isinstance(value, str) else json.dumps(value)


@pytest.fixture(scope="module")
def text() -> str:
    return DOC.read_text(encoding="utf-8")


@pytest.fixture(scope="module")
def set_table(text) -> tuple[list[str], dict[str, list[str]]]:
    """(the preset columns, {key: [cells]}) of the `--set` table."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| key |"))
    head = [c.strip(" `") for c in lines[start].strip("|").split("|")]
    rows = {}
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        key = cells[0].strip("`")
        assert key not in rows, f"{key} has two rows"
        rows[key] = [c.strip("`") for c in cells]
    return head, rows


def test_every_config_field_has_one_row_and_every_row_is_a_field(set_table):
    _, rows = set_table
    missing = [f for f in ModelConfig.model_fields if f not in rows]
    stale = [k for k in rows if k not in ModelConfig.model_fields]
    assert not missing, f"docs/training.md's --set table lacks {missing}"
    assert not stale, f"docs/training.md's --set table names fields that do not exist: {stale}"
    assert all(r[-1] for r in rows.values()), "every key needs its meaning"


def test_the_preset_columns_are_the_presets_values(set_table):
    head, rows = set_table
    columns = [h for h in head if h in PRESETS]
    assert sorted(columns) == sorted(PRESETS)
    for name in columns:
        config = get_preset(name)
        for key, cells in rows.items():
            assert cells[head.index(name)] == cell(getattr(config, key)), f"{key} of preset {name}"


def test_each_recipe_is_described_with_every_field_it_sets(text):
    for name, recipe in RECIPES.items():
        bullet = next((b for b in text.split("\n- ") if b.startswith(f"**`{name}`**")), None)
        assert bullet is not None, f"recipe {name} is not described"
        for key, value in recipe.config.items():
            assert f"`{key}={cell(value)}`" in bullet, f"recipe {name}: {key}={cell(value)}"


def test_the_train_commands_use_only_flags_train_has(text):
    train = build_parser()._subparsers._group_actions[0].choices["train"]
    known = {s for a in train._actions for s in a.option_strings}
    blocks = re.findall(r"```\n(.*?)```", text, re.S)
    commands = [c for b in blocks for c in b.replace("\\\n", " ").splitlines() if re.search(r"\btrain --", c)]
    assert len(commands) >= 4
    for command in commands:
        args = command.split("#")[0].split(" train ", 1)[1]  # (torchrun's own flags come before it)
        flags = [w.split("=")[0] for w in shlex.split(args) if w.startswith("--")]
        unknown = [f for f in flags if f not in known]
        assert not unknown, f"{command!r}: dimgestor train has no {unknown}"


FREE = {"train": "--data", "export": "--out", "distill": "--data"}  # where the guide may name another folder


def _options(command: str, sub: str) -> list[str]:
    """The words after `dimgestor SUB`, sorted, without the FREE flag's value."""
    words = shlex.split(command.split(f"dimgestor {sub} ", 1)[1])
    return sorted(w for i, w in enumerate(words) if not (i and words[i - 1] == FREE[sub]))


def test_the_shipped_recipe_is_the_makefiles_default_model(text):
    make = (DOC.parents[1] / "Makefile").read_text().replace("\\\n", " ")
    target = re.search(r"^default-model:.*?\n((?:\t.*\n)+)", make, re.M).group(1)
    subs = ("train", "export", "distill")
    made = [(sub, _options(line.replace("$(BIN)/", ""), sub)) for line in target.splitlines()
            for sub in subs if f"dimgestor {sub} " in line]
    block = next(b for b in re.findall(r"```\n(.*?)```", text, re.S) if "--out runs/default" in b)
    shown = [(sub, _options(line, sub)) for line in block.replace("\\\n", " ").splitlines()
             for sub in subs if f"dimgestor {sub} " in line]
    assert [sub for sub, _ in made] == ["train", "export", "distill", "distill", "export"]
    # (export's --sample-steps is spelled --steps in the guide, as in the CLI's one name for it)
    assert shown == [(sub, sorted(w.replace("--sample-steps", "--steps") for w in words)) for sub, words in made]
    assert "benchmarks/speech_corpus.py --out runs/speech" in block and "speech_corpus.py --out runs/speech" in target
