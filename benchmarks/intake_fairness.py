"""Issue 40 item 8: fast senders at a high rate beside a real-time talker, against `dimgestor serve --source ws`.

For each number of flooders (default 1, 3, 7): a fresh server, one talker sending 16 kHz PCM16 speech paced in real
time, quiet for Q seconds, then beside the flooders for F seconds (each sends 1 MiB messages of 192 kHz stereo
float32 as fast as the socket takes them, ignoring `slow_down`), then 2 s quiet and `audio_end`. Reports the talker's
frame latency p50/p95 quiet and flooded, the `slow_down` and `resume` each flooder was told, the messages each got
in, and whether the talker got every frame (tests/helpers/intake_load.py measures).

    python benchmarks/intake_fairness.py                         # the tiny random model, 1/3/7 flooders
    python benchmarks/intake_fairness.py --flooders 3 --flood-s 20 --checkpoint runs/x
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
from pathlib import Path

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def one(checkpoint: Path, flooders: int, quiet_s: float, flood_s: float) -> dict:
    from helpers.intake_load import talker_beside_flood
    from helpers.serve import serve

    s = serve(checkpoint, "--source", "ws")
    try:
        url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
        r = asyncio.run(talker_beside_flood(url, flooders, quiet_s=quiet_s, flood_s=flood_s))
    finally:
        s.proc.terminate()
        s.finish(10)
    talker, counts = r["talker"], r["counts"]
    per = lambda key: [counts.get(f"{k}:{key}", 0) for k in range(flooders)]  # noqa: E731
    out = {
        "flooders": flooders,
        "talker_p95_quiet_ms": round(1000 * r["quiet_p95_s"], 1),
        "talker_p95_flooded_ms": round(1000 * r["flooded_p95_s"], 1),
        "talker_p50_quiet_ms": round(1000 * talker.percentile(*r["quiet"], q=50), 1),
        "talker_p50_flooded_ms": round(1000 * talker.percentile(*r["flooded"], q=50), 1),
        "slow_down": per("slow_down"), "resume": per("resume"), "messages_in": per("sent"),
        "talker_frames": talker.frames, "talker_end_frames": (talker.end or {}).get("frames"),
        "talker_errors": [e["code"] for e in talker.errors],
        "traceback_in_log": "Traceback" in s.output,
    }
    print(out, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flooders", type=int, nargs="+", default=[1, 3, 7])
    ap.add_argument("--quiet-s", type=float, default=6.0)
    ap.add_argument("--flood-s", type=float, default=10.0)
    ap.add_argument("--checkpoint", type=Path, default=None, help="default: a tiny random-init model (the tests')")
    ap.add_argument("--out", default=str(RESULTS / "intake_fairness.json"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        checkpoint = args.checkpoint
        if checkpoint is None:
            from helpers.checkpoint import make_tiny_checkpoint

            checkpoint = make_tiny_checkpoint(Path(tmp))
        load_before = load_average()
        runs = [one(checkpoint, n, args.quiet_s, args.flood_s) for n in args.flooders]
    write_json(Path(args.out), {
        "when": utc_now(), "code_version": code_version(), "device": describe_device("cpu"),
        "load_average_before": load_before, "load_average_after": load_average(),
        "checkpoint": str(args.checkpoint or "tiny random-init (tests/helpers/checkpoint.py)"),
        "flood": "1 MiB messages of 192 kHz stereo float32 (0.68 s each), as fast as the socket takes them",
        "talker": "16 kHz PCM16 speech in 50 ms messages paced in real time", "quiet_s": args.quiet_s,
        "flood_s": args.flood_s, "runs": runs})


if __name__ == "__main__":
    main()
