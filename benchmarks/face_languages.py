"""The speaking face's mouth in many languages: espeak-ng speech whose every phone's time is known, scored as the
real English takes are (`benchmarks/face.py`), language by language.

For each language of `dimgestor.evaluation.phone_timed` and each espeak-ng voice variant (`--variants`), one
passage (`phone_timed.passage`: the language's sentences, rate and pitch drawn per sentence, pauses between) is
streamed through the shipped face (`FaceStream`, 20 fps, lookahead 0.3 s, in `--chunk-ms` pieces; its own
listener, and beside it the pocketsphinx listener where installed) and scored with
`dimgestor.face.evaluate.mouth_scores` against espeak-ng's own phone times, each IPA phone mapped onto the mouth of
an ARPAbet phone by its articulation (`dimgestor.face.ipa`). Beside it, the loudness-only jaw of
`benchmarks/face.py` (the best of its grid per passage). The face's listener was trained on espeak-ng speech of
these languages with other voice variants (`benchmarks/face_net.py`: these variants are held out; the sentences
are the same); pocketsphinx's English acoustic model never heard these voices or languages.

    .venv/bin/python benchmarks/face_languages.py                 # writes results/face_languages.json and .png
    .venv/bin/python benchmarks/face_languages.py --languages de ja --variants f2
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json
from face import RATE, loudness_jaw, rounded, stream_face

SCORES = ("openness_r", "vowel_top1", "vowel_mean_recall", "closures", "rest")


def parse_args(argv=None) -> argparse.Namespace:
    from dimgestor.evaluation.phone_timed import LANGUAGES

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--languages", nargs="+", default=list(LANGUAGES), choices=LANGUAGES, metavar="LANG",
                   help=f"espeak-ng languages (default: all: {' '.join(LANGUAGES)})")
    p.add_argument("--variants", nargs="+", default=["m3", "f2", "klatt3"], help="espeak-ng voice variants")
    p.add_argument("--sentences", type=int, default=None, help="sentences per passage (default: all of the language's)")
    p.add_argument("--seed", type=int, default=0, help="rates, pitches and pauses of the passages")
    p.add_argument("--chunk-ms", type=int, default=100, help="audio pushed per call to the face, as a live stream")
    p.add_argument("--out", type=Path, default=RESULTS / "face_languages.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def score_passage(spoken, chunk: int) -> dict:
    from dimgestor.evaluation.phone_timed import alignment
    from dimgestor.face import FaceOptions
    from dimgestor.face.evaluate import mouth_scores

    assert spoken.rate == RATE
    phones = alignment(spoken)
    face, _ = stream_face(spoken.audio, 20, 0.3, FaceOptions(), chunk)
    other = {}
    if importlib.util.find_spec("pocketsphinx") is not None:
        ps, _ = stream_face(spoken.audio, 20, 0.3, FaceOptions(listener="pocketsphinx"), chunk)
        other["pocketsphinx"] = mouth_scores(ps, phones, 20)
    grid = {f"{rng:g}dB^{pw:g}": mouth_scores(loudness_jaw(spoken.audio, 20, 0.3, rng, pw), phones, 20)
            for rng in (20, 30, 40) for pw in (0.5, 1.0)}
    best = max(grid, key=lambda k: grid[k]["openness_r"])
    return {"face": mouth_scores(face, phones, 20), **other,
            "loudness_jaw": {**{k: grid[best][k] for k in ("frames", "openness_r", "closures", "rest")},
                             "setting": best}}


def summarise(rows: list[dict]) -> dict:
    """Per language: each score's mean over the voices (the face's, and the loudness jaw's openness r)."""
    out = {}
    for lang in dict.fromkeys(r["language"] for r in rows):
        mine = [r for r in rows if r["language"] == lang]
        out[lang] = {"voices": len(mine), "seconds": round(sum(r["seconds"] for r in mine), 1),
                     **{s: round(float(np.mean([r["face"][s] for r in mine])), 3) for s in SCORES},
                     "always_A": round(float(np.mean([r["face"]["always_A"] for r in mine])), 3),
                     "loudness_openness_r": round(float(np.mean([r["loudness_jaw"]["openness_r"] for r in mine])), 3),
                     **({"pocketsphinx": {s: round(float(np.mean([r["pocketsphinx"][s] for r in mine])), 3)
                                          for s in SCORES}} if all("pocketsphinx" in r for r in mine) else {})}
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    langs = list(result["per_language"])
    per = result["per_language"]
    fig, ax = plt.subplots(figsize=(max(7.0, 0.9 * len(langs) + 2), 4.4))
    x = np.arange(len(langs))
    bars = (("openness_r", "jaw openness r"), ("vowel_top1", "vowel class top-1"),
            ("vowel_mean_recall", "vowel mean recall"), ("closures", "lips closed at M/B/P"))
    w = 0.8 / len(bars)
    for i, (k, label) in enumerate(bars):
        ax.bar(x + (i - 1.5) * w, [per[lang][k] for lang in langs], w, label=label)
    ax.scatter(x - 1.5 * w, [per[lang]["loudness_openness_r"] for lang in langs], marker="_", s=200, color="k",
               zorder=3, label="loudness-only jaw: openness r")
    ax.scatter(x + 0.5 * w, [per[lang]["always_A"] for lang in langs], marker="_", s=200, color="tab:red",
               zorder=3, label='always "A": top-1')
    ax.set_xticks(x, langs)
    ax.set_ylim(0, 1)
    ax.set_ylabel("score (higher is better)")
    ax.set_title("The face's mouth on espeak-ng speech, per language (mean over voices)")
    ax.legend(fontsize=7, ncol=6, loc="upper center", bbox_to_anchor=(0.5, -0.08), frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    from dimgestor.evaluation.phone_timed import passage

    args = parse_args(argv)
    chunk = RATE * args.chunk_ms // 1000
    rows, load_before = [], load_average()
    t0 = time.perf_counter()
    for lang in args.languages:
        for k, variant in enumerate(args.variants):
            spoken = passage(lang, variant, seed=args.seed * 1000 + k, sentences=args.sentences, sample_rate=RATE)
            r = score_passage(spoken, chunk)
            rows.append({"language": lang, "voice": spoken.voice, "seconds": round(spoken.seconds, 2),
                         "phones": sum(1 for _, _, p in spoken.phones if p), **rounded(r)})
            f = r["face"]
            print(f"{spoken.voice:12s} {spoken.seconds:5.1f} s  r {f['openness_r']:.2f} (loudness "
                  f"{r['loudness_jaw']['openness_r']:.2f})  vowel {f['vowel_top1']:.2f} / {f['vowel_mean_recall']:.2f}"
                  f"  closures {f['closures']:.2f}  rest {f['rest']:.2f}", flush=True)
    result = {"benchmark": "face_languages", "code_version": code_version(), "device": describe_device("cpu"), "load_average_before": load_before,
              "utc": utc_now(), "argv": args.argv, "note": args.note,
              "listener": "the shipped FaceStream (pocketsphinx's English acoustic model), 20 fps, lookahead 0.3 s",
              "reference": "espeak-ng's phoneme events (libespeak-ng), IPA mapped by dimgestor.face.ipa",
              "seconds_taken": round(time.perf_counter() - t0, 1), "rows": rows, "per_language": summarise(rows)}
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    print(f"wrote {args.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
