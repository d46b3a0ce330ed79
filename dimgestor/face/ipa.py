"""Speech sounds of any language written in IPA -> the ARPAbet phone whose mouth they share, so that the face's
tables (`visemes.py`: viseme, jaw opening, vowel class) and its evaluation (`evaluate.py`) read every language the
way they read English forced alignments.

The mapping goes by articulation, not by sound: what the lips and the jaw do.
- Vowels by height, backness and rounding. Open vowels (a ä ɐ ɑ ɒ ʌ æ, and the schwa ə, as ARPAbet's AH) are "A";
  close and close-mid front unrounded ones (i ɪ ɨ e ᵻ) "I"; rounded close ones (u ʊ y ʏ) and Japanese's
  unrounded ɯ, whose mouth shape is the VRM "u", are "U"; open-mid front ɛ and a pure e of a language with five
  vowels are "E" (English's e only comes as the diphthong eɪ, which ARPAbet writes EY: "I"); rounded mid vowels
  (o ɔ ø œ ɤ) are "O"; r-coloured and central mid ones (ɜ ɝ ɚ ɘ ɵ) are ER, with no vowel class.
  A diphthong takes its first part, as `visemes.py` does; a long vowel is the short one.
- Consonants by place: bilabial stops and nasals (p b m) close the lips, labiodentals are F, dentals TH,
  alveolar stops and taps T/D, sibilants and affricates on s S/Z, post-alveolar and palatal ones CH, velar,
  uvular and glottal ones K/G/NG/HH, nasals and laterals N/L, rhotics R, w W and j Y.
- Stress, length, tone (digits or tone letters), syllable marks and diacritics (nasal ~, lowered, palatalised
  ʲ, aspirated ʰ, ...) do not change the mouth's class and are dropped.

`arpabet("tʃ")` is "CH"; `arpabet("")` (a pause) is "SIL"; a symbol not in the tables raises `ValueError` naming it.
"""

from __future__ import annotations

import unicodedata

__all__ = ["arpabet", "FIVE_VOWEL_LANGUAGES"]

# Languages whose mid front vowel is one pure e (no e/ɛ contrast worth a different mouth): their e is "E".
FIVE_VOWEL_LANGUAGES = frozenset({"es", "ja", "it", "ru", "el", "eu", "sw", "hi", "ko", "yue"})

_VOWELS = {
    "a": "AA", "ä": "AA", "ɐ": "AH", "ɑ": "AA", "ɒ": "AA", "ʌ": "AH", "æ": "AE", "ə": "AH", "ɶ": "AA",
    "i": "IY", "ɪ": "IH", "ɨ": "IH", "ᵻ": "IH", "e": "EY", "ɯ": "UW", "ɤ": "OW",
    "u": "UW", "ʊ": "UH", "y": "UW", "ʏ": "UH", "ʉ": "UW",
    "ɛ": "EH",
    "o": "OW", "ɔ": "AO", "ø": "OW", "œ": "AO",
    "ɜ": "ER", "ɝ": "ER", "ɚ": "ER", "ɘ": "ER", "ɵ": "ER",
}
_CONSONANTS = {
    "p": "P", "b": "B", "m": "M", "ɓ": "B", "ʙ": "B",
    "f": "F", "v": "V", "ɱ": "F", "ɸ": "F", "β": "V", "ʋ": "V",
    "θ": "TH", "ð": "DH",
    "t": "T", "d": "D", "ʈ": "T", "ɖ": "D", "ɾ": "D", "ɽ": "D", "ɗ": "D",
    "s": "S", "z": "Z",
    "ʃ": "SH", "ʒ": "ZH", "ɕ": "SH", "ʑ": "ZH", "ʂ": "SH", "ʐ": "ZH", "ç": "SH", "ʝ": "ZH", "c": "CH", "ɟ": "JH",
    "k": "K", "g": "G", "ɡ": "G", "ŋ": "NG", "x": "HH", "ɣ": "G", "q": "K", "ɢ": "G", "χ": "HH", "ħ": "HH",
    "ʕ": "HH", "h": "HH", "ɦ": "HH", "ʔ": "HH",
    "n": "N", "ɲ": "N", "ɳ": "N", "ɴ": "NG", "l": "L", "ɫ": "L", "ʎ": "L", "ɭ": "L", "ɬ": "L", "ɮ": "L",
    "r": "R", "ɹ": "R", "ʁ": "R", "ʀ": "R", "ɻ": "R", "ɺ": "R",
    "w": "W", "ɥ": "W", "ʍ": "W", "ɰ": "W", "j": "Y",
}
# Affricates and the like: the first two symbols decide (ts is on s, tʃ and dʒ post-alveolar, pf labiodental)
_PAIRS = {"ts": "S", "dz": "Z", "tʃ": "CH", "dʒ": "JH", "tɕ": "CH", "dʑ": "JH", "tʂ": "CH", "dʐ": "JH", "pf": "F",
          "tθ": "TH", "kx": "K"}
# Marks that do not change the mouth's class: stress, length, syllable and tone marks (tone letters, digits)
_DROP = set("ˈˌːˑ.-|‖‿ʰʲʷˠˤⁿˡ̩ᵝ'ʼ˞") | set("0123456789") | set("˥˦˧˨˩")


def _symbols(ipa: str) -> str:
    """The phone's base symbols: diacritics (combining marks) and the marks in _DROP removed; a letter the
    tables hold stays whole (ç is not c with a cedilla here)."""
    out = []
    for ch in unicodedata.normalize("NFC", ipa):
        if unicodedata.combining(ch) or ch in _DROP:
            continue
        if ch in _VOWELS or ch in _CONSONANTS:
            out.append(ch)
        else:
            out.extend(c for c in unicodedata.normalize("NFD", ch) if not unicodedata.combining(c))
    return "".join(out)


def arpabet(ipa: str, language: str = "en") -> str:
    """The ARPAbet phone (no stress digit) whose mouth `ipa` (one phone, e.g. "aɪ", "tʃ", "e̞", "ɯᵝ", "iː") shares;
    "SIL" for a pause (""). `language` (an espeak-ng name such as "es" or "en-us") decides a pure e: "E" in a
    five-vowel language, "I" (EY) elsewhere."""
    s = _symbols(ipa)
    if not s:
        return "SIL"
    if s[:2] in _PAIRS:
        return _PAIRS[s[:2]]
    first = s[0]
    if first in _VOWELS:
        if s.startswith("eɪ") or s.startswith("ei"):
            return "EY"  # the diphthong: ARPAbet's EY ("I"), in every language
        if s.startswith("əʊ"):
            return "OW"  # British English's "go": ARPAbet's OW
        if first == "e" and language.split("-")[0] in FIVE_VOWEL_LANGUAGES:
            return "EH"
        return _VOWELS[first]
    if first in _CONSONANTS:
        return _CONSONANTS[first]
    raise ValueError(f"IPA phone {ipa!r}: no mouth known for {first!r} (U+{ord(first):04X})")
