"""How many real-time streams one process keeps with a face on every stream, against none (issue 49: at least
0.85 as many): `streams.max_streams` on the embedded default model (K = 4, 100 ms windows, batched, staggered
clients, the batcher on as many torch threads as `dimgestor serve` gives it), once without a face and once with
`FaceOptions()` (the face's own listener) on every session, and with `--pocketsphinx` also with pocketsphinx's
listener; `--also CHECKPOINT` adds that model (a distilled student, say) at its own K with a face on every session;
`--onnxruntime` adds the same two (no face, face) on ONNX Runtime, as `dimgestor serve --backend onnxruntime` runs them
(a `BatcherPool` of one-thread `BatchRunner`s), for each lane count of `--lanes`.

    .venv/bin/python benchmarks/face_streams.py            # writes results/face_streams.json and .png
"""
from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=4)
    p.add_argument("--window-ms", type=int, default=100)
    p.add_argument("--seconds", type=float, default=12.0, help="audio per trial")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads of the batcher (default: what `dimgestor serve` gives it here, every core "
                        "but the event loop's)")
    p.add_argument("--cap", type=int, default=96)
    p.add_argument("--pocketsphinx", action="store_true", help="also with pocketsphinx's listener")
    p.add_argument("--also", default=None, metavar="CHECKPOINT",
                   help="one more arm: this checkpoint (e.g. a distilled student) at its own K, with a face")
    p.add_argument("--onnxruntime", action="store_true",
                   help="also on ONNX Runtime: the export of --onnx, else the model's in serve's cache (exported there "
                        "on first use, as `dimgestor serve --backend onnxruntime` does)")
    p.add_argument("--onnx", type=Path, default=None, metavar="DIR", help="the export for --onnxruntime")
    p.add_argument("--lanes", type=int, nargs="+", default=None, metavar="N",
                   help="ONNX Runtime's batchers (lanes) to try (default: 1 and what serve gives it here)")
    p.add_argument("--out", type=Path, default=RESULTS / "face_streams.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    if args.threads is None:
        from streamer.server import inference_threads

        args.threads = inference_threads()
    if args.lanes is None:
        from streamer.server import onnx_lanes

        args.lanes = sorted({1, onnx_lanes()})
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arms = list(result["arms"])
    fig, ax = plt.subplots(figsize=(max(6.0, 1.3 * len(arms)), 3.8))
    ax.bar(range(len(arms)), [result["arms"][a]["max_realtime_streams"] for a in arms],
           color=[f"C{i}" for i in range(len(arms))])
    ax.set_xticks(range(len(arms)), [textwrap.fill(a, 14) for a in arms], fontsize=8)
    ax.set_ylabel("real-time streams a process")
    ax.set_title(f"K={result['steps']}, {result['window_ms']} ms windows, {result['threads']} torch "
                 f"thread{'s' if result['threads'] > 1 else ''}: "
                 f"face / none {result['ratio']:.2f}", fontsize=9)
    fig.suptitle(f"face_streams ({result['code_version']}, {result['device'][:50]})", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    args = parse_args(argv)
    from dimgestor.face import FaceOptions
    from dimgestor.streaming.checkpoint import load_checkpoint
    from streams import max_streams

    bundle = load_checkpoint(None)
    before = load_average()
    faces = {"no face": None, "face": FaceOptions()}
    if args.pocketsphinx:
        faces["face, pocketsphinx"] = FaceOptions(listener="pocketsphinx")
    arms = {}
    for name, face in faces.items():
        print(f"{name}:", flush=True)
        arms[name] = max_streams(bundle, args.steps, args.window_ms, args.seconds, True, args.threads, args.cap,
                                 face=face, log=lambda s: print(s, flush=True))
    if args.onnxruntime:
        from dimgestor.export.onnx_batch import BatchRunner
        from dimgestor.export.onnx_stream import OnnxModel

        if args.onnx is None:
            from dimgestor.export.onnx_cache import cached_export
            from streamer.server import SERVE_BATCHES

            args.onnx = cached_export(bundle, args.steps, bundle.config.guidance, batches=SERVE_BATCHES)
        onnx = OnnxModel.load(args.onnx)
        for lanes in args.lanes:
            for name, face in (("no face", None), ("face", faces["face"])):
                label = f"ONNX Runtime, {name}, {lanes} lane{'s' if lanes > 1 else ''}"
                print(f"{label}:", flush=True)
                arms[label] = max_streams(bundle, args.steps, args.window_ms, args.seconds, True, 1, args.cap,
                                          onnx=onnx, batch_runner=[BatchRunner.of(onnx, 1) for _ in range(lanes)],
                                          face=face, log=lambda s: print(s, flush=True))
                arms[label]["lanes"] = lanes
    if args.also:
        other = load_checkpoint(args.also)
        name = f"face, {Path(args.also).name} (K={other.config.sample_steps}, guidance {other.config.guidance:g})"
        print(f"{name}:", flush=True)
        arms[name] = max_streams(other, other.config.sample_steps, args.window_ms, args.seconds, True, args.threads,
                                 args.cap, face=FaceOptions(), log=lambda s: print(s, flush=True))
    base = arms["no face"]["max_realtime_streams"]
    result = {"benchmark": "face_streams", "code_version": code_version(), "device": describe_device("cpu"),
              "utc": utc_now(), "argv": args.argv, "note": args.note, "load_average_before": before,
              "load_average_after": load_average(), "steps": args.steps, "window_ms": args.window_ms,
              "threads": args.threads, "arms": arms,
              **({"onnx": str(args.onnx), "lanes": args.lanes} if args.onnxruntime else {}),
              "ratio": arms["face"]["max_realtime_streams"] / base if base else float("nan"),
              **({"ratio_pocketsphinx": arms["face, pocketsphinx"]["max_realtime_streams"] / base}
                 if args.pocketsphinx and base else {}),
              **({"also": args.also, "also_over_face": arms[name]["max_realtime_streams"]
                  / arms["face"]["max_realtime_streams"] if arms["face"]["max_realtime_streams"] else float("nan")}
                 if args.also else {})}
    print(f"streams: none {base}, face {arms['face']['max_realtime_streams']} (ratio {result['ratio']:.2f})")
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
