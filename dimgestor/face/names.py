"""The face's name sets: the canonical face vector (`visemes.FACE_LABELS`) as the blendshape names a rig knows.

- "vrm0": VRM 0.x presets A I U E O, Blink, Blink_L, Blink_R, Joy (VSeeFace, VMagicMirror, UniVRM 0.x);
- "vrm1": VRM 1.0 expressions aa ih ou ee oh, blink, blinkLeft, blinkRight, happy;
- "arkit": Apple ARKit's 52 blendshapes (MetaHuman's curves, Live Link Face, many VTuber rigs), all of them;
- "oculus": the 15 Oculus visemes as Ready Player Me names them (viseme_sil ... viseme_U), and its eyeBlinkLeft,
  eyeBlinkRight.

Rigs with only the five vowels (VRM) show consonants as the vowel shape nearest to them (a little open); lips
closed on M, B, P are the vowels at zero. Both eyes closing together is `Blink`/`blink`, and what one eye closes
beyond the other its own name, so the two never add up to more than a full blink.
"""

from __future__ import annotations

import numpy as np

from dimgestor.face.visemes import FACE_LABELS, V, VISEMES

__all__ = ["NAME_SETS", "DEFAULT_NAMES", "ARKIT", "names_of", "convert", "check_name_set"]

ARKIT = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose", "mouthFunnel",
    "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft",
    "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft", "mouthPressRight",
    "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "browDownLeft",
    "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff", "cheekSquintLeft",
    "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut")

# Each viseme as the five vowel shapes (A I U E O) of a rig that has only those: consonants take the vowel
# nearest their mouth, at the strength a consonant's opening shows.
_VOWEL_OF = {
    "sil": {}, "PP": {},
    "FF": {"I": 0.2}, "TH": {"E": 0.25}, "DD": {"E": 0.2, "I": 0.1}, "kk": {"E": 0.2, "A": 0.1},
    "CH": {"U": 0.2, "I": 0.1}, "SS": {"I": 0.25}, "nn": {"E": 0.2, "I": 0.1}, "RR": {"O": 0.2, "U": 0.2},
    "aa": {"A": 1.0}, "E": {"E": 1.0}, "I": {"I": 1.0}, "O": {"O": 1.0}, "U": {"U": 1.0},
}
_VOWELS = ("A", "I", "U", "E", "O")
_TO_VOWELS = np.zeros((len(VISEMES), 5))
for _v, _w in _VOWEL_OF.items():
    for _s, _x in _w.items():
        _TO_VOWELS[VISEMES.index(_v), _VOWELS.index(_s)] = _x


def _vowels(face: np.ndarray) -> np.ndarray:
    """(T, 5) A I U E O: the vowel visemes carry their own height; consonants add their nearest vowel."""
    vis = face[:, : len(VISEMES)].copy()
    for v in ("aa", "E", "I", "O", "U"):  # a vowel viseme's weight is already its height (visemes.phone_targets)
        vis[:, V[v]] = face[:, V[v]]
    return np.clip(vis @ _TO_VOWELS, 0, 1)


def _blinks(face: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    left, right = face[:, V["blinkLeft"]], face[:, V["blinkRight"]]
    both = np.minimum(left, right)
    return both, left - both, right - both


def _vrm0(face):
    both, left, right = _blinks(face)
    return np.column_stack([_vowels(face), both, left, right, face[:, V["smile"]]])


def _arkit(face):
    out = np.zeros((len(face), len(ARKIT)))
    col = {n: i for i, n in enumerate(ARKIT)}
    f = lambda name: face[:, V[name]]  # noqa: E731
    jaw = f("jawOpen")
    out[:, col["jawOpen"]] = jaw
    out[:, col["eyeBlinkLeft"]], out[:, col["eyeBlinkRight"]] = f("blinkLeft"), f("blinkRight")
    out[:, col["mouthClose"]] = np.minimum(f("PP"), 0.3)  # lips together over a slightly open jaw
    out[:, col["mouthPressLeft"]] = out[:, col["mouthPressRight"]] = 0.5 * f("PP")
    out[:, col["mouthFunnel"]] = np.clip(0.6 * f("O") + 0.5 * f("CH") + 0.3 * f("RR"), 0, 1)
    out[:, col["mouthPucker"]] = np.clip(0.9 * f("U") + 0.3 * f("RR") + 0.2 * f("O"), 0, 1)
    stretch = np.clip(0.6 * f("I") + 0.4 * f("E") + 0.3 * f("SS"), 0, 1)
    out[:, col["mouthStretchLeft"]] = out[:, col["mouthStretchRight"]] = stretch
    out[:, col["mouthRollLower"]] = 0.7 * f("FF")
    out[:, col["mouthUpperUpLeft"]] = out[:, col["mouthUpperUpRight"]] = 0.3 * f("FF")
    lower = np.clip(0.4 * f("aa") + 0.3 * f("E") + 0.2 * f("TH"), 0, 1)
    out[:, col["mouthLowerDownLeft"]] = out[:, col["mouthLowerDownRight"]] = lower
    out[:, col["tongueOut"]] = 0.3 * f("TH")
    smile = f("smile")
    out[:, col["mouthSmileLeft"]] = out[:, col["mouthSmileRight"]] = smile
    out[:, col["cheekSquintLeft"]] = out[:, col["cheekSquintRight"]] = 0.4 * smile
    out[:, col["browInnerUp"]] = f("browUp")
    out[:, col["browOuterUpLeft"]] = out[:, col["browOuterUpRight"]] = 0.7 * f("browUp")
    return np.clip(out, 0, 1)


def _oculus(face):
    return np.column_stack([face[:, : len(VISEMES)], face[:, V["blinkLeft"]], face[:, V["blinkRight"]]])


NAME_SETS = {
    "vrm0": (("A", "I", "U", "E", "O", "Blink", "Blink_L", "Blink_R", "Joy"), _vrm0),
    "vrm1": (("aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft", "blinkRight", "happy"), _vrm0),
    "arkit": (ARKIT, _arkit),
    "oculus": (tuple(f"viseme_{v}" for v in ("sil", "PP", "FF", "TH", "DD", "kk", "CH", "SS", "nn", "RR", "aa", "E",
                                               "I", "O", "U")) + ("eyeBlinkLeft", "eyeBlinkRight"), _oculus),
}
DEFAULT_NAMES = "vrm0"


def check_name_set(name: str) -> str:
    """`name` if it is a known set, else a ValueError listing the known ones."""
    if name not in NAME_SETS:
        raise ValueError(f"unknown face name set {name!r}: known sets are {', '.join(NAME_SETS)}")
    return name


def names_of(name_set: str) -> tuple[str, ...]:
    return NAME_SETS[check_name_set(name_set)][0]


def convert(face: np.ndarray, name_set: str) -> np.ndarray:
    """Canonical face frames (T, len(FACE_LABELS)) or one frame (len,) -> that set's weights, 0..1, its order."""
    face = np.asarray(face, dtype=np.float64)
    if face.shape[-1] != len(FACE_LABELS):
        raise ValueError(f"a face frame has {len(FACE_LABELS)} values ({', '.join(FACE_LABELS)}), got {face.shape}")
    one = face.ndim == 1
    out = NAME_SETS[check_name_set(name_set)][1](np.atleast_2d(face))
    return np.clip(out[0] if one else out, 0.0, 1.0)
