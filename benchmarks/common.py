"""Helpers shared by the benchmarks: the device description, memory readings, result files."""

from __future__ import annotations

import json
import os
import platform
import resource
import time
from pathlib import Path

import numpy as np
import torch

from dimgestor.audio import SAMPLE_RATE

RESULTS = Path(__file__).resolve().parent / "results"


def describe_device(device: str) -> str:
    """One line naming the hardware a number was measured on."""
    if device.startswith("cuda"):
        return f"{torch.cuda.get_device_name(device)} (CUDA {torch.version.cuda}), torch {torch.__version__}"
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return (f"CPU {cpu}, {os.cpu_count()} cores visible, torch {torch.__version__} "
            f"({torch.get_num_threads()} intra-op threads)")


def rss_mb() -> float:
    """Current resident set size of this process (MB), from /proc (Linux)."""
    with open("/proc/self/statm") as f:
        resident_pages = int(f.read().split()[1])
    return resident_pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def peak_rss_mb() -> float:
    """High-water mark of this process's resident set size (MB); ru_maxrss is in kB on Linux."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def load_average() -> list[float]:
    """1, 5 and 15 minute load averages: how busy the (shared) machine was."""
    return [round(x, 2) for x in os.getloadavg()]


def percentile_ms(seconds: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(seconds) * 1000.0, q)) if seconds else float("nan")


def write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")
    print(f"wrote {path}")


def read_before(path: Path, before: Path | None) -> dict | None:
    """A benchmark's results from the code before: --before, else STEM_before.json beside the results."""
    if before is None:
        before = path.with_name(path.stem + "_before.json")
        if before == path or not before.exists():
            return None
    return json.loads(before.read_text())


def utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def test_audio(seconds: float, sr: int = SAMPLE_RATE, seed: int = 0, start_s: float = 0.0) -> np.ndarray:
    """Speech-like synthetic audio: a voiced tone with syllable-rate loudness and noise (deterministic).

    The benchmarks time the network, which does not look at what the audio says; a chunk of any span of
    this signal can be made on demand, so an hour of it is never held in memory.
    """
    t = start_s + np.arange(int(round(seconds * sr))) / sr
    rng = np.random.default_rng(seed + int(start_s * 1000))
    envelope = 0.5 * (1 + np.sin(2 * np.pi * 4.0 * t)) * (0.6 + 0.4 * np.sin(2 * np.pi * 0.3 * t))
    voiced = np.sin(2 * np.pi * (140 + 30 * np.sin(2 * np.pi * 0.5 * t)) * t)
    return (0.3 * envelope * voiced + 0.01 * rng.standard_normal(t.size)).astype(np.float32)


def real_voice(path: Path) -> tuple[str, str]:
    """(group, row name) of a file of real speech: BEAT's `4_lawrence_0_19_19.wav` is ("lawrence",
    "lawrence_0_19_19"); any other name is a real-world speaker of its own, `clip000028_tCAkv4ggPgI.wav`
    ("realworld", "realworld_clip000028")."""
    parts = Path(path).stem.split("_")
    if len(parts) >= 5 and parts[0].isdigit():
        return parts[1], "_".join(parts[1:])
    return "realworld", f"realworld_{parts[0]}"


def code_version() -> str:
    """The commit the measured code is at, marked '+dirty' when dimgestor/ has uncommitted changes."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "dimgestor"], cwd=root, capture_output=True,
                               text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
    return head + ("+dirty" if dirty else "")


def reference_line(ax, metric: str, reference: dict | None) -> None:
    """The real (or ground-truth) motion's value of an eval metric as a black line; ratios are 1 by definition."""
    if metric.endswith("_ratio"):
        ax.axhline(1.0, color="k", lw=1)
    elif reference and metric in reference:
        ax.axhline(reference[metric], color="k", lw=1)


def save_panels(fig, axes, title: str, path) -> None:
    """Legend on the first panel, grids, the title, and the PNG written."""
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def save_against_before(fig, ax, lines: list[str], before_code: str | None, path) -> None:
    """Title a one-panel plot of this code beside the code before it (hatched bars), and write the PNG."""
    if before_code is not None:
        lines = lines + [f"code before (hatched): {before_code}"]
    ax.set_title("\n".join(lines), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    print(f"wrote {path}")


def commit_of(root: Path) -> str:
    """The short commit of a code root, '+dirty' when its dimgestor/ or streamer/ has uncommitted changes."""
    import subprocess

    git = lambda *a: subprocess.run(["git", *a], cwd=root, capture_output=True, text=True, check=True).stdout.strip()  # noqa: E731
    try:
        return git("rev-parse", "--short", "HEAD") + ("+dirty" if git("status", "--porcelain", "--", "dimgestor", "streamer") else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
