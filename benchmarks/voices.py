"""Does the motion follow the voice it is given? A per-voice table for one or more models (issue 20).

For each voice: loudness coupling (metrics.speech_coupling) beside its circularly-shifted-audio baseline
(mean, sd, and whether coupling > mean + 2 sd), onset alignment of the stressed onsets (the strongest 40%;
of all onsets too, in the JSON) beside as many onsets shuffled inside speech,
speech/pause contrast, wrist speed in speech over wrist speed in 6 s of silence inserted into the clip,
and wrist jerk; each a mean over seeds (`dimgestor.evaluation.eval.voice_report`, the same rows as
`dimgestor eval --wavs`). Voices:

  zeggs_heldout   the training speaker's held-out last 15 s (../shared ZEGGS sample), and the real
                  capture's own numbers on that stretch and on the whole clip (references)
  lawrence_*      BEAT speaker "lawrence", two takes (../shared/data/unseen_speech): unseen, real speech
  scott_*         BEAT2 speaker "scott", two takes (../shared/data/phone_aligned_speech): unseen, real speech
  realworld_*     the real-world speakers beside them (clip000028, clip000070): unseen, real speech
  demo_en/zh      the bundled espeak clips (dimgestor/assets)
  espeak_*        espeak-ng voices in six languages at several pitches and rates, made at run time from
                  the fixed texts below (sentences joined by fixed pauses, peak-normalized to -1 dBFS)

Each row also has its variety: the median distance of its 1 s upper-body windows to the nearest 1 s window of
the training stretch (`nearest`, cm), over the real actor's own figure (her held-out 15 s against the same
stretch): 1 = as far from the training motion as the actor herself strays, below 1 = replaying what it saw.

summary: per kind of unseen voice, real (lawrence + scott + realworld: the targets are on these) and synthetic
(espeak_*), and over all of them: mean coupling, how many clear their chance level, mean onset margin over shuffled, mean silence
ratio, jerk and variety. Rows that need ../shared are skipped with a note when it is absent.

    python benchmarks/voices.py                                  # the embedded default model, ~10 min
    python benchmarks/voices.py --real --checkpoint runs/new     # the real voices only (and the held-out stretch)
    python benchmarks/voices.py --checkpoint runs/new --out /tmp/new.json
    python benchmarks/voices.py --compare benchmarks/results/voices.json /tmp/new.json   # old vs new table
    python benchmarks/voices.py --checkpoint default --checkpoint runs/new --label old --label new
    python benchmarks/voices.py --checkpoint runs/new --checkpoint runs/new --guidance 1 --guidance 2 \
        --label unguided --label guided   # (with classifier-free guidance in dimgestor)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, code_version, describe_device, load_average, real_voice, utc_now, write_json  # noqa: E402
from dimgestor.audio import SAMPLE_RATE  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
ZEGGS = SHARED / "zeggs_sample"
LAWRENCE = SHARED / "unseen_speech"
SCOTT = SHARED / "phone_aligned_speech"
SCHEMA = 2  # 2: real and synthetic summaries apart, the scott takes, variety

# Fixed texts (written for this benchmark), a sentence per item; pauses between sentences below.
TEXTS = {
    "en": ["Good morning, and thank you all for coming today.",
           "I want to tell you a short story about a small town by the sea.",
           "Every summer, the fishermen would paint their boats in bright colours.",
           "Red, yellow, blue and green, all lined up along the harbour wall.",
           "One year, a storm came in the night and scattered them across the bay.",
           "Nobody was hurt, but the boats were everywhere!",
           "So the whole town went out together, and brought them back, one by one.",
           "That is what I love about that place: people simply help each other.",
           "And that, I think, is the best reason to go back there."],
    "de": ["Guten Morgen, und vielen Dank, dass Sie heute gekommen sind.",
           "Ich möchte Ihnen eine kurze Geschichte über eine kleine Stadt am Meer erzählen.",
           "Jeden Sommer haben die Fischer ihre Boote in hellen Farben gestrichen.",
           "Rot, gelb, blau und grün, alle in einer Reihe an der Hafenmauer.",
           "In einem Jahr kam nachts ein Sturm und verteilte sie über die ganze Bucht.",
           "Niemand wurde verletzt, aber die Boote waren überall!",
           "Also ging die ganze Stadt gemeinsam hinaus und holte sie zurück, eines nach dem anderen.",
           "Das liebe ich an diesem Ort: Die Menschen helfen einander einfach."],
    "fr": ["Bonjour à tous, et merci d'être venus aujourd'hui.",
           "Je voudrais vous raconter une petite histoire sur un village au bord de la mer.",
           "Chaque été, les pêcheurs peignaient leurs bateaux de couleurs vives.",
           "Rouge, jaune, bleu et vert, tous alignés le long du port.",
           "Une année, une tempête est arrivée dans la nuit et les a dispersés dans la baie.",
           "Personne n'a été blessé, mais il y avait des bateaux partout !",
           "Alors tout le village est sorti ensemble, et les a ramenés, un par un.",
           "C'est ce que j'aime dans cet endroit : les gens s'entraident, tout simplement."],
    "es": ["Buenos días a todos, y gracias por venir hoy.",
           "Quiero contarles una pequeña historia sobre un pueblo junto al mar.",
           "Cada verano, los pescadores pintaban sus barcos de colores brillantes.",
           "Rojo, amarillo, azul y verde, todos en fila junto al muelle.",
           "Un año, llegó una tormenta por la noche y los dispersó por toda la bahía.",
           "Nadie salió herido, ¡pero había barcos por todas partes!",
           "Así que todo el pueblo salió junto, y los trajo de vuelta, uno por uno.",
           "Eso es lo que me encanta de ese lugar: la gente simplemente se ayuda."],
    "cmn": ["大家早上好，谢谢你们今天来到这里。",
            "我想给大家讲一个关于海边小镇的小故事。",
            "每年夏天，渔民们都会把自己的船涂成鲜艳的颜色。",
            "红色，黄色，蓝色和绿色，整整齐齐地排在码头边上。",
            "没有人受伤，可是到处都是船！",
            "于是全镇的人一起出海，把船一条一条地拉了回来。",
            "这就是我喜欢那个地方的原因：人们总是互相帮助。"],
}
PAUSES_S = (0.6, 1.2, 0.8, 1.6, 0.7, 1.0, 2.0, 0.9)  # between sentences, cycled: natural pauses, some long
LEAD_S = 0.5  # silence before the first sentence and after the last

# (row name, espeak-ng voice, pitch 0-99, words per minute, text); --quick keeps the first three
ESPEAK_VOICES = (
    ("espeak_en-us_p50_s160", "en-us", 50, 160, "en"),
    ("espeak_de_p40_s150", "de", 40, 150, "de"),
    ("espeak_cmn_p60_s170", "cmn", 60, 170, "cmn"),
    ("espeak_en-gb_p30_s140", "en-gb", 30, 140, "en"),
    ("espeak_en-us+f3_p70_s180", "en-us+f3", 70, 180, "en"),
    ("espeak_fr_p50_s150", "fr-fr", 50, 150, "fr"),
    ("espeak_es_p55_s170", "es", 55, 170, "es"),
    ("espeak_cmn_p35_s165", "cmn", 35, 165, "cmn"),
)
KINDS = {"real": ("lawrence", "scott", "realworld"), "synthetic": ("espeak",)}  # the unseen voices, by kind
UNSEEN_GROUPS = KINDS["real"] + KINDS["synthetic"]


def espeak_version() -> str | None:
    exe = shutil.which("espeak-ng")
    if exe is None:
        return None
    return subprocess.run([exe, "--version"], capture_output=True, text=True).stdout.split("  Data at")[0].strip()


def espeak_clip(voice: str, pitch: int, wpm: int, sentences: list[str], folder: Path) -> np.ndarray:
    """The sentences spoken one by one by espeak-ng, joined by PAUSES_S, peak at -1 dBFS, 16 kHz mono."""
    from dimgestor.audio import load_wav

    parts = [np.zeros(int(LEAD_S * SAMPLE_RATE), np.float32)]
    for i, text in enumerate(sentences):
        path = folder / f"{voice}_{pitch}_{wpm}_{i}.wav"
        subprocess.run(["espeak-ng", "-v", voice, "-p", str(pitch), "-s", str(wpm), "-w", str(path), text],
                       check=True, capture_output=True)
        parts.append(load_wav(path))
        parts.append(np.zeros(int((PAUSES_S[i % len(PAUSES_S)] if i < len(sentences) - 1 else LEAD_S) * SAMPLE_RATE),
                              np.float32))
    audio = np.concatenate(parts)
    return (audio * (10 ** (-1 / 20) / max(np.abs(audio).max(), 1e-9))).astype(np.float32)


def collect_voices(quick: bool, folder: Path, real_only: bool = False) -> tuple[dict, dict]:
    """({name: {"group", "source", "audio", ["real": raw features]}}, {name: why skipped})."""
    from dimgestor.audio import load_wav

    voices, skipped = {}, {}
    if (ZEGGS / "067_Speech_2_x_1_0.wav").is_file():
        voices["zeggs_heldout"] = {"group": "heldout", "source": "067_Speech_2_x_1_0.wav, last 15 s"}
    else:
        skipped["zeggs_heldout"] = f"{ZEGGS} not found (the ZEGGS sample lives beside the dev checkout)"
    takes = sorted(LAWRENCE.glob("*.wav"))[:1 if quick else None] if LAWRENCE.is_dir() else []
    for p in takes:
        group, name = real_voice(p)
        voices[name] = {"group": group, "source": p.name, "audio": load_wav(p)}
    if not takes:
        skipped["lawrence"] = f"{LAWRENCE} not found (BEAT takes live beside the dev checkout)"
    takes = sorted(SCOTT.glob("*.wav"))[:1 if quick else None] if SCOTT.is_dir() else []
    for p in takes:  # (scott's takes, and the real-world speakers beside them)
        group, name = real_voice(p)
        voices[name] = {"group": group, "source": p.name, "audio": load_wav(p)}
    if not takes:
        skipped["scott"] = f"{SCOTT} not found (BEAT2 takes live beside the dev checkout)"
    if real_only:
        return voices, skipped
    for name in ("demo_en", "demo_zh"):
        voices[name] = {"group": "demo", "source": f"dimgestor/assets/{name}.wav",
                        "audio": load_wav(REPO / "dimgestor" / "assets" / f"{name}.wav")}
    if espeak_version() is None:
        skipped["espeak"] = "espeak-ng not installed (apt-get install espeak-ng)"
        return voices, skipped
    for name, voice, pitch, wpm, lang in ESPEAK_VOICES[:3] if quick else ESPEAK_VOICES:
        voices[name] = {"group": "espeak", "source": f"espeak-ng -v {voice} -p {pitch} -s {wpm}, text '{lang}'",
                        "audio": espeak_clip(voice, pitch, wpm, TEXTS[lang], folder)}
    return voices, skipped


def zeggs_real(bundle) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(held-out audio, its real raw features, whole-clip audio, whole-clip features) of the ZEGGS sample."""
    from dimgestor.evaluation.eval import valid_clips
    from dimgestor.training.dataset import GestureDataset

    valid = GestureDataset(ZEGGS, spec=bundle.feature_spec, split="valid", window_s=4.0, valid_seconds=15.0)
    (audio, raw), = valid_clips(valid)
    clip = valid.clips[0]
    return audio, raw, np.asarray(clip.audio, np.float32), np.asarray(clip.features, np.float32)


def real_row(bundle, audio: np.ndarray, raw: np.ndarray) -> dict:
    """The per-voice numbers of real capture on its own speech (no inserted silence: it was never recorded)."""
    from dimgestor.evaluation.eval import clip_stats, voice_row

    row = voice_row([clip_stats(raw, audio, bundle.skeleton, bundle.feature_spec)])
    return {k: v for k, v in row.items() if k not in ("speed_silence", "silence_ratio")}


def summarize(rows: dict, groups: dict) -> dict:
    """Means over the unseen voices of each kind ("real", "synthetic") and over all of them ("unseen"): coupling,
    the count above chance, onset margin, silence ratio, contrast, jerk (and its ratio) and variety."""
    out = {}
    for kind, members in (*KINDS.items(), ("unseen", UNSEEN_GROUPS)):
        rs = [rows[n] for n in rows if groups[n] in members]
        if not rs:
            continue
        mean = lambda key: float(np.nanmean([r.get(key, np.nan) for r in rs]))  # noqa: E731
        out[kind] = {"voices": len(rs), "coupling": mean("coupling"),
                     "coupling_min": float(np.nanmin([r["coupling"] for r in rs])),
                     "coupling_shifted": mean("coupling_shifted"),
                     "above_chance": int(sum(r["coupling_above"] for r in rs)),
                     "onset_margin": float(np.nanmean([r["onset_align"] - r["onset_shuffled"] for r in rs])),
                     "silence_ratio": mean("silence_ratio"), "silence_ratio_min": float(np.nanmin(
                         [r["silence_ratio"] for r in rs])), "contrast": mean("contrast"),
                     "hand_jerk": mean("hand_jerk"), "jerk_ratio": mean("jerk_ratio"),
                     "jerk_ratio_max": float(np.nanmax([r.get("jerk_ratio", np.nan) for r in rs])),
                     "nearest": mean("nearest"), "variety": mean("variety")}
    return out


def unseen_summary(m: dict, kind: str = "unseen") -> dict | None:
    """A model result's summary of one kind of voice, in the keys above; result files of schema 1 had only the
    flat "unseen_*" keys over lawrence + espeak (read as "unseen")."""
    s = m.get("summary") or {}
    if kind in s:
        return s[kind]
    if kind == "unseen" and "unseen_coupling" in s:
        return {k[len("unseen_"):]: v for k, v in s.items() if k.startswith("unseen_")}
    return None


def evaluate(checkpoint: str | None, voices: dict, steps: int | None, seeds: int, seed: int,
             guidance: float | None = None, log=print, eta: float = 0.0) -> dict:
    """One model's rows over the voices (+ the real capture's reference rows) and its summary."""
    import torch

    from dimgestor.evaluation.eval import upper_positions, variety_distance, voice_report
    from dimgestor.streaming.checkpoint import load_checkpoint

    bundle = load_checkpoint(checkpoint)
    bundle.model.eval()
    if guidance is not None:  # as `dimgestor eval --guidance`: every generation takes the config's scale
        if "guidance" not in type(bundle.config).model_fields:
            raise SystemExit("--guidance: this dimgestor has no classifier-free guidance (config.guidance)")
        bundle.config = bundle.model.config = bundle.config.model_copy(update={"guidance": float(guidance)})
    steps = steps or bundle.config.sample_steps
    rows, reference, started = {}, {}, time.time()
    train_upper, actor_nearest = None, float("nan")
    if "zeggs_heldout" in voices:
        audio, raw, whole_audio, whole_raw = zeggs_real(bundle)
        voices["zeggs_heldout"]["audio"] = audio
        reference["zeggs_heldout_real"] = real_row(bundle, audio, raw)
        reference["zeggs_whole_real"] = real_row(bundle, whole_audio, whole_raw)
        # variety: against the training stretch (the clip before its held-out tail), over the actor's own figure
        train_upper = upper_positions(whole_raw[:len(whole_raw) - len(raw)], bundle.skeleton, bundle.feature_spec)
        actor_nearest = variety_distance(upper_positions(raw, bundle.skeleton, bundle.feature_spec), train_upper,
                                         float(bundle.feature_spec.fps))
        reference["zeggs_heldout_real"].update(nearest=actor_nearest, variety=1.0)
    for name, v in voices.items():
        with torch.inference_mode():
            rows[name] = voice_report(bundle, v["audio"], steps, seeds, seed, smoothing=None,
                                      reference_upper=train_upper, eta=eta)
        rows[name]["variety"] = rows[name]["nearest"] / actor_nearest
        log(f"{name:28s} coupling {rows[name]['coupling']:+.3f} (shifted {rows[name]['coupling_shifted']:+.3f} "
            f"+- {rows[name]['coupling_shifted_sd']:.3f}), onsets {rows[name]['onset_align']:.3f} vs "
            f"{rows[name]['onset_shuffled']:.3f}, silence ratio {rows[name]['silence_ratio']:.2f}, variety "
            f"{rows[name]['variety']:.2f} ({time.time() - started:.0f} s)")
    if "zeggs_heldout_real" in reference:
        real_jerk = reference["zeggs_heldout_real"]["hand_jerk"]
        for r in rows.values():
            r["jerk_ratio"] = r["hand_jerk"] / real_jerk
    return {"checkpoint": checkpoint or "embedded default", "steps": steps, "seeds": seeds,
            "guidance": getattr(bundle.config, "guidance", None), "eta": eta, "rows": rows,
            "reference": reference,
            "summary": summarize(rows, {n: v["group"] for n, v in voices.items()})}


# ------------------------------------------------------------------------------------------------ tables

COLUMNS = (("coupling", "coupling", "{:+.2f}"), ("coupling_shifted", "shifted", "{:+.2f}"),
           ("coupling_shifted_sd", "sd", "{:.2f}"), ("coupling_above", ">+2sd", "{}"),
           ("onset_align", "onsets", "{:.2f}"), ("onset_shuffled", "shuffled", "{:.2f}"),
           ("contrast", "pauses", "{:.2f}"), ("silence_ratio", "silence", "{:.2f}"),
           ("hand_jerk", "jerk", "{:.3g}"), ("jerk_ratio", "jerk/real", "{:.2f}"), ("variety", "variety", "{:.2f}"))


def cell(fmt: str, v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return fmt.format("yes" if v is True else "no" if v is False else v)


def model_table(result: dict, label: str) -> str:
    """Markdown: one row per voice (and the real capture), the summary last."""
    m = result["models"][label]
    head = "| voice | " + " | ".join(h for _, h, _ in COLUMNS) + " |"
    lines = [f"**{label}** ({m['checkpoint']}, K = {m['steps']}, {result['settings']['seeds']} seeds)", "",
             head, "|" + "---|" * (len(COLUMNS) + 1)]
    for name, row in list(m["reference"].items()) + list(m["rows"].items()):
        lines.append(f"| {name} | " + " | ".join(cell(f, row.get(k)) for k, _, f in COLUMNS) + " |")
    for kind in ("real", "synthetic", "unseen"):
        t = unseen_summary(m, kind)
        if t:
            lines.append(f"| **{'all' if kind == 'unseen' else kind} unseen mean ({t['voices']} voices)** | {t['coupling']:+.2f} | "
                         f"{t['coupling_shifted']:+.2f} | | {t['above_chance']}/{t['voices']} | "
                         f"margin {t['onset_margin']:+.2f} | | {t['contrast']:.2f} | {t['silence_ratio']:.2f} | "
                         f"{t['hand_jerk']:.3g} | {cell('{:.2f}', t.get('jerk_ratio'))} | "
                         f"{cell('{:.2f}', t.get('variety'))} |")
    return "\n".join(lines)


def compare_table(models: list[tuple[str, dict]]) -> str:
    """Markdown, old against new: per voice coupling (shifted baseline), onset margin, silence ratio, jerk."""
    labels = [lab for lab, _ in models]
    voices = [v for v in dict.fromkeys(v for _, m in models for v in m["rows"])]
    cols = ["coupling (shifted)", "onsets - shuffled", "silence ratio", "wrist jerk", "variety"]
    head = "| voice | " + " | ".join(f"{c} {lab}" for c in cols for lab in labels) + " |"
    lines = [head, "|" + "---|" * (1 + len(cols) * len(labels))]

    def fmt(m, voice, col):
        r = m["rows"].get(voice)
        if r is None:
            return "-"
        if col == 0:
            return f"{r['coupling']:+.2f} ({r['coupling_shifted']:+.2f})" + ("" if r["coupling_above"] else " ~")
        if col == 1:
            return cell("{:+.2f}", r["onset_align"] - r["onset_shuffled"])
        return cell(("{:.2f}", "{:.3g}", "{:.2f}")[col - 2], r.get(("silence_ratio", "hand_jerk", "variety")[col - 2]))

    for v in voices:
        lines.append(f"| {v} | " + " | ".join(fmt(m, v, c) for c in range(len(cols)) for _, m in models) + " |")

    def total(m, col, kind):
        t = unseen_summary(m, kind)
        if not t:
            return "-"
        return [f"{t['coupling']:+.2f} ({t['above_chance']}/{t['voices']} above)", f"{t['onset_margin']:+.2f}",
                f"{t['silence_ratio']:.2f}", f"{t['hand_jerk']:.3g}", cell("{:.2f}", t.get("variety"))][col]

    for kind, what in (("real", f"real unseen mean ({' + '.join(KINDS['real'])})"),
                       ("synthetic", "synthetic unseen mean (espeak)"), ("unseen", "all unseen mean")):
        if any(unseen_summary(m, kind) for _, m in models):
            lines.append(f"| **{what}** | "
                         + " | ".join(total(m, c, kind) for c in range(len(cols)) for _, m in models) + " |")
    lines.append("\n~ : coupling not above its shifted baseline + 2 sd. "
                 + "; ".join(f"{lab}: {m['checkpoint']}, K = {m['steps']}, {m.get('seeds', '?')} seeds"
                             + (f", guidance {m['guidance']:g}" if m.get("guidance") is not None else "")
                             for lab, m in models))
    return "\n".join(lines)


def labelled_models(paths: list[str]) -> list[tuple[str, dict]]:
    """(label, model result) of every model in the given result files, labels made unique by file stem."""
    out = []
    for p in paths:
        result = json.loads(Path(p).read_text())
        for label, m in result["models"].items():
            m = {"seeds": result["settings"]["seeds"], **m}  # files written before models carried their seeds
            out.append((label if len(paths) == 1 else f"{Path(p).stem}:{label}", m))
    return out


# ------------------------------------------------------------------------------------------------ plot

def plot(result: dict, path: Path) -> None:
    """Per voice: coupling beside the shifted baseline's mean + 2 sd, onset alignment beside shuffled, silence
    ratio; one colour per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = list(result["models"])
    voices = list(dict.fromkeys(v for m in result["models"].values() for v in m["rows"]))
    x = np.arange(len(voices))
    width = 0.8 / len(labels)
    colours = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728"]
    fig, axes = plt.subplots(3, 1, figsize=(max(8, 0.8 * len(voices) + 2), 9), sharex=True)
    for j, label in enumerate(labels):
        rows = result["models"][label]["rows"]
        get = lambda k: np.array([rows[v][k] if v in rows else np.nan for v in voices], float)  # noqa: E731
        xs = x + (j - (len(labels) - 1) / 2) * width
        c = colours[j % len(colours)]
        axes[0].bar(xs, get("coupling"), width, color=c, label=label)
        axes[0].errorbar(xs, get("coupling_shifted"), yerr=2 * get("coupling_shifted_sd"), fmt="_", color="k",
                         capsize=2, lw=1, label="shifted audio, mean +- 2 sd" if j == 0 else None)
        axes[1].bar(xs, get("onset_align"), width, color=c, label=label)
        axes[1].plot(xs, get("onset_shuffled"), "k_", ms=10, label="onsets shuffled in speech" if j == 0 else None)
        axes[2].bar(xs, get("silence_ratio"), width, color=c, label=label)
    ref = next(iter(result["models"].values()))["reference"].get("zeggs_heldout_real")
    if ref:
        axes[0].axhline(ref["coupling"], color="#555555", ls="--", lw=1, label="real capture, held-out ZEGGS")
    axes[0].set_ylabel("loudness coupling r")
    axes[1].set_ylabel("onsets with a wrist peak")
    axes[2].set_ylabel("speech / inserted silence")
    axes[2].axhline(3.0, color="#555555", ls=":", lw=1, label="issue 20 target")
    axes[2].set_xticks(x, voices, rotation=40, ha="right", fontsize=8)
    for ax in axes:
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=7)
    s = result["settings"]
    ks = "/".join(str(k) for k in dict.fromkeys(m["steps"] for m in result["models"].values()))
    fig.suptitle(f"hands following the voice: K = {ks}, {s['seeds']} seeds, no filter "
                 f"({result['code_version']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


# ------------------------------------------------------------------------------------------------ main

def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", action="append", default=None,
                   help="checkpoint or run folder; 'default' = the embedded model; repeat to compare models")
    p.add_argument("--label", action="append", default=None, help="a name per --checkpoint (default: its path)")
    p.add_argument("--steps", type=int, default=None, help="DDIM steps K (default: each checkpoint's sample_steps)")
    p.add_argument("--guidance", action="append", type=float, default=None, metavar="S",
                   help="classifier-free guidance scale, one per --checkpoint or one for all (default: the "
                        "checkpoint's)")
    p.add_argument("--eta", type=float, default=0.0,
                   help="DDIM eta of every generation (0: deterministic DDIM, 1: DDPM-like fresh noise each step)")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="three espeak voices (en-us, de, cmn), one take of each real speaker and one seed")
    p.add_argument("--real", action="store_true",
                   help="the real voices only: the training speaker's held-out stretch, lawrence and scott")
    p.add_argument("--out", default=str(RESULTS / "voices.json"))
    p.add_argument("--plot", default=None, help="PNG (default: --out with .png)")
    p.add_argument("--compare", nargs="+", metavar="JSON",
                   help="print the old-vs-new markdown table of these result files and exit (no model is run)")
    args = p.parse_args()
    if args.compare:
        print(compare_table(labelled_models(args.compare)))
        return 0
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    checkpoints = [None if c in (None, "default") else c for c in (args.checkpoint or [None])]
    labels = args.label or [c or "default" for c in checkpoints]
    if len(labels) != len(checkpoints):
        p.error("give one --label per --checkpoint")
    guidance = args.guidance or [None]
    guidance = guidance * len(checkpoints) if len(guidance) == 1 else guidance
    if len(guidance) != len(checkpoints):
        p.error("give one --guidance for all, or one per --checkpoint")
    seeds = 1 if args.quick else args.seeds
    load_before = load_average()
    with tempfile.TemporaryDirectory(prefix="voices_") as tmp:
        voices, skipped = collect_voices(args.quick, Path(tmp), real_only=args.real)
    for name, why in skipped.items():
        print(f"skipped {name}: {why}")
    from dimgestor.evaluation.eval import NOTES

    result = {"benchmark": "voices", "schema": SCHEMA, "created": utc_now(), "code_version": code_version(),
              "device": describe_device("cpu"), "torch": torch.__version__, "espeak_ng": espeak_version(),
              "load_avg_before": load_before,
              "settings": {"steps": args.steps, "seeds": seeds, "seed": args.seed, "quick": args.quick,
                           "real_only": args.real, "variety_window_s": 1.0, "variety_hop_s": 0.25,
                           "smoothing": "off", "silence_s": 6.0, "coupling_smooth_s": 0.5, "coupling_max_lag_s": 0.2,
                           "coupling_shifts": 20, "onset_window_s": [-0.1, 0.3], "onset_stressed_keep": 0.4,
                           "onset_shuffle_draws": 10},
              "voices": {n: {"group": v["group"], "source": v["source"]} for n, v in voices.items()},
              "skipped": skipped, "unseen_groups": list(UNSEEN_GROUPS), "kinds": {k: list(v) for k, v in KINDS.items()},
              "models": {},
              "notes": {k: NOTES[k] for k in ("coupling", "coupling_shifted", "onset_align", "onset_shuffled",
                                              "silence_ratio", "hand_jerk", "nearest", "variety")}}
    started = time.time()
    for label, ckpt, scale in zip(labels, checkpoints, guidance):
        print(f"== {label}")
        result["models"][label] = evaluate(ckpt, voices, args.steps, seeds, args.seed, scale, eta=args.eta)
    result["seconds"] = round(time.time() - started, 1)
    result["load_avg_after"] = load_average()
    for name, v in voices.items():
        result["voices"][name]["seconds"] = len(v["audio"]) / SAMPLE_RATE
    out = Path(args.out)
    write_json(out, result)
    for label in labels:
        print("\n" + model_table(result, label))
    if len(labels) > 1:
        print("\n" + compare_table(list(result["models"].items())))
    plot(result, Path(args.plot) if args.plot else out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
