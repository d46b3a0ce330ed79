"""The face's listener: which speech sound is heard when, from a phone recognizer run on the live stream with a
bounded lookahead (pocketsphinx's English acoustic model and phone language model, both in its PyPI wheel).

Deterministic whatever the chunking: audio is fed in fixed 10 ms blocks on the stream's absolute clock, and the
phones at frame i are read from the recognizer's best path right after the block that completes the audio up to
frame i's time plus the lookahead; so a stream pushed in any pieces reads exactly what the whole recording pushed
at once reads. The recognizer's utterance restarts at a pause (and at least every `max_utterance_s`) so a
stream of hours costs the same per frame as its first minute.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import threading
import warnings
from dataclasses import dataclass, field

import numpy as np

from dimgestor.face.visemes import canonical_phone

__all__ = ["PhoneListener", "Segment", "unavailable", "phone_decoder"]

BLOCK = 160  # samples (10 ms at 16 kHz): the recognizer's frame
RATE = 16000


@dataclass(frozen=True)
class Segment:
    phone: str
    start: float  # s on the stream's clock
    end: float


def unavailable() -> str | None:
    """Why the listener cannot run here, or None: pocketsphinx publishes no wheel for some Pythons and platforms
    (Python 3.14; Linux aarch64 on 3.10 and 3.12), where the engine installs without it (pyproject.toml)."""
    if importlib.util.find_spec("pocketsphinx") is not None:
        return None
    return (f"the face's listener needs pocketsphinx, which has no wheel for Python {sys.version_info[0]}."
            f"{sys.version_info[1]} on this platform: `pip install pocketsphinx` builds it (cmake and a C compiler), "
            "or use Python 3.11 or 3.13")


def phone_decoder(beam: float = 1e-20, pbeam: float = 1e-20, lw: float = 2.0):
    """A pocketsphinx decoder of English phones (acoustic model and phone language model of its wheel): the
    listener's, with its default beams and language weight."""
    if (why := unavailable()) is not None:
        raise ImportError(why)
    from pocketsphinx import Config, Decoder, get_model_path, set_loglevel

    set_loglevel("FATAL")
    model = get_model_path()
    config = Config(hmm=os.path.join(model, "en-us", "en-us"),
                    allphone=os.path.join(model, "en-us", "en-us-phone.lm.bin"),
                    lm=None, dict=None,  # (the defaults load the 26 MB word model and dictionary: 29 MB a decoder)
                    beam=beam, pbeam=pbeam, lw=lw, loglevel="FATAL")
    return Decoder(config)


class DecoderPool:
    """Decoders of ended streams kept for the next ones: making one costs ~16 ms and 7 MB, which a server whose
    clients start many short sessions pays at each. A decoder taken from here starts as a new one does: its
    cepstral mean and noise statistics (which it learns as it listens) are reset: it hears as a new one
    (tests/test_face.py)."""

    KEEP = 8

    def __init__(self):
        self.idle: dict[tuple, list] = {}
        self.fresh_cmn: dict[tuple, str] = {}
        self.lock = threading.Lock()

    def take(self, key: tuple):
        with self.lock:
            d = self.idle.get(key, []).pop() if self.idle.get(key) else None
        if d is None:
            d = phone_decoder(*key)
            with self.lock:
                self.fresh_cmn.setdefault(key, d.get_cmn())
        else:
            d.set_cmn(self.fresh_cmn[key])
            with warnings.catch_warnings():  # (pocketsphinx 5 calls it unnecessary, yet without it the noise
                warnings.simplefilter("ignore", DeprecationWarning)  # statistics of the last stream carry over)
                d.start_stream()
        d.start_utt()
        return d

    def give(self, key: tuple, d) -> None:
        try:
            d.end_utt()
        except RuntimeError:
            pass  # not in an utterance
        with self.lock:
            idle = self.idle.setdefault(key, [])
            if len(idle) < self.KEEP:
                idle.append(d)


DECODERS = DecoderPool()


@dataclass
class PhoneListener:
    """Push 16 kHz audio; `ready` then holds the phone segments around each frame whose lookahead is complete."""

    fps: int
    lookahead_s: float
    context_s: float = 0.12          # phones kept each side of a frame's time (coarticulation)
    max_utterance_s: float = 20.0
    pause_s: float = 0.3
    beam: float = 1e-20
    pbeam: float = 1e-20
    lw: float = 2.0
    blocks_in: int = 0               # 10 ms blocks fed so far
    next_frame: int = 0
    ready: list = field(default_factory=list)   # [(frame index, [Segment, ...])]
    _pending: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int16))
    _done: list = field(default_factory=list)   # final segments of ended utterances (recent ones only)
    _utt_start: int = 0                         # block where the running utterance began
    start_sample: int = 0                       # where on the stream's clock listening began (a resumed stream)
    start_frame: int = 0

    def __post_init__(self):
        self.blocks_in, self.next_frame = self.start_sample // BLOCK, self.start_frame
        self._utt_start = self.blocks_in
        self._pending = np.zeros(self.start_sample % BLOCK, np.int16)
        if self.lookahead_s < self.context_s:
            raise ValueError(f"the face's lookahead ({self.lookahead_s} s) must cover its context ({self.context_s} s)")
        self._decoder = DECODERS.take((self.beam, self.pbeam, self.lw))

    def push(self, samples: np.ndarray) -> None:
        pcm = (np.clip(np.asarray(samples, np.float32), -1, 1) * 32767).astype(np.int16)
        pcm = np.concatenate([self._pending, pcm])
        at = 0
        # The blocks up to the one that completes the next frame, in one call, once all of them are in: the
        # recognizer's running cepstral mean moves at each call's end, so the calls must not follow the pieces.
        while len(pcm) - at >= (n := max(1, self._due_block() - self.blocks_in) * BLOCK):
            self._decoder.process_raw(pcm[at:at + n].tobytes(), False, False)
            self.blocks_in += n // BLOCK
            at += n
            self._frames_due()
        self._pending = pcm[at:]

    def _due_block(self) -> int:
        """The block count at which the next frame's lookahead is complete."""
        return int(np.ceil((self.next_frame / self.fps + self.lookahead_s) * RATE / BLOCK - 1e-6))

    def finish(self, frames: int) -> None:
        """The audio ended: the utterance's final best path gives every frame left up to `frames` (silence after
        the audio's end); the decoder goes back to the pool."""
        if self._decoder is None:
            return
        if len(self._pending):
            self._decoder.process_raw(self._pending.tobytes(), False, False)
        self._end_utterance()
        segments = self._done
        while self.next_frame < frames:
            t = self.next_frame / self.fps
            self.ready.append((self.next_frame, [s for s in segments if s.end > t - self.context_s
                                                 and s.start < t + self.context_s]))
            self.next_frame += 1
        self.close()

    def close(self) -> None:
        """Done listening: the decoder goes back to the pool (idempotent)."""
        if self._decoder is not None:
            DECODERS.give((self.beam, self.pbeam, self.lw), self._decoder)
            self._decoder = None

    def _frames_due(self) -> None:
        now = self.blocks_in * BLOCK / RATE
        if (self.next_frame / self.fps) + self.lookahead_s > now + 1e-9:
            return  # no frame completes in this block: the best path is read only when one does (it is costly)
        segments = self.segments()
        while (self.next_frame / self.fps) + self.lookahead_s <= now + 1e-9:
            t = self.next_frame / self.fps
            segs = [s for s in segments if s.end > t - self.context_s and s.start < t + self.context_s]
            self.ready.append((self.next_frame, segs))
            self.next_frame += 1
        self._maybe_restart(now, segments)

    def segments(self) -> list[Segment]:
        """The ended utterances' segments kept, then the running utterance's best path so far."""
        offset = self._utt_start * BLOCK / RATE
        running = [Segment(canonical_phone(s.word), offset + s.start_frame / 100, offset + (s.end_frame + 1) / 100)
                   for s in (self._decoder.seg() or ())]
        return self._done + running

    def _maybe_restart(self, now: float, segments: list[Segment]) -> None:
        """At a frame's block: end the utterance where the best path ends in a pause (or it grew too long)."""
        length = now - self._utt_start * BLOCK / RATE
        if length < 2 * self.lookahead_s + self.pause_s:
            return
        tail = [s for s in segments if s.end > now - self.pause_s]
        paused = tail and all(s.phone == "SIL" for s in tail) and tail[0].start <= now - self.pause_s
        if not (paused or length >= self.max_utterance_s):
            return
        self._end_utterance(keep_from=now - self.lookahead_s - 2 * self.context_s)
        self._utt_start = self.blocks_in
        self._decoder.start_utt()

    def _end_utterance(self, keep_from: float = -np.inf) -> None:
        self._decoder.end_utt()
        offset = self._utt_start * BLOCK / RATE
        final = [Segment(canonical_phone(s.word), offset + s.start_frame / 100, offset + (s.end_frame + 1) / 100)
                 for s in (self._decoder.seg() or ())]
        self._done = [s for s in self._done + final if s.end > keep_from]
