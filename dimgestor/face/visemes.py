"""What a mouth does for each speech sound: ARPAbet phones (the English phone set of the CMU dictionary, which
the listener's acoustic model uses) -> the 15 visemes of the Oculus/Ready Player Me set and how open the jaw is.

The face's canonical vector (`FACE_LABELS`) is those 15 viseme weights, the jaw's opening, both eyelids, the
brows and a smile; every name set a sink sends (VRM 0, VRM 1, ARKit, Oculus) is made from it (`names.py`).

Openness follows phonetics' vowel height (the same table the evaluation's reference uses): open vowels 1, mid
0.7-0.8, close 0.4-0.5, other consonants 0.25, lips closed (M, B, P) and silence 0.
"""

from __future__ import annotations

import numpy as np

__all__ = ["VISEMES", "FACE_LABELS", "PHONES", "OPENNESS", "VOWEL_CLASS", "phone_targets", "canonical_phone",
           "viseme_of"]

VISEMES = ("sil", "PP", "FF", "TH", "DD", "kk", "CH", "SS", "nn", "RR", "aa", "E", "I", "O", "U")
FACE_LABELS = VISEMES + ("jawOpen", "blinkLeft", "blinkRight", "browUp", "smile")
V = {name: i for i, name in enumerate(FACE_LABELS)}

# phone -> (viseme, openness). Diphthongs take their first, longer part; ER is a rounded mid vowel.
_PHONES = {
    "AA": ("aa", 1.0), "AE": ("aa", 1.0), "AH": ("aa", 1.0), "AW": ("aa", 1.0), "AY": ("aa", 1.0),
    "EH": ("E", 0.75), "EY": ("I", 0.7), "ER": ("RR", 0.7),
    "IH": ("I", 0.5), "IY": ("I", 0.4),
    "AO": ("O", 0.8), "OW": ("O", 0.7), "OY": ("O", 0.75),
    "UH": ("U", 0.5), "UW": ("U", 0.4),
    "M": ("PP", 0.0), "B": ("PP", 0.0), "P": ("PP", 0.0),
    "F": ("FF", 0.25), "V": ("FF", 0.25),
    "TH": ("TH", 0.25), "DH": ("TH", 0.25),
    "T": ("DD", 0.25), "D": ("DD", 0.25),
    "K": ("kk", 0.25), "G": ("kk", 0.25), "NG": ("kk", 0.25), "HH": ("kk", 0.25),
    "CH": ("CH", 0.25), "JH": ("CH", 0.25), "SH": ("CH", 0.25), "ZH": ("CH", 0.25),
    "S": ("SS", 0.25), "Z": ("SS", 0.25),
    "N": ("nn", 0.25), "L": ("nn", 0.25),
    "R": ("RR", 0.25), "W": ("U", 0.25), "Y": ("I", 0.25),
    "SIL": ("sil", 0.0),
}
PHONES = tuple(_PHONES)
OPENNESS = {p: o for p, (_, o) in _PHONES.items()}

# The five VRM mouth shapes of the vowels (the evaluation's classes; ER has none of them)
VOWEL_CLASS = {"AA": "A", "AH": "A", "AE": "A", "AY": "A", "AW": "A", "IY": "I", "IH": "I", "EY": "I",
               "UW": "U", "UH": "U", "EH": "E", "AO": "O", "OW": "O", "OY": "O"}


def canonical_phone(label: str) -> str:
    """An ARPAbet label as a key of the tables: stress digits dropped, upper case; silence, noise and anything
    unknown ("", "sp", "+NSN+", "<sil>") is "SIL"."""
    p = "".join(ch for ch in label if not ch.isdigit()).upper()
    return p if p in _PHONES else "SIL"


def phone_targets(phone: str) -> np.ndarray:
    """The canonical face vector (len(FACE_LABELS),) a phone aims at: its viseme's weight and the jaw's opening
    (viseme weight 1 except for the vowels' height, which scales their shape as it scales the jaw)."""
    viseme, openness = _PHONES[canonical_phone(phone)]
    out = np.zeros(len(FACE_LABELS))
    out[V[viseme]] = openness if viseme in ("aa", "E", "I", "O", "U") else 1.0
    out[V["jawOpen"]] = openness
    return out


def viseme_of(phone: str) -> str:
    """The viseme (one of `VISEMES`) a phone's mouth makes."""
    return _PHONES[canonical_phone(phone)][0]
