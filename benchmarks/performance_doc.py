"""docs/performance.md, written from benchmarks/results/*.json so that its figures cannot drift from them.

    python benchmarks/performance_doc.py            # rewrite docs/performance.md from the results
    python benchmarks/performance_doc.py --check    # exit 1 (and say so) when docs/performance.md is not current

Each section reads one results file, named in `SOURCES` and under its table in the page. When a benchmark is
re-run into another file, point its entry here at that file and rewrite the page. Only the standard library is
used, so the check runs anywhere. The CPU results must all come from one kind of machine (the page names it once);
a file from another machine is refused rather than mixed in silently.
"""

from __future__ import annotations

import argparse
import difflib
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
DOC = REPO / "docs" / "performance.md"

# What each section reads: the current run of each measurement (benchmarks/README.md has their histories).
SOURCES = {
    "windows": "onnx_runtime_windows.json",  # one stream's window, torch against ONNX Runtime, K = 1, 4, 8
    "streams": "onnx_runtime_batched.json",  # streams per process, the default model, every scheduler searched 3x
    "preset": "streaming.json",  # the realtime preset: one stream's RTF, streams per process, the paper preset, memory
    "cost": "model_cost.json",  # the default model's window beside the realtime preset's
    "vmc": "latency.json",  # microphone -> VMC, default and live model, 100 and 200 ms windows
    "vmc_jitter": "latency_vmc_jitter50.json",  # the same with --vmc-jitter-ms 50
    "talk": "latency_talk_worker.json",  # the viewer's Talk button (the newest run of each avatar)
    "gpu": "onnx_cuda.json",  # many streams on one GPU
    "face": "face.json",  # a Session window with and without the face; generate with and without its CSV
    "face_streams": "face_streams.json",  # streams per process with a face on each, against none
    "face_trials": "serving_folded.json",  # serving trials at fixed counts, a face on each (its "after" code)
    "blas": "serving_issue50.json",  # those trials: serve's one BLAS thread, numpy's pool, serve before issue 50
    "face_process": "serving_face_process.json",  # those trials: the faces on the inference thread or in a child
}
CPU_SOURCES = ("windows", "streams", "preset", "cost", "vmc", "vmc_jitter", "talk")  # one machine; the face's
# cost is a ratio of two arms of one run, whose machine its section names


class ResultsError(ValueError):
    """A results file that is missing, malformed, or from another machine than the rest."""


def load(results: Path) -> dict[str, dict]:
    out = {}
    for key, name in SOURCES.items():
        path = results / name
        try:
            out[key] = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ResultsError(f"{path}: results file not found (named in SOURCES[{key!r}])") from None
        except json.JSONDecodeError as e:
            raise ResultsError(f"{path}: not JSON: {e}") from None
    return out


def machine(device: str) -> str:
    """'CPU AMD EPYC, 2 cores visible, torch 2.13.0+cpu (1 intra-op threads), ...' -> 'AMD EPYC, 2 cores'."""
    cpu, _, rest = device.partition(",")
    cores = rest.split(",")[0].strip().replace(" visible", "")
    return f"{cpu.removeprefix('CPU ').strip()}, {cores}"


def devices(key: str, data: dict) -> list[str]:
    """Every device string a results file records (latency files record one per run)."""
    found = [data["device"]] if "device" in data else []
    found += [r["device"] for r in data.get("runs", []) if "device" in r]
    if not found:
        raise ResultsError(f"{SOURCES[key]}: records no device")
    return found


def cpu_machine(r: dict[str, dict]) -> str:
    seen = {(machine(d), SOURCES[k]) for k in CPU_SOURCES for d in devices(k, r[k])}
    names = sorted({m for m, _ in seen})
    if len(names) != 1:
        raise ResultsError("the CPU results come from different machines: "
                           + "; ".join(f"{m} ({', '.join(sorted(f for n, f in seen if n == m))})" for m in names))
    return names[0]


def measured_on(device: str, r: dict[str, dict]) -> str:
    """The machine a result came from, or "the machine above" where it is the page's CPU machine (named once)."""
    return "the machine above" if machine(device) == cpu_machine(r) else machine(device)


def source(key: str) -> str:
    return f"*From `benchmarks/results/{SOURCES[key]}`.*"


def table(head: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]


def ms(x: float) -> str:
    return f"{x:.1f}"


def rtf(x: float) -> str:
    return f"{x:.3f}"


# ---- sections ----------------------------------------------------------------------------------------------------

def one_stream(r: dict[str, dict]) -> list[str]:
    w = r["windows"]
    rows = [[str(x["steps"]), ms(x["torch"]["ms_p50"]), rtf(x["torch"]["rtf"]), ms(x["onnxruntime"]["ms_p50"]),
             rtf(x["onnxruntime"]["rtf"]), f"{x['ratio_p50']:.2f}"]
            for x in sorted(w["results"], key=lambda x: x["steps"])]
    worst = max(x["max_abs_diff"] for x in w["results"])
    return ["## One stream", "",
            f"The embedded default model, {w['window_ms']} ms windows, one thread. The real-time factor (RTF) is "
            "compute time over audio time: 0.1 means a window costs a tenth of its length.", "",
            *table(["DDIM steps K", "torch ms a window (median)", "torch RTF (mean)", "ONNX Runtime ms",
                    "ONNX Runtime RTF (mean)", "ONNX Runtime / torch"], rows), "",
            f"The two backends' frames agree within {worst:.0e} (normalized features).", "", source("windows"), ""]


def streams(r: dict[str, dict]) -> list[str]:
    s = r["streams"]["streams"][0]
    label = {"torch_batched": "torch, batched (`dimgestor serve`)",
             "torch_unbatched": "torch, each window alone (`--no-batch`)",
             "onnxruntime_batched": "ONNX Runtime, batched (`--backend onnxruntime`)",
             "onnxruntime": "ONNX Runtime, each window alone (`--backend onnxruntime --no-batch`)"}
    rows = []
    for key, name in label.items():
        e = s[key]
        found = [x["max_realtime_streams"] if isinstance(x, dict) else x for x in e.get("searches", [])]
        span = f" ({min(found)}-{max(found)})" if len(set(found)) > 1 else ""
        rows.append([name, f"{e['max_realtime_streams']}{span}"])
    n = max(len(s[k].get("searches", [])) for k in label)
    p = r["preset"]["max_realtime_streams_by_k"]
    capped = {k: v["batched"].get("capped", False) for k, v in r["preset"]["streams"]["by_k"].items()}
    ks = sorted(p["batched"], key=int)
    preset_rows = [[k, (">= " if capped.get(k) else "") + str(p["batched"][k]), str(p["unbatched"][k])] for k in ks]
    return ["## Real-time streams per process", "",
            f"How many live streams one serving process keeps in real time on {s['cores']} cores: the embedded default "
            f"model, K = {s['steps']}, {r['streams']['window_ms']} ms windows, clients joining at random moments. "
            f"Each count was searched {n} times, the configurations taking turns: the median, the range in brackets.", "",
            *table(["backend, scheduler", "streams"], rows), "", source("streams"), "",
            "A model of the `realtime` preset's size with the log-mel front end and no guidance (what `dimgestor train "
            "--preset realtime` makes without `--cond-drop` or `--set frontend=speech`) costs about half as much per "
            "stream (the next section compares the two), on torch:", "",
            *table(["K", "batched", "each window alone"], preset_rows), "", source("preset"), ""]


def model_cost(r: dict[str, dict]) -> list[str]:
    c = r["cost"]
    rows = [[str(x["steps"]), str(x["batch"]), ms(x["default"]["ms_p50"]), ms(x["default_unguided"]["ms_p50"]),
             ms(x["preset"]["ms_p50"]), f"{x['ratio_p50']:.2f}"]
            for x in sorted(c["rows"], key=lambda x: (x["steps"], x["batch"]))]
    return ["## The default model's cost", "",
            "The embedded default model runs one network row per stream and step, in 2 steps: the classifier-free "
            "guidance of the model it was distilled from is folded into it, and its steps halved (MODEL_CARD.md). "
            "That guided model ran a second, "
            "unconditional row per stream (guidance 1.25); both have a speech front end that keeps running "
            "statistics. One batched call for B streams of the guided model, with its two rows and with one (what a "
            f"4-step student of it costs; the default's 2 steps cost less), {c['window_ms']} ms windows, one thread, "
            "median ms:", "",
            *table(["K", "streams B", "two rows (guidance 1.25)", "one row", "`realtime` preset",
                    "two rows / preset"], rows), "", source("cost"), ""]


def presets(r: dict[str, dict]) -> list[str]:
    p = r["preset"]
    sweep = {(x["preset"], x["steps"], x["window_ms"]): x for x in p["results"]}
    ks = sorted({k for (name, k, w) in sweep if name == "realtime" and w == 100})
    one = ", ".join(f"{rtf(sweep['realtime', k, 100]['rtf'])} at K = {k}" for k in ks)
    paper = {(x["steps"], x["window_ms"]): x for x in p["paper"]["rows"]}
    k, w = max(paper)
    hour = p["hour_run"]
    return ["## Presets", "",
            f"- `realtime` preset, one stream, 100 ms windows, one thread: RTF {one}.",
            f"- `paper` preset ({p['paper']['params'] / 1e6:.0f} M parameters), one stream, K = {k}, {w / 1000:g} s "
            f"windows, {p['paper']['threads']} threads: RTF {rtf(paper[k, w]['rtf'])} in fp32, "
            f"{rtf(p['paper']['bf16']['rtf'])} with bf16 matmuls (`torch.autocast`).",
            f"- Memory: one stream fed {hour['audio_s'] / 3600:g} h of audio holds {hour['rss_mb_start']:.1f} MB "
            f"(process RSS) after warm-up and {hour['rss_mb_after_1h']:.1f} MB at the end.", "", source("preset"), ""]


def latency(r: dict[str, dict]) -> list[str]:
    runs = [x for key in ("vmc", "vmc_jitter") for x in r[key]["runs"] if x["path"] == "vmc"]
    rows = [[x["model"], str(x["window_ms"]), f"{x['vmc_jitter_buffer_ms']:g}", f"{x['lookahead_s'] * 1000:.0f}",
             f"{x['server_side']['median_ms']:.0f} ({x['server_side']['p90_ms']:.0f})"]
            for x in sorted(runs, key=lambda x: (x["model"], x["window_ms"], -x["vmc_jitter_buffer_ms"]))]
    onsets = sorted({x["onsets"] for x in runs})
    spoken = " or ".join(sorted({f"{x['seconds']:g} s" for x in runs}))
    jitter = " and ".join(sorted({f"`--vmc-jitter-ms {x['vmc_jitter_ms']:g}`" for x in r["vmc_jitter"]["runs"]
                                  if x["path"] == "vmc"}))
    newest = {}  # (avatar, window ms) -> its newest run
    for x in r["talk"]["runs"]:
        key = (x.get("avatar"), x["window_ms"])
        if x["path"] == "talk" and key[0] and x["date"] >= newest.get(key, {"date": ""})["date"]:
            newest[key] = x
    talk = [[a, x["checkpoint"] or "default", str(w), f"{x['total']['median_ms']:.0f} ({x['total']['p90_ms']:.0f})"]
            for (a, w), x in sorted(newest.items())]
    return ["## Latency: speech to motion", "",
            "**Microphone to VMC** (`dimgestor serve --source mic --vmc ...`): from a sound reaching the server to its "
            f"VMC bundle sent, median (p90) in ms over {onsets[0]}-{onsets[-1]} speech onsets of a {spoken} run. "
            "The microphone's own "
            "input latency comes before it. *Algorithmic* is the model's share: one 50 ms frame plus its audio "
            "lookahead.", "",
            *table(["model", "window ms", "VMC jitter buffer ms", "algorithmic ms", "microphone -> VMC sent"], rows),
            "",
            f"*From `benchmarks/results/{SOURCES['vmc']}`; the {jitter} row from "
            f"`benchmarks/results/{SOURCES['vmc_jitter']}`.*", "",
            "**Talk in the browser viewer**: from a microphone chunk reaching the "
            "page to the first page frame that presents its motion, median (p90) in ms, in headless Chromium drawing "
            "WebGL in software (a GPU-drawn page presents sooner).", "",
            *table(["viewer avatar", "model", "window ms", "speech -> motion on screen"], talk), "", source("talk"), ""]


def gpu(r: dict[str, dict]) -> list[str]:
    g = r["gpu"]
    rows = [[str(x["batch"]), ms(x["torch"]["ms_p50"]) + ("" if x["torch"]["realtime"] else " (not real time)"),
             ms(x["onnxruntime"]["ms_p50"]) + ("" if x["onnxruntime"]["realtime"] else " (not real time)")]
            for x in sorted(g["rows"], key=lambda x: x["batch"])]
    best = g["largest_realtime_batch"]
    # what a GPU does in the benchmark's own loop; `serve --device cuda` through real clients is not measured yet
    # (issue 50: where a GPU machine is lent)
    return ["## Many streams on one GPU (a benchmark's own loop)", "",
            "`dimgestor serve --device cuda` runs the model on an NVIDIA GPU (torch's CUDA build; with `--backend "
            "onnxruntime`, the onnxruntime-gpu package's CUDA provider), the windows of all streams batched as on "
            "the CPU; how many avatars it keeps through `serve` itself is not measured yet. What one GPU can do "
            "was measured by `benchmarks/onnx_cuda.py`, which runs the same graphs in its own loop: "
            f"on an {g['device'].split(',')[0]}, the embedded default model, K = {g['steps']}, "
            f"{g['window_ms']:g} ms windows, B streams in lockstep, the median ms of a round from the host's audio to "
            f"the host's frames (real time: under {g['window_ms']:g} ms). That loop keeps **{best['onnxruntime']:,} "
            f"streams on ONNX Runtime** (its CUDA provider, states kept on the GPU) and **{best['torch']:,} on "
            "torch**.", "",
            *table(["streams B", "torch CUDA ms a round", "ONNX Runtime CUDA ms a round"], rows), "", source("gpu"), ""]


def face(r: dict[str, dict]) -> list[str]:
    c = r["face"]["compute"]
    rows = [["body", ms(c["body"]["ms_p50"]), ms(c["body"]["cpu_ms_mean"])],
            ["body and face", ms(c["body_face"]["ms_p50"]), ms(c["body_face"]["cpu_ms_mean"])]]
    if "body_face_pocketsphinx" in c:
        rows.append(["body and face, `--face-listener pocketsphinx`", ms(c["body_face_pocketsphinx"]["ms_p50"]),
                     ms(c["body_face_pocketsphinx"]["cpu_ms_mean"])])
    if "body_face_both" in c:
        rows.append(["body and face, `--face-listener net+pocketsphinx`", ms(c["body_face_both"]["ms_p50"]),
                     ms(c["body_face_both"]["cpu_ms_mean"])])
    other = (f"; pocketsphinx's listener +{100 * c['added_cpu_pocketsphinx']:.0f} %"
             if "added_cpu_pocketsphinx" in c else "")
    other += (f", both together +{100 * c['added_cpu_both']:.0f} %" if "added_cpu_both" in c else "")
    return ["## The face's cost", "",
            "The face's listener runs on each stream that has a face (the server's own source, and the clients "
            f"that ask for one), beside the model: one `Session` window of the embedded default model, K = {c['steps']}, "
            f"{c['window_ms']} ms windows, one thread, measured on {measured_on(r['face']['device'], r)}. Streams "
            "without a face (`--face none`, or clients that do not ask) cost what the streams-per-process counts "
            "above say; "
            f"each stream with one costs the difference more (+{100 * c['added_cpu']:.0f} % CPU on this model"
            f"{other}).{generate(r)}", "",
            *table(["", "ms a window (median)", "CPU ms a window (mean)"], rows), "", source("face"), "",
            *face_batched(r)]


def generate(r: dict[str, dict]) -> str:
    g = r["face"].get("generate")
    return (f" `dimgestor generate --face-csv` takes {g['ratio']:.2f}x the CPU of `generate` ({g['audio_s']:.0f} s "
            "of speech).") if g else ""


def face_batched(r: dict[str, dict]) -> list[str]:
    """The faces of a batch's streams run together: streams per process with a face on each, and `generate`."""
    f, lines = r["face_streams"], []
    arms = f["arms"]
    lines.append(f"A batch's faces are made together (the listener's layers as one product for all its streams): "
                 f"one process kept {arms['face']['max_realtime_streams']} real-time streams with a face on each "
                 f"against {arms['no face']['max_realtime_streams']} without ({f['ratio']:.2f} as many; K = "
                 f"{f['steps']}, {f['window_ms']} ms windows, the batcher on {f['threads']} torch "
                 f"thread{'s' if f['threads'] > 1 else ''} as `serve` gives it here, measured on "
                 f"{measured_on(f['device'], r)}).")
    lines += ["", source("face_streams"), "", *face_trials(r), *blas(r), *face_process(r)]
    return lines


def face_trials(r: dict[str, dict]) -> list[str]:
    """Serving trials at fixed counts with a face on every session (the newer code of the file's two): the most
    streams kept in real time in every trial of a count, and the most in any."""
    t = r["face_trials"]
    runs = [x for x in t["trials"] if x["code"] == "after"]
    counts = sorted({x["streams"] for x in runs})
    every = [n for n in counts if all(x["ok"] for x in runs if x["streams"] == n)]
    some = [n for n in counts if any(x["ok"] for x in runs if x["streams"] == n)]
    per = len(runs) // len(counts)
    line = (f"Served at fixed counts (K = {runs[0]['steps']}, {t['window_ms']} ms windows, {runs[0]['seconds']:g} s "
            f"trials, {per} a count, the face on every session, the batcher on one torch thread, measured on "
            f"{measured_on(t['device'], r)}), one process kept "
            f"{max(every)} streams with a face in real time in every trial")
    if max(some) > max(every):
        line += f", and {max(some)} in some"
    return [line + ".", "", source("face_trials"), ""]


def blas(r: dict[str, dict]) -> list[str]:
    """`serve`'s numpy BLAS on one thread against numpy's own pool, in fixed-count trials with a face: the most
    streams each kept in every trial, alone and beside a busy core, and the process's CPU a trial."""
    t = r["blas"]

    def kept(arm: str, neighbour: bool) -> str:
        runs = [x for x in t["trials"] if x["arm"] == arm and x["neighbour"] == neighbour]
        counts = sorted({x["streams"] for x in runs})
        every = [n for n in counts if all(x["ok"] for x in runs if x["streams"] == n)]
        return str(max(every)) if every else f"fewer than {counts[0]}"

    def cpu(arm: str) -> str:
        xs = sorted(x["process_cpu_s"] for x in t["trials"] if x["arm"] == arm and not x["neighbour"])
        return f"{xs[0]:.0f}" if round(xs[0]) == round(xs[-1]) else f"{xs[0]:.0f}-{xs[-1]:.0f}"

    steps = sorted({x["model_steps"] for x in t["trials"] if x["arm"] != "before" and "model_steps" in x})
    k = f"the default model at K = {steps[0]}, " if len(steps) == 1 else ""
    line = ("`dimgestor serve` runs numpy's BLAS (the faces' products) on one thread, not on the pool numpy starts "
            f"by itself (a thread a core, spinning between products). In trials as above ({k}"
            f"{t['seconds']:g} s, a face on every session, measured on {measured_on(t['device'], r)}), one process "
            f"kept {kept('one thread', False)} streams with a face in every trial against {kept('pool', False)} with "
            f"the pool, and used {cpu('one thread')} s of CPU a trial against {cpu('pool')} s")
    if any(x["neighbour"] for x in t["trials"]):
        line += (f"; beside a busy loop on one core (another program on the machine) it kept "
                 f"{kept('one thread', True)} against {kept('pool', True)}")
    line += "."
    if any(x["arm"] == "before" for x in t["trials"]):
        b = next(x for x in t["trials"] if x["arm"] == "before")
        rows = (f"guided, K = {b['model_steps']}, two network rows a stream and step" if b["guidance"] != 1
                else f"K = {b['model_steps']}, one network row a stream and step")
        line += (f" In the same run, `serve` as it was before these changes (the default model then: {rows}; numpy's "
                 f"pool) kept {kept('before', False)}.")
    return [line, "", source("blas"), ""]


def face_process(r: dict[str, dict]) -> list[str]:
    """`serve --face-process` against the faces on the inference thread (and serve before these changes), in
    fixed-count trials with a face on every session: the most streams each kept in every trial of that count and
    of every smaller one."""
    t = r["face_process"]

    def kept(arm: str) -> str:  # (the most kept in every trial of that count and of every count below it)
        runs = [x for x in t["trials"] if x["arm"] == arm and not x["neighbour"]]
        counts = sorted({x["streams"] for x in runs})
        held = [n for k, n in enumerate(counts) if all(x["ok"] for x in runs if x["streams"] in counts[:k + 1])]
        return str(max(held)) if held else f"fewer than {counts[0]}"

    now = [x for x in t["trials"] if x["arm"] != "before"]
    per = len(now) // len({(x["arm"], x["streams"]) for x in now})
    line = ("`dimgestor serve --face-process` makes the sessions' faces in a second process, on a core of their own, "
            "while the inference thread steps the bodies (the face was about a third of that thread's work, and "
            "the GIL keeps a second thread from sharing it). In trials as above (the default model at K = "
            f"{now[0]['model_steps']}, {t['seconds']:g} s, {per} a count, a face on every session, measured on "
            f"{measured_on(t['device'], r)}), one process kept {kept('face process')} streams with a face in every "
            f"trial, against {kept('one thread')} with the faces on the inference thread")
    if any(x["arm"] == "before" for x in t["trials"]):
        line += f"; in the same run, `serve` as it was before these changes kept {kept('before')}"
    return [line + ".", "", source("face_process"), ""]


def render(results: Path = RESULTS) -> str:
    r = load(results)
    head = ["# Performance", "",
            "<!-- Written by benchmarks/performance_doc.py from benchmarks/results/: do not edit by hand. -->", "",
            "What the engine costs, as last measured. The CPU figures come from one machine: "
            f"{cpu_machine(r)}, no GPU, torch's CPU build. Each table says which results file it comes from; how "
            "each benchmark works, how to re-run it and the history of its numbers are in "
            "[benchmarks/README.md](../benchmarks/README.md). "
            "After a benchmark is re-run, `python benchmarks/performance_doc.py` rewrites this page "
            "(`--check` says whether it is current). Most figures of the default model were measured on the models "
            "it was distilled from (K = 4 or 8, two network rows a stream and step, or one): the model it serves now, "
            "K = 2 of one row, costs less a window than they say. The sections that measured it say K = 2.", ""]
    body = one_stream(r) + streams(r) + model_cost(r) + face(r) + presets(r) + latency(r) + gpu(r)
    return "\n".join(head + body).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="write docs/performance.md from benchmarks/results/*.json")
    ap.add_argument("--check", action="store_true", help="do not write: exit 1 when the page differs from the results")
    ap.add_argument("--results", type=Path, default=RESULTS, help="results folder")
    ap.add_argument("--doc", type=Path, default=DOC, help="the page to write or check")
    a = ap.parse_args(argv)
    try:
        text = render(a.results)
    except (ResultsError, KeyError, TypeError, IndexError) as e:
        print(f"performance_doc: cannot render: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    if a.check:
        current = a.doc.read_text(encoding="utf-8") if a.doc.is_file() else ""
        if current == text:
            return 0
        diff = difflib.unified_diff(current.splitlines(), text.splitlines(), str(a.doc), "rendered", lineterm="", n=0)
        print(f"{a.doc} is not what the results say; run `python benchmarks/performance_doc.py`:", file=sys.stderr)
        print("\n".join(list(diff)[:40]), file=sys.stderr)
        return 1
    a.doc.write_text(text, encoding="utf-8")
    print(f"wrote {a.doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
