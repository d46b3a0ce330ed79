"""What a client's session machine (`streamer.client_session`) hears and says: its events (what happened, turned
into values by the shell: `streamer.connection`) and its actions (what the shell is to do). Plain frozen values,
no behaviour beyond a property."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Union

from dimgestor.audio import SAMPLE_RATE
from streamer import protocol as P
from streamer.frames import Channel

__all__ = ["Text", "Audio", "Decoded", "Failed", "Queuing", "OverShare", "WithinShare", "Frames", "Broadcast",
           "Boundary", "Saved", "HandOver", "HandedOver", "Taken", "Restored", "NotRestored", "SessionEnded", "Left",
           "Send", "SendFrames", "Close", "ReplaySourceAudio", "Charge", "Decode", "WaitForSession", "StartSession",
           "Feed", "EndAudio", "SetSmile", "StopSession", "SaveState", "Forget", "Release", "TakeState", "Count",
           "Refused", "Log", "RigSet", "RigRefused", "SetRig", "Event", "Action"]


# ---- events: what happened ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Text:
    """A text message (hello, ping, audio_end, resume_session); `now`: the server's clock; `parsed`: what
    `protocol.parse_text` made of it (a dict, or the ProtocolError it raised) where that was done off the event
    loop (a long message: a rig), else None (the machine parses it)."""
    text: str
    now: float = 0.0
    parsed: object = None


@dataclass(frozen=True)
class Audio:
    """A binary message: audio in the client's format, not yet checked."""
    data: bytes


@dataclass(frozen=True)
class Decoded:
    """The audio of the last `Audio` decoded (`Decode` done): it may go to a session now."""


@dataclass(frozen=True)
class RigSet:
    """The client's rig (`SetRig`) is in use: its frames carry `joints` rotations, `humanoid` its bones recognised
    ({HumanBodyBones name: joint}); joints 0: back on the server's skeleton."""
    joints: int
    humanoid: dict | None = None


@dataclass(frozen=True)
class RigRefused:
    """The client's rig could not be used (its joints not recognised, a bad bone map): why."""
    message: str


@dataclass(frozen=True)
class Failed:
    """Something the client sent was refused on the way (e.g. decoding it): reply with its error."""
    error: P.ProtocolError


@dataclass(frozen=True)
class Queuing:
    """A piece of audio is about to be queued for the session, whose queue holds `backlog_s` (full: at the cap)."""
    backlog_s: float
    full: bool


@dataclass(frozen=True)
class OverShare:
    """The client's work on the worker thread (decode, channel mix, resample, its frames' encoding) went over its
    share of it (`streamer.intake.ComputeBudget`): its socket is read more slowly until `WithinShare`."""


@dataclass(frozen=True)
class WithinShare:
    """Its budget on the worker thread has refilled (to half): it may send at full speed again; `backlog_s`: its
    session's audio queue now."""
    backlog_s: float


@dataclass(frozen=True)
class Frames:
    """The session emits `count` frames (0: a window's call gave none); its audio queue holds `backlog_s`."""
    count: int
    backlog_s: float
    window: object = None  # the `WindowTiming` they came from (None: the flush after the audio ended)


@dataclass(frozen=True)
class Broadcast:
    """The server's own source made `count` frames (from `window`, a `WindowTiming`, or None): due to every
    client that follows it."""
    count: int
    window: object = None


@dataclass(frozen=True)
class Boundary:
    """Between two windows of session `session_id` (state, decoder and frames agree): `samples_in` 16 kHz in."""
    session_id: int
    samples_in: int


@dataclass(frozen=True)
class Saved:
    """A periodic save of session `session_id` reached the store (`SaveState` done)."""
    session_id: int
    token: str
    samples: int
    frames: int


@dataclass(frozen=True)
class HandOver:
    """The server stops with a state store: this session finishes the audio it holds, then is saved."""


@dataclass(frozen=True)
class HandedOver:
    """The session's state is in the store under `token`, covering the client's audio up to sample `samples`."""
    token: str
    samples: int


@dataclass(frozen=True)
class Taken:
    """`TakeState` done: the saved state (None: unknown, expired or used token); `error`: the store failed;
    `live_s`: refused, the token's session is live on a connection (its lease runs this many seconds more)."""
    data: bytes | None
    error: str | None = None
    live_s: float | None = None


@dataclass(frozen=True)
class Restored:
    """The taken state is the session's now: `frames` made before, `samples_in` 16 kHz covered; the resampler's
    own input count when it was restored too (None: not)."""
    frames: int
    samples_in: int
    resampler_inputs: int | None = None


@dataclass(frozen=True)
class NotRestored:
    """The taken state does not fit this server's model (`message` says how)."""
    message: str


@dataclass(frozen=True)
class SessionEnded:
    """The session's task is over: `frames` in all; handed_over, failed (`error`) or cancelled; `session_id`:
    which session (None: the current one)."""
    frames: int = 0
    handed_over: bool = False
    error: str | None = None
    cancelled: bool = False
    session_id: int | None = None


@dataclass(frozen=True)
class Left:
    """The connection is gone."""


Event = Union[Text, Audio, Decoded, Failed, Queuing, OverShare, WithinShare, Frames, Broadcast, Boundary, Saved,
              HandOver, HandedOver, Taken, Restored, NotRestored, SessionEnded, Left, RigSet, RigRefused]


# ---- actions: what to do ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Send:
    """Queue a message; kind "ctl" is never dropped, "note" may be (streamer/outbox.py)."""
    message: str
    kind: str = "ctl"


@dataclass(frozen=True)
class SendFrames:
    """Encode the frames (the session's, never dropped; or the broadcast's) in `encoding` with `channels` and
    queue them; `layout`: a `channels` message to queue just before them; `window`: also its `timing` message."""
    window: object = None
    encoding: str = "json"
    channels: Mapping[str, Channel] = field(default_factory=dict)
    layout: str | None = None


@dataclass(frozen=True)
class Close:
    """Close the connection with `code` once what is queued went out (within `drain_s`)."""
    code: int
    reason: str
    drain_s: float = 0.0


@dataclass(frozen=True)
class ReplaySourceAudio:
    """Queue the server source's recent audio (a client that asked for it now)."""


@dataclass(frozen=True)
class Charge:
    """Take `tokens` from the client's message budget (work its message costs beyond the usual)."""
    tokens: float


@dataclass(frozen=True)
class Decode:
    """Decode the audio message in the worker; then `Decoded`, or `Failed` with its error."""
    data: bytes
    fmt: P.AudioFormat


@dataclass(frozen=True)
class WaitForSession:
    """The previous session is still finishing: wait for its `SessionEnded`, then deliver `Decoded` again."""


@dataclass(frozen=True)
class StartSession:
    """Start session `session_id` with a fresh audio queue; resample from `rate` unless it is 16 kHz; its periodic
    saves go under `save_token` (None: none); `restore`: a saved state to go on from (then `Restored`); `smile`:
    the expression its face holds (None: the server's); `face`: whether it makes a face (the client asked for one:
    a face costs its listener ~5 % of a core per stream, which a client that shows none should not pay);
    `speaker`: the speaker it plays (None: no speaker in particular; a model without speakers ignores it)."""
    session_id: int
    rate: int
    save_token: str | None = None
    restore: bytes | None = None
    smile: float | None = None
    face: bool = False
    speaker: str | None = None

    @property
    def resample(self) -> bool:
        return self.rate != SAMPLE_RATE


@dataclass(frozen=True)
class Feed:
    """Queue the decoded audio for the session in pieces of `piece` samples (a `Queuing` before each)."""
    piece: int


@dataclass(frozen=True)
class EndAudio:
    """The session's audio has ended: flush the resampler's tail into its queue and close it. handover: the
    session stops after the audio held, unfinished (then `HandedOver` once saved)."""
    handover: bool = False


@dataclass(frozen=True)
class SetSmile:
    """The running session's face holds this expression (0..1) from its next frames on (`Session.set_smile`)."""
    smile: float


@dataclass(frozen=True)
class SetRig:
    """Send this client's frames on `rig` (a checked `hello.rig`), or on the server's skeleton again (None); then
    `RigSet` or `RigRefused`."""
    rig: dict | None


@dataclass(frozen=True)
class StopSession:
    """Cancel the session now (its client left): its queued audio and its seat are free."""


@dataclass(frozen=True)
class SaveState:
    """Snapshot session `session_id` now (between windows) and put it in the store under `token`; then `Saved`."""
    session_id: int
    token: str
    samples: int
    frames: int


@dataclass(frozen=True)
class Forget:
    """The session ended (or was handed over under another token): remove its periodic save from the store and
    consume its token (nobody will resume it)."""
    token: str


@dataclass(frozen=True)
class Release:
    """The connection is gone: its session's periodic-save token is no longer live (it may be resumed now)."""
    token: str


@dataclass(frozen=True)
class TakeState:
    """Take the state saved under `token` from the store; then `Taken`."""
    token: str


@dataclass(frozen=True)
class Count:
    """Count it in the metrics: "sessions_started", "sessions_saved", "sessions_resumed", "sessions_handed_over"."""
    name: str


@dataclass(frozen=True)
class TakeSeat:
    """A session starts: it holds one of the server's seats (`Seats`) until its `FreeSeat`; `face`: it makes a face."""
    face: bool = False


@dataclass(frozen=True)
class FreeSeat:
    """Its session ended or was let go (its client left, its resume was refused): the seat is free again; `face`:
    the session made a face."""
    face: bool = False


@dataclass(frozen=True)
class Refused:
    """A session refused for `reason` (counted once per attempt)."""
    reason: str


@dataclass(frozen=True)
class Log:
    level: int
    text: str


Action = Union[Send, SendFrames, Close, ReplaySourceAudio, Charge, Decode, WaitForSession, TakeSeat, StartSession,
               Feed, EndAudio, SetSmile, SetRig, StopSession, FreeSeat, SaveState, Forget, Release, TakeState, Count,
               Refused, Log]
