"""Peak memory of `dimgestor generate` against the recording's length: a .bvh (made and written a block at a time), a
.glb (the model streamed a block at a time, the animation held whole to be written), and the model run on the whole
recording at once (what generate did for every output before issue 52). Each run is a fresh process (its peak
resident set, from the kernel), on speech made by looping the packaged demo clip.

    .venv/bin/python benchmarks/generate_memory.py [--minutes 1 5 20] [--out benchmarks/results/generate_memory.json]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.common import RESULTS, code_version, describe_device, load_average, utc_now, write_json  # noqa: E402
from dimgestor.audio import SAMPLE_RATE, load_wav, save_wav  # noqa: E402
from streamer.sources import DEMO_WAV  # noqa: E402

WHOLE = """
import sys
from dimgestor.audio import load_wav
from dimgestor.bvh import write_bvh
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor_app.generate import generate_motion
b = load_checkpoint(None)
write_bvh(sys.argv[2], generate_motion(b, load_wav(sys.argv[1])))
"""


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, nargs="+", default=[1.0, 5.0, 20.0])
    p.add_argument("--out", type=Path, default=RESULTS / "generate_memory.json")
    args = p.parse_args()
    demo = load_wav(DEMO_WAV)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for minutes in args.minutes:
            n = int(minutes * 60 * SAMPLE_RATE)
            wav = Path(tmp) / f"speech_{minutes:g}min.wav"
            save_wav(wav, np.resize(demo, n), SAMPLE_RATE)
            row = {"minutes": minutes, "wav_mb": round(wav.stat().st_size / 2**20, 1)}
            generate = [sys.executable, "-m", "dimgestor_app", "generate", "--audio", str(wav), "--out"]
            for name, cmd in (("streamed_bvh", [*generate, str(Path(tmp) / "streamed.bvh")]),
                              ("glb", [*generate, str(Path(tmp) / "streamed.glb")]),
                              ("whole", [sys.executable, "-c", WHOLE, str(wav), str(Path(tmp) / "whole.bvh")])):
                peak, wall = measure(cmd)
                row[f"{name}_peak_rss_mb"], row[f"{name}_wall_s"] = round(peak, 1), round(wall, 2)
                print(f"{minutes:g} min, {name}: peak {peak:.0f} MB, {wall:.1f} s", flush=True)
            rows.append(row)
    result = {"benchmark": "generate_memory", "date": utc_now(), "code": code_version(),
              "device": describe_device("cpu"), "load_average": load_average(), "runs": rows}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))


# The command runs under this small wrapper: the child of a fork counts its parent's pages in its peak until it execs,
# and this benchmark's own process (torch, the audio) is far larger than the wrapper.
WRAPPER = """
import resource, subprocess, sys, time
t = time.perf_counter()
done = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
if done.returncode:
    sys.exit(done.stderr[-2000:])
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, time.perf_counter() - t)
"""


def measure(cmd: list[str]) -> tuple[float, float]:
    """(peak RSS in MB, wall seconds) of `cmd` run to its end in a fresh process."""
    done = subprocess.run([sys.executable, "-c", WRAPPER, *cmd], capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"{' '.join(map(str, cmd[:5]))} ... failed: {done.stderr[-2000:]}")
    peak, wall = map(float, done.stdout.split())
    return peak, wall


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = result["runs"]
    x = [r["minutes"] for r in runs]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(x, [r["streamed_bvh_peak_rss_mb"] for r in runs], "o-", label=".bvh, a block at a time")
    ax.plot(x, [r["glb_peak_rss_mb"] for r in runs], "^-", label=".glb: streamed, the animation held whole")
    ax.plot(x, [r["whole_peak_rss_mb"] for r in runs], "s--", label="the model on the whole recording (before)")
    ax.set_xlabel("recording (minutes)")
    ax.set_ylabel("peak resident memory (MB)")
    ax.set_title(f"dimgestor generate, default model\n{result['code']}", fontsize=9)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
