"""Which listener makes the gestures follow a stranger's real voice? Train each candidate, score it on real voices.

Issue "real voices": every candidate is the default model's recipe (`make default-model`: realtime preset, speech
front end, 300 ms lookahead, condition dropout 0.15, 1200 steps, batch 8, 5 s windows, mirrored and 0.9x / 1.1x
speed-perturbed copies, seed 0, last 15 s held out) with one change, then scored by `benchmarks/voices.py`'s
real voices (the training speaker's held-out 15 s; BEAT lawrence and BEAT2 scott, two takes each), K = 4, 3
seeds, the candidate's guidance (1.25): coupling, rest in an inserted silence, wrist jerk over the real capture's,
variety. How far each front end's features move between speakers is `benchmarks/speaker_shift.py`.

    python benchmarks/listeners.py --runs runs/listeners                  # train every candidate, then score
    python benchmarks/listeners.py --runs runs/listeners --only embed     # one candidate
    python benchmarks/listeners.py --runs runs/listeners --no-train       # score the run folders there

Each candidate trains in about 6 minutes on one core (OMP_NUM_THREADS=1); scoring takes about 2 minutes.
Needs ../shared (the ZEGGS clip and the real voices).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json  # noqa: E402
import voices  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
ZEGGS = REPO.parent / "shared" / "data" / "zeggs_sample"
SCHEMA = 1

# The default model's training run (Makefile `default-model`), as TrainConfig fields.
BASE = dict(preset="realtime", recipe="streaming", max_steps=1200, window_s=5.0, batch_size=8, ckpt_every=400,
            valid_every=400, seed=0, valid_seconds=15.0, augment=False, mirror=True, speeds=(0.9, 1.1),
            cond_drop=0.15, overrides={"frontend": "speech", "lookahead_ms": 300, "down_kernel": 41})

# Only the loudness contour changes (no voice, room, noise, microphone or level): `flat*` below.
_ONLY_DYNAMICS = {"p_pitch": 0.0, "p_formant": 0.0, "p_reverb": 0.0, "p_noise": 0.0, "p_eq": 0.0, "p_band": 0.0,
                  "p_gain": 0.0, "p_dynamics": 0.75, "dynamics_ratio": (0.35, 1.0)}

# name: (what changes, TrainConfig fields replacing BASE's; "overrides" are merged into BASE's)
CANDIDATES: dict[str, tuple[str, dict]] = {
    "default": ("the default model's own recipe (`make default-model`)", {}),
    "voice_aug": ("voice-conversion augmentation of the training audio: 4 copies, pitch -8..+3 semitones (p 0.8), "
                  "formants x0.8-1.12 (vocal-tract length, p 0.8), some room, noise, microphone EQ and band limits",
                  {"augment": True, "aug_copies": 4,
                   "aug_config": {"p_pitch": 0.8, "semitones": (-8.0, 3.0), "p_formant": 0.8,
                                  "formant_ratio": (0.8, 1.12), "p_reverb": 0.2, "p_noise": 0.2,
                                  "snr_db": (15.0, 35.0), "p_eq": 0.4, "p_band": 0.2}}),
    "mel8": ("8 level-free bands instead of 64 (coarser spectra: less timbre, less of what was said)",
             {"overrides": {"n_mels": 8}}),
    "mel2": ("2 bands: prosody (loudness, onsets, voicing, pitch, pauses) and spectral tilt only",
             {"overrides": {"n_mels": 2}}),
    "embed": ("the speech front end plus Google's pretrained speech embedding (96 numbers every 80 ms, "
              "openWakeWord's ONNX copy; dimgestor/frontend/embed.py)", {"overrides": {"frontend": "embedding"}}),
    "embed_mel8": ("the embedding with 8 bands: the embedding carries what was said",
                   {"overrides": {"frontend": "embedding", "n_mels": 8}}),
    "warp": ("more time warping: 0.8x, 0.9x, 1.1x, 1.25x speed-perturbed copies", {"speeds": (0.8, 0.9, 1.1, 1.25)}),
    "drop30": ("condition dropout 0.3 and 1600 steps (more of the unconditional motion, longer)",
               {"cond_drop": 0.3, "max_steps": 1600}),
    "flat": ("the actor's loudness contour flattened in 3 of 4 extra copies of the training audio (its deviations "
             "x0.35-1, log-uniform): strangers vary their loudness half to three quarters as much as she does",
             {"augment": True, "aug_copies": 4, "aug_config": _ONLY_DYNAMICS}),
    "flat_seed1": ("`flat`, training seed 1", {"augment": True, "aug_copies": 4, "aug_config": _ONLY_DYNAMICS, "seed": 1}),
    "flat_seed2": ("`flat`, training seed 2", {"augment": True, "aug_copies": 4, "aug_config": _ONLY_DYNAMICS, "seed": 2}),
    "arms": ("body-part mixing: a third copy of every window with one arm's motion on both sides (its mirror "
             "image on the other, the sides taking turns), on the same speech", {"arm_mix": True}),
    "arms_seed1": ("`arms`, training seed 1", {"arm_mix": True, "seed": 1}),
    "arms_seed2": ("`arms`, training seed 2", {"arm_mix": True, "seed": 2}),
    # how far the training seed alone moves the numbers: compare a candidate with these, not with `default` alone
    "default_seed1": ("the default recipe, training seed 1", {"seed": 1}),
    "default_seed2": ("the default recipe, training seed 2", {"seed": 2}),
    "embed_seed1": ("`embed`, training seed 1", {"overrides": {"frontend": "embedding"}, "seed": 1}),
}


def train_config(name: str, runs: Path):
    from dimgestor.training.train import TrainConfig

    fields = {**BASE, **{k: v for k, v in CANDIDATES[name][1].items() if k != "overrides"}}
    fields["overrides"] = {**BASE["overrides"], **CANDIDATES[name][1].get("overrides", {})}
    return TrainConfig(data=str(ZEGGS), out=str(runs / name), progress=False, **fields)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", required=True, help="folder of the candidates' run folders (one per name)")
    p.add_argument("--only", action="append", choices=list(CANDIDATES), help="these candidates (repeatable)")
    p.add_argument("--no-train", action="store_true", help="score the run folders already in --runs")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--out", default=str(RESULTS / "listeners.json"),
                   help="results file; candidates already in it and not run now are kept")
    args = p.parse_args()
    if not ZEGGS.is_dir():
        print(f"skipped: {ZEGGS} not found (the ZEGGS clip and the real voices live beside the dev checkout)")
        return 0
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    names = args.only or list(CANDIDATES)
    runs = Path(args.runs)
    load_before = load_average()
    with tempfile.TemporaryDirectory(prefix="listeners_") as tmp:
        heard, skipped = voices.collect_voices(False, Path(tmp), real_only=True)
    result = {"benchmark": "listeners", "schema": SCHEMA, "created": utc_now(), "code_version": code_version(),
              "device": describe_device("cpu"), "torch": torch.__version__, "load_avg_before": load_before,
              "base_recipe": {k: (list(v) if isinstance(v, tuple) else v) for k, v in BASE.items()},
              "settings": {"steps": 4, "seeds": args.seeds, "guidance": "each checkpoint's (1.25)"},
              "voices": {n: {"group": v["group"], "source": v["source"]} for n, v in heard.items()},
              "skipped": skipped, "candidates": {}}
    out = Path(args.out)
    if out.is_file():  # keep the candidates scored before and not run now (each records its own code version)
        kept = json.loads(out.read_text()).get("candidates", {})
        result["candidates"] = {n: m for n, m in kept.items() if n not in names}
    for name in names:
        what, _ = CANDIDATES[name]
        folder = runs / name
        trained_s = None
        if not args.no_train:
            from dimgestor.training.train import train

            started = time.time()
            train(train_config(name, runs))
            trained_s = round(time.time() - started, 1)
        checkpoint = str(folder)
        if not folder.is_dir():
            if name != "default":
                print(f"{name}: no run folder {folder} (train it, or drop --no-train)")
                continue
            checkpoint = None  # the embedded default model: `make default-model` trains it bit for bit
        print(f"== {name}: {what}")
        m = voices.evaluate(checkpoint, dict(heard), None, args.seeds, 0)
        m["what"], m["train_seconds"], m["code_version"] = what, trained_s, result["code_version"]
        m["train_options"] = train_config(name, runs).model_dump(mode="json", exclude={"data", "out", "progress"})
        result["candidates"][name] = m
    result["candidates"] = {n: result["candidates"][n] for n in CANDIDATES if n in result["candidates"]}
    result["load_avg_after"] = load_average()
    write_json(out, result)
    print("\n" + table(result))
    plot(result, out.with_suffix(".png"))
    return 0


def table(result: dict) -> str:
    """Markdown: a row per candidate: held-out and real unseen coupling, above chance, silence, jerk, variety."""
    lines = ["| candidate | held-out coupling | real unseen coupling (min) | above chance | silence ratio (min) | "
             "jerk / real (max) | variety |", "|---|---|---|---|---|---|---|"]
    for name, m in result["candidates"].items():
        h = m["rows"].get("zeggs_heldout", {})
        s = voices.unseen_summary(m, "real") or {}
        lines.append(f"| {name} | {voices.cell('{:+.2f}', h.get('coupling'))} | "
                     f"{s.get('coupling', float('nan')):+.2f} ({s.get('coupling_min', float('nan')):+.2f}) | "
                     f"{s.get('above_chance', 0)}/{s.get('voices', 0)} | {s.get('silence_ratio', float('nan')):.2f} "
                     f"({s.get('silence_ratio_min', float('nan')):.2f}) | {s.get('jerk_ratio', float('nan')):.2f} "
                     f"({s.get('jerk_ratio_max', float('nan')):.2f}) | {s.get('variety', float('nan')):.2f} |")
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["candidates"])
    if not names:
        return
    summ = [voices.unseen_summary(result["candidates"][n], "real") or {} for n in names]
    held = [result["candidates"][n]["rows"].get("zeggs_heldout", {}).get("coupling", np.nan) for n in names]
    x = np.arange(len(names))
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    axes[0].bar(x - 0.2, held, 0.4, label="training speaker, held-out")
    axes[0].bar(x + 0.2, [s.get("coupling", np.nan) for s in summ], 0.4, label="real unseen voices (mean)")
    axes[0].axhline(0.45, color="k", ls=":", lw=1, label="issue target, real voices")
    axes[0].set_ylabel("loudness coupling r")
    axes[1].bar(x, [s.get("silence_ratio", np.nan) for s in summ], 0.6)
    axes[1].axhline(3.0, color="k", ls=":", lw=1)
    axes[1].set_ylabel("speech / inserted silence (real voices)")
    axes[2].bar(x - 0.2, [s.get("variety", np.nan) for s in summ], 0.4, label="variety")
    axes[2].bar(x + 0.2, [s.get("jerk_ratio", np.nan) for s in summ], 0.4, label="wrist jerk / real")
    axes[2].axhline(0.85, color="C0", ls=":", lw=1)
    axes[2].axhline(1.5, color="C1", ls=":", lw=1)
    for ax in axes:
        ax.set_xticks(x, names, rotation=35, ha="right", fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[2].legend(fontsize=7)
    fig.suptitle(f"listener candidates on real voices: K = 4, {result['settings']['seeds']} seeds "
                 f"({result['code_version']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())
