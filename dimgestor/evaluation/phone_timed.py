"""Speech whose every phone's time is known, in many languages: espeak-ng synthesis with its own phoneme events.

libespeak-ng (the library of Debian's `espeak-ng` package) reports, while it synthesises, the sample at which each
phoneme starts and the phoneme in IPA. `speak` returns the utterance at 16 kHz with those phones as intervals
(start s, end s, IPA), the last one ending where the audio ends; a pause is "". `dimgestor.face.ipa.arpabet` maps
each phone onto the mouth of an ARPAbet phone, so the face's evaluation scores any language as it scores English
forced alignments (`alignment`).

The library is loaded (ctypes) in a child process forked for each utterance, so that an utterance is the same
whatever was spoken before it (`_synth`); it is used for measuring and making training data only, and is not
needed to run the engine.

TEXTS holds sentences per language, written for this project: those of the voice world
(`dimgestor.evaluation.voiceworld.TEXTS`) where espeak-ng reads the script, plus Japanese in kana (espeak-ng reads
no kanji) and Cantonese in Chinese characters. Mandarin is absent: Debian's espeak-ng 1.51 reads Chinese
characters for `cmn` as pinyin spelled out in English (`espeak-ng -v cmn -q --ipa 你好` gives "nɪ5θɹˈiː5 ..."),
so its phones are not Mandarin's.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import threading
from dataclasses import dataclass

import numpy as np

from dimgestor.audio import SAMPLE_RATE, resample
from dimgestor.face.ipa import arpabet

__all__ = ["Spoken", "speak", "passage", "alignment", "TEXTS", "LANGUAGES", "EspeakMissing"]

TEXTS_JA = [
    "わたしは まいあさ パンを たべて、コーヒーを のみます。",
    "きょうは とても いい てんきですね。",
    "あした ともだちと いっしょに えいがを みに いきます。",
    "この みちを まっすぐ いって、みぎに まがって ください。",
    "むかし むかし、ある ところに おじいさんと おばあさんが いました。",
    "すみません、えきまで どのくらい かかりますか。",
    "ぼくは おんがくが だいすきで、まいにち ピアノを ひきます。",
    "ふゆに なると、やまの うえに ゆきが ふります。",
]
TEXTS_YUE = [
    "你好，今日天氣好好。",
    "我哋每日朝早一齊食麵包，飲咖啡。",
    "聽日我會同朋友去睇戲。",
    "呢條路一直行，然後轉右。",
    "唔該，去火車站要幾耐？",
    "我好鍾意音樂，每日都彈鋼琴。",
    "冬天嘅時候，山頂會落雪。",
    "佢話一定會準時到。",
]


def _texts() -> dict[str, list[str]]:
    from dimgestor.evaluation.voiceworld import TEXTS as WORLD

    out = {lang: list(t) for lang, t in WORLD.items() if lang not in ("cmn", "en-gb")}
    return {**out, "ja": TEXTS_JA, "yue": TEXTS_YUE}


TEXTS = _texts()
LANGUAGES = tuple(TEXTS)

_INIT_PHONEME_EVENTS, _INIT_PHONEME_IPA, _INIT_DONT_EXIT = 0x0001, 0x0002, 0x8000
_SYNCHRONOUS, _POS_CHARACTER, _CHARS_UTF8 = 2, 1, 1
_EVENT_END_OF_LIST, _EVENT_PHONEME = 0, 7
_RATE, _PITCH, _VOLUME = 1, 3, 2  # espeak_PARAMETER


class EspeakMissing(RuntimeError):
    """libespeak-ng is not installed."""


class _Id(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):  # espeak_EVENT (speak_lib.h)
    _fields_ = [("type", ctypes.c_int), ("unique_identifier", ctypes.c_uint), ("text_position", ctypes.c_int),
                ("length", ctypes.c_int), ("audio_position", ctypes.c_int), ("sample", ctypes.c_int),
                ("user_data", ctypes.c_void_p), ("id", _Id)]


_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.POINTER(_Event))


class _Engine:
    """The process's libespeak-ng, initialised once, synchronous, with IPA phoneme events."""

    def __init__(self):
        name = ctypes.util.find_library("espeak-ng") or "libespeak-ng.so.1"
        try:
            self.lib = ctypes.CDLL(name)
        except OSError as e:
            raise EspeakMissing(f"libespeak-ng not found ({e}); Debian: apt-get install espeak-ng") from None
        self.rate = self.lib.espeak_Initialize(_SYNCHRONOUS, 0, None,
                                               _INIT_PHONEME_EVENTS | _INIT_PHONEME_IPA | _INIT_DONT_EXIT)
        if self.rate <= 0:
            raise EspeakMissing(f"libespeak-ng did not start (espeak_Initialize returned {self.rate})")
        self.lib.espeak_Synth.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.c_uint, ctypes.c_int,
                                          ctypes.c_uint, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p]
        self.chunks: list[np.ndarray] = []
        self.events: list[tuple[int, str]] = []
        self._callback = _CALLBACK(self._on_synth)  # (kept referenced: the library holds the pointer)
        self.lib.espeak_SetSynthCallback(self._callback)

    def _on_synth(self, wav, n, events) -> int:
        if n > 0:
            self.chunks.append(np.ctypeslib.as_array(wav, (n,)).copy())
        i = 0
        while events[i].type != _EVENT_END_OF_LIST:
            if events[i].type == _EVENT_PHONEME:
                self.events.append((int(events[i].sample), events[i].id.string.decode("utf-8", "replace")))
            i += 1
        return 0

    def synth(self, text: str, voice: str, rate: int, pitch: int, volume: int) -> tuple[np.ndarray, list]:
        base, _, variant = voice.partition("+")  # ("fr-fr" is "fr" to the library, though its program takes both)
        names = [voice] + ([base.split("-")[0] + ("+" + variant if variant else "")] if "-" in base else [])
        if all(self.lib.espeak_SetVoiceByName(name.encode()) != 0 for name in names):
            raise ValueError(f"espeak-ng has no voice {voice!r} (espeak-ng --voices lists them)")
        for param, value in ((_RATE, rate), (_PITCH, pitch), (_VOLUME, volume)):
            self.lib.espeak_SetParameter(param, int(value), 0)
        self.chunks, self.events = [], []
        data = text.encode("utf-8")
        err = self.lib.espeak_Synth(data, len(data) + 1, 0, _POS_CHARACTER, 0, _CHARS_UTF8, None, None)
        if err != 0:
            raise RuntimeError(f"espeak-ng could not speak {text!r} (error {err})")
        self.lib.espeak_Synchronize()
        audio = np.concatenate(self.chunks) if self.chunks else np.zeros(0, np.int16)
        return audio, self.events


def _speak_once(conn, text: str, voice: str, rate: int, pitch: int, volume: int) -> None:
    """In a child process: a fresh library speaks one utterance; (pcm, events, rate) or the error goes back."""
    try:
        engine = _Engine()
        pcm, events = engine.synth(text, voice, rate, pitch, volume)
        conn.send((pcm, events, engine.rate))
    except Exception as e:  # (sent back and raised in the caller)
        conn.send(e)
    finally:
        conn.close()


def _synth(text: str, voice: str, rate: int, pitch: int, volume: int) -> tuple[np.ndarray, list, int]:
    """One utterance from a library that has spoken nothing before: libespeak-ng carries its voice source's state
    from one utterance to the next, so in one process the same text comes out different after another. A forked
    child per utterance makes each the same whatever was spoken before (and the caller's process never loads
    the library). Where processes cannot fork (Windows) the utterance is spoken here, by a library that is not
    fresh after the first."""
    if "fork" not in multiprocessing.get_all_start_methods():
        global _engine
        with _lock:
            _engine = _engine or _Engine()
            return (*_engine.synth(text, voice, rate, pitch, volume), _engine.rate)
    ctx = multiprocessing.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)
    with _lock:
        child = ctx.Process(target=_speak_once, args=(send, text, voice, rate, pitch, volume), daemon=True)
        child.start()
        send.close()
        try:
            got = receive.recv()
        except EOFError:
            got = None
        finally:
            receive.close()
            child.join()
    if got is None:
        raise RuntimeError(f"espeak-ng's process ended without an answer (exit code {child.exitcode})")
    if isinstance(got, Exception):
        raise got
    return got


_engine: _Engine | None = None
_lock = threading.Lock()


@dataclass(frozen=True, eq=False)  # (compared by its fields: an array has no single truth value)
class Spoken:
    """One utterance: audio at `rate` Hz and its phones [(start s, end s, IPA)], "" where it pauses."""

    text: str
    voice: str
    audio: np.ndarray
    rate: int
    phones: list[tuple[float, float, str]]

    @property
    def seconds(self) -> float:
        return len(self.audio) / self.rate


def speak(text: str, voice: str = "en-us", rate: int = 160, pitch: int = 50, volume: int = 100,
          sample_rate: int = SAMPLE_RATE) -> Spoken:
    """`text` spoken by espeak-ng's `voice` (a language such as "de", optionally with a variant: "de+f2") at
    `rate` words a minute and base `pitch` (0-99), at `sample_rate`, with each phone's interval."""
    pcm, events, native = _synth(text, voice, rate, pitch, volume)
    if not len(pcm):
        raise ValueError(f"espeak-ng gave no audio for {text!r} ({voice})")
    audio = resample(pcm.astype(np.float32) / 32768.0, native, sample_rate)
    end = len(pcm) / native
    # ("(en)" and the like mark a switch of language inside the text, not a phone)
    starts = [(min(max(s, 0), len(pcm)) / native, p) for s, p in events if not (p.startswith("(") and p.endswith(")"))]
    phones = []
    for k, (a, p) in enumerate(starts):  # each phone lasts until the next starts (a duplicate start is dropped)
        b = starts[k + 1][0] if k + 1 < len(starts) else end
        if b > a:
            phones.append((a, b, p))
    if phones and phones[0][0] > 0:
        phones.insert(0, (0.0, phones[0][0], ""))
    return Spoken(text, voice, audio.astype(np.float32), sample_rate, phones)


def alignment(spoken: Spoken) -> list[tuple[float, float, str]]:
    """The phones as ARPAbet (`dimgestor.face.ipa.arpabet`, with the voice's language), what
    `dimgestor.face.evaluate.mouth_scores` reads; a pause is ""."""
    lang = spoken.voice.split("+")[0]
    return [(a, b, "" if (p := arpabet(ipa, lang)) == "SIL" else p) for a, b, ipa in spoken.phones]


def passage(language: str, variant: str = "m3", seed: int = 0, sentences: int | None = None,
            pause_s: tuple[float, float] = (0.4, 1.0), sample_rate: int = SAMPLE_RATE) -> Spoken:
    """The first `sentences` of TEXTS[language] (all by default) read by one voice (`language+variant`), each at
    a rate of 140-190 words a minute and a base pitch of 30-70 drawn from `seed`, after 0.5 s of silence and each
    followed by a pause drawn from `pause_s`: one recording with every phone's interval."""
    if language not in TEXTS:
        raise ValueError(f"no texts for language {language!r} (known: {', '.join(LANGUAGES)})")
    rng = np.random.default_rng(seed)
    voice = f"{language}+{variant}" if variant else language
    lead = int(round(0.5 * sample_rate))
    parts, phones, at = [np.zeros(lead, np.float32)], [(0.0, lead / sample_rate, "")], lead
    for text in TEXTS[language][:sentences]:
        s = speak(text, voice, rate=int(rng.integers(140, 191)), pitch=int(rng.integers(30, 71)),
                  sample_rate=sample_rate)
        t = at / sample_rate
        phones += [(a + t, min(b, s.seconds) + t, p) for a, b, p in s.phones if a < s.seconds]
        gap = int(round(float(rng.uniform(*pause_s)) * sample_rate))
        parts += [s.audio, np.zeros(gap, np.float32)]
        at += len(s.audio)
        phones.append((at / sample_rate, (at + gap) / sample_rate, ""))
        at += gap
    return Spoken(" ".join(TEXTS[language][:sentences]), voice, np.concatenate(parts), sample_rate, phones)
