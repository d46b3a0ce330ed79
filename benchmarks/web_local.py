"""The viewer's local mode in headless Chromium: one stream's per-window cost and real-time factor of the embedded
default model run by onnxruntime-web (WebAssembly, in the page's Web Worker) at K = 1, 4, 8, 100 ms windows.

For each K the model is exported (`streamer web`'s folder: frame_step.onnx, manifest.json, web.json) and served
by `streamer web`'s server; for each thread setting a fresh page (`/?local=model/&threads=N`, 0 = onnxruntime-web's
default, which is 1 unless the page is cross-origin isolated and then min(4, ceil(cores / 2))) runs `--calls` calls
of the frame step on a fresh stream of noise through `window.dimgestorLocal.bench` and reports each call's time
(worker side: the graph call, the state carried, no drawing). The warm-up calls and the first two real ones are left
out. Result: median, p90 and mean ms per window, the real-time factor (mean / window), load time.

    python benchmarks/web_local.py                        # K = 1, 4, 8; threads 1, 2 and the default
    python benchmarks/web_local.py --exports /tmp/web     # keep the exported graphs for the next run

Chromium is driven over the DevTools protocol by the tests' `Browser` (tests/test_clients_web.py).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, percentile_ms, utc_now, write_json

REPO = Path(__file__).resolve().parents[1]


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, nargs="+", default=[1, 4, 8], help="DDIM steps K")
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2, 0],
                   help="onnxruntime-web threads (0: its default for this machine)")
    p.add_argument("--calls", type=int, default=60, help="100 ms windows per measurement")
    p.add_argument("--exports", type=Path, default=None,
                   help="folder of the exported graphs (reused when present; default: a temporary folder)")
    p.add_argument("--out", type=Path, default=RESULTS / "web_local.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def chromium_version() -> str:
    import shutil
    import subprocess

    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        raise SystemExit("chromium is needed (Debian: apt-get install chromium)")
    return subprocess.run([exe, "--version"], capture_output=True, text=True).stdout.strip()


def measure(folder: Path, threads: int, calls: int, tmp: Path) -> dict:
    sys.path.insert(0, str(REPO / "tests"))
    from test_clients_web import Browser

    from streamer.web import make_server

    server = make_server("127.0.0.1", 0, folder)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    profile = Path(tempfile.mkdtemp(dir=tmp))
    url = f"http://127.0.0.1:{server.server_address[1]}/?local=model/&threads={threads}"
    browser = Browser(profile, url)
    try:
        browser.wait_page()
        browser.wait_for("window.dimgestorLocal && window.dimgestorLocal.info", 180, "the local model")
        info = browser.eval("window.dimgestorLocal.info")
        cores = browser.eval("navigator.hardwareConcurrency")
        bench = browser.eval(f"window.dimgestorLocal.bench({calls})")
    finally:
        browser.close()
        server.shutdown()
        server.server_close()
    skip = info["call"]["warmup_calls"] + 2
    ms = bench["ms"][skip:]
    window_ms = 1000 * bench["samplesPerCall"] / bench["sampleRate"]
    return {"threads_asked": threads, "threads": info["threads"], "cross_origin_isolated": info["crossOriginIsolated"],
            "hardware_concurrency": cores, "load_ms": info["loadMs"], "window_ms": window_ms, "windows": len(ms),
            "ms_p50": percentile_ms([m / 1000 for m in ms], 50), "ms_p90": percentile_ms([m / 1000 for m in ms], 90),
            "ms_mean": float(np.mean(ms)), "rtf": float(np.mean(ms) / window_ms)}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common import save_panels

    rows = result["results"]
    settings = sorted({r["threads_asked"] for r in rows})
    ks = sorted({r["steps"] for r in rows})
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    width = 0.8 / len(settings)
    for i, t in enumerate(settings):
        sel = {r["steps"]: r for r in rows if r["threads_asked"] == t}
        p50 = [sel[k]["ms_p50"] for k in ks]
        p90 = [sel[k]["ms_p90"] for k in ks]
        label = f"threads {sel[ks[0]]['threads']}" + (" (default)" if t == 0 else "")
        axes[0].bar(np.arange(len(ks)) + (i - (len(settings) - 1) / 2) * width, p50, width,
                    yerr=[[0] * len(ks), np.subtract(p90, p50)], capsize=3, label=f"{label}: p50, p90 whisker")
        axes[1].plot(ks, [sel[k]["rtf"] for k in ks], "o-", label=label)
    axes[0].set_xticks(np.arange(len(ks)), [f"K={k}" for k in ks])
    axes[0].set_ylabel("ms per 100 ms window")
    axes[1].axhline(0.5, color="k", lw=1, ls="--", label="target 0.5")
    axes[1].set_xlabel("K")
    axes[1].set_ylabel("real-time factor (mean)")
    axes[1].set_ylim(0, max(1.1, max(r["rtf"] for r in rows) * 1.1))
    browser = result["browser"].split(" built")[0]  # "Chromium N.N.N.N"
    save_panels(fig, axes, f"local mode in headless {browser} (onnxruntime-web WASM), one stream, default model, "
                           f"shared 2-core CPU (load {result['load_average'][0]})", path)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    from streamer.web import prepare_model

    browser = chromium_version()
    rows = []
    with tempfile.TemporaryDirectory(prefix="web-bench-") as tmp:
        folder = args.exports or Path(tmp)
        for k in args.steps:
            model = folder / f"default_k{k}_f2"
            t0 = time.perf_counter()
            prepare_model(model, None, steps=k, frames=2)
            print(f"K={k}: model ready in {time.perf_counter() - t0:.0f} s")
            for t in args.threads:
                row = {"steps": k, **measure(model, t, args.calls, Path(tmp))}
                rows.append(row)
                print(f"K={k}, threads {row['threads']} (asked {t}): p50 {row['ms_p50']:.1f} ms, "
                      f"p90 {row['ms_p90']:.1f} ms, RTF {row['rtf']:.2f}")
    import json

    lock = json.loads((REPO / "clients" / "web" / "package-lock.json").read_text())
    ort_web = lock["packages"]["node_modules/onnxruntime-web"]["version"]
    result = {"benchmark": "web_local", "date": utc_now(), "code": code_version(), "argv": args.argv,
              "device": describe_device("cpu"), "browser": f"{browser} headless, onnxruntime-web {ort_web} (wasm)",
              "load_average": load_average(), "note": args.note, "window_ms": 100,
              "model": "embedded default (speech front end, guidance 1.25: 2 rows), 2 frames a call",
              "results": rows}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
