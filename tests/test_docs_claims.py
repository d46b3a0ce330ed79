"""The user docs' checkable claims hold (issue 47): every flag written after `dimgestor <command>` exists in that
command's parser under its current spelling, and every number a doc quotes beside a results file is in that file.

The convention for quoting a measurement: a sentence (or a table row) that names `results/NAME.json` quotes only
numbers from that file, written as the file has them rounded to the digits shown (0.6564 may be written 0.656 or
0.66; a share may be written as a percentage: 0.624 as 62 %). Single-digit whole numbers (K = 4, 3 seeds) and
what is in backticks are not checked. docs/performance.md is generated from the results (test_performance_doc.py);
benchmarks/README.md keeps the history, with older files, and is not checked here."""

import argparse
import json
import math
import re
import shlex
from functools import cache
from pathlib import Path

import pytest

from dimgestor.cli_help import DeprecatedAlias
from dimgestor_app.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DOCS = sorted([ROOT / "README.md", ROOT / "MODEL_CARD.md", ROOT / "clients" / "README.md",
               *ROOT.glob("clients/*/README.md"), *(ROOT / "docs").glob("*.md")])
CITING_DOCS = [p for p in DOCS if p.name != "performance.md"]


def name(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


# ---- flags ---------------------------------------------------------------------------------------------------

@cache
def commands() -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def code_of(text: str) -> list[str]:
    """The command lines a doc shows: each line of its code blocks (continuations joined) and each inline span."""
    lines = []
    for block in re.findall(r"^```[^\n]*\n(.*?)^```", text, re.M | re.S):
        lines += block.replace("\\\n", " ").splitlines()
    prose = re.sub(r"^```[^\n]*\n.*?^```", "", text, flags=re.M | re.S)
    return lines + re.findall(r"`([^`\n]+)`", prose)


def invocations(line: str) -> list[tuple[str, list[str]]]:
    """(command, its --flags) for each `dimgestor COMMAND ...` in a line (`.venv/bin/dimgestor`, and an inline span
    that starts with the command's name, `serve --face`, count too); a `#` comment ends the line."""
    found = []
    starts = [m.end() for m in re.finditer(r"(?:^|[\s/])dimgestor\s+(?=[a-z])", line)]
    first = line.split(" ", 1)[0]
    if first in commands() and line.startswith(f"{first} -"):
        starts.append(0)
    for start in starts:
        rest = line[start:].split(" #", 1)[0]
        try:
            words = shlex.split(rest, comments=True)
        except ValueError:
            words = rest.split()
        if not words or words[0] not in commands():
            continue
        flags = [w.strip("[]()|,;.").split("=", 1)[0] for w in words[1:]]
        found.append((words[0], [f for f in flags if re.fullmatch(r"--[a-z][a-z0-9-]*", f)]))
    return found


def test_the_flag_finder_reads_code_blocks_inline_spans_and_comments():
    text = ("Run\n```\n.venv/bin/dimgestor serve --source mic \\\n  --vmc 127.0.0.1:39539   # --not-a-flag\n```\n"
            "then `dimgestor generate --audio a.wav [--face-csv F]`, `train --arm-mix` or `make demo --x`.")
    found = [inv for line in code_of(text) for inv in invocations(line)]
    assert found == [("serve", ["--source", "--vmc"]), ("generate", ["--audio", "--face-csv"]),
                     ("train", ["--arm-mix"])]


def test_every_flag_the_docs_write_after_a_dimgestor_command_is_in_its_parser_as_spelled_now():
    wrong = []
    for path in DOCS:
        for line in code_of(path.read_text(encoding="utf-8")):
            for command, flags in invocations(line):
                options = commands()[command]._option_string_actions
                for flag in flags:
                    if flag not in options:
                        wrong.append(f"{name(path)}: `dimgestor {command}` has no {flag}: {line.strip()[:90]}")
                    elif isinstance(options[flag], DeprecatedAlias):
                        wrong.append(f"{name(path)}: `dimgestor {command} {flag}` is deprecated "
                                     f"(now {options[flag].replaced_by}): {line.strip()[:90]}")
    assert not wrong, "\n".join(wrong)


# ---- numbers quoted from benchmarks/results/ -----------------------------------------------------------------

REFERENCE = re.compile(r"results/([\w.-]+?\.json)")
NUMBER = re.compile(r"(?<![\w.^/])([-+]?\d+(?:,\d{3})*(?:\.\d+)?)(\s?%|x)?(?![\w^/]|\.\d)")  # 62 %, 1.5x


@cache
def values(file: str) -> tuple[float, ...]:
    """Every number in a results file: its numeric leaves, and the numbers inside its strings."""
    out = []

    def walk(v):
        if isinstance(v, bool):
            return
        if isinstance(v, (int, float)):
            if math.isfinite(v):
                out.append(float(v))
        elif isinstance(v, str):
            out.extend(float(x) for x in re.findall(r"-?\d+(?:\.\d+)?", v))
        elif isinstance(v, dict):
            for x in v.values():
                walk(x)
        elif isinstance(v, list):
            for x in v:
                walk(x)
    walk(json.loads((RESULTS / file).read_text()))
    return tuple(out)


def written_as(value: float, text: str) -> bool:
    """`value` shown with `text`'s digits: rounded either way at a half, sign and thousands separators aside."""
    text = text.replace(",", "").lstrip("+")
    digits = len(text.split(".")[1]) if "." in text else 0
    shown = float(text)
    return any(abs(v - shown) <= 0.5 * 10 ** -digits * (1 + 1e-9) for v in (value, -value))


def quoted(file: str, number: str, percent: bool) -> bool:
    return any(written_as(v, number) or (percent and written_as(100 * v, number)) for v in values(file))


def sentences(text: str) -> list[str]:
    """A doc's prose sentences and table rows, code blocks left out. A table's rows carry the results files its
    caption names: the sentence just before it that ends with ":", or a `*From ...*` line just after it."""
    text = re.sub(r"^```[^\n]*\n.*?^```", "", text, flags=re.M | re.S)
    blocks = re.split(r"\n\s*\n", text)
    out = []
    for i, block in enumerate(blocks):
        lines = block.splitlines()
        rows = [line for line in lines if line.lstrip().startswith("|")]
        prose = " ".join(line for line in lines if line not in rows and not line.startswith("#"))
        said = [s for s in re.split(r"(?<=[.!?])\s+(?=\S)|\s(?=- )", prose) if s.strip()]
        if rows:
            before = said[-1] if said and said[-1].rstrip().endswith(":") else (
                blocks[i - 1].strip() if i and blocks[i - 1].rstrip().endswith(":") else "")
            after = blocks[i + 1].strip() if i + 1 < len(blocks) and blocks[i + 1].lstrip().startswith("*From") else ""
            caption = " ".join(f"(results/{f})" for f in REFERENCE.findall(before + " " + after))
            rows = [f"{row} {caption}" for row in rows if not re.fullmatch(r"[|\s:-]+", row)]
        out += said + rows
    return out


def claims(text: str) -> list[tuple[str, list[str], list[tuple[str, bool]]]]:
    """(sentence, the results files it names, the numbers it quotes) for each sentence that names one."""
    found = []
    for sentence in sentences(text):
        files = REFERENCE.findall(sentence)
        if not files:
            continue
        # code, links and a parenthesis that starts with a doc's or script's path are not quotes
        plain = re.sub(r"`[^`]*`|\[[^\]]*\]\([^)]*\)|\(\s*[\w./-]+\.(?:md|py)\b[^()]*\)", " ", sentence)
        plain = REFERENCE.sub(" ", plain)
        plain = re.sub(r"(?<=\d)-(?=\d)", " - ", plain)  # a range: both ends are quoted numbers
        numbers = [(m.group(1), "%" in (m.group(2) or "")) for m in NUMBER.finditer(plain)
                   if not re.fullmatch(r"[-+]?\d", m.group(1))]
        found.append((sentence, files, numbers))
    return found


def test_the_number_finder_reads_ranges_percentages_and_leaves_code_and_small_counts_alone():
    [(sentence, files, numbers)] = claims("Blinks 18-23 a minute, 3 seeds, cost +12 % and r 0.637, 1.5x "
                                         "(`--steps 4`; `results/face.json`). Next sentence 77.")
    assert files == ["face.json"] and numbers == [("18", False), ("23", False), ("+12", True), ("0.637", False),
                                                  ("1.5", False)]
    assert all(quoted("face.json", n, p) for n, p in numbers)
    assert quoted("face.json", "0.64", False)  # 0.637 to two digits
    assert not quoted("face.json", "987", False) and not quoted("face.json", "0.6371", False)
    assert written_as(412.5, "412") and written_as(412.5, "413") and not written_as(412.5, "414")


def test_a_table_is_checked_against_the_file_its_caption_names():
    text = "Measured (`results/face.json`):\n\n| take | r |\n|---|---|\n| 1 | 0.637 |\n| 2 | 0.888 |\n\nThen 0.999."
    rows = [(numbers, files) for _, files, numbers in claims(text)]
    assert rows[2:] == [([("0.637", False)], ["face.json"]), ([("0.888", False)], ["face.json"])]  # (after the header)
    assert not quoted("face.json", "0.888", False)
    assert [n for _, _, n in claims("| a | 12.5 |\n|---|---|\n\n*From `benchmarks/results/face.json`.*")] == [
        [("12.5", False)], []]


@pytest.mark.parametrize("path", CITING_DOCS, ids=name)
def test_every_number_quoted_beside_a_results_file_is_in_that_file(path):
    wrong = []
    for sentence, files, numbers in claims(path.read_text(encoding="utf-8")):
        missing = [f for f in files if not (RESULTS / f).is_file()]
        if missing:
            wrong.append(f"names {missing}, not in benchmarks/results/: {sentence[:120]}")
            continue
        for number, percent in numbers:
            if not any(quoted(f, number, percent) for f in files):
                wrong.append(f"{number}{' %' if percent else ''} is not in {', '.join(files)}: {sentence[:160]}")
    assert not wrong, f"{name(path)}:\n" + "\n".join(wrong)


# ---- claims one doc makes about another ----------------------------------------------------------------------

NUMBER_WORDS = {w: i for i, w in enumerate("zero one two three four five six seven eight nine ten".split())}


def test_the_clients_overview_counts_the_unity_files_the_unity_guide_has_you_copy():
    said = re.search(r"copy (\w+) `\.cs` files", (ROOT / "clients" / "README.md").read_text()).group(1)
    guide = (ROOT / "clients" / "unity" / "README.md").read_text()
    step = re.search(r"^1\. Copy (.*?) into `Assets/", guide, re.M | re.S).group(1)
    files = re.findall(r"`(\w+\.cs)`", step)
    assert NUMBER_WORDS[said] == len(files), (said, files)
    assert all((ROOT / "clients" / "unity" / f).is_file() for f in files), files


def test_the_readmes_vtuber_command_is_the_vtuber_guides_one_command():
    readme = (ROOT / "README.md").read_text().split("## VTubers", 1)[1].split("\n## ", 1)[0]
    guide = (ROOT / "docs" / "vtuber.md").read_text().split("## The one command", 1)[1].split("\n## ", 1)[0]
    shown = re.findall(r"^(?:\.venv/bin/)?(dimgestor serve .*)$", readme, re.M)
    assert shown and shown == re.findall(r"^(dimgestor serve .*)$", guide, re.M)
