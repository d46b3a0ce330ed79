"""What `serve --face-process`'s child costs: how long it takes to answer after it is started, and the memory it
holds, idle and with `--faces` faces pushed `--seconds` of speech in 100 ms windows (one exchange a window).

Each measurement runs in a fresh `python -c` process: multiprocessing's spawn imports the starting program's main
module again in the child, and this script's (like every benchmark's, through `common`) imports torch, which
`dimgestor serve`'s does not; a `-c` program has no main module to import, as the console script has next to none.

    .venv/bin/python benchmarks/face_process_start.py --repeats 5 --faces 56 --seconds 5
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from common import RESULTS, code_version, describe_device, utc_now, write_json

PROBE = r"""
import json, sys, time
import numpy as np
from dimgestor.face import FaceOptions
from streamer.face_process import FaceProcess

faces_n, seconds = int(sys.argv[1]), float(sys.argv[2])

def rss_mb(pid):
    with open(f"/proc/{pid}/status") as f:
        return next(int(l.split()[1]) for l in f if l.startswith("VmRSS")) / 1024

t = time.perf_counter()
process = FaceProcess()
process.ready()
start_s = time.perf_counter() - t
idle = rss_mb(process.pid)
faces = [process.face(20, 0.3, FaceOptions(seed=k)) for k in range(faces_n)]
rng = np.random.default_rng(0)
audio = (rng.standard_normal((faces_n, int(16000 * seconds))) * 0.1).astype(np.float32)
exchange = []
for at in range(0, audio.shape[1], 1600):
    t = time.perf_counter()
    answer, _ = process.push_many(faces, list(audio[:, at:at + 1600]))
    exchange.append(time.perf_counter() - t)
    for f in faces:
        f.receive(answer)
        f.take(f.frames_ready)
busy = rss_mb(process.pid)
process.close()
print(json.dumps({"start_s": start_s, "idle_rss_mb": idle, "busy_rss_mb": busy,
                  "exchange_ms_median": 1000 * float(np.median(exchange)), "torch_in_parent": "torch" in sys.modules}))
"""


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=5, help="fresh processes, each starting one child")
    p.add_argument("--faces", type=int, default=56, help="faces pushed together, as a batch of a served process")
    p.add_argument("--seconds", type=float, default=5.0, help="speech pushed to each face")
    p.add_argument("--out", type=Path, default=RESULTS / "face_process_start.json")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def probe(args) -> dict:
    proc = subprocess.run([sys.executable, "-c", PROBE, str(args.faces), str(args.seconds)], capture_output=True,
                          text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"the probe failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = result["runs"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    axes[0].scatter(range(1, len(runs) + 1), [r["start_s"] for r in runs])
    axes[0].set(xlabel="run", ylabel="s", title="from start to the child's first answer", ylim=(0, None))
    for key, label in (("idle_rss_mb", "idle"), ("busy_rss_mb", f"{result['faces']} faces, {result['seconds']:g} s")):
        axes[1].scatter(range(1, len(runs) + 1), [r[key] for r in runs], label=label)
    axes[1].set(xlabel="run", ylabel="MB", title="the child's resident memory", ylim=(0, None))
    axes[1].legend(fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(f"serve --face-process's child ({result['code']}, {result['device']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    runs = [probe(args) for _ in range(args.repeats)]
    for r in runs:
        print(f"start {r['start_s']:.2f} s, idle {r['idle_rss_mb']:.0f} MB, {args.faces} faces "
              f"{r['busy_rss_mb']:.0f} MB, an exchange {r['exchange_ms_median']:.1f} ms (median)", flush=True)
    result = {"benchmark": "face_process_start", "created": utc_now(), "code": code_version(),
              "device": describe_device("cpu"), "command": "python benchmarks/face_process_start.py "
              + " ".join(args.argv), "faces": args.faces, "seconds": args.seconds, "runs": runs,
              "start_s_max": max(r["start_s"] for r in runs),
              "idle_rss_mb_max": max(r["idle_rss_mb"] for r in runs),
              "busy_rss_mb_max": max(r["busy_rss_mb"] for r in runs)}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
