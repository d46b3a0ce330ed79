"""The speaking face (`dimgestor.face`) on real speech: issue 37's targets, the candidates beside it, blinks, cost.

mouth    every phone-aligned clip (`../shared/data/phone_aligned_speech`: BEAT2's "scott", a speaker the default
         model never heard, two takes; two real-world speakers), each streamed live in `--chunk-ms` pieces, scored
         frame by frame against the forced alignment with `dimgestor.face.evaluate.mouth_scores` (openness r, vowel
         class top-1 and mean recall, lips closed at M/B/P centres, rest in silences); `held_out`: the shipped
         listener never trained on it. Systems:
           face            the shipped `FaceStream` at 20 fps, lookahead 0.3 s (its own listener, `net`)
           pocketsphinx    the same face with pocketsphinx's phone recognizer as its listener (`--face-listener`)
           net+pocketsphinx  both listeners, each frame's mouth the mean of theirs (`--face-listener net+pocketsphinx`)
           face_la0.35     asked for 0.35 s (the default model's lookahead): capped to 0.3, the same frames
           face_la0.15     the live model's lookahead (0.15 s): what a face made with it gets
           loudness_jaw    a jaw from loudness alone (40 ms RMS against the recent peak, as the face scales its
                           mouth; no vowels): the best of a small grid of its range and power, per take
           no_loudness     the face without the loudness scale (loud_range_db 1e6: the scale is 1 everywhere)
           face_50fps      the face made at 50 fps, scored at 50 fps; beside it the 20 fps face linearly
                           interpolated to 50 fps (what a client shows between frames), scored the same way
           headaudio       HeadAudio 0.1.0 (npm @met4citizen/headaudio: MFCCs, Gaussian prototypes; pinned in
                           tests/node), its own code and default settings, offline in Node
                           (`tests/node/headaudio.mjs`): its 15 Oculus visemes at each frame's time, the jaw
                           their weights times each viseme's openness (the mean of its phones' in `visemes.py`);
                           `headaudio_delay100` the same read 100 ms later (its README's delay of the speech)
blinks   the first `--blink-s` seconds of each take, seeds 0-4: blinks a minute, and the share of consecutive
         intervals between blinks alike within 50 ms (issue: 10-25 a minute, at most a third alike)
compute  a `streamer.sessions.Session` window (`infer`: the model at K, pose decoding, and the face when it has one)
         without a face, with the face (`face=FaceOptions()`), with the pocketsphinx face and with both listeners,
         the embedded default
         model, `--window-ms` windows of a take, in turn, one torch thread: ms per window (wall, and this thread's
         CPU time: what it cost whatever else ran on the machine), and what each face adds
generate `dimgestor generate` on the first take (60 s; synthetic speech without the data) with `--face-csv` and
         without, `--generate-runs` times each in turn, the processes' user + sys CPU: the face CSV's cost

    .venv/bin/python benchmarks/face.py                    # writes results/face.json and face.png
    .venv/bin/python benchmarks/face.py --windows 100 --steps 4
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, percentile_ms, test_audio, utc_now, write_json

REPO = Path(__file__).resolve().parents[1]
TAKES = ("2_scott_0_2_2", "2_scott_0_4_4")  # (the blinks are counted on these)
RATE = 16000
TARGETS = {"openness_r": (">=", 0.65), "vowel_top1": (">=", 0.60), "vowel_mean_recall": (">=", 0.55),
           "closures": (">=", 0.5), "rest": ("<=", 0.15), "blinks_per_min": ("in", (10, 25)),
           "alike_share": ("<=", 1 / 3), "compute_added": ("<=", 0.15), "generate_ratio": ("<=", 1.15)}
SCORES = ("openness_r", "vowel_top1", "vowel_mean_recall", "closures", "rest")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "phone_aligned_speech",
                   help="folder of the phone-aligned takes (WAV + TextGrid)")
    p.add_argument("--chunk-ms", type=int, default=100, help="audio pushed per call to the face, as a live stream")
    p.add_argument("--blink-s", type=float, default=60.0, help="speech the blink statistics are taken on")
    p.add_argument("--seeds", type=int, default=5, help="blink seeds 0..N-1")
    p.add_argument("--checkpoint", default=None, help="model to time (default: the embedded default model)")
    p.add_argument("--steps", type=int, default=4, help="DDIM steps K of the timed windows")
    p.add_argument("--window-ms", type=int, default=100, help="audio per timed Session window")
    p.add_argument("--windows", type=int, default=200, help="timed windows per arm")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--generate-runs", type=int, default=9, help="`dimgestor generate` runs per arm (0: none)")
    p.add_argument("--out", type=Path, default=RESULTS / "face.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def headaudio_faces(audio: np.ndarray, frames: int, fps: int = 20) -> dict[str, np.ndarray] | str:
    """HeadAudio's face of `audio` (frames at fps): as it comes, and 100 ms later; or why it was not run."""
    import json
    import shutil
    import subprocess
    import tempfile

    from dimgestor.face import FACE_LABELS
    from dimgestor.face.visemes import OPENNESS, PHONES, V, VISEMES, viseme_of

    if shutil.which("node") is None:
        return "node is not installed"
    if not (REPO / "tests" / "node" / "node_modules" / "@met4citizen" / "headaudio").is_dir():
        return "tests/node's packages are not installed (`make test` installs them)"
    with tempfile.TemporaryDirectory() as tmp:
        np.asarray(audio, np.float32).tofile(f"{tmp}/speech.f32")
        subprocess.run(["node", str(REPO / "tests" / "node" / "headaudio.mjs"), f"{tmp}/speech.f32", str(RATE),
                        f"{tmp}/out.json"], check=True, capture_output=True, timeout=600)
        out = json.loads(Path(f"{tmp}/out.json").read_text())
    steps = np.asarray(out["steps"], np.float64)  # step k at (k + 1) * step_s
    ours = [V[name.removeprefix("viseme_")] for name in out["visemes"]]
    opening = {v: float(np.mean([OPENNESS[p] for p in PHONES if viseme_of(p) == v])) for v in VISEMES}
    jaw = np.array([opening[name.removeprefix("viseme_")] for name in out["visemes"]])
    faces = {}
    for name, delay in (("headaudio", 0.0), ("headaudio_delay100", 0.1)):
        k = np.floor((np.arange(frames) / fps + delay) / out["step_s"] + 1e-9).astype(int) - 1  # the latest step
        rows = np.where((k >= 0)[:, None], steps[np.clip(k, 0, len(steps) - 1)], 0.0)
        face = np.zeros((frames, len(FACE_LABELS)))
        face[:, ours] = rows
        face[:, V["jawOpen"]] = np.clip(rows @ jaw, 0, 1)
        faces[name] = face
    return faces


def stream_face(audio: np.ndarray, fps: int, lookahead_s: float, options, chunk: int):
    """The face of `audio` pushed in `chunk`-sample pieces as a live stream, taken as it is made."""
    from dimgestor.face import FaceStream

    face, rows = FaceStream(fps, lookahead_s, options), []
    for at in range(0, len(audio), chunk):
        face.push(audio[at:at + chunk])
        rows.append(face.take(face.frames_ready))
    face.finish()
    rows.append(face.take(face.frames_ready))
    return np.concatenate(rows), face


def loudness_jaw(audio: np.ndarray, fps: int, lookahead_s: float, range_db: float, power: float,
                 peak_s: float = 2.0) -> np.ndarray:
    """(T, len(FACE_LABELS)) faces whose only motion is a jaw from loudness: the 40 ms around each frame against the
    loudest such frame of the last `peak_s` and of the lookahead (what FaceStream scales its mouth with)."""
    from dimgestor.face import FACE_LABELS
    from dimgestor.face.visemes import V

    n = int(np.ceil(len(audio) / RATE * fps))
    db = np.empty(n)
    for i in range(n):
        c = int(round(i / fps * RATE))
        x = audio[max(0, c - 320):c + 320].astype(np.float64)
        db[i] = 10 * np.log10(np.mean(x**2) + 1e-10) if len(x) else -100.0
    ahead = max(0, min(5, int((lookahead_s - 0.02) * fps)))
    peak = np.array([db[max(0, i - int(peak_s * fps)):i + ahead + 1].max() for i in range(n)])
    face = np.zeros((n, len(FACE_LABELS)))
    face[:, V["jawOpen"]] = np.clip((db - (peak - range_db)) / range_db, 0, 1) ** power
    return face


def resample_face(face: np.ndarray, fps: int, to_fps: int) -> np.ndarray:
    """Frames at `fps` linearly interpolated to `to_fps` (what a client shows between frames)."""
    t_old, t_new = np.arange(len(face)) / fps, np.arange(int(len(face) * to_fps / fps)) / to_fps
    return np.stack([np.interp(t_new, t_old, face[:, j]) for j in range(face.shape[1])], axis=1)


def rounded(scores: dict) -> dict:
    return {k: (round(v, 4) if isinstance(v, float) else rounded(v) if isinstance(v, dict) else v)
            for k, v in scores.items()}


def mouth(takes: dict, args) -> dict:
    from dimgestor.face import FaceOptions
    from dimgestor.face.evaluate import mouth_scores
    from dimgestor.face.net import weights_meta

    trained_on = set(weights_meta().get("real_train", []))

    chunk = RATE * args.chunk_ms // 1000
    out = {}
    for name, (audio, phones) in takes.items():
        r = {}
        t0 = time.perf_counter()
        face, stream = stream_face(audio, 20, 0.3, FaceOptions(), chunk)
        r["face"] = {**mouth_scores(face, phones, 20), "face_s_per_audio_s": (time.perf_counter() - t0) / (len(audio) / RATE)}
        if _version("pocketsphinx") != "not installed":
            t0 = time.perf_counter()
            ps, _ = stream_face(audio, 20, 0.3, FaceOptions(listener="pocketsphinx"), chunk)
            r["pocketsphinx"] = {**mouth_scores(ps, phones, 20),
                                 "face_s_per_audio_s": (time.perf_counter() - t0) / (len(audio) / RATE)}
            t0 = time.perf_counter()
            both, _ = stream_face(audio, 20, 0.3, FaceOptions(listener="net+pocketsphinx"), chunk)
            r["net+pocketsphinx"] = {**mouth_scores(both, phones, 20),
                                     "face_s_per_audio_s": (time.perf_counter() - t0) / (len(audio) / RATE)}
        capped, stream35 = stream_face(audio, 20, 0.35, FaceOptions(), chunk)
        r["face_la0.35"] = {**mouth_scores(capped, phones, 20), "lookahead_used_s": stream35.lookahead_s,
                            "same_frames_as_0.3": bool(np.array_equal(capped, face))}
        live, stream15 = stream_face(audio, 20, 0.15, FaceOptions(), chunk)  # the live model's lookahead
        r["face_la0.15"] = {**mouth_scores(live, phones, 20), "lookahead_used_s": stream15.lookahead_s}
        grid = {f"{rng:g}dB^{pw:g}": mouth_scores(loudness_jaw(audio, 20, 0.3, rng, pw), phones, 20)
                for rng in (20, 30, 40) for pw in (0.5, 1.0)}
        best = max(grid, key=lambda k: grid[k]["openness_r"])
        r["loudness_jaw"] = {**{k: grid[best][k] for k in ("frames", "openness_r", "closures", "rest")},
                             "vowel_top1": None, "vowel_mean_recall": None, "setting": best,
                             "openness_r_grid": {k: v["openness_r"] for k, v in grid.items()}}
        flat, _ = stream_face(audio, 20, 0.3, FaceOptions(loud_range_db=1e6), chunk)
        r["no_loudness"] = mouth_scores(flat, phones, 20)
        t0 = time.perf_counter()
        face50, _ = stream_face(audio, 50, 0.3, FaceOptions(), chunk)
        r["face_50fps"] = {**mouth_scores(face50, phones, 50),
                           "face_s_per_audio_s": (time.perf_counter() - t0) / (len(audio) / RATE)}
        r["face_20fps_at_50"] = mouth_scores(resample_face(face, 20, 50), phones, 50)
        peers = headaudio_faces(audio, len(face))
        if isinstance(peers, str):
            print(f"HeadAudio not run: {peers}", flush=True)
        else:
            r.update({k: mouth_scores(v, phones, 20) for k, v in peers.items()})
        out[name] = {"held_out": name not in trained_on, "seconds": round(len(audio) / RATE, 2), **rounded(r)}
        print(f"{name}: " + ", ".join(f"{s} r {v['openness_r']:.3f}" for s, v in r.items()), flush=True)
    return out


def blinks(takes: dict, args) -> dict:
    from dimgestor.face import FaceOptions

    chunk = RATE * args.chunk_ms // 1000
    rows = []
    for name, (audio, _) in takes.items():
        clip = audio[: int(args.blink_s * RATE)]
        for seed in range(args.seeds):
            _, stream = stream_face(clip, 20, 0.3, FaceOptions(seed=seed), chunk)
            onsets = np.array([t for t in stream.blinks.started if t < len(clip) / RATE])
            gaps = np.diff(onsets)
            alike = float(np.mean(np.abs(np.diff(gaps)) < 0.05)) if len(gaps) > 1 else float("nan")
            rows.append({"take": name, "seed": seed, "seconds": len(clip) / RATE, "blinks": len(onsets),
                         "blinks_per_min": round(len(onsets) / (len(clip) / RATE) * 60, 2),
                         "alike_share": round(alike, 4), "interval_s_min": round(float(gaps.min()), 3),
                         "interval_s_max": round(float(gaps.max()), 3), "intervals_s": np.round(gaps, 3).tolist()})
            print(f"blinks {name} seed {seed}: {rows[-1]['blinks_per_min']}/min, alike {alike:.2f}", flush=True)
    return {"rows": rows, "per_min_range": [min(r["blinks_per_min"] for r in rows), max(r["blinks_per_min"] for r in rows)],
            "alike_share_max": max(r["alike_share"] for r in rows)}


def compute(audio: np.ndarray, args) -> dict:
    """ms per Session window with and without a face, windows alternating between the two sessions."""
    import torch

    from dimgestor.face import FaceOptions
    from dimgestor.streaming.checkpoint import load_checkpoint
    from streamer.sessions import Session

    bundle = load_checkpoint(args.checkpoint)
    window = RATE * args.window_ms // 1000
    need = (args.windows + 10) * window
    audio = np.concatenate([audio] * int(np.ceil(need / len(audio))))[:need]
    arms = {"body": Session.from_bundle(bundle, steps=args.steps, seed=0),
            "body_face": Session.from_bundle(bundle, steps=args.steps, seed=0, face=FaceOptions())}
    if _version("pocketsphinx") != "not installed":
        arms["body_face_pocketsphinx"] = Session.from_bundle(bundle, steps=args.steps, seed=0,
                                                             face=FaceOptions(listener="pocketsphinx"))
        arms["body_face_both"] = Session.from_bundle(bundle, steps=args.steps, seed=0,
                                                     face=FaceOptions(listener="net+pocketsphinx"))
    times = {name: [] for name in arms}
    cpu = {name: [] for name in arms}  # this thread's CPU time: what the window cost, whatever else ran meanwhile
    with torch.inference_mode():
        for k in range(args.windows + 10):
            x = audio[k * window:(k + 1) * window]
            for name in (list(arms) if k % 2 == 0 else list(arms)[::-1]):  # (in turn, each first as often)
                t0, c0 = time.perf_counter(), time.thread_time()
                arms[name].infer(x)
                if k >= 10:  # past the lookahead: frames come every window
                    times[name].append(time.perf_counter() - t0)
                    cpu[name].append(time.thread_time() - c0)
    rows = {name: {"ms_p50": percentile_ms(t, 50), "ms_p95": percentile_ms(t, 95), "ms_mean": 1000 * float(np.mean(t)),
                   "cpu_ms_mean": 1000 * float(np.mean(cpu[name]))} for name, t in times.items()}
    return {"model": f"checkpoint {args.checkpoint or 'embedded default'}", "steps": args.steps,
            "window_ms": args.window_ms, "windows": args.windows, **rows,
            "added_p50": rows["body_face"]["ms_p50"] / rows["body"]["ms_p50"] - 1,
            "added_mean": rows["body_face"]["ms_mean"] / rows["body"]["ms_mean"] - 1,
            "added_cpu": rows["body_face"]["cpu_ms_mean"] / rows["body"]["cpu_ms_mean"] - 1,
            **({f"added_cpu_{arm}": rows[f"body_face_{arm}"]["cpu_ms_mean"] / rows["body"]["cpu_ms_mean"] - 1
                for arm in ("pocketsphinx", "both")} if "body_face_pocketsphinx" in rows else {})}


def generate_cost(audio: np.ndarray, args) -> dict:
    """User + sys CPU of `dimgestor generate` with `--face-csv` and without, runs in turn: the median ratio."""
    import resource
    import subprocess
    import tempfile

    from dimgestor.audio import save_wav

    cpu: dict[str, list[float]] = {"body": [], "body_face": []}
    with tempfile.TemporaryDirectory() as tmp:
        wav = Path(tmp) / "speech.wav"
        save_wav(wav, audio, RATE)
        for k in range(args.generate_runs):
            for arm in (list(cpu) if k % 2 == 0 else list(cpu)[::-1]):
                cmd = [str(Path(sys.executable).with_name("dimgestor")), "generate", "--audio", str(wav),
                       "--out", f"{tmp}/out.bvh"]
                if arm == "body_face":
                    cmd += ["--face-csv", f"{tmp}/out.face.csv"]
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                subprocess.run(cmd, check=True, capture_output=True, cwd=REPO)
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu[arm].append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    body, face = float(np.median(cpu["body"])), float(np.median(cpu["body_face"]))
    return {"audio_s": len(audio) / RATE, "runs": args.generate_runs, "cpu_s": cpu, "cpu_s_median_body": body,
            "cpu_s_median_body_face": face, "ratio": face / body}


def verdict(result: dict) -> dict:
    """Each target: the worst value over the takes (and seeds) against it."""
    out = {}
    if result.get("mouth"):
        faces = [r["face"] for r in result["mouth"].values()]
        for k in SCORES:
            worst = (max if TARGETS[k][0] == "<=" else min)(f[k] for f in faces)
            out[k] = {"worst": worst, "target": TARGETS[k], "met": _met(worst, TARGETS[k])}
        margin = min(r["face"]["openness_r"] - r["loudness_jaw"]["openness_r"] for r in result["mouth"].values())
        out["openness_over_loudness"] = {"worst": margin, "target": (">=", 0.08), "met": margin >= 0.08}
        both = [r for r in result["mouth"].values() if "net+pocketsphinx" in r]
        if both:  # (the opt-in listener: --face-listener net+pocketsphinx)
            out["net+pocketsphinx"] = {k: {"worst": (w := (max if TARGETS[k][0] == "<=" else min)(
                r["net+pocketsphinx"][k] for r in both)), "met": _met(w, TARGETS[k])} for k in SCORES}
            margin = min(r["net+pocketsphinx"]["openness_r"] - r["loudness_jaw"]["openness_r"] for r in both)
            out["net+pocketsphinx"]["openness_over_loudness"] = {"worst": margin, "met": margin >= 0.08}
    if result.get("blinks"):
        lo, hi = result["blinks"]["per_min_range"]
        out["blinks_per_min"] = {"range": [lo, hi], "target": TARGETS["blinks_per_min"],
                                 "met": 10 <= lo and hi <= 25}
        worst = result["blinks"]["alike_share_max"]
        out["alike_share"] = {"worst": worst, "target": TARGETS["alike_share"], "met": _met(worst, TARGETS["alike_share"])}
    c = result["compute"]
    out["compute_added"] = {"cpu": c["added_cpu"], "target": TARGETS["compute_added"],
                            "met": _met(c["added_cpu"], TARGETS["compute_added"])}
    if g := result.get("generate"):
        out["generate_ratio"] = {"ratio": g["ratio"], "target": TARGETS["generate_ratio"],
                                 "met": _met(g["ratio"], TARGETS["generate_ratio"])}
    return out


def _met(value: float, target: tuple) -> bool:
    op, bound = target
    return bool(value >= bound) if op == ">=" else bool(value <= bound)


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common import save_panels

    fig, axes = plt.subplots(1, 3, figsize=(15, 4), gridspec_kw={"width_ratios": [3, 1.2, 1]})
    ax = axes[0]
    systems = ("face", "pocketsphinx", "net+pocketsphinx", "loudness_jaw", "no_loudness", "headaudio_delay100")
    takes = list(result.get("mouth", {}))
    width = 0.8 / (len(systems) * max(1, len(takes)))
    x = np.arange(len(SCORES))
    for i, s in enumerate(systems):
        for j, take in enumerate(takes):
            v = [result["mouth"][take].get(s, {}).get(k) for k in SCORES]
            v = [np.nan if a is None else a for a in v]
            ax.bar(x + (i * len(takes) + j) * width - 0.4, v, width, color=f"C{i}", alpha=1.0 - 0.2 * j,
                   label=f"{s}" if j == 0 else None)
    for xi, k in zip(x, SCORES):
        ax.hlines(TARGETS[k][1], xi - 0.42, xi + 0.42, color="k", lw=1.2)
    ax.set_xticks(x, SCORES, fontsize=8)
    ax.set_title(f"mouth vs the alignment, {len(takes)} real clips (lighter: later ones); black: target", fontsize=9)
    ax = axes[1]
    if result.get("blinks"):
        rows = result["blinks"]["rows"]
        ax.scatter([r["blinks_per_min"] for r in rows], [r["alike_share"] for r in rows], label="take x seed")
        ax.axvspan(10, 25, color="g", alpha=0.1)
        ax.axhline(1 / 3, color="k", lw=1)
        ax.set_xlabel("blinks a minute", fontsize=8)
        ax.set_ylabel("consecutive intervals alike (50 ms)", fontsize=8)
        ax.set_title(f"blinks on {rows[0]['seconds']:.0f} s of speech", fontsize=9)
    ax = axes[2]
    c = result["compute"]
    arms = [a for a in ("body", "body_face", "body_face_pocketsphinx", "body_face_both") if a in c]
    for i, arm in enumerate(arms):
        ax.bar(i, c[arm]["ms_p50"], color=f"C{i}", label=arm)
        ax.scatter(i, c[arm]["ms_p95"], color="k", marker="_", s=150, zorder=3)
    ax.set_xticks(range(len(arms)), ["body", "+face", "+pocketsphinx\nface", "+both"][:len(arms)], fontsize=8)
    ax.set_ylabel("ms per window (p50; p95 -)", fontsize=8)
    ax.set_title(f"Session window, K={c['steps']}, {c['window_ms']} ms: +{100 * c['added_p50']:.0f} % p50, "
                 f"+{100 * c['added_cpu']:.0f} % CPU", fontsize=9)
    save_panels(fig, axes, f"face ({result['code_version']}, {result['device'][:60]})", path)


def main(argv=None) -> int:
    args = parse_args(argv)
    import torch

    from dimgestor.audio import load_wav
    from dimgestor.face.textgrid import read_tiers

    torch.set_num_threads(args.threads)
    result = {"measured_at": utc_now(), "code_version": code_version(), "device": describe_device("cpu"),
              "argv": args.argv, "note": args.note, "load_avg_before": load_average(),
              "pocketsphinx": _version("pocketsphinx"), "chunk_ms": args.chunk_ms, "targets": TARGETS}
    if all((args.data / f"{t}.wav").is_file() for t in TAKES):
        clips = {w.stem: (load_wav(w), read_tiers(w.with_suffix(".TextGrid"))["phones"])
                 for w in sorted(args.data.glob("*.wav")) if w.with_suffix(".TextGrid").is_file()}
        takes = {t: clips[t] for t in TAKES}
        result["mouth"] = mouth(clips, args)
        result["blinks"] = blinks(takes, args)
        speech = takes[TAKES[0]][0]
    else:
        result["skipped"] = f"{args.data}: the phone-aligned takes are not there (mouth and blinks not measured)"
        print(f"skipped: {result['skipped']}", flush=True)
        speech = test_audio(30.0)
    result["compute"] = compute(speech, args)
    c = result["compute"]
    print(f"Session window K={args.steps}: {c['body']['ms_p50']:.2f} ms, with the face {c['body_face']['ms_p50']:.2f} ms "
          f"(+{100 * c['added_p50']:.1f} % p50, +{100 * c['added_mean']:.1f} % mean, +{100 * c['added_cpu']:.1f} % CPU "
          f"time)", flush=True)
    if args.generate_runs:
        result["generate"] = g = generate_cost(speech[: 60 * RATE], args)
        print(f"dimgestor generate on {g['audio_s']:.0f} s: {g['cpu_s_median_body']:.2f} s CPU, with the face CSV "
              f"{g['cpu_s_median_body_face']:.2f} s ({g['ratio']:.2f}x)", flush=True)
    result["targets_met"] = verdict(result)
    result["load_avg_after"] = load_average()
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    return 0


def _version(package: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return "not installed"


if __name__ == "__main__":
    sys.exit(main())
