"""The viewer's local mode in headless Chromium: one stream's per-window cost and real-time factor of the embedded
default model run by onnxruntime-web (WebAssembly, in the page's Web Worker) at K = 1, 4, 8, 100 ms windows.

For each K the model is exported (`dimgestor web`'s folder: frame_step.onnx, manifest.json, web.json) and served
by `dimgestor web`'s server; for each thread setting a fresh page (`/?local=model/&threads=N`, 0 = onnxruntime-web's
default, which is 1 unless the page is cross-origin isolated and then min(4, ceil(cores / 2))) runs `--calls` calls
of the frame step on a fresh stream of noise through `window.dimgestorLocal.bench` and reports each call's time
(worker side: the graph call, the state carried, no drawing). The warm-up calls and the first two real ones are left
out. Result: median, p90 and mean ms per window, the real-time factor (mean / window), load time.

Talk (`--talk-s`, per K, onnxruntime-web's default threads): a fresh page whose microphone is Chromium's fake one
fed the demo speech WAV (looped) talks for that long; every 250 ms, in an animation frame after the page's own
(which picks the pose and draws it), it reads the HUD's speech -> motion readout (`dimgestor.delayMs`: measured
from when each microphone chunk reached the page, or an estimate where the page gives none: `hud_measured`), the
playout buffer (`bufferMs`: newest frame's pts - the pts drawn) and, independent of the page's readout, the lag
on screen: the pts of all the audio handed to the model by then minus the pts drawn then. The first `--settle`
seconds are left out. `--web DIR` serves another copy of clients/web (e.g. an older commit's, with its
node_modules) to measure before / after a change.

    python benchmarks/web_local.py                        # K = 1, 4, 8; threads 1, 2 and the default; Talk 30 s
    python benchmarks/web_local.py --exports /tmp/web     # keep the exported graphs for the next run

Chromium is driven over the DevTools protocol by the tests' `Browser` (tests/helpers/browser.py).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
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
    p.add_argument("--talk-s", type=float, default=30, help="seconds of Talk per K (0: none)")
    p.add_argument("--settle", type=float, default=5, help="Talk's first seconds left out")
    p.add_argument("--web", type=Path, default=None, help="serve this clients/web folder instead of the repo's")
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


@contextmanager
def local_page(folder: Path, threads: int, tmp: Path, web: Path | None, flags: tuple[str, ...] = ()):
    """A fresh headless Chromium on `/?local=model/` served by `dimgestor web`'s server, the model loaded."""
    sys.path.insert(0, str(REPO / "tests"))
    from helpers.browser import Browser

    import streamer.web
    from streamer.web import make_server

    if web is not None:
        streamer.web.WEB_DIR = web.resolve()  # (make_server mounts it at "/")
    server = make_server("127.0.0.1", 0, folder)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    profile = Path(tempfile.mkdtemp(dir=tmp))
    url = f"http://127.0.0.1:{server.server_address[1]}/?local=model/&threads={threads}"
    browser = Browser(profile, url, flags)
    try:
        browser.wait_page()
        browser.wait_for("window.dimgestorLocal && window.dimgestorLocal.info", 180, "the local model")
        yield browser
    finally:
        browser.close()
        server.shutdown()
        server.server_close()


def measure(folder: Path, threads: int, calls: int, tmp: Path, web: Path | None) -> dict:
    with local_page(folder, threads, tmp, web) as browser:
        info = browser.eval("window.dimgestorLocal.info")
        cores = browser.eval("navigator.hardwareConcurrency")
        bench = browser.eval(f"window.dimgestorLocal.bench({calls})")
    skip = info["call"]["warmup_calls"] + 2
    ms = bench["ms"][skip:]
    window_ms = 1000 * bench["samplesPerCall"] / bench["sampleRate"]
    return {"threads_asked": threads, "threads": info["threads"], "cross_origin_isolated": info["crossOriginIsolated"],
            "hardware_concurrency": cores, "load_ms": info["loadMs"], "window_ms": window_ms, "windows": len(ms),
            "ms_p50": percentile_ms([m / 1000 for m in ms], 50), "ms_p90": percentile_ms([m / 1000 for m in ms], 90),
            "ms_mean": float(np.mean(ms)), "rtf": float(np.mean(ms) / window_ms)}


# Read in an animation frame callback after the page's own, which picked the pose drawn in this frame.
TALK_READ = """new Promise((done) => requestAnimationFrame(() => {
  const d = window.dimgestor, l = window.dimgestorLocal;
  done({t: performance.now() / 1000, hud: d.delayMs, measured: !!d.delayMeasured, buffer: d.bufferMs,
        shown: d.shownFrame ? d.shownFrame.pts : null, sent: l.audioS + l.backlogS, dropped: l.droppedS,
        rtf: l.rtf, frameMs: d.frameMs});
}))"""


def measure_talk(folder: Path, seconds: float, settle: float, tmp: Path, web: Path | None) -> dict:
    """Talk through the fake microphone for `seconds`: the HUD's readout, the buffer and the lag on screen."""
    sys.path.insert(0, str(REPO / "tests"))
    from helpers.clients import SPEECH_WAV

    flags = ("--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
             f"--use-file-for-fake-audio-capture={SPEECH_WAV}")
    with local_page(folder, 0, tmp, web, flags) as browser:
        browser.eval("window.dimgestor.talk()", user_gesture=True)
        browser.wait_for("window.dimgestor.shownFrame", 60, "a frame from the microphone on screen")
        t0, reads = time.monotonic(), []
        while time.monotonic() - t0 < seconds:
            time.sleep(0.25)
            reads.append(browser.eval(TALK_READ))
        clock = browser.eval("(({underruns, catchUps, marginS, baseMarginS, slackS}) => ({underruns, catchUps, marginS, "
                             "baseMarginS, slackS}))(window.dimgestor.clock)")
        browser.eval("window.dimgestor.stopTalk()")
    start = reads[0]["t"] + settle
    kept = [r for r in reads if r["t"] >= start and r["shown"] is not None]
    hud = [r["hud"] / 1000 for r in kept if r["hud"] is not None]
    buffer = [r["buffer"] / 1000 for r in kept if r["buffer"] is not None]
    lag = [r["sent"] - r["shown"] for r in kept]
    return {"threads_asked": 0, "seconds": seconds, "settle_s": settle, "reads": len(kept),
            "hud_measured": float(np.mean([r["measured"] for r in kept])) if kept else float("nan"),
            "hud_ms_p50": percentile_ms(hud, 50), "hud_ms_p90": percentile_ms(hud, 90),
            "lag_ms_p50": percentile_ms(lag, 50), "lag_ms_p90": percentile_ms(lag, 90),
            "buffer_ms_p50": percentile_ms(buffer, 50), "buffer_ms_p90": percentile_ms(buffer, 90),
            "rtf": kept[-1]["rtf"] if kept else float("nan"), "dropped_s": reads[-1]["dropped"],
            "page_frame_ms": float(np.mean([r["frameMs"] for r in kept])) if kept else float("nan"),
            "clock_at_end": clock}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common import save_panels

    rows = result["results"]
    settings = sorted({r["threads_asked"] for r in rows})
    ks = sorted({r["steps"] for r in rows})
    talk = result.get("talk", [])
    fig, axes = plt.subplots(1, 3 if talk else 2, figsize=(13.5 if talk else 9, 3.4))
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
    if talk:
        hud = "HUD speech->motion" + ("" if all(r["hud_measured"] == 1 for r in talk) else " (estimated)")
        kinds = [("hud", hud), ("lag", "audio sent - pts drawn"), ("buffer", "playout buffer")]
        width = 0.8 / len(kinds)
        for i, (k, label) in enumerate(kinds):
            p50 = [r[f"{k}_ms_p50"] for r in talk]
            p90 = [r[f"{k}_ms_p90"] for r in talk]
            axes[2].bar(np.arange(len(talk)) + (i - 1) * width, p50, width, yerr=[[0] * len(talk), np.subtract(p90, p50)],
                        capsize=3, label=f"{label}: p50, p90 whisker")
        axes[2].set_xticks(np.arange(len(talk)), [f"Talk K={r['steps']}" for r in talk])
        axes[2].set_ylabel("ms")
        axes[2].legend(fontsize=7)
    browser = result["browser"].split(" built")[0]  # "Chromium N.N.N.N"
    save_panels(fig, axes, f"local mode in headless {browser} (onnxruntime-web WASM), one stream, default model, "
                           f"shared 2-core CPU (load {result['load_average'][0]})", path)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    from streamer.web import prepare_model

    browser = chromium_version()
    rows, talk = [], []
    with tempfile.TemporaryDirectory(prefix="web-bench-") as tmp:
        folder = args.exports or Path(tmp)
        for k in args.steps:
            model = folder / f"default_k{k}_f2"
            t0 = time.perf_counter()
            prepare_model(model, None, steps=k, frames=2)
            print(f"K={k}: model ready in {time.perf_counter() - t0:.0f} s")
            for t in args.threads:
                row = {"steps": k, **measure(model, t, args.calls, Path(tmp), args.web)}
                rows.append(row)
                print(f"K={k}, threads {row['threads']} (asked {t}): p50 {row['ms_p50']:.1f} ms, "
                      f"p90 {row['ms_p90']:.1f} ms, RTF {row['rtf']:.2f}")
            if args.talk_s > 0:
                row = {"steps": k, **measure_talk(model, args.talk_s, args.settle, Path(tmp), args.web)}
                talk.append(row)
                print(f"K={k}, Talk: HUD {row['hud_ms_p50']:.0f} / {row['hud_ms_p90']:.0f} ms (measured "
                      f"{row['hud_measured']:.0%}), lag on screen {row['lag_ms_p50']:.0f} / {row['lag_ms_p90']:.0f} "
                      f"ms, buffer {row['buffer_ms_p50']:.0f} / {row['buffer_ms_p90']:.0f} ms (p50 / p90)")
    import json

    lock = json.loads((REPO / "clients" / "web" / "package-lock.json").read_text())
    ort_web = lock["packages"]["node_modules/onnxruntime-web"]["version"]
    result = {"benchmark": "web_local", "date": utc_now(), "code": code_version(), "argv": args.argv,
              "device": describe_device("cpu"), "browser": f"{browser} headless, onnxruntime-web {ort_web} (wasm)",
              "load_average": load_average(), "note": args.note, "window_ms": 100,
              "model": "embedded default (speech front end, guidance 1.25: 2 rows), 2 frames a call",
              "web": str(args.web) if args.web else "clients/web (this commit)", "results": rows, "talk": talk}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
