"""How well a mouth follows what was said: per-frame measures against a forced phone alignment (the issue's
targets; `benchmarks/face.py` runs them on real speech).

- openness: Pearson correlation of the jaw's opening with the alignment's phone openness (`visemes.OPENNESS`);
- vowel class: on frames inside a vowel of the five VRM classes, whether the strongest of A I U E O is that
  vowel's (top-1 accuracy, and the mean of the per-class recalls);
- closures: at the centre of each M, B, P the jaw is at most 0.35 of its median over vowel frames;
- rest: in silences of 0.3 s and more, from 0.15 s in, the jaw's mean over that vowel median.
"""

from __future__ import annotations

import numpy as np

from dimgestor.face.visemes import OPENNESS, V, VOWEL_CLASS, canonical_phone

__all__ = ["mouth_scores", "mouth_lag", "VOWEL_SHAPES"]

VOWEL_SHAPES = ("A", "I", "U", "E", "O")
_SHAPE_INDEX = [V["aa"], V["I"], V["U"], V["E"], V["O"]]


def mouth_scores(face: np.ndarray, phones: list[tuple[float, float, str]], fps: int) -> dict:
    """face: (T, len(FACE_LABELS)) canonical frames (frame i at i / fps); phones: the alignment's intervals."""
    from dimgestor.face.textgrid import phones_at

    times = np.arange(len(face)) / fps
    ref = [canonical_phone(p) for p in phones_at(phones, times)]
    ref_open = np.array([OPENNESS[p] for p in ref])
    jaw = face[:, V["jawOpen"]]
    out = {"frames": len(face), "openness_r": float(np.corrcoef(jaw, ref_open)[0, 1])}

    vowel = np.array([p in VOWEL_CLASS for p in ref])
    shapes = face[:, _SHAPE_INDEX]
    guess = np.array(VOWEL_SHAPES)[np.argmax(shapes, axis=1)]
    truth = np.array([VOWEL_CLASS.get(p, "") for p in ref])
    out["vowel_top1"] = float(np.mean(guess[vowel] == truth[vowel]))
    recalls = {c: float(np.mean(guess[truth == c] == c)) for c in VOWEL_SHAPES if np.any(truth == c)}
    out["vowel_recall"] = recalls
    out["vowel_mean_recall"] = float(np.mean(list(recalls.values())))
    out["always_A"] = float(np.mean(truth[vowel] == "A"))

    median = float(np.median(jaw[vowel])) if vowel.any() else 1.0
    centres = [(a + b) / 2 for a, b, p in phones if canonical_phone(p) in ("M", "B", "P")]
    idx = [int(round(c * fps)) for c in centres if int(round(c * fps)) < len(face)]
    out["closures"] = float(np.mean(jaw[idx] <= 0.35 * median)) if idx else float("nan")
    rest = []
    for a, b, p in phones:
        if canonical_phone(p) == "SIL" and b - a >= 0.3:
            k0, k1 = int(np.ceil((a + 0.15) * fps)), min(int(np.floor(b * fps)), len(face))
            rest.extend(jaw[k0:k1])
    out["rest"] = float(np.mean(rest) / max(median, 1e-9)) if rest else float("nan")
    out["vowel_median_jaw"] = median
    return out


def mouth_lag(face: np.ndarray, phones: list[tuple[float, float, str]], fps: int, rate: int = 100,
              max_s: float = 0.2) -> tuple[float, dict[float, float]]:
    """When the mouth shows a sound against when it was said: the lag (s, positive = the mouth late) at which the
    jaw, held at its frames and read at `rate` Hz, best correlates with the alignment's openness, and the
    correlation at each lag tried (within +-max_s, a 1/rate step)."""
    from dimgestor.face.textgrid import phones_at

    times = np.arange(int(len(face) / fps * rate)) / rate
    jaw = face[np.minimum((times * fps + 1e-9).astype(int), len(face) - 1), V["jawOpen"]]
    ref = np.array([OPENNESS[canonical_phone(p)] for p in phones_at(phones, times)])
    k = int(round(max_s * rate))
    r = {}
    for lag in range(-k, k + 1):  # jaw[t + lag] against ref[t]
        a, b = (jaw[lag:], ref[:len(ref) - lag]) if lag >= 0 else (jaw[:lag], ref[-lag:])
        r[lag / rate] = float(np.corrcoef(a, b)[0, 1])
    best = max(r, key=r.get)
    return best, r
