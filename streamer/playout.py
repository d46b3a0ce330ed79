"""The playout side of a voice agent's avatar (`streamer.pipecat`): each utterance's audio as the output transport
plays it, and the clock that says when each moment of it is heard. No pipecat in here: the stage feeds it what the
pipeline does (audio pushed, playout reported) and reads when each frame is due.

An utterance's timeline ("local" seconds) is its audio with the silences the transport plays between chunks that
came late (a TTS slower than real time): frame k shows local time k / fps, heard at `start` + k / fps.
"""

from __future__ import annotations

import asyncio
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from dimgestor.audio import SAMPLE_RATE
from streamer.sessions import Session
from streamer.sources import PushSource

LATER_AFTER = 2     # playout reports in a row later than the clock that move it later (one late report: a busy loop)
UNCONFIRMED_S = 0.1  # how long past its time a frame waits for the transport's report of its audio


@dataclass
class Utterance:
    """One answer of the agent: its session (audio in, frames out) and where its audio stands in the playout."""

    number: int
    session: Session | None
    source: PushSource | None
    resampler: object | None  # to 16 kHz (`StreamingResampler`); None: the TTS's rate is 16 kHz
    rate: int
    start: float | None = None   # monotonic time its first sample is heard
    pts0: float = 0.0            # its first frame's pts (its frames' and its audio's clock: fixed at its first release)
    pushed_s: float = 0.0        # audio (and transport gaps) handed to the transport so far
    samples: int = 0             # of which audio, in samples at `rate` (counted, not summed as seconds: see gaps)
    gaps: list = field(default_factory=list)  # (audio_s before it, seconds): silence the transport plays
    heard_s: float = 0.0         # audio the transport reported playing (`Playout.heard`)
    last_chunk_s: float = 0.0    # the last reported chunk's length
    confirmed: bool = False      # the transport reported playing it (until then its start is an estimate)
    offsets: deque = field(default_factory=lambda: deque(maxlen=LATER_AFTER))  # reports later than `start`
    open: bool = True            # more of its audio may come
    done: bool = False           # its session ended: every frame is in `frames` or released
    frames: deque = field(default_factory=deque)
    first_ready: asyncio.Event = field(default_factory=asyncio.Event)
    audio: list = field(default_factory=list)  # (local pts, 16 kHz samples) not yet heard: for on_audio
    task: asyncio.Task | None = None
    released: int = 0

    @property
    def audio_s(self) -> float:
        """Seconds of audio handed to the transport. A gap starts exactly here: a frame whose pts is the same
        moment (k / fps == samples / rate) shows the gap's silence, where a sum of 20 ms chunks (0.4000000000000001
        after twenty) would have put it a rounding error into the gap and labelled it audio."""
        return self.samples / self.rate

    def audio_at(self, local: float) -> float | None:
        """The moment of its audio heard at `local` seconds into its timeline (None: a gap the transport filled)."""
        silence = 0.0
        for at, gap in self.gaps:
            if local < at + silence:
                break
            if local < at + silence + gap:
                return None
            silence += gap
        return local - silence

    async def feed(self, x: np.ndarray) -> None:
        """Audio at its rate (float mono) to its session, kept until heard (`give_audio`)."""
        y = x if self.resampler is None else np.asarray(self.resampler.process(x), dtype=np.float32)
        if len(y):
            self.audio.append((self.source.samples_in / SAMPLE_RATE, y))
            await self.source.put(y)  # (waits only when an hour of audio is queued)

    async def close(self) -> None:
        """Its audio has all come: the session flushes its last frames."""
        self.open = False
        if self.resampler is not None:
            tail = np.asarray(self.resampler.flush(), dtype=np.float32)
            if len(tail):
                self.audio.append((self.source.samples_in / SAMPLE_RATE, tail))
                await self.source.put(tail)
        await self.source.close()

    def give_audio(self, until: float, on_audio: Callable[[float, np.ndarray], None] | None) -> None:
        """Its audio up to local time `until` to on_audio(pts, samples), as it is heard (never what an
        interruption cut)."""
        while self.audio and self.audio[0][0] < until:
            pts, y = self.audio.pop(0)
            n = len(y) if until == np.inf else min(len(y), int(round((until - pts) * SAMPLE_RATE)))
            if n < len(y):  # the rest is heard later
                self.audio.insert(0, (pts + n / SAMPLE_RATE, y[n:]))
            if n <= 0:
                break
            if on_audio is not None:
                on_audio(self.pts0 + pts, y[:n])


class Playout:
    """When the utterances' audio is heard: the transport's queue as this side models it (`schedule`), corrected
    by what the transport reports playing (`heard`, from `streamer.pipecat.PlayoutObserver`) or, without reports,
    by its BotStartedSpeaking (`bot_started`). `changed()` is called whenever a time moved."""

    def __init__(self, changed: Callable[[], None] = lambda: None):
        self.changed = changed
        self.playing: deque[Utterance] = deque()  # utterances whose audio the transport has not all played
        self.play_end = 0.0  # when the audio pushed so far ends playing
        self.observed = False  # the transport's playout is reported (an observer sees the pipeline)

    def schedule(self, u: Utterance, samples: int, now: float) -> float:
        """`samples` of u's audio (at its rate) are pushed to the transport at `now`: when they play (u's start
        is set by its first). Returns the silence (s) the transport plays before them, part of u's timeline (a
        TTS slower than real time)."""
        seconds = samples / u.rate
        begin = max(now, self.play_end)
        if u.start is None:
            u.start, gap = begin, 0.0
        else:
            gap = begin - (u.start + u.pushed_s)
            if gap < 0.5 / u.rate:  # (under half a sample: the rounding of sums of clock times, not silence)
                gap = 0.0
        if gap > 0:
            u.gaps.append((u.audio_s, gap))
        if not u.samples:
            self.playing.append(u)
        u.pushed_s += gap + seconds
        u.samples += samples
        self.play_end = begin + seconds
        self.changed()
        return gap

    def heard(self, wall: float, seconds: float) -> None:
        """The output transport reported playing `seconds` of audio from `wall`: the playing utterance's clock
        follows. A report is never early but may be late (the loop was busy when the transport pushed it on), so
        an earlier one moves the clock at once, a later one only when the last `LATER_AFTER` reports agree (the
        device really ran dry: a stalled loop, a slow write)."""
        if not self.playing:
            return
        u = self.playing[0]
        local = u.heard_s + sum(g for at, g in u.gaps if at <= u.heard_s + 1e-6)
        offset = wall - local  # when u's local time 0 was heard, by this report
        u.heard_s += seconds
        u.last_chunk_s = seconds
        if not u.open and u.heard_s >= u.audio_s - 1e-6:  # (its last chunk may be padded with silence)
            self.playing.popleft()
        shift = 0.0
        if not u.confirmed:
            u.confirmed, shift = True, offset - u.start
        elif offset < u.start - 1e-3:
            shift = offset - u.start
        else:
            u.offsets.append(offset)
            if len(u.offsets) == LATER_AFTER and min(u.offsets) > u.start + 5e-3:
                shift = min(u.offsets) - u.start
        if shift:
            u.offsets.clear()
            later = [v for v in self.playing if v is not u and v.start is not None and v.start > u.start]
            for v in [u, *later]:  # what is queued behind it plays that much later (or earlier) too
                v.start += shift
            self.play_end += shift
        self.changed()

    def bot_started(self, now: float, utterances) -> None:
        """The transport started playing (without playout reports): an utterance that began in silence began now
        (if later than thought)."""
        if self.observed:
            return
        for u in utterances:
            if u.start is not None and u.released == 0 and u.start < now:
                u.start = now
                self.changed()
                break

    def unheard(self, u: Utterance, pts: float, due: float, now: float) -> bool:
        """The transport has not reported playing the audio of u's frame at `pts` yet (it ran late: the frame waits
        for it, up to UNCONFIRMED_S past its due time, so reports that come late or never cannot stop the avatar)."""
        if not self.observed or now > due + UNCONFIRMED_S:
            return False
        moment = u.audio_at(pts)  # (the chunk after the last reported one follows it: report latency allowed)
        return moment is not None and moment >= u.heard_s + u.last_chunk_s

    def started(self, u: Utterance | None, now: float) -> bool:
        """u's start is known well enough to release its frames: reported, or estimated where no report comes
        (no observer, or none UNCONFIRMED_S past it)."""
        return u is not None and u.start is not None and (u.confirmed or not self.observed or
                                                           now > u.start + UNCONFIRMED_S)

    def clear(self, now: float) -> None:
        """An interruption: nothing queued will be heard."""
        self.playing.clear()
        self.play_end = now
        self.changed()
