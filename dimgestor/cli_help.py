"""The help and option conventions every `dimgestor` subcommand shares: grouped help with one default per option
and examples at the end (`HelpFormatter`, `examples`), old spellings of renamed options (`deprecated_alias`), and
the value of a flag several subcommands take (`smoothing_from_flag`).

Its own module so that the subcommands' modules (here and in `streamer`) use it without importing the command
line that registers them.
"""
from __future__ import annotations

import argparse
import re
import sys
import textwrap

__all__ = ["HelpFormatter", "DeprecatedAlias", "deprecated_alias", "examples", "smoothing_from_flag"]


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """One default per option: "(default: X)" is added only where the help states none and there is one to state
    (not None, False or empty). Descriptions and epilogs are wrapped, except paragraphs with indented lines
    (examples), which are kept as written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text, default = action.help or "", action.default
        if (not action.option_strings or action.required or default is None or default is False
                or default is argparse.SUPPRESS or (isinstance(default, (list, tuple)) and not default)
                or re.search(r"\bdefault", text, re.IGNORECASE)):
            return text
        return f"{text} (default: %(default)s)"

    def _split_lines(self, text: str, width: int) -> list[str]:
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)  # (never "--window-" "ms")

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        out = []
        for paragraph in textwrap.dedent(text).strip("\n").split("\n\n"):
            lines = paragraph.splitlines()
            if any(line[:1].isspace() for line in lines):
                out.append("\n".join(indent + line for line in lines))
            else:
                out.append(textwrap.fill(" ".join(paragraph.split()), width, initial_indent=indent,
                                         subsequent_indent=indent))
        return "\n\n".join(out)


class DeprecatedAlias(argparse.Action):
    """An old spelling of an option: stores into the new option's field and says once, on stderr, what replaced it.
    Hidden from --help (the subcommand's epilog lists the old spellings)."""

    def __init__(self, option_strings, dest, replaced_by: str = "", note: str = "", **kwargs):
        kwargs.update(default=argparse.SUPPRESS, help=argparse.SUPPRESS)  # the new option's default stands
        super().__init__(option_strings, dest, **kwargs)
        self.replaced_by, self.note, self.said = replaced_by, note, False

    def __call__(self, parser, namespace, values, option_string=None):
        if not self.said:
            print(f"{parser.prog}: {option_string} is now {self.replaced_by}{self.note}", file=sys.stderr, flush=True)
            self.said = True
        setattr(namespace, self.dest, values)


def deprecated_alias(parser: argparse.ArgumentParser, old: str, new: argparse.Action, note: str = "") -> None:
    """Accept `old` as a deprecated spelling of the option `new` (the action add_argument returned): same value."""
    parser.add_argument(old, action=DeprecatedAlias, dest=new.dest, type=new.type, nargs=new.nargs,
                        choices=new.choices, metavar=new.metavar, replaced_by=new.option_strings[-1], note=note)


def examples(*lines: str, deprecated: str = "") -> str:
    """A subcommand's epilog: "examples:" and the command lines (kept as written), then the old spellings."""
    text = "examples:\n" + "\n".join(f"  {line}" for line in lines)
    return text + (f"\n\ndeprecated spellings, still accepted: {deprecated}" if deprecated else "")


def smoothing_from_flag(hz: float | None):
    """A command line's --smooth HZ as a `smoothing` argument: None -> "config", 0 -> off, else the cutoff."""
    if hz is None:
        return "config"
    if hz < 0:
        raise ValueError(f"--smooth must be >= 0 Hz (0 = off), got {hz}")
    return hz or None
