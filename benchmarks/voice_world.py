"""Do the model's strokes follow voices it never heard, where the right answer is known? (issue 20, item 4)

`dimgestor.evaluation.voiceworld` makes paired speech and motion from espeak-ng voices (11 languages, 10 variants,
pitches, rates, microphone levels) with a rule computed from the audio alone: arms engage while speaking,
strokes at the onsets of stressed syllables sized by their prominence, rest in pauses. A model is trained on
the train voices at each data size (10, 30, 60 min) and scored at several training steps on held-out voices
(disjoint variants, and Italian, a language it never heard), beside:

  rule                 the rule's own motion on the held-out clips: the truth, what a perfect model scores
  rule_shuffled_audio  the rule's motion of clip i scored against the audio of clip i + 1: no relation
  rule_heard           the rule as a perfect streaming listener makes it: each stress decided on the audio
                       heard by the time its stroke starts with the model's lookahead (`rule_events(heard_s=)`),
                       scored against the world's rule: the most a model with that lookahead can score
  rule_learnt_listener the rule's strokes (full size, on time) on the syllables a small MLP trained on the train
                       clips' syllables calls stressed (`voiceworld.StressListener`, the envelope 1 s before to
                       0.25 s after each onset): what a perfect stroke generator with a learnt listener scores;
                       `stress_accuracy` is its balanced accuracy on the held-out syllables

The world's rule decides a stress on its whole phrase (`--rule-heard` unset: the phrase's median loudness, the
spacing against louder syllables on both sides), which no streaming model can hear; `--rule-heard S` writes a
world whose rule decides each stress on what is heard S seconds past its onset (0.25: what a model with 300 ms
of lookahead hears when the stroke starts, 0.05 s before the onset), so that everything it asks is learnable.

Measures (dimgestor/evaluation/metrics.py; every one beside its chance level): speech/silence wrist-speed contrast in
natural pauses; loudness coupling beside circularly shifted audio; stroke alignment: the fraction of the
rule's stroke onsets (computed from the held-out audio) with a wrist-speed peak from 0.1 s before to 0.3 s
after, beside as many onsets shuffled inside speech; stroke gain: the mean wrist speed in the 0.35 s after
each stroke onset over the mean in speech (an event-locked average: how large the movement that follows is,
where the alignment only asks whether some peak is near), beside shuffled onsets; onset alignment to every speech onset (metrics.audio_onsets,
what a researcher measures without knowing the rule) and BeatAlign, each beside its shuffled level.
Pass: stroke-alignment margin over shuffled >= half the rule's, contrast >= half the rule's.

    python benchmarks/voice_world.py                       # 10, 30, 60 min x 500 steps, log-mel: ~50 min here
    python benchmarks/voice_world.py --quick               # 1 + 2 min x 60 steps: a smoke run (~3 min)
    python benchmarks/voice_world.py --set frontend=speech --train-args "--augment" --out results/voice_world_speech.json
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, save_panels, utc_now, write_json

def learnt_listener(data: Path, clips, bundle, heard: float | None, seed: int) -> dict:
    """The rule's motion on the held-out clips with its stresses decided by a StressListener trained on the train
    clips' syllables: full, on-time strokes after a learnt decision, so what a generator with that listening could
    score (its balanced accuracy on the held-out syllables beside it)."""
    from dimgestor.audio import load_wav
    from dimgestor.evaluation.voiceworld import (StressListener, balanced_accuracy, listener_motion, score_motion,
                                                 syllables)
    from dimgestor.features import motion_to_features

    train = [syllables(load_wav(data / f"{name}.wav"), heard_s=heard)
             for name in json.loads((data / "split.json").read_text())["train"]]
    listener = StressListener(seed=seed).fit(np.concatenate([s.windows for s in train]),
                                             np.concatenate([s.stressed for s in train]))
    held = [syllables(a, heard_s=heard) for a, _ in clips]
    raws = [motion_to_features(listener_motion(a, listener, 30.0, heard_s=heard)[0], bundle.feature_spec)[: len(r)]
            for a, r in clips]
    row = score_motion(raws, [a for a, _ in clips], bundle.skeleton, bundle.feature_spec, heard_s=heard)
    row["stress_accuracy"] = balanced_accuracy(np.concatenate([s.stressed for s in held]),
                                               np.concatenate([listener(s.windows) for s in held]))
    return row


def train_run(data: Path, run: Path, args, cache: Path) -> float:
    """`dimgestor train` on the world's train split (its split.json holds the held-out voices out); wall s."""
    from dimgestor.training.train import register

    p = argparse.ArgumentParser()
    register(p.add_subparsers())
    argv = ["train", "--data", str(data), "--out", str(run), "--preset", args.preset, "--recipe", args.recipe,
            "--max-steps", str(args.steps), "--batch-size", str(args.batch_size), "--window-s", "5",
            "--ckpt-every", str(args.ckpt_every), "--valid-every", str(args.steps), "--keep", "0",
            "--threads", "1", "--cache-dir", str(cache), "--no-progress"]
    for item in args.set or []:
        argv += ["--set", item]
    argv += shlex.split(args.train_args)
    ns = p.parse_args(argv)
    started = time.time()
    ns.func(ns)
    return time.time() - started


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", default="10,30,60", help="training data sizes (minutes of train voices)")
    p.add_argument("--heldout-minutes", type=float, default=3.0, help="held-out voices scored")
    p.add_argument("--steps", type=int, default=500, help="training steps per data size")
    p.add_argument("--ckpt-every", type=int, default=125, help="score a checkpoint every this many steps")
    p.add_argument("--preset", default="realtime")
    p.add_argument("--recipe", default="streaming")
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="model config override passed to dimgestor train, e.g. frontend=speech (repeatable)")
    p.add_argument("--train-args", default="", help="more dimgestor train options, e.g. \"--augment --cond-drop 0.1\"")
    p.add_argument("--k", type=int, default=None, help="DDIM steps K when scoring (default: the model's)")
    p.add_argument("--guidance", type=float, default=None, metavar="S",
                   help="classifier-free guidance scale when scoring (default: the model's; needs --cond-drop in "
                        "--train-args)")
    p.add_argument("--eta", type=float, default=0.0,
                   help="DDIM eta when scoring (0: deterministic, as the engine samples; 1: stochastic)")
    p.add_argument("--seed", type=int, default=0, help="world seed (voices' clips, held-out set)")
    p.add_argument("--rule-heard", type=float, default=None, metavar="S",
                   help="the world's rule decides each stress on the audio heard S s past its onset (default: on "
                        "its whole phrase); a new world is written (another --work)")
    p.add_argument("--work", default="runs/voice_world", help="data and runs (reused when present)")
    p.add_argument("--out", default=str(RESULTS / "voice_world.json"))
    p.add_argument("--quick", action="store_true", help="1 and 2 min, 1 min held out, 60 steps: a smoke run")
    args = p.parse_args()
    if args.quick:
        args.minutes, args.heldout_minutes, args.steps, args.ckpt_every = "1,2", 1.0, 60, 30
    import torch

    torch.set_num_threads(1)
    from dimgestor.evaluation.eval import generate_raw, valid_clips
    from dimgestor.features import motion_to_features
    from dimgestor.streaming.checkpoint import load_checkpoint
    from dimgestor.training.dataset import GestureDataset
    from dimgestor.evaluation.voiceworld import (make_voice_world, margins, rule_motion, score_motion, verdict,
                                                 voice_split, world_rule)

    work = Path(args.work)
    cache = work / "cache"
    minutes = [float(m) for m in args.minutes.split(",")]
    tag = "_".join(sorted(args.set or [])) or "default"
    results, truth, timing = {}, None, {}
    for m in minutes:
        data, run = work / f"world_{m:g}min", work / f"run_{m:g}min_{tag}"
        if not (data / "split.json").is_file():
            started = time.time()
            make_voice_world(data, m, args.heldout_minutes, seed=args.seed, heard_s=args.rule_heard)
            timing[f"make_{m:g}min_s"] = round(time.time() - started, 1)
        heard = world_rule(data)
        if heard != args.rule_heard:
            raise SystemExit(f"{data} was written with rule_heard {heard}, not {args.rule_heard}: use another --work")
        if not (run / f"ckpt_{args.steps:07d}").is_dir():
            wall = train_run(data, run, args, cache)
            timing[f"train_{m:g}min_s"] = round(wall, 1)
            print(f"{m:g} min: trained {args.steps} steps in {wall:.0f} s")
        ckpts = sorted(run.glob("ckpt_*"))
        results[f"{m:g}"] = {}
        for ckpt in ckpts:
            bundle = load_checkpoint(ckpt)
            bundle.model.eval()
            spec = bundle.feature_spec
            valid = GestureDataset(data, spec=spec, split="valid", window_s=5.0, cache_dir=cache)
            clips = valid_clips(valid)
            audios = [a for a, _ in clips]
            if truth is None:  # the held-out set is the same in every world (same seed)
                listener_s = bundle.config.lookahead_ms / 1000.0 - 0.05  # heard when the stroke starts
                heard_raws = [motion_to_features(rule_motion(a, 30.0, heard_s=listener_s)[0], spec)[: len(r)]
                              for a, r in clips]
                truth = {"rule": score_motion([r for _, r in clips], audios, bundle.skeleton, spec, heard_s=heard),
                         "rule_shuffled_audio": score_motion([r for _, r in clips], audios[1:] + audios[:1],
                                                            bundle.skeleton, spec, heard_s=heard),
                         "rule_heard": score_motion(heard_raws, audios, bundle.skeleton, spec, heard_s=heard),
                         "rule_learnt_listener": learnt_listener(data, clips, bundle, heard, args.seed)}
                truth["rule_heard"]["heard_s"] = round(listener_s, 3)
                for name, row in truth.items():
                    row.update(margins(row))
                    print(f"{name}: " + ", ".join(f"{k} {v:.3g}" for k, v in row.items()))
            if args.guidance is not None:
                bundle.config = bundle.model.config = bundle.config.model_copy(update={"guidance": args.guidance})
            K = args.k or bundle.config.sample_steps
            started = time.time()
            raws = [generate_raw(bundle, a, K, seed=i, eta=args.eta) for i, a in enumerate(audios)]
            row = score_motion(raws, audios, bundle.skeleton, spec, heard_s=heard)
            row.update(margins(row))
            row.update(verdict(row, truth["rule"]))
            heard_verdict = verdict(row, truth["rule_heard"])  # against what a streaming listener can know
            row["stroke_margin_vs_heard"] = heard_verdict["stroke_margin_vs_rule"]
            row["stroke_gain_margin_vs_heard"] = heard_verdict["stroke_gain_margin_vs_rule"]
            row["generate_s"] = round(time.time() - started, 1)
            step = int(ckpt.name.split("_")[1])
            results[f"{m:g}"][str(step)] = row
            print(f"{m:g} min, step {step}, K={K}: " + ", ".join(f"{k} {v:.3g}" for k, v in row.items()))
    train_voices, held_voices = voice_split(args.seed)
    out = Path(args.out)
    write_json(out, {
        "benchmark": "voice_world", "created": utc_now(), "code_version": code_version(),
        "device": describe_device("cpu"), "load_average": load_average(),
        "command": " ".join(["python", "benchmarks/voice_world.py"] + sys.argv[1:]),
        "preset": args.preset, "recipe": args.recipe, "set": args.set or [], "train_args": args.train_args,
        "guidance": args.guidance, "eta": args.eta, "rule_heard_s": args.rule_heard,
        "train_steps": args.steps, "batch_size": args.batch_size, "heldout_minutes": args.heldout_minutes,
        "train_voices": [v.name for v in train_voices], "heldout_voices": [v.name for v in held_voices],
        "output_filter": "off", "timing_s": timing, "truth": truth, "results": results,
        "notes": {"stroke_align": "fraction of the rule's stroke onsets (from the held-out audio) with a wrist-speed "
                                  "peak 0.1 s before to 0.3 s after (metrics.onset_alignment)",
                  "stroke_shuffled": "the same for as many onsets shuffled inside speech: chance",
                  "stroke_gain": "mean wrist speed 0-0.35 s after the rule's stroke onsets / mean speed in speech "
                                 "(metrics.onset_locked_speed): how large the movement after a stroke onset is; "
                                 "stroke_gain_shuffled: the same after shuffled onsets (~1)",
                  "onset_align": "the same for every speech onset (metrics.audio_onsets)",
                  "contrast": "mean wrist speed in speech / in silence (0.75 s away from speech), natural pauses",
                  "coupling": "metrics.speech_coupling; coupling_shifted: the mean against shifted audio",
                  "passes": "stroke margin >= half the rule's and contrast >= half the rule's"}})
    plot(results, truth, out.with_suffix(".png"), args)
    return 0


def plot(results: dict, truth: dict, path: Path, args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("contrast", "speech / silence wrist speed"), ("stroke_margin", "stroke alignment - shuffled"),
              ("stroke_gain_margin", "speed after strokes - shuffled"),
              ("coupling_margin", "loudness coupling - shifted"), ("onset_margin", "all-onset alignment - shuffled")]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.4 * len(panels), 3.4))
    for ax, (metric, title) in zip(axes, panels):
        for m, by_step in results.items():
            steps = sorted(int(s) for s in by_step)
            ax.plot(steps, [by_step[str(s)][metric] for s in steps], "o-", label=f"{m} min")
        ax.axhline(truth["rule"][metric], color="k", lw=1, label="rule (truth)")
        ax.axhline(0.5 * truth["rule"][metric], color="k", lw=1, ls="--", label="half the rule")
        ax.axhline(truth["rule_shuffled_audio"][metric], color="0.6", lw=1, ls=":", label="rule, shuffled audio")
        ax.axhline(truth["rule_heard"][metric], color="tab:red", lw=1, ls="-.",
                   label=f"rule heard {truth['rule_heard']['heard_s']:g} s past onsets")
        if "rule_learnt_listener" in truth:  # results written before it have no such row
            ax.axhline(truth["rule_learnt_listener"][metric], color="tab:green", lw=1, ls="--",
                       label=f"rule on a learnt listener's calls "
                             f"({truth['rule_learnt_listener']['stress_accuracy']:.2f} right)")
        ax.set_xlabel("training steps")
        ax.set_title(title, fontsize=9)
    extra = " ".join(args.set or []) + (f" {args.train_args}" if args.train_args else "")
    save_panels(fig, axes, f"voice world, held-out voices: {args.preset} {extra or '(log-mel)'}", path)


if __name__ == "__main__":
    sys.exit(main())
