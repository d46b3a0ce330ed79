"""Admission by capacity: a new session is admitted only while the sessions already admitted stay in real time.

Every session's real-time work runs on the inference thread(s), a cycle at a time (`streamer.scheduling`): one
batched model call for every due window, then, session by session, its frames decoded and its face made. The
batched call costs little more for one more stream; a face does not batch: each one is the listener's work on the
same thread, about 0.1 s of it per second of speech on a laptop's core. Seven faces on a two-core machine once
took the whole thread, and every client, admitted by `--max-sessions` alone, fell 9-19 s behind.

So, besides the seats:
- no new session while the worker is not ready (`streamer.health.Readiness`: its real-time load over its limit,
  or a real-time client's audio piling up): everyone admitted is then already short of real time;
- a session with a face only while the real-time load, plus the faces admitted too recently to be in it yet (each
  1.5x a face's cost), plus this face stays within `max_load` (0.7) of the inference thread(s): a face's cost is
  measured once when the worker starts (`FaceCost.measure`, twice what one face alone takes: in a server it shares
  the GIL with every client's other work) and then learnt from every face the sessions make (`FaceCost.add`).
A session refused gets `busy` with `retry_after_s` (`RETRY_AFTER_S`): capacity frees as sessions end; or, with
`without_face` (`serve --faces-beyond-capacity no-face`), a session refused only for its face is admitted without
one and told so (`face_withheld`). `/readyz` and the metrics say how many more faces fit (`faces_left`).
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable

import numpy as np

__all__ = ["Admission", "FaceCost", "RETRY_AFTER_S", "MAX_LOAD"]

MAX_LOAD = 0.7  # of the inference thread(s), at most, for the sessions admitted with the next one (at 0.8 the
#                 talkers' frames came 2-3x later than alone: every cycle waits for the one before it)
RETRY_AFTER_S = 5.0  # what a refused client is told to wait before it tries again
FACE_SETTLE_S = 10.0  # a face admitted this recently is not yet all in the measured load (its 10 s window) ...
PRIOR_MARGIN = 2.0  # a face measured alone at start costs about this much less than in a server's thread beside
#                    the clients' other work (the GIL it shares): the prior, until the faces made say better
SETTLING_MARGIN = 1.5  # ... so it counts as this many times a face's cost: a crowd arriving at once on a busy machine
#                        (where a face costs more than measured) is admitted a few at a time (the rest retry)


class FaceCost:
    """Seconds of the inference thread one second of a session's face costs: measured once (`measure`), then an
    exponential average of what the sessions' faces took (`add`, from the thread that makes them), quick to rise
    (`rise`: a machine got busier) and slow to fall (`fall`)."""

    def __init__(self, seconds_per_s: float | None = None, rise: float = 0.2, fall: float = 0.02):
        self.value, self.rise, self.fall = seconds_per_s, rise, fall
        self._lock = threading.Lock()

    def add(self, took_s: float, audio_s: float) -> None:
        if audio_s <= 0:
            return
        with self._lock:
            x = took_s / audio_s
            if self.value is None:
                self.value = x
            else:
                self.value += (self.rise if x > self.value else self.fall) * (x - self.value)

    def measure(self, options, fps: int, lookahead_s: float, seconds: float = 1.0) -> float:
        """Time one face over `seconds` of synthetic speech, as a session makes it (20 fps, 0.1 s pieces): the CPU
        time of this thread, which other processes starting beside it do not inflate (timed by the wall clock, a
        worker started beside another measured 0.77 s a second where 0.1 was true, and then admitted no face)."""
        from dimgestor.face import FaceStream
        from dimgestor.training.synthetic import synthetic_speech

        x = np.asarray(synthetic_speech(seconds, seed=7), np.float32)
        face = FaceStream(fps, lookahead_s, options)
        t = time.thread_time()
        try:
            for i in range(0, len(x), 1600):
                face.push(x[i:i + 1600])
                face.take(face.frames_ready)
        finally:
            face.close()
        self.add(PRIOR_MARGIN * (time.thread_time() - t), seconds)
        return self.value


class Admission:
    """Whether one more session (with a face or without) is admitted now (`refusal`); `admitted` tells it one was.
    `readiness`: the worker's `streamer.health.Readiness`; `lanes`: the inference threads the work is spread on."""

    def __init__(self, readiness, face_cost: FaceCost | None = None, lanes: int = 1, max_load: float = MAX_LOAD,
                 retry_after_s: float = RETRY_AFTER_S, now: Callable[[], float] = time.monotonic,
                 without_face: bool = False):
        self.readiness, self.face_cost, self.lanes = readiness, face_cost, lanes
        self.max_load, self.retry_after_s, self.now = max_load, retry_after_s, now
        self.without_face = without_face  # a session refused only for its face: admitted without one (and told)
        self._recent: deque[float] = deque()  # when the faces of the last FACE_SETTLE_S were admitted
        self.faces = 0  # sessions with a face admitted and not yet freed
        readiness.faces_left = self.faces_left  # (/readyz and the metrics say it)

    def _settling(self) -> int:
        cutoff = self.now() - FACE_SETTLE_S
        while self._recent and self._recent[0] <= cutoff:
            self._recent.popleft()
        return len(self._recent)

    def faces_left(self) -> int | None:
        """How many more sessions with a face fit now (None: no face is made, or its cost is not known yet). A
        worker making no face has room for one whatever its cost is thought to be (`refusal` checks first that it
        is ready): it is how the cost is learnt where it is made, and an estimate made too high (a busy moment at
        start) would otherwise refuse every face for ever."""
        cost = self.face_cost.value if self.face_cost is not None else None
        if not cost:
            return None
        room = ((self.max_load - self.readiness.load.value()) * self.lanes
                - self._settling() * cost * SETTLING_MARGIN)
        return max(0 if self.faces else 1, int(room / cost + 1e-9))

    def refusal(self, face: bool) -> str | None:
        """None to admit one more session (`face`: it makes a face), else why not (the `busy` error's message)."""
        ready, why = self.readiness.check()
        if not ready:
            return f"this worker is at capacity ({why.removeprefix('not ready: ')}): try again after retry_after_s"
        if face and (left := self.faces_left()) is not None and left < 1:
            settling = self._settling()
            recent = (f", {settling} face{'s' if settling > 1 else ''} admitted in the last {FACE_SETTLE_S:g} s not "
                      "yet all in it" if settling else "")
            return (f"this worker is at capacity for faces ({self.face_cost.value:.2f} s of compute a second each, "
                    f"real-time load {self.readiness.load.value():.2f}{recent}, limit {self.max_load:g}): try again "
                    "after retry_after_s, or ask for no face (hello.face \"none\")")
        return None

    def admitted(self, face: bool) -> None:
        if face:
            self.faces += 1
            self._recent.append(self.now())

    def freed(self, face: bool) -> None:
        """A session ended: a face of it admitted too recently to be in the load is no longer coming (the latest)."""
        if face:
            self.faces = max(0, self.faces - 1)
        if face and self._settling():
            self._recent.pop()
