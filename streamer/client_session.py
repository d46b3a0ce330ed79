"""One WebSocket client's session as a state machine without I/O: events in, actions out (docs/protocol.md).

The shell (`streamer/ws.py`) turns what its socket, worker thread and session task do into events and carries
out the actions this returns; nothing here awaits, opens a socket, starts a thread or reads a clock (time
comes with the events), so every rule of a client's session is tested by driving it alone
(tests/test_client_session.py), and another transport can reuse it.

A client is IDLE (no session), STREAMING (its audio goes to its session) or FINISHING (its audio has ended,
or is being handed over: the session still runs to its `end` or its save). A session holds one of the
server's `Seats` from its start until it ends or its client leaves: the machine reads whether one is free and
says `TakeSeat` / `FreeSeat`; only the shell, carrying those out, changes the count.

Which channels a client's frames carry is its own (revision 7): the face in the name set its hello asked (or the
server's), in JSON always when the server makes one, in binary only once asked; a `channels` message with the
binary layout goes out with the first frames after each hello that names a `face`.

The events it hears and the actions it returns are plain values, in `streamer.client_events`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from enum import Enum
from functools import lru_cache
from typing import Callable, Mapping

from dimgestor.audio import SAMPLE_RATE
from streamer import protocol as P
# (the machine's vocabulary: the shell and the tests import it from here too)
from streamer.client_events import (  # noqa: F401
    Action, Audio, Boundary, Broadcast, Charge, Close, Count, Decode, Decoded, EndAudio, Event, Failed, Feed, Forget,
    FreeSeat, Frames, HandedOver, HandOver, Left, Log, NotRestored, OverShare, Queuing, Refused, Release,
    ReplaySourceAudio, Restored, RigRefused, RigSet, Saved, SaveState, Send, SendFrames, SessionEnded, SetRig, SetSmile,
    StartSession, StopSession, Taken, TakeSeat, TakeState, Text, WaitForSession, WithinShare)
from streamer.face import FACE, face_channel
from streamer.frames import Channel

__all__ = ["ClientSession", "Terms", "Seats", "Keepalive", "Phase", "PIECE_S"]

PIECE_S = 0.5  # client audio is resampled in pieces of at most this many seconds (of its own rate) ...
PIECE_SAMPLES = 24000  # ... and samples: a piece's cost (~10 ms whatever the rate) is what another client's job
#                        may wait behind it on the worker thread (0.125 s of 192 kHz; 0.5 s up to 48 kHz)


# ---- the server's side ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Terms:
    """The terms every client's session is served on: fixed when the server starts."""

    max_sessions: int
    accepts_audio: bool = True       # False: --no-client-audio
    offers_source_audio: bool = False  # the hello offers the server source's audio
    max_backlog_s: float = 30.0      # a session's audio queue (slow_down at the cap, resume at half)
    resumable: bool = False          # a state store: resume_session is served
    save_every_s: float | None = None  # periodic saves (with a store)
    face: str | None = None          # the face's name set unless a client asks another (None: the server makes none)
    joints: int = 0                  # a frame's joints (the offsets of a binary layout)
    speakers: tuple[str, ...] = ()   # the speakers of a model with a speaker condition (a client may ask one)
    speaker: str | None = None       # the one a session plays unless its client asks (--speaker; None: none)
    speaker_fixed: bool = False      # the server plays `speaker` only (ONNX Runtime: its vector is in the graph)

    def speaker_refusal(self, asked: str | None) -> str | None:
        """Why a client's hello may not ask `asked` (a name, or None for no speaker in particular), or None."""
        if asked == self.speaker:
            return None
        if self.speaker_fixed:
            plays = f"speaker {self.speaker!r}" if self.speaker is not None else "no speaker in particular"
            return (f"speaker {asked!r}: this server plays {plays} only (its ONNX Runtime backend holds one speaker "
                    "in its graph; a server on the torch backend lets each client choose)")
        if asked is None or asked in self.speakers:
            return None
        known = ", ".join(self.speakers) or "none (its model was trained without --speaker-condition)"
        return f"speaker {asked!r}: this server's model knows {known}"


class Seats:
    """What every client's session shares: the server's `Terms`, how many sessions hold a seat now (including those
    flushing after audio_end) and whether the server is stopping. The machines read it; a seat is taken and freed
    only by carrying out their `TakeSeat` and `FreeSeat` (`carry_out`), `closing` is set by the server."""

    def __init__(self, terms: Terms, admission=None):
        self.terms = terms
        self.admission = admission  # a `streamer.capacity.Admission` (None: the seats alone)
        self._taken = 0
        self.closing = False

    @property
    def taken(self) -> int:
        return self._taken

    @property
    def full(self) -> bool:
        return self._taken >= self.terms.max_sessions

    def refusal(self, face: bool) -> tuple[str, float] | None:
        """(why, retry_after_s) when one more session (`face`: with a face) would not keep everyone in real time
        (`streamer.capacity`), else None."""
        if self.admission is None or (why := self.admission.refusal(face)) is None:
            return None
        return why, self.admission.retry_after_s

    def withholds_face(self, why: tuple[str, float]) -> bool:
        """Whether a session with a face refused for `why` is admitted without its face instead (the server's
        choice: `serve --faces-beyond-capacity no-face`), i.e. it would be admitted without one."""
        return self.admission is not None and self.admission.without_face and self.refusal(False) is None

    def carry_out(self, action: TakeSeat | FreeSeat) -> None:
        if isinstance(action, TakeSeat):
            if self.full:  # (the machine checks `full` in the same step: a bug, never a race)
                raise RuntimeError(f"all {self.terms.max_sessions} seats are taken")
            self._taken += 1
            if self.admission is not None:
                self.admission.admitted(action.face)
        else:
            if self._taken == 0:
                raise RuntimeError("a seat freed that was never taken")
            self._taken -= 1
            if self.admission is not None:
                self.admission.freed(action.face)


class Phase(Enum):
    IDLE = "idle"
    STREAMING = "streaming"
    FINISHING = "finishing"


class _SavesAndResumes:
    """`ClientSession`'s periodic saves, hand-over and resume (its fields are the session's: see there)."""

    def _on_Boundary(self, e: Boundary) -> list[Action]:
        """--save-state-every: once the session's audio is save_every_s past its last save, save it (a crash
        then loses at most that much: the client resumes from the save)."""
        audio_s = e.samples_in / SAMPLE_RATE
        if (self.terms.save_every_s is None or self.save_token is None or self.handing_over
                or e.session_id != self.session_id or audio_s - self.saved_audio_s < self.terms.save_every_s):
            return []
        self.saved_audio_s = audio_s
        return [SaveState(self.session_id, self.save_token, self._samples(e.samples_in), self.frames)]

    def _on_Saved(self, e: Saved) -> list[Action]:
        if e.session_id != self.session_id or self.handing_over or self.gone:
            return []
        return [Send(P.session_saved(e.token, e.samples, e.frames, self.audio.rate)), Count("sessions_saved")]

    def _on_HandOver(self, e: HandOver) -> list[Action]:
        self.handing_over = True  # audio that arrives meanwhile is ignored, never refused
        return self._end_audio(handover=True) if self.phase is Phase.STREAMING else []

    def _on_HandedOver(self, e: HandedOver) -> list[Action]:
        out: list[Action] = [Send(P.goaway(e.token, e.samples, self.frames, self.audio.rate)),
                             Count("sessions_handed_over")]
        if self.save_token is not None:  # the goaway's token goes on from later: the periodic save must not fork it
            out.append(Forget(self.save_token))
            self.save_token = None
        return out

    def _resume(self, token: str) -> list[Action]:
        """resume_session: the state saved under `token` (by any worker) becomes this client's session."""
        if not self.terms.resumable:
            raise P.ProtocolError("resume_failed", "this server keeps no session states (--state-store)")
        if self.seats.closing:  # the token is not taken: it resumes on another worker
            raise P.ProtocolError("busy", "this worker is stopping: resume_session on another (the token stays valid)")
        if self.running:
            raise P.ProtocolError("resume_failed", "resume_session before any audio (or after audio_end's `end`)")
        if not self.terms.accepts_audio:
            raise P.ProtocolError("audio_disabled", "this server does not accept client audio")
        if self.holds_seat:  # (its resume_session is being taken from the store)
            raise P.ProtocolError("resume_failed", "a resume_session is under way")
        out, admitted = self._admit()  # (refused: the token stays unused, for a retry here or elsewhere)
        if not admitted:
            return out
        return [*out, *self._take_seat(), TakeState(token)]  # (held while the store answers: no one else gets it)

    def _on_Taken(self, e: Taken) -> list[Action]:
        if e.data is not None and e.error is None and e.live_s is None:
            return self._start(restore=e.data)
        out = self._free_seat()
        if e.live_s is not None:  # a periodic-save token is for a lost connection only: its owner still talks
            return [*out, Log(logging.INFO, "session_live: resume_session refused, its session is live"),
                    Send(P.session_live(e.live_s))]
        why = (f"the state store failed: {e.error}" if e.error is not None
               else "unknown or expired resume token (or one already used): start a new stream")
        return [*out, *self._on_Failed(Failed(P.ProtocolError("resume_failed", why)))]

    def _on_NotRestored(self, e: NotRestored) -> list[Action]:
        """The taken state was refused: the session started for it is dropped unseen (it made no frame, so no
        `end`), its seat freed; the client goes on from its own audio, whose next message starts a fresh session."""
        self.phase = Phase.IDLE
        return [StopSession(), *self._free_seat(), Log(logging.WARNING, f"a saved session state was refused "
                                                                        f"({e.message}): its client goes on with a "
                                                                        "fresh session"),
                Send(P.error("resume_failed", e.message))]

    def _on_Restored(self, e: Restored) -> list[Action]:
        self.frames = e.frames
        self.saved_audio_s = e.samples_in / SAMPLE_RATE  # (its periodic saves go on from here)
        samples = e.resampler_inputs if e.resampler_inputs is not None else self._samples(e.samples_in)
        return [Count("sessions_resumed"), Send(P.session_resumed(samples, self.frames, self.audio.rate))]

    def _samples(self, samples_in: int) -> int:
        """16 kHz samples -> the client's own (what it re-sends from)."""
        return samples_in * self.audio.rate // SAMPLE_RATE


@dataclass
class ClientSession(_SavesAndResumes):
    """One client's protocol state; `handle(event) -> actions`. `new_token` names periodic saves."""

    seats: Seats
    new_token: Callable[[], str]
    encoding: str = "json"
    timing: bool = False        # asked for each window's `timing`
    source_audio: bool = False  # asked for the server source's audio
    audio: P.AudioFormat = field(default_factory=P.AudioFormat)
    own: bool = False           # sent audio once: gets its own frames from then on, not the broadcast
    phase: Phase = Phase.IDLE
    session_id: int = 0         # the current (or last) session
    frames: int = 0             # frames of the current session (its `end`, `goaway`, saves)
    slowed: bool = False        # its audio queue is at the cap: slow_down, until it is down to half
    over_share: bool = False    # its work on the worker thread is over its share: slow_down, until WithinShare
    refused: bool = False       # its current audio was refused a session (counted once)
    handing_over: bool = False  # its session is being saved for hand-over (its audio is ignored meanwhile)
    gone: bool = False
    holds_seat: bool = False    # one of the server's seats is its (from its session's start, or its resume_session)
    seat_face: bool = False     # ... for a session with a face
    save_token: str | None = None  # its session's periodic saves go under this token (live: its lease is held)
    saved_audio_s: float = 0.0     # the audio its last periodic save covers
    face: str | None = None        # the face's name set its hello asked, or "none" (None: never asked)
    face_withheld: bool = False    # its current session was admitted without the face it asked (at capacity)
    smile: float | None = None     # the expression its own sessions' face holds (None: the server's)
    speaker: str | None = None     # the speaker its own sessions play, when `speaker_asked` (else the server's)
    speaker_asked: bool = False
    layout_due: bool = False       # a `channels` message goes with its next frames
    joints: int = 0                # its frames' joints on its own rig (revision 8; 0: the server's skeleton's)
    rigs_refused: int = 0          # `bad_rig`s it was sent (the MAX_REFUSED_RIGS-th closes the connection)
    after_session: list[str] = field(default_factory=list)  # replies due once the running session sent `end`

    @property
    def terms(self) -> Terms:
        return self.seats.terms

    @property
    def running(self) -> bool:
        return self.phase is not Phase.IDLE

    def channels(self, encoding: str) -> Mapping[str, Channel]:
        """The channels of its frames in `encoding`: the server's (`P.WS_CHANNELS`), then the face when the server
        makes one and the client did not say "none" (in binary only once it asked: an old client's layout stays;
        its own audio's frames only once it asked: they have a face only then, see `StartSession.face`)."""
        names = None if self.face == "none" or self.face_withheld else self.face or self.terms.face
        if names is None or self.terms.face is None or (self.face is None and (encoding == "binary" or self.own)):
            return dict(P.WS_CHANNELS)
        return {**P.WS_CHANNELS, FACE: _face_channel(names)}

    def _send_frames(self, window) -> SendFrames:
        layout = None
        if self.layout_due:
            self.layout_due = False
            layout = P.channels_message(P.channel_layout(self.joints or self.terms.joints, self.channels("binary")))
        return SendFrames(window, self.encoding, self.channels(self.encoding), layout)

    def handle(self, event: Event) -> list[Action]:
        try:
            return getattr(self, HANDLERS[type(event)])(event)
        except P.ProtocolError as e:
            if e.code == "bad_rig":
                return self._rig_refused(e)
            return self._on_Failed(Failed(e))

    # ---- messages ----

    def _on_Text(self, e: Text) -> list[Action]:
        msg = P.parse_text(e.text) if e.parsed is None else e.parsed
        if isinstance(msg, P.ProtocolError):
            raise msg
        kind = msg["type"]
        if kind == "ping":
            return [Send(P.dumps({**msg, "type": "pong", "server_time_s": round(e.now, 6)}), "note")]
        if kind == "hello":
            return self._hello(msg)
        if kind == "resume_session":
            return self._resume(msg["token"])
        self.refused = False  # audio_end: its next audio is another attempt
        if self.phase is Phase.STREAMING:
            return self._end_audio()
        if self.phase is Phase.IDLE:
            return [Send(P.end(0))]  # no audio since the last end: an empty stream, ended
        self.after_session.append(P.end(0))  # the previous session's `end` first, then this empty stream's
        return []

    def _hello(self, msg: dict) -> list[Action]:
        if "speaker" in msg and (why := self.terms.speaker_refusal(msg["speaker"])) is not None:
            raise P.ProtocolError("bad_message", why)  # (before anything of this hello applies)
        out: list[Action] = []
        self.encoding = msg.get("encoding", self.encoding)
        self.timing = msg.get("timing", self.timing)
        if msg.get("source_audio") and not self.source_audio and self.terms.offers_source_audio:
            out.append(ReplaySourceAudio())  # the audio of the frames still to come
        self.source_audio = bool(msg.get("source_audio", self.source_audio)) and self.terms.offers_source_audio
        if "face" in msg and self.terms.face is not None:  # (a server that makes no face ignores it)
            self.face, self.layout_due = msg["face"], True
        if "rig" in msg:
            out.append(SetRig(msg["rig"]))  # (then RigSet or RigRefused)
        if "smile" in msg:
            self.smile = msg["smile"]
            if self.running:
                out.append(SetSmile(self.smile))
        if "speaker" in msg:  # (from its next session on: a running one keeps the speaker it began with)
            self.speaker, self.speaker_asked = msg["speaker"], True
        if "audio" in msg and msg["audio"] != self.audio:
            out.append(Charge(25))  # a new resampler is designed: costs as much as 25 messages
            if self.phase is Phase.STREAMING:
                out += self._end_audio()  # later audio starts a session at the new rate
            self.audio = msg["audio"]
        return out

    def _on_RigSet(self, e: RigSet) -> list[Action]:
        self.joints, self.layout_due = e.joints, True
        layout = P.channel_layout(self.joints or self.terms.joints, self.channels("binary"))
        return [Send(P.rig_reply(self.joints or self.terms.joints, e.humanoid, layout), "note")]

    def _on_RigRefused(self, e: RigRefused) -> list[Action]:
        return self._rig_refused(P.ProtocolError("bad_rig", e.message))

    def _rig_refused(self, e: P.ProtocolError) -> list[Action]:
        """A rig refused (malformed, or not fitted): `bad_rig` with why; each costs the client's message budget
        (its next messages are read later), and the MAX_REFUSED_RIGS-th closes the connection."""
        self.rigs_refused += 1
        out: list[Action] = [Log(logging.INFO, f"bad_rig: {e}"), Send(P.error("bad_rig", str(e)), "note"),
                             Charge(P.REFUSED_RIG_TOKENS)]
        if self.rigs_refused >= P.MAX_REFUSED_RIGS:
            out += [Log(logging.WARNING, f"closing: {self.rigs_refused} rigs refused"),
                    Close(1008, f"{self.rigs_refused} rigs refused", drain_s=1.0)]
        return out

    def _on_Failed(self, e: Failed) -> list[Action]:
        err = e.error
        out: list[Action] = [Log(logging.INFO, f"{err.code}: {err}"), Send(P.error(err.code, str(err)), "note")]
        if err.code == "unsupported_protocol":
            out.append(Close(1002, "unsupported protocol version", drain_s=1.0))
        return out

    # ---- audio ----

    def _on_Audio(self, e: Audio) -> list[Action]:
        if (refusal := self._refusal()) is not None:
            return refusal
        P.check_audio(e.data, self.audio)
        return [Decode(e.data, self.audio)]

    def _refusal(self) -> list[Action] | None:
        """Audio this server will not take now: [] to ignore it, the refusal, or None (it may)."""
        if not self.terms.accepts_audio:
            return self._refuse("audio_disabled", "audio_disabled", "this server does not accept client audio")
        if self.seats.closing:
            if self.handing_over:  # its state is being saved: the client re-sends from the goaway's sample
                return []
            return self._refuse("draining", "busy", "the server is shutting down")
        return None

    def _on_Decoded(self, e: Decoded) -> list[Action]:
        if self.phase is Phase.FINISHING:
            return [WaitForSession()]
        if self.phase is Phase.IDLE:
            if (refusal := self._refusal()) is not None:
                return refusal
            out, admitted = self._admit()
            if not admitted:
                return out
            out += self._start()
        else:
            out = []
        return [*out, Feed(max(1, min(int(PIECE_S * self.audio.rate), PIECE_SAMPLES)))]

    def _on_Queuing(self, e: Queuing) -> list[Action]:
        if e.full and not self.slowed:
            told, self.slowed = self.over_share, True  # until the backlog is down to half: `resume` (_on_Frames)
            return [] if told else [Send(P.error(
                "slow_down", f"audio arrives faster than it is processed: {e.backlog_s:.0f} s are queued; pause until "
                             "`resume` (or the server reads more as it catches up; nothing is dropped)"))]
        return []

    def _on_OverShare(self, e: OverShare) -> list[Action]:
        """Fair shares are counted in compute, not in audio seconds: a second of 192 kHz stereo costs ~100x one of
        16 kHz mono to take in, so a fast sender at a high rate is slowed down sooner."""
        if self.over_share or self.gone:
            return []
        told, self.over_share = self.slowed, True
        a = self.audio
        return [] if told else [Send(P.error(
            "slow_down", f"your audio ({a.rate} Hz, {a.channels} channel(s), {a.format}) costs more than your share of "
                         "the server to take in at this speed: pause until `resume` (or the server reads it more "
                         "slowly; nothing is dropped)"))]

    def _on_WithinShare(self, e: WithinShare) -> list[Action]:
        if not self.over_share or self.gone:
            return []
        self.over_share = False
        return [] if self.slowed else [Send(P.resume(e.backlog_s))]

    def _start(self, restore: bytes | None = None) -> list[Action]:
        self.own, self.phase, self.refused, self.frames = True, Phase.STREAMING, False, 0
        self.session_id += 1
        self.save_token = self.new_token() if self.terms.save_every_s is not None else None
        self.saved_audio_s = 0.0
        face = self._face_wanted()
        speaker = self.speaker if self.speaker_asked else self.terms.speaker
        return [*self._take_seat(), StartSession(self.session_id, self.audio.rate, self.save_token, restore,
                                                 self.smile, face, speaker), Count("sessions_started")]

    def _face_wanted(self) -> bool:
        """Whether its next session makes a face: the server makes one and the client asked for it (and it was not
        withheld at capacity)."""
        return self.terms.face is not None and self.face not in (None, "none") and not self.face_withheld

    def _admit(self) -> tuple[list[Action], bool]:
        """One more session of this client, new or resumed, against the seats and the capacity: (actions, admitted).
        Refused: `busy` (every seat taken; or at capacity, with retry_after_s); admitted without its face where the
        server says so (`--faces-beyond-capacity no-face`), and told."""
        if self.seats.full:
            return self._busy(), False
        if self.face_withheld:  # (the last session's): this one asks again
            self.face_withheld, self.layout_due = False, True
        if (refused := self.seats.refusal(self._face_wanted())) is not None:
            if not (self._face_wanted() and self.seats.withholds_face(refused)):
                return self._refuse("capacity", "busy", *refused), False
            return self._withhold_face(*refused), True
        return [], True

    def _withhold_face(self, why: str, retry_after_s: float) -> list[Action]:
        """Admitted at capacity without the face it asked: told so (`face_withheld`), its frames carry none (a
        `channels` message without it), and its next session asks again."""
        self.face_withheld, self.layout_due = True, True
        message = (f"admitted without a face: {why.split(': try again')[0]}; this session's frames carry none (the "
                   "next session, after audio_end, asks again: wait retry_after_s)")
        return [Log(logging.INFO, f"face_withheld: {message}"), Count("faces_withheld"),
                Send(P.error("face_withheld", message, retry_after_s), "note")]

    def _take_seat(self) -> list[Action]:
        if self.holds_seat:  # (taken at its resume_session)
            return []
        self.holds_seat, self.seat_face = True, self._face_wanted()
        return [TakeSeat(self.seat_face)]

    def _free_seat(self) -> list[Action]:
        if not self.holds_seat:
            return []
        self.holds_seat = False
        return [FreeSeat(self.seat_face)]

    def _end_audio(self, handover: bool = False) -> list[Action]:
        self.phase = Phase.FINISHING
        return [EndAudio(handover)]

    def _refuse(self, reason: str, code: str, message: str, retry_after_s: float | None = None) -> list[Action]:
        out: list[Action] = []
        if not self.refused:  # once per stream the client tries (its audio until `audio_end`), not per message
            self.refused = True
            out.append(Refused(reason))
        if retry_after_s is None:
            return [*out, *self._on_Failed(Failed(P.ProtocolError(code, message)))]
        return [*out, Log(logging.INFO, f"{code}: {message}"), Send(P.error(code, message, retry_after_s), "note")]

    def _busy(self) -> list[Action]:
        return self._refuse("busy", "busy", f"at most {self.terms.max_sessions} client audio sessions at once")

    # ---- the session's progress ----

    def _on_Frames(self, e: Frames) -> list[Action]:
        out: list[Action] = []
        if self.slowed and e.backlog_s <= self.terms.max_backlog_s / 2:
            self.slowed = False
            if not self.over_share:  # a client that paused at slow_down may send again
                out.append(Send(P.resume(e.backlog_s)))
        if e.count:
            self.frames += e.count
            out.append(self._send_frames(e.window if self.timing else None))
        return out

    def _on_Broadcast(self, e: Broadcast) -> list[Action]:
        if self.own or self.gone or not e.count:  # (a client with audio of its own gets its own frames)
            return []
        return [self._send_frames(e.window if self.timing else None)]

    def _on_SessionEnded(self, e: SessionEnded) -> list[Action]:
        if self.gone or not self.running or e.session_id not in (None, self.session_id):
            return []  # (a session already let go: its client left, or its resume failed)
        out: list[Action] = []
        if e.error is not None:  # the model failed on this audio: tell the client, keep the server up
            out += [Log(logging.ERROR, f"session failed: {e.error}"), Send(P.error("internal", f"session failed: "
                                                                                               f"{e.error}"), "note")]
            if self.phase is Phase.STREAMING:  # (the shell closed its audio queue)
                self.phase = Phase.FINISHING
        elif not e.cancelled and not e.handed_over:
            out.append(Send(P.end(e.frames)))
        if self.slowed and self.phase is not Phase.STREAMING:  # ended while the client was paused: let it go on
            self.slowed = False
            if not self.over_share:
                out.append(Send(P.resume(0.0)))
        if not e.cancelled:
            out += [Send(m) for m in self.after_session]
        self.after_session.clear()
        if self.save_token is not None and not e.cancelled and not e.handed_over and not self.seats.closing:
            out.append(Forget(self.save_token))  # its periodic save will not be resumed (else the TTL drops it)
            self.save_token = None
        self.phase = Phase.IDLE
        return [*out, *self._free_seat()]

    def _on_Left(self, e: Left) -> list[Action]:
        self.gone = True
        self.after_session.clear()
        out: list[Action] = []
        if self.running:
            self.phase = Phase.IDLE
            out.append(StopSession())
        out += self._free_seat()
        if self.save_token is not None:  # a lost connection: its last periodic save may be resumed now
            out.append(Release(self.save_token))
            self.save_token = None
        return out

# Which handler hears which event, by its method's name (every `Event`: tests/test_client_session.py checks)
HANDLERS: dict[type, str] = {
    Text: "_on_Text", Audio: "_on_Audio", Decoded: "_on_Decoded",
    RigSet: "_on_RigSet", RigRefused: "_on_RigRefused", Failed: "_on_Failed",
    Queuing: "_on_Queuing", OverShare: "_on_OverShare",
    WithinShare: "_on_WithinShare", Frames: "_on_Frames",
    Broadcast: "_on_Broadcast", SessionEnded: "_on_SessionEnded", Left: "_on_Left",
    Boundary: "_on_Boundary", Saved: "_on_Saved", HandOver: "_on_HandOver",
    HandedOver: "_on_HandedOver", Taken: "_on_Taken",
    NotRestored: "_on_NotRestored", Restored: "_on_Restored",
}


@lru_cache(maxsize=None)
def _face_channel(names: str) -> Channel:
    return face_channel(names)


class Keepalive:
    """When to ping and when to give up on a client: nothing heard for interval + timeout, counted only while
    the server reads it or nothing moves (while its handler holds one of its messages the server reads
    nothing of it, pongs included: then it is blamed only when frames wait for it and none went out)."""

    def __init__(self, interval: float, timeout: float, now: float):
        self.interval, self.timeout = interval, timeout
        self.last_heard = now
        self.sent: int | None = None

    def heard(self, now: float) -> None:
        self.last_heard = now

    def tick(self, now: float, holding: bool, frames_sent: int, awaits_reading: bool) -> Close | None:
        """Every interval: None (ping if none is in flight), or close."""
        if holding and (frames_sent != self.sent or not awaits_reading):
            self.last_heard = now
        self.sent = frames_sent
        if now - self.last_heard > self.interval + self.timeout:
            return Close(1011, "keepalive ping timeout")
        return None

    def silent_s(self, now: float) -> float:
        return now - self.last_heard
