"""Cost of one VMC frame on the event loop: humanoid local pose + OSC bundle, old path vs new.

old: the per-bone local pose walk (`HumanoidRig.local_pose_reference`) and python-osc's builders
     (`vmc.reference_bundle`), as streamer/vmc.py did before;
new: the vectorised local pose and the struct packer (`VmcEncoder.packets`), byte-identical output.

    .venv/bin/python benchmarks/vmc_frame.py [--frames 300] [--out benchmarks/results/vmc_frame.json]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.common import RESULTS, code_version, describe_device, load_average, percentile_ms, utc_now, write_json  # noqa: E402
from dimgestor.rotations import quat_normalize  # noqa: E402
from dimgestor.streaming.checkpoint import load_checkpoint  # noqa: E402
from streamer.frames import Frame  # noqa: E402
from streamer.pose import HumanoidRig, load_humanoid_map, to_unity_position, to_unity_quat  # noqa: E402
from streamer.vmc import VmcEncoder, VmcOptions, reference_bundle  # noqa: E402


def old_bundle(enc: VmcEncoder, f: Frame) -> bytes:
    """streamer/vmc.py before: per-bone pose walk, one python-osc message per bone."""
    pos, rot = enc.rig.local_pose_reference(f.root_pos[None], f.rotations[None])
    pos, rot = to_unity_position(pos[0], enc.scale), to_unity_quat(rot[0])
    msgs = [("/VMC/Ext/Root/Pos", list(enc.root_args))]
    msgs += [("/VMC/Ext/Bone/Pos", [n, *map(float, p), float(q[1]), float(q[2]), float(q[3]), float(q[0])])
             for n, p, q in zip(enc.names, pos, rot)]
    msgs += [("/VMC/Ext/Blend/Apply", []), ("/VMC/Ext/OK", [1]), ("/VMC/Ext/T", [float(f.pts)])]
    return reference_bundle(msgs)


def time_per_frame(fn, frames) -> list[float]:
    out = []
    for f in frames:
        t = time.perf_counter()
        fn(f)
        out.append(time.perf_counter() - t)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--out", type=Path, default=RESULTS / "vmc_frame.json")
    args = ap.parse_args()

    bundle = load_checkpoint(None)
    sk = bundle.skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    enc = VmcEncoder(rig, VmcOptions(positions="all"))  # "all": the old path's output exactly
    rng = np.random.default_rng(0)
    frames = [Frame(i, i / 20, rng.normal(size=3) * 10, quat_normalize(rng.normal(size=(len(sk.names), 4))), None)
              for i in range(args.frames)]
    assert old_bundle(enc, frames[0]) == enc.packets(frames[0])[0], "old and new bundles differ"

    parts = {
        "pose_old": lambda f: rig.local_pose_reference(f.root_pos[None], f.rotations[None]),
        "pose_new": lambda f: rig.local_pose(f.root_pos[None], f.rotations[None]),
        "frame_old": lambda f: old_bundle(enc, f),
        "frame_new": lambda f: enc.packets(f),
    }
    for fn in parts.values():  # warm-up
        time_per_frame(fn, frames[:20])
    rows = {}
    for name, fn in parts.items():
        s = time_per_frame(fn, frames)
        rows[name] = {"median_ms": percentile_ms(s, 50), "p95_ms": percentile_ms(s, 95), "max_ms": percentile_ms(s, 100)}
        print(f"{name:10s} median {rows[name]['median_ms']:7.3f} ms  p95 {rows[name]['p95_ms']:7.3f} ms")
    result = {
        "what": "ms per VMC frame (52 bones, 4404-byte bundle): humanoid local pose, and pose + bundle, old vs new",
        "device": describe_device("cpu"), "code_version": code_version(), "date": utc_now(),
        "load_average": load_average(), "frames": args.frames, "bones": len(rig.bones),
        "bundle_bytes": len(enc.packets(frames[0])[0]), "results": rows,
        "speedup_frame": rows["frame_old"]["median_ms"] / rows["frame_new"]["median_ms"],
        "share_of_a_core_at_20fps": {k: 20 * v["median_ms"] / 1000 for k, v in rows.items() if k.startswith("frame")},
    }
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))


def plot(result, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = result["results"]
    names = ["pose_old", "pose_new", "frame_old", "frame_new"]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    med = [r[n]["median_ms"] for n in names]
    p95 = [r[n]["p95_ms"] for n in names]
    x = np.arange(len(names))
    ax.bar(x - 0.18, med, 0.36, label="median", color=["#c66", "#4a4", "#c66", "#4a4"])
    ax.bar(x + 0.18, p95, 0.36, label="p95", color=["#e99", "#8c8", "#e99", "#8c8"])
    ax.set_xticks(x, ["local pose\n(per-bone walk)", "local pose\n(vectorised)", "pose + bundle\n(python-osc)",
                      "pose + bundle\n(struct)"])
    ax.set_yscale("log")
    ax.set_ylabel("ms per frame (log)")
    for xi, m in zip(x, med):
        ax.annotate(f"{m:.2f}", (xi - 0.18, m), ha="center", va="bottom", fontsize=8)
    ax.set_title(f"VMC frame cost, {result['bones']} bones ({result['code_version']})", fontsize=10)
    ax.legend(fontsize=8)
    fig.text(0.01, 0.01, result["device"][:110] + f"; load {result['load_average'][0]}", fontsize=6)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
