"""Gestures against their audio through a real pipecat pipeline: how far from the moment its audio is heard each
gesture frame reaches the sinks, with a TTS bursting faster than real time (streamer/pipecat.py).

Each run: examples/pipecat_avatar.py's bursting TTS (`--speed` x real time, `--burst-s` bursts, `--rate` Hz) ->
GestureProcessor (the embedded model) -> an output transport that plays in real time and records when each
chunk starts. Per frame: release time - playout time of its audio (both time.monotonic). Also: how long the
first audio was held, the longest event-loop stall (a 20 ms sleeper's worst lateness), the gaps between frames.

    .venv/bin/python benchmarks/pipecat_sync.py [--runs 5] [--audio-s 8] [--out benchmarks/results/pipecat_sync.json]
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "examples"))
from benchmarks.common import RESULTS, code_version, describe_device, load_average, utc_now, write_json  # noqa: E402

FPS = 20


async def one_run(bundle, speech: np.ndarray, rate: int, speed: float, burst_s: float) -> dict:
    from pipecat.frames.frames import EndFrame, TTSSpeakFrame
    from pipecat.pipeline.pipeline import Pipeline
    from pipecat.pipeline.worker import PipelineParams, PipelineWorker
    from pipecat.workers.runner import WorkerRunner
    from pipecat_avatar import PacedAudioOutput, WavTTS

    from streamer.pipecat import GestureProcessor

    released, worst = [], [0.0]
    gestures = GestureProcessor([], bundle=bundle, on_release=released.append)
    tts, output = WavTTS(speech, rate, speed=speed, burst_s=burst_s), PacedAudioOutput(rate)
    worker = PipelineWorker(Pipeline([tts, gestures, output]), idle_timeout_secs=None, enable_rtvi=False,
                            params=PipelineParams(audio_out_sample_rate=rate), observers=[gestures.playout_observer])

    async def watch() -> None:
        while True:
            before = time.monotonic()
            await asyncio.sleep(0.02)
            worst[0] = max(worst[0], time.monotonic() - before - 0.02)

    marks = {}

    async def script() -> None:
        await asyncio.sleep(0.5)
        marks["speak"] = time.monotonic()
        await worker.queue_frames([TTSSpeakFrame("benchmark")])
        await asyncio.sleep(len(speech) / rate + 1.0)
        await worker.queue_frames([EndFrame()])

    watcher = asyncio.create_task(watch())
    runner = WorkerRunner(handle_sigint=False)
    await runner.add_workers(worker)
    driver = asyncio.create_task(script())
    await runner.run()
    await driver
    watcher.cancel()

    chunks = [p for p in output.played if p.start >= marks["speak"]]
    first = np.cumsum([0] + [p.samples for p in chunks])
    errors = []
    speech_frames = [r for r in released if r.utterance == 0]
    for r in speech_frames:
        n = r.audio_s * rate
        i = int(np.searchsorted(first, n, side="right")) - 1
        errors.append(r.wall - (chunks[i].start + (n - first[i]) / rate))
    walls = np.array([r.wall for r in speech_frames])
    return {"frames": len(speech_frames), "errors_ms": [round(1000 * e, 3) for e in errors],
            "held_ms": round(1000 * gestures.stats.held_s, 2), "loop_stall_ms": round(1000 * worst[0], 2),
            "late_frames": gestures.stats.late, "max_gap_ms": round(1000 * float(np.diff(walls).max()), 2)}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for i, run in enumerate(result["runs"]):
        e = np.array(run["errors_ms"])
        a.plot(np.arange(len(e)) / FPS, e, lw=0.8, label=f"run {i + 1} (stall {run['loop_stall_ms']:.0f} ms)")
    a.axhline(50, color="r", ls="--", lw=0.8)
    a.axhline(-50, color="r", ls="--", lw=0.8, label="target +/-50 ms")
    a.set(xlabel="audio time in the utterance (s)", ylabel="frame sent - its audio heard (ms)",
          title=f"TTS {result['speed']:g}x real time, {result['burst_s']:g} s bursts, {result['rate']} Hz")
    a.legend(fontsize=7)
    allerr = np.concatenate([r["errors_ms"] for r in result["runs"]])
    b.hist(allerr, bins=40)
    b.set(xlabel="frame sent - its audio heard (ms)", ylabel="frames",
          title=f"p50 {result['error_ms_p50']:.1f}, p99 {result['error_ms_p99']:.1f}, "
                f"max |e| {result['abs_error_ms_max']:.1f} ms")
    fig.suptitle(f"{result['device']}\n{result['code_version']}", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--audio-s", type=float, default=8.0, help="seconds of demo speech per run")
    p.add_argument("--speed", type=float, default=5.0, help="TTS speed: audio per second of wall time")
    p.add_argument("--burst-s", type=float, default=1.0)
    p.add_argument("--rate", type=int, default=24000)
    p.add_argument("--out", type=Path, default=RESULTS / "pipecat_sync.json")
    args = p.parse_args()
    import torch

    from dimgestor.streaming.checkpoint import load_checkpoint
    from pipecat_avatar import load_speech

    torch.set_num_threads(1)
    speech = load_speech(REPO / "dimgestor" / "assets" / "demo_en.wav", args.rate)[: int(args.audio_s * args.rate)]
    bundle = load_checkpoint(None)
    load_before = load_average()
    runs = [asyncio.run(one_run(bundle, speech, args.rate, args.speed, args.burst_s)) for _ in range(args.runs)]
    allerr = np.concatenate([r["errors_ms"] for r in runs])
    result = {
        "what": "gesture frame release - playout of its audio, TTS bursting through a real pipecat pipeline",
        "device": describe_device("cpu"), "code_version": code_version(), "date": utc_now(),
        "load_avg_before": load_before, "load_avg_after": load_average(),
        "speed": args.speed, "burst_s": args.burst_s, "rate": args.rate, "audio_s": args.audio_s,
        "error_ms_p50": round(float(np.percentile(allerr, 50)), 3),
        "error_ms_p99": round(float(np.percentile(allerr, 99)), 3),
        "abs_error_ms_max": round(float(np.abs(allerr).max()), 3),
        "frames_within_50ms": round(float(np.mean(np.abs(allerr) <= 50)), 4),
        "held_ms_max": max(r["held_ms"] for r in runs), "loop_stall_ms_max": max(r["loop_stall_ms"] for r in runs),
        "runs": runs,
    }
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    print(f"sync error p50 {result['error_ms_p50']} ms, p99 {result['error_ms_p99']} ms, max |e| "
          f"{result['abs_error_ms_max']} ms, {100 * result['frames_within_50ms']:.1f} % within 50 ms; audio held up to "
          f"{result['held_ms_max']} ms; loop stalls up to {result['loop_stall_ms_max']} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
