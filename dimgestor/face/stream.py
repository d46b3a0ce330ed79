"""A face that streams with the body: push the same 16 kHz audio the gesture stream gets, take one canonical face
frame (`visemes.FACE_LABELS`) per body frame.

Frame i is made once the audio up to its time plus `lookahead_s` is in: the body's own lookahead, so the face adds
no latency (a body frame exists only after that audio came). The mouth is the phones heard around frame i
(`listener.py`), each a viseme and a jaw opening (`visemes.py`), blended over +-`blend_s` the way neighbouring
sounds shape each other; lips close fully inside M, B, P; the shape scales with how loud the voice is against
its recent peak, so it rests in silence and pauses. Blinks, brows and a smile come from `life.py`.

Streaming equals offline: every part steps on the stream's absolute clock in fixed blocks, so any chunking of the
audio gives the same frames.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

from dimgestor.face.life import Blinks, Brows, pitch_semitones
from dimgestor.face.listener import BLOCK, PhoneListener, Segment
from dimgestor.face.net import Heard, NetListener
from dimgestor.face.visemes import FACE_LABELS, V, VISEMES, VOWEL_CLASS, phone_targets

__all__ = ["FaceStream", "FaceOptions", "MAX_LOOKAHEAD_S", "LISTENERS"]

RATE = 16000
MAX_LOOKAHEAD_S = 0.3   # more adds latency to a model that looks further ahead, and nothing measurable
_CLOSED = ("M", "B", "P")
_MOUTH = slice(0, V["jawOpen"] + 1)
LISTENERS = ("net", "pocketsphinx", "net+pocketsphinx")  # the last: both hear, their mouths averaged
# the vowel shapes' weight when the network hears them, as `visemes.py` weighs them by the vowels' height
_SHAPE_WEIGHT = np.array([{"aa": 1.0, "E": 0.75, "I": 0.5, "O": 0.75, "U": 0.5}.get(v, 1.0) for v in VISEMES])
_VOWEL_VISEMES = {V[v] for v in ("aa", "E", "I", "O", "U")}


@dataclass(frozen=True)
class FaceOptions:
    """How the face is made (defaults measured on real speech: benchmarks/face.py)."""

    blend_s: float = 0.03        # half width of the triangle over which neighbouring phones blend
    loud_range_db: float = 35.0  # the mouth scales from this far below the recent peak (closed) to the peak
    loud_power: float = 0.5
    peak_s: float = 2.0          # the recent peak: the loudest 40 ms of the last peak_s
    silence_dbfs: float = -70.0  # 40 ms under this level (dB of full scale) is silence: the mouth rests
    seed: int = 0                # the blinks' draws
    smile: float = 0.0           # the expression held under the speech (0..1), settable while streaming
    listener: str = "net"        # "net": the face's own network (net.py); "pocketsphinx": its phone recognizer;
    # "net+pocketsphinx": both, each frame's mouth the mean of theirs (closer to real voices, at both costs)
    weights: str | None = None   # the network's weights (None: those in the package)


class FaceStream:
    """push(samples) the stream's audio; take(n) the next n face frames, (n, len(FACE_LABELS))."""

    def __init__(self, fps: int, lookahead_s: float, options: FaceOptions = FaceOptions(), *, start_sample: int = 0,
                 start_frame: int = 0):
        self.fps, self.options = fps, options
        self.lookahead_s = min(float(lookahead_s), MAX_LOOKAHEAD_S)
        self.smile = options.smile
        if options.listener not in LISTENERS:
            raise ValueError(f"face listener {options.listener!r}: one of {', '.join(LISTENERS)}")
        if options.listener != "pocketsphinx":  # (a lookahead under the network's: the mouth follows late by it)
            self.listener = NetListener(fps, start_sample=start_sample, start_frame=start_frame,
                                        weights=options.weights, late=NetListener.late_frames(self.lookahead_s),
                                        frames_per_step=NetListener.frames_per_step(fps, self.lookahead_s))
        phones = None if options.listener == "net" else PhoneListener(
            fps, self.lookahead_s, context_s=min(0.12, self.lookahead_s), start_sample=start_sample,
            start_frame=start_frame)
        if options.listener == "pocketsphinx":
            self.listener, phones = phones, None
        self.phones = phones                              # the second listener of "net+pocketsphinx"
        self._next = start_frame                          # the next frame to make
        self.blinks = Blinks(seed=options.seed)
        self.brows = Brows(fps=fps)
        self._keep = int((options.peak_s + 2 * self.lookahead_s + 0.1) * RATE)
        self._buf = np.zeros(2 * self._keep, np.float32)  # the newest samples (at most 2 keep), for loudness, pitch
        self._held = 0                                    # samples in _buf
        self._audio_end = start_sample                    # absolute index after the newest sample
        self._loud = {}                                # frame -> dB of its 40 ms
        self._peaks: collections.deque = collections.deque()  # (frame, dB), dB falling: the recent peak first
        self._peak_next: int | None = None             # the next frame the recent peak takes in
        self._speech_run = 0.0                         # seconds of speech before the frame being made
        self._rows: collections.deque = collections.deque()

    @property
    def frames_ready(self) -> int:
        return len(self._rows)

    def push(self, samples: np.ndarray) -> None:
        """Each frame made as soon as the listener's 10 ms block that completes its lookahead is in (pieces cut at
        those blocks on the stream's clock): what a frame reads is the same whatever pieces the audio came in."""
        FaceStream.push_many([self], [samples])

    @staticmethod
    def push_many(faces: list["FaceStream"], audio: list[np.ndarray]) -> None:
        """`push` each stream's audio, the streams' networks stepped together (`NetListener.run_many`: what a
        server's batch of windows does); each face the same as pushed alone, to the matrix products' rounding."""
        audio = [np.asarray(x, np.float32).reshape(-1) for x in audio]
        nets = [f.listener for f in faces if isinstance(f.listener, NetListener)]
        for f, x in zip(faces, audio):
            if isinstance(f.listener, NetListener):
                f.listener.push(x, run=False)
        NetListener.run_many(nets)
        for f, x in zip(faces, audio):
            f._settle(x)

    def _settle(self, samples: np.ndarray) -> None:
        """The frames whose audio `samples` completes (the network has heard them; the phone listener hears
        them here)."""
        at = 0
        while at < len(samples):
            piece = samples[at:at + max(1, self._due() - self._audio_end)]
            self._hold(piece)
            if not isinstance(self.listener, NetListener):
                self.listener.push(piece)
            if self.phones is not None:
                self.phones.push(piece)
            self._make()
            at += len(piece)

    def _due(self) -> int:
        """The sample (stream clock) after the block in which the next frame's lookahead completes."""
        need = (self._next / self.fps + self.lookahead_s) * RATE
        return int(np.ceil(need / BLOCK - 1e-6)) * BLOCK

    def _hold(self, piece: np.ndarray) -> None:
        if self._held + len(piece) > len(self._buf):
            self._buf[: self._keep] = self._buf[self._held - self._keep:self._held]
            self._held = self._keep
        self._buf[self._held:self._held + len(piece)] = piece
        self._held += len(piece)
        self._audio_end += len(piece)

    def finish(self) -> None:
        """The audio ended: every frame up to its end plus the lookahead is made, silence after it."""
        pad = int(np.ceil((self.lookahead_s + 0.05) * RATE))
        frames = int(np.ceil((self._audio_end + pad) / RATE * self.fps - 1e-9))
        self._hold(np.zeros(pad, np.float32))  # (heard as silence by loudness and pitch; the listener has ended)
        self.listener.finish(frames)
        if self.phones is not None:
            self.phones.finish(frames)
        self._make(ended=True)

    def close(self) -> None:
        """Done: the listener's decoder is given back for another stream."""
        self.listener.close()
        if self.phones is not None:
            self.phones.close()

    def take(self, n: int) -> np.ndarray:
        if n > len(self._rows):
            raise RuntimeError(f"{n} face frames asked, {len(self._rows)} made: the face's lookahead "
                               f"({self.lookahead_s} s) exceeds the caller's")
        return np.array([self._rows.popleft() for _ in range(n)]).reshape(n, len(FACE_LABELS))

    # -- making a frame ---------------------------------------------------------------------------------------
    def _make(self, ended: bool = False) -> None:
        """Frames whose lookahead is in (the network hears sooner than that; the loudness and pitch read up to
        it); after the end, every frame the listener gave."""
        while self.listener.ready and (self.phones is None or self.phones.ready) and \
                (ended or self._due() <= self._audio_end):
            index, heard = self.listener.ready.pop(0)
            if self.phones is not None:  # (both listeners give every frame in order, from the same first one)
                heard = (heard, self.phones.ready.pop(0)[1])
            self._rows.append(self._frame(index, heard))
            self._next = index + 1

    def _window(self, centre: float, half_s: float) -> np.ndarray:
        c = int(round(centre * RATE))
        lo, hi = c - int(half_s * RATE), c + int(half_s * RATE)
        first = self._audio_end - self._held
        lo, hi = max(lo, first), min(hi, self._audio_end)
        if hi <= lo:
            return np.zeros(0, np.float32)
        return self._buf[lo - first:hi - first]

    def _db(self, frame: int) -> float:
        if frame not in self._loud:
            x = self._window(frame / self.fps, 0.02)
            x = x.astype(np.float64)
            self._loud[frame] = 10 * np.log10(np.add.reduce(x * x) / len(x) + 1e-10) if len(x) else -100.0
        return self._loud[frame]

    def _peak(self, lo: int, hi: int) -> float:
        """The loudest of frames lo..hi (each bound never falling from one frame to the next): a running maximum,
        each frame's loudness taken in once."""
        for j in range(lo if self._peak_next is None else max(self._peak_next, lo), hi + 1):
            d = self._db(j)
            while self._peaks and self._peaks[-1][1] <= d:
                self._peaks.pop()
            self._peaks.append((j, d))
        self._peak_next = hi + 1 if self._peak_next is None else max(self._peak_next, hi + 1)
        while self._peaks[0][0] < lo:
            self._peaks.popleft()
        return self._peaks[0][1]

    def _frame(self, index: int, heard: list[Segment] | Heard | tuple[Heard, list[Segment]]) -> np.ndarray:
        o, t = self.options, index / self.fps
        mouths = [self._mouth_heard(h) if isinstance(h, Heard) else self._mouth_of_phones(t, h)
                  for h in (heard if isinstance(heard, tuple) else (heard,))]
        # Loudness against the recent peak: the shape in full at the peak, none loud_range_db under it.
        ahead = max(0, min(5, int((self.lookahead_s - 0.02) * self.fps)))
        peak = self._peak(max(0, index - int(o.peak_s * self.fps)), index + ahead)
        db = self._db(index)
        level = min(max(float((db - (peak - o.loud_range_db)) / o.loud_range_db), 0.0), 1.0) ** o.loud_power
        for out, _, closed in mouths:
            out[_MOUTH] *= level if db >= o.silence_dbfs else 0.0
            out[V["PP"]] = max(out[V["PP"]], 1.0 if closed else 0.0)
            out[V["sil"]] = max(0.0, 1.0 - out[V["PP"]:V["U"] + 1].sum())  # the rest shape: what the others leave
        out, now = mouths[0][0], mouths[0][1]  # (two listeners: the mean of their mouths; the network's "now")
        if len(mouths) > 1:
            out = (out + mouths[1][0]) / 2
        while (first := next(iter(self._loud))) < index - int(o.peak_s * self.fps):  # (in the order they came)
            del self._loud[first]
        # Blinks (more at a phrase's end), brows on pitch accents, the smile under the speech.
        speaking = now != "SIL"
        phrase_end = not speaking and self._speech_run >= 1.0
        self._speech_run = self._speech_run + 1 / self.fps if speaking else 0.0
        out[V["blinkLeft"]], out[V["blinkRight"]] = self.blinks.step(t, phrase_end)
        semitones = pitch_semitones(self._window(t, 0.02)) if speaking else None
        out[V["browUp"]] = self.brows.step(semitones, db - peak, now in VOWEL_CLASS or now == "ER")
        out[V["smile"]] = self.smile * (1 - 0.5 * out[V["jawOpen"]])
        return out

    def _mouth_heard(self, heard: Heard) -> tuple[np.ndarray, str, bool]:
        """The network's mouth: each viseme by its probability (vowel shapes by their height), the jaw by the
        opening it hears, shut by the chance of M, B, P; (the mouth, "SIL" / a vowel / "C", lips closed)."""
        out = np.zeros(len(FACE_LABELS))
        p = heard.visemes
        out[:len(VISEMES)] = p * _SHAPE_WEIGHT
        out[V["jawOpen"]] = heard.opening * (1.0 - p[V["PP"]])
        best = int(np.argmax(p))
        now = "SIL" if best == V["sil"] else "AA" if best in _VOWEL_VISEMES else "C"
        closed = best == V["PP"]
        if closed:
            out[_MOUTH] *= 0.2
            out[V["PP"]] = 1.0
        return out, now, closed

    def _mouth_of_phones(self, t: float, segments: list[Segment]) -> tuple[np.ndarray, str, bool]:
        o = self.options
        out = np.zeros(len(FACE_LABELS))
        # The mouth: phones blended over a triangle around t, lips shut inside a closure.
        weights = 0.0
        for u in np.linspace(t - o.blend_s, t + o.blend_s, 9):
            k = 1 - abs(u - t) / o.blend_s + 1e-3
            phone = next((s.phone for s in segments if s.start <= u < s.end), "SIL")  # nothing heard: silence
            out += k * phone_targets(phone)
            weights += k
        if weights:
            out /= weights
        now = next((s.phone for s in segments if s.start <= t < s.end), "SIL")
        if now in _CLOSED:
            out[_MOUTH] *= 0.2
            out[V["PP"]] = 1.0
        return out, now, now in _CLOSED
