"""Cost of retargeting live frames onto a user's rig (`serve --target`, a client's `hello.rig`): ms per call and
per frame for the windows a stream sends (1, 4 and 20 frames), onto an A-posed Unreal-named copy of the default
model's skeleton (75 joints, 52 humanoid bones), and the one-off cost of fitting a rig.

    .venv/bin/python benchmarks/retarget.py [--repeats 50] [--out benchmarks/results/retarget.json]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]
from benchmarks.common import RESULTS, code_version, describe_device, load_average, percentile_ms, utc_now, write_json  # noqa: E402
from dimgestor import rotations as R  # noqa: E402
from dimgestor.retarget import Retarget, Rig, resolve_map  # noqa: E402
from dimgestor.streaming.checkpoint import load_checkpoint  # noqa: E402
from helpers.rigs import a_pose  # noqa: E402  (the tests' A-pose copy)

WINDOWS = (1, 4, 20)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--out", type=Path, default=RESULTS / "retarget.json")
    args = ap.parse_args()

    sk = load_checkpoint(None).skeleton
    source, target = Rig.from_skeleton(sk), Rig.from_skeleton(a_pose(sk), "mannequin.bvh")
    fits = []
    for _ in range(5):
        t = time.perf_counter()
        rt = Retarget(source, target, resolve_map(source), resolve_map(target), move="root")
        fits.append(time.perf_counter() - t)
    rng = np.random.default_rng(0)
    rows = {}
    for n in WINDOWS:
        q = R.expmap_to_quat(rng.normal(0, 0.4, (n, sk.num_joints, 3)))
        tr = np.broadcast_to(sk.offsets, (n, sk.num_joints, 3)).copy()
        rt(q, tr)  # warm-up (the tables)
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            rt(q, tr)
            times.append(time.perf_counter() - t)
        rows[str(n)] = {"median_ms": percentile_ms(times, 50), "p95_ms": percentile_ms(times, 95),
                        "per_frame_ms": percentile_ms(times, 50) / n}
        print(f"{n:3d} frames: median {rows[str(n)]['median_ms']:6.2f} ms per call, "
              f"{rows[str(n)]['per_frame_ms']:6.3f} ms per frame")
    result = {
        "what": "ms to retarget a window of frames onto an A-posed, renamed, resized copy of the default model's "
                "skeleton (75 joints, 52 humanoid bones), and to fit the rig once",
        "device": describe_device("cpu"), "code_version": code_version(), "date": utc_now(),
        "load_average": load_average(), "repeats": args.repeats, "joints": sk.num_joints, "bones": len(rt.bones),
        "fit_ms": percentile_ms(fits, 50), "windows": rows,
    }
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    n = [int(k) for k in result["windows"]]
    ax.bar([str(k) for k in n], [result["windows"][str(k)]["per_frame_ms"] for k in n], color="#4a7ab5")
    ax.set_xlabel("frames per call (a window)")
    ax.set_ylabel("ms per frame (median)")
    ax.set_title(f"retarget onto a 75-joint A-pose rig; fitting it once: {result['fit_ms']:.0f} ms\n"
                 f"{result['device']}, code {result['code_version']}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
