"""Every `dimgestor` subcommand's --help: each option explained, its default stated once, examples at the end; and
the old spellings (`streamer ...`, `--osc`, `--sample-steps`, `--ks`) still work and say what
replaced them."""

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from dimgestor.cli_help import DeprecatedAlias, HelpFormatter
from dimgestor.config import PRESETS
from dimgestor_app.cli import build_parser, streamer_main
from dimgestor_app.cli import main as dimgestor_main

REPO = Path(__file__).resolve().parents[1]
COMMANDS = ["serve", "generate", "train", "distill", "render", "eval", "convert", "info", "export", "export-onnx", "devices", "web"]
SERVE_GROUPS = ["input", "model and sampling", "outputs", "network and security", "operations"]
DEFAULT = re.compile(r"\(?\bdefault\b[:)]", re.IGNORECASE)  # a stated default: "(default: X)", "default: X", "(default)"


def subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def help_problems(parser: argparse.ArgumentParser) -> list[str]:
    """What is wrong with one (sub)command's help: options without help text, defaults stated twice or as None."""
    problems = []
    formatter = parser._get_formatter()
    for action in parser._actions:
        name = "/".join(action.option_strings) or action.dest
        if action.help is argparse.SUPPRESS:
            if not isinstance(action, DeprecatedAlias):  # (an old spelling is hidden: the epilog lists it)
                problems.append(f"{name}: hidden")
            continue
        if not (action.help or "").strip():
            problems.append(f"{name}: no help text")
            continue
        text = formatter._expand_help(action)
        if len(DEFAULT.findall(text)) > 1:
            problems.append(f"{name}: default stated twice: {text!r}")
        if re.search(r"\(default: (None|False|\[\]|\(\))\)", text):
            problems.append(f"{name}: says {text!r}")
    return problems


def test_the_commands_are_one_tool_in_this_order():
    assert list(subparsers(build_parser())) == COMMANDS


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_is_explained_with_one_default_and_the_help_ends_with_examples(command):
    parser = subparsers(build_parser())[command]
    assert help_problems(parser) == []
    text = parser.format_help()
    assert "(default: None)" not in text and "(default: False)" not in text
    examples = text.split("\nexamples:\n")[-1].split("\n\n")[0].splitlines()
    assert len(text.split("\nexamples:\n")) == 2 and examples, text
    assert all(line.startswith(("  dimgestor ", "  torchrun ")) for line in examples), examples
    assert any(line.startswith(f"  dimgestor {command}") for line in examples), examples
    for line in examples:  # and each example parses as the command line it shows
        argv = line.split("#")[0].split()
        if argv[0] == "dimgestor":
            args = build_parser().parse_args(argv[1:])
            assert args.command == argv[1]


def test_serve_help_is_grouped_by_purpose():
    serve = subparsers(build_parser())["serve"]
    titles = [g.title for g in serve._action_groups if g._group_actions and g.title not in ("options",)]
    assert titles == SERVE_GROUPS
    text = serve.format_help()
    for flag in ("--vmc HOST:PORT", "--input-device N|NAME", "--steps K", "--state-store URL", "--token-file FILE"):
        assert flag in text, flag
    assert "--osc" not in text.split("\nexamples:\n")[0]  # only named as an old spelling
    assert "deprecated spellings, still accepted: --osc (now --vmc)" in " ".join(text.split())
    assert "--device cpu|cuda|cuda:N" in text


def test_preset_takes_one_of_the_presets(capsys):
    for command in ("info", "train"):
        preset = next(a for a in subparsers(build_parser())[command]._actions if a.dest == "preset")
        assert list(preset.choices) == list(PRESETS) == ["paper", "realtime", "tiny"]
    for argv in (["info"], ["train", "--data", "d", "--out", "o"]):
        with pytest.raises(SystemExit) as e:
            build_parser().parse_args([*argv, "--preset", "huge"])
        assert e.value.code == 2 and "--preset: invalid choice: 'huge'" in capsys.readouterr().err


def test_the_check_finds_what_it_looks_for():
    """help_problems on a parser with each defect (the one this replaced doubled its defaults)."""
    bad = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    bad.add_argument("--smooth", default=None, help="cutoff (default: the checkpoint's setting)")
    bad.add_argument("--seed", type=int, default=0)
    bad.add_argument("--steps", default=None, help="DDIM steps")
    bad.add_argument("--secret", default=1, help=argparse.SUPPRESS)
    problems = help_problems(bad)
    assert {p.split(":")[0] for p in problems} == {"--smooth", "--seed", "--steps", "--secret"}, problems
    assert any(p.startswith("--smooth: default stated twice") for p in problems)
    assert "--seed: no help text" in problems and "--secret: hidden" in problems
    assert any(p.startswith("--steps: says") and "(default: None)" in p for p in problems)
    good = argparse.ArgumentParser(formatter_class=HelpFormatter)
    good.add_argument("--smooth", default=None, help="cutoff (default: the checkpoint's setting)")
    good.add_argument("--seed", type=int, default=0, help="noise seed")
    good.add_argument("--fast", action="store_true", help="as fast as possible")
    good.add_argument("--ws", default="127.0.0.1:8765", help="address; by default local only")
    assert help_problems(good) == []
    text = good.format_help()
    assert "noise seed (default: 0)" in text and "(default: False)" not in text and "local only\n" in text


@pytest.mark.parametrize("argv, old, new", [
    (["serve", "--osc", "127.0.0.1:39539"], "--osc", "--vmc"),
    (["export", "--checkpoint", "c", "--out", "o", "--sample-steps", "4"], "--sample-steps", "--steps"),
    (["eval", "--ks", "1,2,4"], "--ks", "--steps"),
    (["generate", "--audio", "a.wav", "--out", "a.bvh", "--face", "a.csv"], "--face", "--face-csv"),
])
def test_an_old_spelling_parses_as_the_new_one_and_says_so_once(argv, old, new, capsys):
    args = vars(build_parser().parse_args(argv))
    err = capsys.readouterr().err
    assert err.count(f"{old} is now {new}") == 1 and len(err.splitlines()) == 1, err
    renamed = vars(build_parser().parse_args([new if a == old else a for a in argv]))
    assert args == renamed
    assert capsys.readouterr().err == ""  # the new spelling: no note


def test_eval_steps_takes_one_k_or_several():
    parse = build_parser().parse_args
    assert parse(["eval", "--steps", "4"]).ks == "4" and parse(["eval", "--steps", "1,2,4,8"]).ks == "1,2,4,8"
    assert parse(["eval"]).ks is None and parse(["eval"]).steps is None  # the checkpoint's


def test_streamer_runs_the_same_command_and_says_once_what_replaced_it(capsys):
    assert dimgestor_main(["info", "--preset", "tiny", "--json"]) == 0
    new = capsys.readouterr()
    assert streamer_main(["info", "--preset", "tiny", "--json"]) == 0
    old = capsys.readouterr()
    assert old.out == new.out and json.loads(old.out)["parameters"]["total"] > 0 and new.err == ""
    assert old.err == "streamer is now `dimgestor`: run `dimgestor info ...` (the same options)\n"
    assert streamer_main(["export", "--checkpoint", "/no/such", "--out", "x", "--sample-steps", "0"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("streamer is now `dimgestor`: run `dimgestor export ...`")
    assert err[1:] == ["streamer export: --sample-steps is now --steps", "error: --steps must be >= 1"]


def test_streamer_never_repeats_the_rest_of_its_command_line(capsys):
    """(it may hold a token)"""
    with pytest.raises(SystemExit):
        streamer_main(["serve", "--token", "s3cret", "--help"])
    out = capsys.readouterr()
    assert "s3cret" not in out.err and "`dimgestor serve ...`" in out.err


def _script(name: str) -> Path:
    script = Path(sys.executable).with_name(name)
    if not script.exists():
        pytest.skip(f"the {name} console script is not installed beside {sys.executable}")
    return script


def test_the_console_scripts_as_a_user_runs_them():
    r = subprocess.run([_script("dimgestor"), "serve", "--help"], cwd=REPO, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and r.stderr == "" and r.stdout.startswith("usage: dimgestor serve "), r.stderr
    assert all(f"\n{title}:\n" in r.stdout for title in SERVE_GROUPS)
    r = subprocess.run([_script("streamer"), "serve", "--osc", "127.0.0.1:9", "--steps", "0", "--no-ws"], cwd=REPO,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.splitlines() == ["streamer is now `dimgestor`: run `dimgestor serve ...` (the same options)",
                                     "streamer serve: --osc is now --vmc",
                                     "dimgestor: --steps must be >= 1, got 0"], r.stderr
