"""Praat TextGrid interval tiers (the forced alignments the face is measured against): read, and the phone at
each frame."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

__all__ = ["read_tiers", "phones_at"]

_TIER = re.compile(r'name\s*=\s*"(?P<name>[^"]*)"(?P<body>.*?)(?=\bitem\s*\[\d+\]|\Z)', re.S)
_INTERVAL = re.compile(r'xmin\s*=\s*(?P<a>[-\d.eE+]+)\s*xmax\s*=\s*(?P<b>[-\d.eE+]+)\s*text\s*=\s*"(?P<t>(?:[^"]|"")*)"')


def read_tiers(path: str | Path) -> dict[str, list[tuple[float, float, str]]]:
    """{tier name: [(start s, end s, text), ...]} of a long-format TextGrid's interval tiers."""
    text = Path(path).read_text(encoding="utf-8", errors="replace")
    tiers = {}
    for m in _TIER.finditer(text.split("item []:", 1)[-1]):
        tiers[m["name"]] = [(float(i["a"]), float(i["b"]), i["t"].replace('""', '"'))
                            for i in _INTERVAL.finditer(m["body"])]
    if not tiers:
        raise ValueError(f"{path}: no interval tiers found (a long-format Praat TextGrid is expected)")
    return tiers


def phones_at(intervals: list[tuple[float, float, str]], times: np.ndarray) -> list[str]:
    """The label of the interval holding each time ("" outside every interval)."""
    starts = np.array([a for a, _, _ in intervals])
    out = []
    for t in times:
        k = int(np.searchsorted(starts, t, side="right")) - 1
        out.append(intervals[k][2] if k >= 0 and t < intervals[k][1] else "")
    return out
