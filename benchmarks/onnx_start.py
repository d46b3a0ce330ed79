"""`dimgestor serve --backend onnxruntime` from the command to the first frame a client receives: the first start
(the model exported into an empty cache) and the starts after it (the cached export reused).

Each start is a fresh `dimgestor serve` process (the demo clip, a WebSocket on a free port, the per-user cache
pointed at one folder by --onnx-cache); a client connects as soon as the address is printed and waits for its
first `frame`. Times are from the process's spawn: the cache line (export or reuse), the WebSocket address and
the first frame. Then the same with `--backend torch`, the baseline a start cannot beat by much (Python, torch and
the checkpoint load the same). Writes results/onnx_start.json and a plot beside it (.png).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TARGET_S = 15.0  # issue 47: a second start to its first frame


def start(cache: Path | None, extra: list[str], timeout: float) -> dict:
    """One `serve --backend onnxruntime` start (cache None: `--backend torch`, the baseline): seconds from spawn to
    each milestone, and the cache line."""
    from websockets.sync.client import connect

    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    backend = ["--backend", "torch"] if cache is None else ["--backend", "onnxruntime", "--onnx-cache", str(cache)]
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "dimgestor_app.cli", "serve", *backend, "--ws", "127.0.0.1:0", *extra],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[tuple[float, str]] = []
    reader = threading.Thread(target=lambda: lines.extend((time.monotonic() - t0, ln) for ln in proc.stdout),
                              daemon=True)
    reader.start()

    def wait(pattern: str) -> tuple[float, re.Match]:
        while time.monotonic() - t0 < timeout:
            for t, ln in list(lines):
                if m := re.search(pattern, ln):
                    return t, m
            if proc.poll() is not None and not reader.is_alive():
                break
            time.sleep(0.01)
        raise RuntimeError(f"{pattern!r} never printed; output:\n" + "".join(ln for _, ln in lines)[-3000:])

    try:
        t_cache, exported = None, False
        if cache is not None:
            t_cache, m = wait(r"(exporting the model for ONNX Runtime|using cached ONNX export)")
            exported = m.group(1).startswith("exporting")
        t_url, m = wait(r"WebSocket\s+(ws://\S+?)[\s?]")
        with connect(m.group(1), open_timeout=timeout) as ws:
            while True:
                msg = ws.recv(timeout=timeout)
                if isinstance(msg, str) and json.loads(msg).get("type") == "frame":
                    break
            t_frame = time.monotonic() - t0
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        reader.join(5)
    return {"backend": "torch" if cache is None else "onnxruntime", "exported": exported,
            "cache_line_s": None if t_cache is None else round(t_cache, 2), "ws_address_s": round(t_url, 2),
            "first_frame_s": round(t_frame, 2),
            "cache_lines": [ln.strip() for _, ln in lines if "ONNX export" in ln or "exporting" in ln]}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = result["runs"] + result.get("torch_runs", [])
    labels = ["torch\n(baseline)" if r["backend"] == "torch" else "first start\n(export)" if r["exported"]
              else f"start {i + 1}\n(cached)" for i, r in enumerate(runs)]
    colors = ["tab:gray" if r["backend"] == "torch" else "tab:red" if r["exported"] else "tab:green" for r in runs]
    fig, ax = plt.subplots(figsize=(9, 4.5))
    bars = ax.bar(range(len(runs)), [r["first_frame_s"] for r in runs], color=colors, tick_label=labels)
    ax.bar_label(bars, fmt="%.1f s")
    ax.axhline(TARGET_S, color="k", ls="--", lw=1, label=f"target for a second start: {TARGET_S:g} s")
    ax.set_yscale("log")
    ax.set_ylabel("spawn to first frame at a client (s, log)")
    ax.set_title("dimgestor serve --backend onnxruntime: first start and cached starts")
    ax.legend(loc="upper right")
    fig.text(0.01, 0.01, f"code {result['code']}; {result['machine']}", fontsize=7)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default=None, help="checkpoint (default: the embedded default model)")
    ap.add_argument("--steps", type=int, default=None, help="K (default: the checkpoint's)")
    ap.add_argument("--no-batch", action="store_true", help="serve --no-batch (one graph exported, not three)")
    ap.add_argument("--warm", type=int, default=3, help="starts after the first, on the cache it wrote")
    ap.add_argument("--torch", type=int, default=1, help="starts of `--backend torch` after them, the baseline")
    ap.add_argument("--cache", type=Path, default=None,
                    help="cache folder (default: a new empty one, deleted at the end: the first start exports)")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds a start may take")
    ap.add_argument("--note", default="measured on a shared 2-core machine: other engineers' jobs were running")
    ap.add_argument("--out", type=Path, default=RESULTS / "onnx_start.json")
    args = ap.parse_args()

    extra = [*(["--checkpoint", args.checkpoint] if args.checkpoint else []),
             *(["--steps", str(args.steps)] if args.steps else []), *(["--no-batch"] if args.no_batch else [])]
    cache = args.cache or Path(tempfile.mkdtemp(prefix="dimgestor-onnx-start-"))
    load_before, code = load_average(), code_version()
    runs, torch_runs = [], []
    try:
        for i in range(1 + args.warm):
            runs.append(start(cache, extra, args.timeout))
            print(f"start {i + 1}: {'exported' if runs[-1]['exported'] else 'cached'}, first frame after "
                  f"{runs[-1]['first_frame_s']} s", flush=True)
        for i in range(args.torch):
            torch_runs.append(start(None, extra, args.timeout))
            print(f"torch start {i + 1}: first frame after {torch_runs[-1]['first_frame_s']} s", flush=True)
    finally:
        if args.cache is None:
            shutil.rmtree(cache, ignore_errors=True)
    warm = sorted(r["first_frame_s"] for r in runs if not r["exported"])
    result = {
        "when": utc_now(), "code": code, "machine": describe_device("cpu"), "argv": sys.argv[1:],
        "load_average_before": load_before, "load_average_after": load_average(), "notes": args.note,
        "model": args.checkpoint or "embedded default", "command": "dimgestor serve --backend onnxruntime "
        "--onnx-cache DIR --ws 127.0.0.1:0 " + " ".join(extra),
        "first_start_s": runs[0]["first_frame_s"], "first_start_exported": runs[0]["exported"],
        "first_start_export_s": round(runs[0]["ws_address_s"] - runs[0]["cache_line_s"], 1)
        if runs[0]["exported"] else None,
        "cached_start_s_median": warm[len(warm) // 2] if warm else None,
        "cached_start_s_max": warm[-1] if warm else None, "target_cached_start_s": TARGET_S,
        "torch_start_s_median": sorted(r["first_frame_s"] for r in torch_runs)[len(torch_runs) // 2]
        if torch_runs else None,
        "runs": runs, "torch_runs": torch_runs,
    }
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
