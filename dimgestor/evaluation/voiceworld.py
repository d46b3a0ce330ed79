"""A synthetic world of many voices where the answer is known: espeak-ng speech and a rule for the gestures.

Speech comes from espeak-ng (the `espeak-ng` program, a Debian package) in many languages, voice variants,
pitches and rates, sentence by sentence from texts shipped below, with natural pauses between sentences
(0.3-3 s) and a different microphone level per clip. The gestures follow a rule computed from the clean
audio alone, so whatever voice speaks, the right motion is known:

  * speech: frames whose loudness is within 35 dB of the clip's loud frames; gaps under 0.25 s are bridged
    (stop closures, commas), so each run is a phrase; the arms engage over a phrase, stay up over pauses
    shorter than HOLD_S and come down to rest in longer ones;
  * strokes: syllable nuclei (peaks of the loudness envelope smoothed over ~50 ms) that stand above their
    phrase's median loudness by STRESS_MARGIN_DB are stressed; each launches a beat stroke at its syllable's
    onset (where the envelope rises through half-way from the valley before it), sized by how far the
    nucleus stands above the phrase median (relative loudness, so the microphone level does not matter).
    That decision needs the whole phrase, which no streaming listener has; `rule_events(heard_s=S)` decides
    each stress on what is heard S seconds past its onset instead (the median so far), and a world can be
    written with that rule (`make_voice_world(heard_s=)`, named in its world.json);
  * the body machinery is `synthetic.gesture_motion` (the same as `speech_and_gestures`), its random choices
    (which hand, stroke length, idle-sway phases) seeded by a hash of the events.

So the motion is exactly a function of the audio. Train voices and held-out voices are disjoint, and one
language (Italian) is held out entirely: `voice_split`.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dimgestor.audio import SAMPLE_RATE
from dimgestor.bvh import BvhMotion
from dimgestor.training.synthetic import gesture_motion

RATE = SAMPLE_RATE
ESPEAK_RATE = 22050  # espeak-ng writes 22.05 kHz mono PCM16

# ---------------------------------------------------------------------------------------------------
# Texts (written for this module), per espeak-ng language
# ---------------------------------------------------------------------------------------------------

_ENGLISH = [
    "I honestly think we should start again from the very beginning.",
    "The train was late, so we walked all the way home in the rain.",
    "Could you tell me why the numbers changed so much last week?",
    "This is the most important part, and I want you to remember it.",
    "We tried three different ideas, but only one of them really worked.",
    "Look at the size of that mountain, it must be enormous!",
    "First you open the box, then you take out the little key.",
    "Nobody expected the concert to be quite so loud.",
    "Well, that depends on what you mean by a good result.",
    "She said yes, absolutely, without even stopping to think.",
    "If the weather holds, we can sail across the bay tomorrow.",
    "The point is simple: more practice gives better results.",
]
TEXTS: dict[str, list[str]] = {
    "en-us": _ENGLISH,
    "en-gb": _ENGLISH,
    "de": [
        "Ich glaube wirklich, dass wir noch einmal von vorne anfangen sollten.",
        "Der Zug hatte Verspätung, also sind wir im Regen nach Hause gelaufen.",
        "Kannst du mir sagen, warum sich die Zahlen so stark verändert haben?",
        "Das ist der wichtigste Teil, und den musst du dir merken.",
        "Wir haben drei Ideen ausprobiert, aber nur eine hat funktioniert.",
        "Schau dir diesen Berg an, der ist ja riesig!",
        "Zuerst öffnest du die Kiste, dann nimmst du den kleinen Schlüssel heraus.",
        "Niemand hat erwartet, dass das Konzert so laut sein würde.",
        "Nun, das hängt davon ab, was du unter einem guten Ergebnis verstehst.",
        "Sie hat sofort ja gesagt, ohne auch nur nachzudenken.",
    ],
    "fr-fr": [
        "Je pense vraiment que nous devrions tout recommencer depuis le début.",
        "Le train était en retard, alors nous sommes rentrés à pied sous la pluie.",
        "Peux-tu me dire pourquoi les chiffres ont tellement changé?",
        "C'est la partie la plus importante, et je veux que tu t'en souviennes.",
        "Nous avons essayé trois idées, mais une seule a vraiment marché.",
        "Regarde cette montagne, elle est immense!",
        "D'abord tu ouvres la boîte, ensuite tu prends la petite clé.",
        "Personne ne pensait que le concert serait aussi fort.",
        "Eh bien, cela dépend de ce que tu appelles un bon résultat.",
        "Elle a dit oui tout de suite, sans même réfléchir.",
    ],
    "es": [
        "Creo sinceramente que deberíamos empezar otra vez desde el principio.",
        "El tren llegó tarde, así que volvimos a casa caminando bajo la lluvia.",
        "¿Me puedes decir por qué los números cambiaron tanto la semana pasada?",
        "Esta es la parte más importante, y quiero que la recuerdes.",
        "Probamos tres ideas distintas, pero solo una funcionó de verdad.",
        "¡Mira el tamaño de esa montaña, es enorme!",
        "Primero abres la caja, y luego sacas la llave pequeña.",
        "Nadie esperaba que el concierto fuera tan ruidoso.",
        "Bueno, eso depende de lo que llames un buen resultado.",
        "Ella dijo que sí enseguida, sin pensarlo dos veces.",
    ],
    "it": [
        "Penso davvero che dovremmo ricominciare tutto dall'inizio.",
        "Il treno era in ritardo, così siamo tornati a casa a piedi sotto la pioggia.",
        "Mi puoi dire perché i numeri sono cambiati così tanto?",
        "Questa è la parte più importante, e voglio che tu la ricordi.",
        "Abbiamo provato tre idee diverse, ma solo una ha funzionato davvero.",
        "Guarda quella montagna, è enorme!",
        "Prima apri la scatola, poi prendi la chiave piccola.",
        "Nessuno si aspettava che il concerto fosse così forte.",
        "Beh, dipende da cosa intendi per un buon risultato.",
        "Lei ha detto subito di sì, senza nemmeno pensarci.",
    ],
    "cmn": [
        "我真的觉得我们应该从头开始。",
        "火车晚点了，所以我们冒着雨走回了家。",
        "你能告诉我为什么这些数字变化这么大吗？",
        "这是最重要的部分，我希望你记住它。",
        "我们试了三个不同的办法，但只有一个真正有效。",
        "你看那座山，真是太大了！",
        "首先打开盒子，然后拿出那把小钥匙。",
        "没有人想到音乐会会这么吵。",
        "嗯，这要看你怎么理解好的结果。",
        "她马上就答应了，连想都没想。",
    ],
    "pt": [
        "Acho mesmo que devíamos começar tudo outra vez desde o início.",
        "O comboio chegou atrasado, por isso fomos a pé para casa à chuva.",
        "Podes dizer-me porque é que os números mudaram tanto?",
        "Esta é a parte mais importante, e quero que te lembres dela.",
        "Experimentámos três ideias, mas só uma funcionou de verdade.",
        "Olha para aquela montanha, é enorme!",
        "Primeiro abres a caixa, depois tiras a chave pequena.",
        "Ninguém esperava que o concerto fosse tão barulhento.",
    ],
    "nl": [
        "Ik denk echt dat we helemaal opnieuw moeten beginnen.",
        "De trein had vertraging, dus we liepen in de regen naar huis.",
        "Kun je me vertellen waarom de cijfers zo sterk veranderd zijn?",
        "Dit is het belangrijkste deel, en dat moet je onthouden.",
        "We hebben drie ideeën geprobeerd, maar maar één werkte echt.",
        "Kijk eens naar die berg, hij is enorm!",
        "Eerst open je de doos, dan pak je het kleine sleuteltje.",
        "Niemand had verwacht dat het concert zo luid zou zijn.",
    ],
    "sv": [
        "Jag tycker verkligen att vi borde börja om från början.",
        "Tåget var försenat, så vi gick hem i regnet.",
        "Kan du berätta varför siffrorna ändrades så mycket?",
        "Det här är den viktigaste delen, och jag vill att du kommer ihåg den.",
        "Vi provade tre olika idéer, men bara en fungerade på riktigt.",
        "Titta på det där berget, det är enormt!",
        "Först öppnar du lådan, sedan tar du fram den lilla nyckeln.",
        "Ingen trodde att konserten skulle vara så högljudd.",
    ],
    "pl": [
        "Naprawdę uważam, że powinniśmy zacząć wszystko od nowa.",
        "Pociąg się spóźnił, więc wróciliśmy do domu pieszo w deszczu.",
        "Czy możesz mi powiedzieć, dlaczego liczby tak bardzo się zmieniły?",
        "To jest najważniejsza część i chcę, żebyś ją zapamiętał.",
        "Spróbowaliśmy trzech pomysłów, ale tylko jeden naprawdę zadziałał.",
        "Spójrz na tę górę, jest ogromna!",
        "Najpierw otwierasz pudełko, potem wyjmujesz mały klucz.",
        "Nikt się nie spodziewał, że koncert będzie tak głośny.",
    ],
}

# ---------------------------------------------------------------------------------------------------
# Voices: a language, an espeak-ng variant, a pitch and a rate
# ---------------------------------------------------------------------------------------------------

HELD_OUT_LANGUAGE = "it"
TRAIN_VARIANTS = ("m1", "m3", "f1", "f2", "klatt", "m7")
HELD_OUT_VARIANTS = ("m2", "f3", "f4", "klatt3")


@dataclass(frozen=True)
class Voice:
    lang: str  # espeak-ng language (a key of TEXTS)
    variant: str  # espeak-ng voice variant (espeak-ng --voices=variant), e.g. f3
    pitch: int  # espeak-ng -p, 0-99 (base pitch)
    rate: int  # espeak-ng -s, words per minute

    @property
    def name(self) -> str:
        return f"{self.lang}+{self.variant}"


def voice_catalogue(seed: int = 0) -> list[Voice]:
    """Every language with every variant, pitch in 20-80 and rate in 120-200 drawn per voice (deterministic)."""
    rng = np.random.default_rng(seed)
    return [Voice(lang, v, int(rng.integers(20, 81)), int(rng.integers(120, 201)))
            for lang in TEXTS for v in TRAIN_VARIANTS + HELD_OUT_VARIANTS]


def voice_split(seed: int = 0) -> tuple[list[Voice], list[Voice]]:
    """(train voices, held-out voices): disjoint variants, and every voice of HELD_OUT_LANGUAGE held out."""
    train, held = [], []
    for v in voice_catalogue(seed):
        (held if v.lang == HELD_OUT_LANGUAGE or v.variant in HELD_OUT_VARIANTS else train).append(v)
    return train, held


# ---------------------------------------------------------------------------------------------------
# Speech
# ---------------------------------------------------------------------------------------------------


def espeak(text: str, voice: Voice, pitch: int | None = None, rate: int | None = None, amp: int = 100) -> np.ndarray:
    """One utterance from espeak-ng, 16 kHz mono float32 (resampled from its 22.05 kHz)."""
    from dimgestor.audio import load_wav

    exe = shutil.which("espeak-ng")
    if exe is None:
        raise RuntimeError("espeak-ng is not installed (Debian: apt-get install espeak-ng)")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "utterance.wav"
        subprocess.run([exe, "-v", voice.name, "-p", str(voice.pitch if pitch is None else pitch),
                        "-s", str(voice.rate if rate is None else rate), "-a", str(amp), "-w", str(path), text],
                       check=True, capture_output=True)
        return load_wav(path, RATE)


def pcm16(x: np.ndarray) -> np.ndarray:
    """x on the PCM16 grid save_wav writes, so that the audio a rule saw is exactly the audio in the file."""
    return (np.round(np.clip(np.asarray(x, np.float64), -1.0, 1.0) * 32767.0) / 32767.0).astype(np.float32)


def voice_clip(seconds: float, voice: Voice, seed: int) -> tuple[np.ndarray, dict]:
    """`seconds` of one voice: sentences of its language (pitch +-5, rate +-10 per sentence) with pauses of
    0.3-3 s, room noise 50 dB under the speech, and a microphone level drawn per clip (-12..0 dB gain, espeak
    amplitude 70-150). Returns (audio on the PCM16 grid, {"gain_db", "amp", "sentences"})."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * RATE))
    audio = np.zeros(n)
    amp = int(rng.integers(70, 151))
    gain_db = float(rng.uniform(-12.0, 0.0))
    texts = TEXTS[voice.lang]
    pos, sentences = int(rng.uniform(0.3, 1.5) * RATE), 0
    while pos < n - int(0.5 * RATE):
        text = texts[int(rng.integers(len(texts)))]
        pitch = int(np.clip(voice.pitch + rng.integers(-5, 6), 0, 99))
        rate = int(np.clip(voice.rate + rng.integers(-10, 11), 80, 450))
        u = espeak(text, voice, pitch, rate, amp)
        nz = np.flatnonzero(np.abs(u) > 1e-4)  # espeak pads with silence: the pause is ours to choose
        u = u[nz[0]:nz[-1] + 1] if nz.size else u[:0]
        take = min(len(u), n - pos)
        audio[pos:pos + take] += u[:take]
        sentences += 1
        pos += take + int(rng.uniform(0.3, 3.0) * RATE)
    speech_rms = np.sqrt(np.mean(audio[np.abs(audio) > 1e-4] ** 2)) if np.any(np.abs(audio) > 1e-4) else 0.1
    audio += speech_rms * 10 ** (-50 / 20) * rng.standard_normal(n)
    audio *= 10 ** (gain_db / 20)
    return pcm16(audio), {"gain_db": round(gain_db, 2), "amp": amp, "sentences": sentences}


# ---------------------------------------------------------------------------------------------------
# The rule: audio -> events -> motion
# ---------------------------------------------------------------------------------------------------

SPEECH_REL_DB = -35.0  # a frame is speech within this of the clip's loud frames (95th percentile)
BRIDGE_S = 0.25  # gaps shorter than this inside speech are not pauses
MIN_PHRASE_S = 0.1
HOLD_S = 1.5  # the arms stay up over pauses shorter than this (a speaker holds a gesture between phrases)
STRESS_MARGIN_DB = 4.0  # a syllable nucleus this far above its phrase's median loudness is stressed
MIN_STROKE_GAP_S = 0.6  # one stroke per stressed nucleus at most every 0.6 s (a stroke lasts 0.4-0.6 s)
ENGAGE_TAU_S = 0.12  # arms rise into gesture space and return to rest as in speech_and_gestures
SIZE_MIN, SIZE_MAX = 1.2, 2.0  # stroke size from the least to the most prominent stressed nucleus
ENV_RATE = 100  # loudness envelope frames per second


def loudness_envelope_db(audio: np.ndarray, rate: int = RATE) -> np.ndarray:
    """(n / rate * ENV_RATE,) RMS in dB over 25 ms around each 10 ms frame, smoothed by a 50 ms Hann window."""
    a = np.asarray(audio, dtype=np.float64)
    hop, half = rate // ENV_RATE, int(0.0125 * rate)
    centres = np.arange(len(a) // hop) * hop + hop // 2
    cum = np.concatenate([[0.0], np.cumsum(a * a)])
    lo, hi = np.clip(centres - half, 0, len(a)), np.clip(centres + half, 0, len(a))
    db = 10 * np.log10(np.maximum((cum[hi] - cum[lo]) / np.maximum(hi - lo, 1), 1e-12))
    w = np.hanning(7)[1:-1]
    return np.convolve(np.pad(db, 2, mode="edge"), w / w.sum(), mode="valid")


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[(start, end)) index runs where mask is true."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def rule_events(audio: np.ndarray, rate: int = RATE, heard_s: float | None = None) -> dict:
    """{"phrases": [(start, end)], "stresses": [(onset t, size)]} (seconds) of speech, from its audio alone.

    heard_s: None, each stress is decided on its whole phrase (its median loudness, the 0.6 s spacing against
    louder nuclei on both sides); a number, on what a listener has heard by heard_s past the syllable's onset
    (the phrase's median so far, nuclei heard by then), as a model streaming with that much lookahead hears
    it. With heard_s past every phrase's end the two agree."""
    env = loudness_envelope_db(audio, rate)
    if env.size == 0:
        return {"phrases": [], "stresses": []}
    phrases = _phrase_spans(env)
    stresses = []
    for a, b in phrases:
        seg = env[a:b]
        stresses += [((a + onset) / ENV_RATE, size) for onset, size in
                     (_phrase_stresses(seg) if heard_s is None else _heard_stresses(seg, heard_s))]
    held = []  # the arms stay in gesture space over pauses shorter than HOLD_S
    for a, b in phrases:
        if held and a - held[-1][1] < HOLD_S * ENV_RATE:
            held[-1] = (held[-1][0], b)
        else:
            held.append((a, b))
    return {"phrases": [(a / ENV_RATE, b / ENV_RATE) for a, b in held], "stresses": stresses}


def _phrase_spans(env: np.ndarray) -> list[tuple[int, int]]:
    """[(start, end)) envelope frames of each phrase (before holding over short pauses): what stresses are
    decided within."""
    speech = env > np.percentile(env, 95) + SPEECH_REL_DB
    for a, b in _runs(~speech):  # bridge short gaps inside speech
        if a > 0 and b < len(speech) and (b - a) < BRIDGE_S * ENV_RATE:
            speech[a:b] = True
    return [(a, b) for a, b in _runs(speech) if b - a >= MIN_PHRASE_S * ENV_RATE]


def _onset(seg: np.ndarray, p: int) -> int:
    """The onset of the syllable whose nucleus is p: where the envelope rises through half-way from the valley
    in the 0.25 s before it."""
    lo = max(0, p - int(0.25 * ENV_RATE))
    valley = lo + int(np.argmin(seg[lo:p + 1]))
    half = 0.5 * (seg[valley] + seg[p])
    return valley + int(np.flatnonzero(seg[valley:p + 1] >= half)[0])


def _stroke_size(peak_db: float, median: float) -> float:
    return round(SIZE_MIN + (SIZE_MAX - SIZE_MIN) * float(np.clip((peak_db - median - STRESS_MARGIN_DB) / 12.0, 0, 1)), 4)


def _phrase_stresses(seg: np.ndarray) -> list[tuple[int, float]]:
    """[(onset frame, size)] of a phrase's envelope, decided on the whole phrase."""
    from scipy.signal import find_peaks

    median = float(np.median(seg))
    peaks, _ = find_peaks(seg, height=median + STRESS_MARGIN_DB, prominence=3.0,
                          distance=int(MIN_STROKE_GAP_S * ENV_RATE))
    return [(_onset(seg, p), _stroke_size(seg[p], median)) for p in peaks]


def _heard_stresses(seg: np.ndarray, heard_s: float) -> list[tuple[int, float]]:
    """[(onset frame, size)] of a phrase's envelope, each stress decided on the envelope up to heard_s past its
    onset, as _phrase_stresses decides on all of it: the nucleus is a peak there, stands STRESS_MARGIN_DB above
    the median so far, no louder such nucleus heard by then lies within MIN_STROKE_GAP_S (louder ones first,
    find_peaks' spacing), and its prominence over what is heard is 3 dB."""
    from scipy.signal import find_peaks, peak_prominences

    ahead = int(round(heard_s * ENV_RATE))
    candidates = []  # (nucleus, onset, frames heard, median heard)
    for p in find_peaks(seg)[0]:
        onset = _onset(seg, p)
        known = min(onset + ahead, len(seg))
        if p + 1 < known or known == len(seg):  # the nucleus is heard to be a peak
            median = float(np.median(seg[:known]))
            if seg[p] >= median + STRESS_MARGIN_DB:
                candidates.append((p, onset, known, median))
    spaced: list[tuple[int, int, int, float]] = []
    for c in sorted(candidates, key=lambda c: -seg[c[0]]):
        if not any(abs(c[0] - q[0]) < MIN_STROKE_GAP_S * ENV_RATE and q[0] < c[2] for q in spaced):
            spaced.append(c)
    return [(onset, _stroke_size(seg[p], median)) for p, onset, known, median in sorted(spaced)
            if peak_prominences(seg[:known], [p])[0][0] >= 3.0]


def events_seed(events: dict) -> int:
    """A seed that is a function of the events alone (times to 10 ms): the motion's random choices then depend
    on what was said, not on the microphone level or the file's sample format."""
    text = json.dumps([[round(a, 2), round(b, 2)] for a, b in events["phrases"]]
                      + [[round(t, 2), round(s, 2)] for t, s in events["stresses"]])
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")


def rule_motion(audio: np.ndarray, fps: float = 30.0, rate: int = RATE, heard_s: float | None = None
                ) -> tuple[BvhMotion, dict]:
    """(the rule's motion for `audio`, its events): a function of the audio alone (heard_s: rule_events')."""
    events = rule_events(audio, rate, heard_s)
    n = int(round(len(audio) / rate * fps))
    return gesture_motion(events, n, fps, np.random.default_rng(events_seed(events)), ENGAGE_TAU_S), events


# ---------------------------------------------------------------------------------------------------
# Corpora
# ---------------------------------------------------------------------------------------------------


def make_voice_corpus(out_dir, minutes: float, voices: list[Voice], seed: int = 0, clip_s: float = 30.0,
                      fps: float = 30.0, prefix: str = "clip", heard_s: float | None = None
                      ) -> list[tuple[Path, Path]]:
    """Write `minutes` of speech by `voices` (cycled in a seeded order) as PREFIX_NNN.bvh/.wav pairs of
    `clip_s` seconds (the last shorter) with the rule's motion, and voices.json naming each clip's voice
    (merged into one already there)."""
    from dimgestor.audio import save_wav
    from dimgestor.bvh import write_bvh

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    order = [voices[i] for i in rng.permutation(len(voices))]
    index_path = out_dir / "voices.json"
    index = json.loads(index_path.read_text()) if index_path.is_file() else {}
    total, paths, i = minutes * 60.0, [], 0
    while total > 1e-6:
        length = min(clip_s, total)
        voice = order[i % len(order)]
        audio, info = voice_clip(length, voice, seed=seed * 100003 + i)
        motion, events = rule_motion(audio, fps, heard_s=heard_s)
        name = f"{prefix}_{i:03d}"
        write_bvh(out_dir / f"{name}.bvh", motion)
        save_wav(out_dir / f"{name}.wav", audio, RATE)
        index[name] = {"voice": voice.name, **asdict(voice), **info, "seconds": round(length, 3),
                       "phrases": len(events["phrases"]), "strokes": len(events["stresses"])}
        paths.append((out_dir / f"{name}.bvh", out_dir / f"{name}.wav"))
        total -= length
        i += 1
    index_path.write_text(json.dumps(index, indent=1) + "\n")
    return paths


def make_voice_world(out_dir, train_minutes: float, heldout_minutes: float, seed: int = 0,
                     clip_s: float = 30.0, fps: float = 30.0, heard_s: float | None = None) -> dict[str, list[str]]:
    """Train clips (train_NNN: train voices) and held-out clips (heldout_NNN: held-out voices and language) in
    one folder, with split.json naming the held-out clips `valid` (dataset.read_split), voices.json, and
    world.json naming the rule (heard_s: rule_events'; world_rule reads it back)."""
    out_dir = Path(out_dir)
    train_voices, held_voices = voice_split()
    train = make_voice_corpus(out_dir, train_minutes, train_voices, seed, clip_s, fps, prefix="train", heard_s=heard_s)
    held = make_voice_corpus(out_dir, heldout_minutes, held_voices, seed + 7777, clip_s, fps, prefix="heldout",
                             heard_s=heard_s)
    split = {"train": [b.stem for b, _ in train], "valid": [b.stem for b, _ in held]}
    (out_dir / "split.json").write_text(json.dumps(split, indent=1) + "\n")
    (out_dir / "world.json").write_text(json.dumps({"seed": seed, "rule_heard_s": heard_s}, indent=1) + "\n")
    return split


def world_rule(world_dir) -> float | None:
    """The rule a world was written with: its heard_s (None: stresses decided on whole phrases; also for worlds
    written before world.json existed)."""
    path = Path(world_dir) / "world.json"
    return json.loads(path.read_text()).get("rule_heard_s") if path.is_file() else None


# ---------------------------------------------------------------------------------------------------
# Scoring motion against the rule (the measures a model is held to, each beside its chance level)
# ---------------------------------------------------------------------------------------------------

SYSTEM_METRICS = ("contrast", "coupling", "coupling_shifted", "coupling_shifted_sd", "stroke_align",
                  "stroke_shuffled", "stroke_gain", "stroke_gain_shuffled", "onset_align", "onset_shuffled",
                  "beat_align", "beat_align_shuffled", "stress_peak", "unstressed_peak", "stress_discrimination")
PEAK_WINDOW_S = 0.35  # after a syllable's onset: where its stroke (if any) makes the hands fastest


def syllable_onsets(audio: np.ndarray, rate: int = RATE, heard_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(onsets of the stressed syllables, onsets of the others) in seconds: every nucleus (a loudness peak of 3 dB
    prominence inside speech) is one or the other, by the rule (rule_events with heard_s)."""
    from scipy.signal import find_peaks

    events = rule_events(audio, rate, heard_s)
    stressed = np.array([t for t, _ in events["stresses"]])
    env, onsets = loudness_envelope_db(audio, rate), []
    for a, b in events["phrases"]:
        seg = env[int(a * ENV_RATE):int(b * ENV_RATE)]
        if len(seg) > 2:
            onsets += [a + _onset(seg, p) / ENV_RATE for p in find_peaks(seg, prominence=3.0)[0]]
    others = np.array([t for t in onsets if not stressed.size or np.abs(stressed - t).min() > 0.1])
    return stressed, others


def onset_peaks(onsets: np.ndarray, speed: np.ndarray, fps: float, speech: np.ndarray) -> np.ndarray:
    """Per onset: the largest hand speed in the PEAK_WINDOW_S after it, over the mean speed in speech."""
    scale = speed[speech].mean() if speech.any() else 1.0
    frames = np.round(onsets * fps).astype(int)
    width = int(round(PEAK_WINDOW_S * fps))
    frames = frames[(frames >= 0) & (frames + width < len(speed))]
    return np.array([speed[f:f + width + 1].max() / scale for f in frames])


def score_motion(raws: list[np.ndarray], audios: list[np.ndarray], skeleton, spec, seed: int = 0,
                 heard_s: float | None = None) -> dict:
    """SYSTEM_METRICS of motion (raw features (T, D) per clip, at spec.fps) against the audio (16 kHz) it is scored
    with, pooled over the clips; strokes are the rule's (rule_events with heard_s: the world's rule) of that audio."""
    from dimgestor.evaluation import metrics
    from dimgestor.evaluation.eval import clip_stats, pool_drive, pool_stats, voice_row

    stats, hits, shuffled, gain, gain_shuffled, n_strokes = [], 0.0, 0.0, 0.0, 0.0, 0
    peaks: dict[str, list[np.ndarray]] = {"stressed": [], "unstressed": []}
    spf = int(round(RATE / spec.fps))
    for i, (raw, audio) in enumerate(zip(raws, audios)):
        n = min(len(raw), len(audio) // spf)
        raw, audio = raw[:n], audio[: n * spf]
        st = clip_stats(raw, audio, skeleton, spec, seed=seed + i)
        stats.append(st)
        strokes = np.array([t for t, _ in rule_events(audio, heard_s=heard_s)["stresses"]])
        strokes = strokes[strokes < n / spec.fps]
        for kind, onsets in zip(peaks, syllable_onsets(audio, heard_s=heard_s)):
            peaks[kind].append(onset_peaks(onsets, st["hand_speed"], spec.fps, st["mask"] == 1))
        if strokes.size:
            speech = st["mask"] == 1
            hits += metrics.onset_hits(strokes, st["hand_speed"], spec.fps).sum()
            shuffled += metrics.shuffled_onset_alignment(len(strokes), st["hand_speed"], spec.fps, speech,
                                                         seed=seed + i) * len(strokes)
            rng = np.random.default_rng(seed + i)
            gain += metrics.onset_locked_speed(strokes, st["hand_speed"], spec.fps, speech) * len(strokes)
            gain_shuffled += np.mean([metrics.onset_locked_speed(
                metrics.shuffled_onsets(len(strokes), speech, spec.fps, rng), st["hand_speed"], spec.fps, speech)
                for _ in range(10)]) * len(strokes)
            n_strokes += len(strokes)
    row = {**pool_stats(stats), **pool_drive([voice_row([s]) for s in stats])}
    row["stroke_align"] = hits / n_strokes if n_strokes else float("nan")
    row["stroke_shuffled"] = shuffled / n_strokes if n_strokes else float("nan")
    row["stroke_gain"] = gain / n_strokes if n_strokes else float("nan")
    row["stroke_gain_shuffled"] = gain_shuffled / n_strokes if n_strokes else float("nan")
    # Stress discrimination: does a stroke-sized movement follow the stressed syllables rather than any syllable?
    # Median over syllables of the hands' peak speed after the onset, stressed against unstressed.
    for kind, key in (("stressed", "stress_peak"), ("unstressed", "unstressed_peak")):
        values = np.concatenate(peaks[kind]) if peaks[kind] else np.zeros(0)
        row[key] = float(np.median(values)) if values.size else float("nan")
    row["stress_discrimination"] = row["stress_peak"] / row["unstressed_peak"]
    return {m: float(row[m]) for m in SYSTEM_METRICS}


def margins(row: dict) -> dict:
    """Each measure above its chance level."""
    return {"stroke_margin": row["stroke_align"] - row["stroke_shuffled"],
            "stroke_gain_margin": row["stroke_gain"] - row["stroke_gain_shuffled"],
            "onset_margin": row["onset_align"] - row["onset_shuffled"],
            "coupling_margin": row["coupling"] - row["coupling_shifted"],
            "beat_margin": row["beat_align"] - row["beat_align_shuffled"],
            "stress_margin": row["stress_discrimination"] - 1.0}  # (1: stressed syllables no different)


def verdict(model: dict, rule: dict) -> dict:
    """Issue 20's bar: stroke-alignment margin and contrast each at least half the rule's."""
    m, r = margins(model), margins(rule)
    return {"stroke_margin_vs_rule": m["stroke_margin"] / r["stroke_margin"],
            "stress_margin_vs_rule": m["stress_margin"] / r["stress_margin"],
            "stroke_gain_margin_vs_rule": m["stroke_gain_margin"] / r["stroke_gain_margin"],
            "contrast_vs_rule": model["contrast"] / rule["contrast"],
            "coupling_margin_vs_rule": m["coupling_margin"] / r["coupling_margin"],
            "passes": bool(m["stroke_margin"] >= 0.5 * r["stroke_margin"] and model["contrast"] >= 0.5 * rule["contrast"])}


# ---------------------------------------------------------------------------------------------------
# A learnt listener: how well the rule's stress decision can be learnt from the audio at all. Its strokes
# are the rule's own (full size, on time), so what it loses against the rule is the listening alone.
# ---------------------------------------------------------------------------------------------------

LISTEN_BACK_S = 1.0  # a listener's window: the envelope from this long before a syllable's onset ...
LISTEN_AHEAD_S = 0.25  # ... to this long after it (a 300 ms lookahead less the stroke's 0.05 s lead)


@dataclass(frozen=True)
class Syllables:
    """Every syllable of a clip's phrases, as a listener meets them (the partition of `syllable_onsets`)."""

    onsets: np.ndarray  # (n,) seconds, in time order
    stressed: np.ndarray  # (n,) bool: the rule strokes here
    windows: np.ndarray  # (n, W) dB: the envelope LISTEN_BACK_S before to LISTEN_AHEAD_S after the onset, relative
    # to the phrase's median heard by then (outside the phrase: its quietest frame)
    strokes: list  # (n,) the rule's (onset, size) stress where stressed, else the size a stroke here would have


def syllables(audio: np.ndarray, rate: int = RATE, heard_s: float | None = None) -> Syllables:
    """The syllables (nuclei of 3 dB prominence inside each phrase, and every stress of the rule with heard_s)
    with the listening window of each; syllables within 0.1 s of a stress are left out, as in syllable_onsets."""
    from scipy.signal import find_peaks

    env = loudness_envelope_db(audio, rate)
    stresses = rule_events(audio, rate, heard_s)["stresses"] if env.size else []
    times = np.array([t for t, _ in stresses])
    back, ahead = int(round(LISTEN_BACK_S * ENV_RATE)), int(round(LISTEN_AHEAD_S * ENV_RATE))
    rows = []  # (onset s, stressed, window, stroke)
    for a, b in (_phrase_spans(env) if env.size else []):
        seg = env[a:b]

        def window(o: int) -> tuple[np.ndarray, float]:
            """(the listening window at onset frame o, the phrase's median heard by then)"""
            median = float(np.median(seg[:min(o + ahead, len(seg))]))
            w = np.full(back + ahead, float(seg.min()) - median)
            lo, hi = max(o - back, 0), min(o + ahead, len(seg))
            w[lo - (o - back):hi - (o - back)] = seg[lo:hi] - median
            return w, median

        for stress in stresses:
            o = int(round(stress[0] * ENV_RATE)) - a
            if 0 <= o < len(seg):
                rows.append((stress[0], True, window(o)[0], stress))
        if len(seg) > 2:
            for p in find_peaks(seg, prominence=3.0)[0]:
                o = _onset(seg, p)
                t = (a + o) / ENV_RATE
                if not times.size or np.abs(times - t).min() > 0.1:
                    w, median = window(o)
                    rows.append((t, False, w, (t, _stroke_size(seg[p], median))))
    rows.sort(key=lambda r: r[0])
    return Syllables(np.array([r[0] for r in rows], dtype=np.float64), np.array([r[1] for r in rows], dtype=bool),
                     np.array([r[2] for r in rows]).reshape(len(rows), back + ahead), [r[3] for r in rows])


def listener_motion(audio: np.ndarray, decide, fps: float = 30.0, rate: int = RATE, heard_s: float | None = None
                    ) -> tuple[BvhMotion, dict]:
    """The rule's motion with its stresses decided by `decide` (windows (n, W) -> bool (n,)) instead of the rule:
    with the rule's own decisions it is the rule's motion exactly."""
    events = rule_events(audio, rate, heard_s)
    syl = syllables(audio, rate, heard_s)
    chosen = np.asarray(decide(syl.windows), dtype=bool) if len(syl.onsets) else np.zeros(0, bool)
    events = {"phrases": events["phrases"], "stresses": [s for s, c in zip(syl.strokes, chosen) if c]}
    n = int(round(len(audio) / rate * fps))
    return gesture_motion(events, n, fps, np.random.default_rng(events_seed(events)), ENGAGE_TAU_S), events


class StressListener:
    """A small MLP that learns the rule's stress decision from listening windows (`syllables`): a generic learner
    given the rule's own input (its loudness envelope, relative to the phrase's median), trained with the
    classes weighted equally."""

    def __init__(self, hidden: int = 128, epochs: int = 300, seed: int = 0):
        self.hidden, self.epochs, self.seed = hidden, epochs, seed

    def fit(self, windows: np.ndarray, stressed: np.ndarray) -> "StressListener":
        import torch

        self.mean, self.sd = windows.mean(0), windows.std(0) + 1e-6
        x = torch.tensor((windows - self.mean) / self.sd, dtype=torch.float32)
        y = torch.tensor(stressed, dtype=torch.float32)
        pos = float(np.clip(stressed.mean(), 1e-3, 1 - 1e-3))
        weight = torch.tensor(np.where(stressed, 0.5 / pos, 0.5 / (1 - pos)), dtype=torch.float32)
        with torch.random.fork_rng():  # seeded here, whatever the caller's generator holds
            torch.manual_seed(self.seed)
            self.net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], self.hidden), torch.nn.GELU(),
                                           torch.nn.Dropout(0.2), torch.nn.Linear(self.hidden, self.hidden),
                                           torch.nn.GELU(), torch.nn.Linear(self.hidden, 1))
            opt = torch.optim.AdamW(self.net.parameters(), 1e-3, weight_decay=1e-2)
            self.net.train()
            for _ in range(self.epochs):  # full batch: a few thousand syllables
                loss = torch.nn.functional.binary_cross_entropy_with_logits(self.net(x)[:, 0], y, reduction="none")
                opt.zero_grad()
                (loss * weight).mean().backward()
                opt.step()
        self.net.eval()
        return self

    def __call__(self, windows: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            x = torch.tensor((windows - self.mean) / self.sd, dtype=torch.float32)
            return self.net(x)[:, 0].numpy() > 0


def balanced_accuracy(truth: np.ndarray, guess: np.ndarray) -> float:
    """Mean of the hit rates on stressed and on unstressed syllables (0.5: chance)."""
    return 0.5 * (float(guess[truth].mean()) + float((~guess[~truth]).mean()))
