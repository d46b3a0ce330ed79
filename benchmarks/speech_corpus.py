"""Speech without motion for `dimgestor distill --audio`: espeak-ng passages, every language of
`dimgestor.evaluation.phone_timed` read by several voice variants, written as 16 kHz WAV files.

    .venv/bin/python benchmarks/speech_corpus.py --out /tmp/speech [--variants m1 m2 f1 ...] [--languages en-us de]

Each file is one passage (all of a language's sentences, pauses between them, rate and pitch drawn from the seed),
named LANGUAGE_VARIANT.wav. Needs Debian's espeak-ng (libespeak-ng). Real speech is better where you have it; this
is what can be made on any machine.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dimgestor.audio import save_wav  # noqa: E402
from dimgestor.evaluation.phone_timed import LANGUAGES, passage  # noqa: E402

VARIANTS = ("m1", "m2", "m4", "m7", "f1", "f4", "klatt2", "iven")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, type=Path, help="folder for the WAV files")
    p.add_argument("--languages", nargs="+", default=list(LANGUAGES), choices=LANGUAGES)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), help="espeak-ng voice variants")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    seconds = 0.0
    for i, lang in enumerate(args.languages):
        for j, variant in enumerate(args.variants):
            spoken = passage(lang, variant, seed=args.seed * 10_000 + i * 100 + j)
            save_wav(args.out / f"{lang}_{variant}.wav", spoken.audio, spoken.rate)
            seconds += spoken.seconds
    print(f"{len(args.languages) * len(args.variants)} passages, {seconds / 60:.1f} min, in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
