"""A client's session driven without sockets or an event loop: events in, actions out (streamer/client_session.py)."""

import itertools
import json

import numpy as np
import pytest

from streamer.client_session import (
    Audio, Boundary, Broadcast, Charge, ClientSession, Close, Count, Decode, Decoded, EndAudio, Feed, Forget, Frames,
    HandedOver, HandOver, Keepalive, Left, NotRestored, OverShare, Phase, Queuing, Refused, Release, Restored,
    SaveState, Saved, Seats, Send, SendFrames, SetSmile, SessionEnded, StartSession, StopSession, TakeState, Taken,
    Terms, Text, WaitForSession, WithinShare)
from streamer.client_events import FreeSeat, TakeSeat
from streamer.sessions import Session


def seats_of(**terms) -> Seats:
    return Seats(Terms(**terms))


class Machine(ClientSession):
    """The machine, with its seat actions carried out on its `Seats` as the shell carries them out."""

    def handle(self, event):
        out = super().handle(event)
        for a in out:
            if isinstance(a, (TakeSeat, FreeSeat)):
                self.seats.carry_out(a)
        return out


def client(seats: Seats) -> ClientSession:
    tokens = itertools.count()
    return Machine(seats, new_token=lambda: f"t{next(tokens)}")


def sent(actions) -> list[dict]:
    """The JSON messages among the actions."""
    return [json.loads(a.message) for a in actions if isinstance(a, Send)]


def kinds(actions) -> list[str]:
    return [m.get("code", m["type"]) for m in sent(actions)]


def text(**msg) -> Text:
    return Text(json.dumps(msg), now=12.5)


def pcm16(n: int) -> bytes:
    return np.zeros(n, "<i2").tobytes()


def audio_in(c: ClientSession, n: int) -> list:
    """One audio message of n samples through decoding: the actions after it is decoded."""
    first = c.handle(Audio(pcm16(n)))
    assert first == [Decode(pcm16(n), c.audio)]
    return c.handle(Decoded())


def test_a_client_over_its_share_of_the_worker_is_told_slow_down_once_and_resume_when_both_causes_are_gone():
    """Fair shares in compute: its intake went over its share (OverShare), and its audio queue filled too; one
    slow_down for both, and `resume` only once it is within its share and its queue is down to half."""
    c = client(seats_of(max_sessions=2, max_backlog_s=4.0))
    c.handle(text(type="hello", audio={"rate": 192000, "format": "float32", "channels": 2}))
    over = c.handle(OverShare())
    assert kinds(over) == ["slow_down"] and over[0].kind == "ctl" and "192000 Hz" in sent(over)[0]["message"]
    assert c.handle(OverShare()) == []  # said once
    assert c.handle(Queuing(backlog_s=4.0, full=True)) == [] and c.slowed  # already told
    assert c.handle(Frames(count=0, backlog_s=1.0)) == []  # its queue is down, its share not yet
    assert sent(c.handle(WithinShare(backlog_s=0.5))) == [{"type": "resume", "backlog_s": 0.5}]
    assert c.handle(WithinShare(backlog_s=0.5)) == []  # (once)
    # the other order: within its share first, then its queue
    c.handle(OverShare())
    c.handle(Queuing(backlog_s=4.0, full=True))
    assert c.handle(WithinShare(backlog_s=4.0)) == []
    assert kinds(c.handle(Frames(count=0, backlog_s=2.0))) == ["resume"]
    c.handle(Left())
    assert c.handle(OverShare()) == []  # gone: nobody to tell


def test_a_full_session_with_slow_down_and_resume():
    seats = seats_of(max_sessions=2, max_backlog_s=4.0, save_every_s=None)
    c = client(seats)
    assert c.handle(text(type="hello", encoding="binary", audio={"rate": 48000})) == [Charge(25)]
    assert (c.encoding, c.audio.rate, c.phase) == ("binary", 48000, Phase.IDLE)
    pong = sent(c.handle(text(type="ping", id=7)))
    assert pong == [{"type": "pong", "id": 7, "server_time_s": 12.5}]

    start = audio_in(c, 4801)  # odd sizes: the pieces and the resampler are the shell's, the decisions are here
    assert start[:2] == [TakeSeat(), StartSession(1, 48000, None, None)] and start[1].resample
    assert start[2:] == [Count("sessions_started"), Feed(24000)]
    assert (c.phase, c.own, seats.taken) == (Phase.STREAMING, True, 1)
    assert audio_in(c, 333) == [Feed(24000)]  # the same session goes on

    assert c.handle(Queuing(backlog_s=1.0, full=False)) == []
    slow = c.handle(Queuing(backlog_s=4.0, full=True))
    assert kinds(slow) == ["slow_down"] and slow[0].kind == "ctl" and c.slowed
    assert c.handle(Queuing(backlog_s=4.0, full=True)) == []  # said once until resumed
    # (frames go out in the encoding in force when they are made: binary, with no channel here)
    assert c.handle(Frames(count=2, backlog_s=3.0)) == [SendFrames(None, "binary")]  # not yet down to half
    resumed = c.handle(Frames(count=3, backlog_s=1.5))
    assert sent(resumed) == [{"type": "resume", "backlog_s": 1.5}] and resumed[1] == SendFrames(None, "binary")
    assert c.frames == 5 and not c.slowed

    assert c.handle(text(type="audio_end")) == [EndAudio(handover=False)]
    assert c.phase is Phase.FINISHING and seats.taken == 1  # flushing still holds its seat
    assert audio_in(c, 3) == [WaitForSession()]  # the next stream waits for this one's end
    assert c.handle(text(type="audio_end")) == []  # an empty stream while the last one finishes: `end` after its
    ended = c.handle(SessionEnded(frames=9))
    assert sent(ended) == [{"type": "end", "frames": 9}, {"type": "end", "frames": 0}]
    assert (c.phase, seats.taken) == (Phase.IDLE, 0)
    assert sent(c.handle(text(type="audio_end"))) == [{"type": "end", "frames": 0}]


def test_a_client_asking_for_timing_gets_the_window_with_its_frames():
    c = client(seats_of(max_sessions=1))
    c.handle(text(type="hello", timing=True))
    audio_in(c, 160)
    assert c.handle(Frames(count=4, backlog_s=0.0, window="w")) == [SendFrames("w")]
    assert c.handle(Frames(count=0, backlog_s=0.0, window="w")) == []


def test_refused_clients_get_one_refusal_per_attempt_and_an_error_per_message():
    seats = seats_of(max_sessions=1)
    a, b = client(seats), client(seats)
    audio_in(a, 160)
    first = audio_in(b, 160)
    assert first[0] == Refused("busy") and kinds(first) == ["busy"]
    assert "at most 1 client audio sessions" in sent(first)[0]["message"]
    again = audio_in(b, 160)
    assert not any(isinstance(x, Refused) for x in again) and kinds(again) == ["busy"]
    b.handle(text(type="audio_end"))  # a new attempt: counted again
    assert audio_in(b, 160)[0] == Refused("busy")
    assert (seats.taken, b.own, b.phase) == (1, False, Phase.IDLE)

    off = client(seats_of(max_sessions=4, accepts_audio=False))
    refused = off.handle(Audio(pcm16(160)))
    assert refused[0] == Refused("audio_disabled") and kinds(refused) == ["audio_disabled"]
    seats.closing = True
    assert kinds(client(seats).handle(Audio(pcm16(160)))) == ["busy"]
    assert kinds(a.handle(Audio(pcm16(3)[:5]))) == ["busy"]  # (refused before its bytes are looked at)


def test_bad_messages_get_their_error_and_an_unknown_protocol_closes():
    c = client(seats_of(max_sessions=1))
    assert kinds(c.handle(Text("{not json"))) == ["bad_message"]
    assert kinds(c.handle(Audio(b"\x00\x01\x02"))) == ["bad_audio"]  # half a sample
    out = c.handle(text(type="hello", protocol=2))
    assert kinds(out) == ["unsupported_protocol"] and out[-1] == Close(1002, "unsupported protocol version", 1.0)
    assert kinds(c.handle(text(type="resume_session", token="x"))) == ["resume_failed"]  # no state store


def test_a_client_that_vanishes_mid_audio_frees_its_slot():
    seats = seats_of(max_sessions=1)
    gone, other = client(seats), client(seats)
    audio_in(gone, 800)
    assert kinds(audio_in(other, 160)) == ["busy"]
    gone.handle(text(type="audio_end"))
    assert gone.handle(Left()) == [StopSession(), FreeSeat()]
    assert seats.taken == 0 and gone.after_session == []
    assert gone.handle(SessionEnded(cancelled=True)) == []  # its task's end, after it left: nothing more
    assert seats.taken == 0
    assert isinstance(audio_in(other, 160)[1], StartSession) and seats.taken == 1
    assert client(seats).handle(Left()) == []  # (one that never sent audio)


def test_a_failed_session_says_why_and_a_paused_client_may_go_on():
    seats = seats_of(max_sessions=1, max_backlog_s=1.0)
    c = client(seats)
    audio_in(c, 160)
    c.handle(Queuing(backlog_s=1.0, full=True))
    out = c.handle(SessionEnded(error="RuntimeError: boom"))
    assert kinds(out) == ["internal", "resume"] and (c.phase, seats.taken) == (Phase.IDLE, 0)


def test_periodic_saves_between_windows_and_forgotten_at_the_end():
    seats = seats_of(max_sessions=1, resumable=True, save_every_s=1.0)
    c = client(seats)
    c.handle(text(type="hello", audio={"rate": 8000}))
    start = audio_in(c, 800)[1]
    assert start.save_token == "t0"
    c.handle(Frames(count=10, backlog_s=0.0))
    assert c.handle(Boundary(1, 8000)) == []  # 0.5 s of audio: not yet
    assert c.handle(Boundary(1, 16000)) == [SaveState(1, "t0", 8000, 10)]
    assert c.handle(Boundary(1, 24000)) == []  # 1.5 s: not yet a second past the last save
    assert sent(c.handle(Saved(1, "t0", 8000, 10))) == [
        {"type": "session_saved", "resume_token": "t0", "samples": 8000, "rate": 8000, "frames": 10}]
    assert c.handle(Boundary(0, 99999)) == []  # (a session that is not the current one)
    c.handle(text(type="audio_end"))
    assert c.handle(SessionEnded(frames=12))[-2:] == [Forget("t0"), FreeSeat()]
    assert kinds(c.handle(Saved(1, "t0", 8000, 10))) == ["session_saved"]  # (a save that lands after the end)
    assert c.handle(Left()) == []  # (its token was consumed: nothing to release)
    assert c.handle(Saved(1, "t0", 8000, 10)) == []


@pytest.fixture(scope="module")
def speech():
    t = np.arange(16000 * 2) / 16000
    return (0.3 * np.sin(2 * np.pi * 180 * t) * (1 + np.sin(2 * np.pi * 3 * t))).astype(np.float32)


def session_of(bundle) -> Session:
    return Session.from_bundle(bundle, steps=2, seed=3, window_ms=100)


def test_a_session_handed_over_goes_on_elsewhere_exactly(bundle, speech):
    pieces = [speech[a:b] for a, b in zip([0, 1601, 4000, 12345, 20000], [1601, 4000, 12345, 20000, len(speech)])]
    whole = session_of(bundle)
    reference = [f for p in pieces for f in whole.infer(p)] + whole.infer_finish()

    seats = seats_of(max_sessions=1, resumable=True)
    old = client(seats)
    audio_in(old, 160)
    first = session_of(bundle)
    frames = [f for p in pieces[:3] for f in first.infer(p)]
    old.handle(Frames(count=len(frames), backlog_s=0.0))
    seats.closing = True
    assert old.handle(HandOver()) == [EndAudio(handover=True)]
    assert old.handle(Audio(pcm16(160))) == []  # ignored while it is saved: the client re-sends it
    data = first.snapshot(old.frames, rate=old.audio.rate, encoding=old.encoding)
    samples = first.stream.samples_in
    goaway = old.handle(HandedOver("tok", samples))
    assert sent(goaway) == [{"type": "goaway", "reason": "restart", "resume_token": "tok", "samples": samples,
                             "frames": len(frames), "rate": 16000}]
    old.handle(SessionEnded(frames=len(frames), handed_over=True))
    assert not any(isinstance(a, Send) for a in old.handle(Left()))

    elsewhere = seats_of(max_sessions=1, resumable=True)
    new = client(elsewhere)
    assert new.handle(text(type="resume_session", token="tok")) == [TakeSeat(), TakeState("tok")]
    assert elsewhere.taken == 1  # (held while the store answers)
    start = new.handle(Taken(data))
    assert start[0] == StartSession(1, 16000, None, data) and elsewhere.taken == 1
    second = session_of(bundle)
    meta = second.restore(start[0].restore)
    assert set(meta) == {"frames", "decoder", "rate", "encoding"}  # the stored format of earlier releases
    resumed = new.handle(Restored(int(meta["frames"]), second.stream.samples_in))
    assert resumed[0] == Count("sessions_resumed")
    assert sent(resumed) == [{"type": "session_resumed", "samples": samples, "rate": 16000, "frames": len(frames)}]
    frames += [f for p in pieces[3:] for f in second.infer(p)] + second.infer_finish()
    assert [f.index for f in frames] == [f.index for f in reference]
    for got, want in zip(frames, reference):
        assert got.pts == want.pts
        np.testing.assert_array_equal(got.root_pos, want.root_pos)
        np.testing.assert_array_equal(got.rotations, want.rotations)
        np.testing.assert_array_equal(got.features, want.features)


def test_a_resume_that_fails_validation_drops_its_session_and_the_client_goes_on_afresh():
    """A taken state that `Session.restore` refuses (another model, cut short, bad values): `resume_failed` with
    the reason and nothing else (no `end` of the session started for it); the client's next audio is a fresh
    session from frame 0, and the dropped session's task ending, early or late, changes nothing."""
    seats = seats_of(max_sessions=1, resumable=True, save_every_s=2.0)
    c = client(seats)
    assert c.handle(text(type="resume_session", token="tok")) == [TakeSeat(), TakeState("tok")]
    start = c.handle(Taken(b"a state of another model"))
    assert start[0] == StartSession(1, 16000, "t0", b"a state of another model") and seats.taken == 1
    failed = c.handle(NotRestored("saved stream state is of another model (weights or config differ)"))
    assert failed[:2] == [StopSession(), FreeSeat()] and kinds(failed) == ["resume_failed"]
    assert failed[-1].kind == "ctl"
    assert "another model" in sent(failed)[0]["message"]
    assert (c.phase, seats.taken) == (Phase.IDLE, 0)  # its seat is free at once
    assert c.handle(SessionEnded(cancelled=True, session_id=1)) == []  # the dropped task's end: no `end`, no Forget

    fresh = audio_in(c, 160)  # the client goes on sending its own audio
    assert fresh[:2] == [TakeSeat(), StartSession(2, 16000, "t1", None)] and seats.taken == 1 and c.frames == 0
    assert c.handle(SessionEnded(cancelled=True, session_id=1)) == []  # (had it come this late: the same)
    assert c.phase is Phase.STREAMING and seats.taken == 1
    c.handle(Frames(count=3, backlog_s=0.0))
    assert c.handle(text(type="audio_end")) == [EndAudio(handover=False)]
    ended = c.handle(SessionEnded(frames=3, session_id=2))
    assert sent(ended) == [{"type": "end", "frames": 3}] and ended[-2:] == [Forget("t1"), FreeSeat()] and seats.taken == 0


def test_resume_is_refused_while_a_session_runs_or_the_token_is_unknown():
    seats = seats_of(max_sessions=1, resumable=True)
    c = client(seats)
    assert kinds(c.handle(Taken(None))) == ["resume_failed"]
    assert "store failed" in sent(c.handle(Taken(None, error="ConnectionError: down")))[0]["message"]
    audio_in(c, 160)
    assert kinds(c.handle(text(type="resume_session", token="x"))) == ["resume_failed"]
    other = client(seats)
    assert kinds(other.handle(text(type="resume_session", token="x"))) == ["busy"]
    seats.closing = True
    assert kinds(other.handle(text(type="resume_session", token="x"))) == ["busy"]


def test_a_periodic_save_token_is_released_when_its_connection_goes_and_forgotten_when_handed_over():
    """A lost connection releases its session's lease (its last save may be resumed now); a hand-over consumes
    the periodic-save token (the goaway's state goes on from later: resuming both would fork the session)."""
    seats = seats_of(max_sessions=2, resumable=True, save_every_s=1.0)
    lost = client(seats)
    audio_in(lost, 160)
    assert lost.handle(Left()) == [StopSession(), FreeSeat(), Release("t0")] and lost.save_token is None
    assert lost.handle(Left()) == []  # (once)
    handed = client(seats)
    audio_in(handed, 160)
    seats.closing = True
    handed.handle(HandOver())
    out = handed.handle(HandedOver("fresh", 160))
    assert kinds(out) == ["goaway"] and out[-1] == Forget("t0") and handed.save_token is None
    handed.handle(SessionEnded(frames=3, handed_over=True))
    assert handed.handle(Left()) == []  # (nothing left to release)


def test_a_session_that_stopped_sending_saves_nothing_more():
    """Boundaries come only with audio, but one without new audio since the last save (a silent client, a
    restored session) saves nothing: abandoned sessions do not fill the store."""
    seats = seats_of(max_sessions=1, resumable=True, save_every_s=1.0)
    c = client(seats)
    audio_in(c, 160)
    assert c.handle(Boundary(1, 16000)) == [SaveState(1, "t0", 16000, 0)]
    assert all(c.handle(Boundary(1, 16000)) == [] for _ in range(100))  # no new audio: no save
    assert c.handle(Boundary(1, 32000)) == [SaveState(1, "t0", 32000, 0)]


def test_a_resume_of_a_live_session_is_refused_with_when_to_try_again():
    c = client(seats_of(max_sessions=1, resumable=True, save_every_s=1.0))
    assert c.handle(text(type="resume_session", token="x")) == [TakeSeat(), TakeState("x")]
    assert kinds(audio_in(client(c.seats), 160)) == ["busy"]  # the seat is held while the store answers
    live = c.handle(Taken(None, live_s=2.5))
    refused = sent(live)
    assert refused[0]["code"] == "session_live" and refused[0]["retry_after_s"] == 2.5
    assert live[0] == FreeSeat() and c.seats.taken == 0  # its seat held for the resume is free again
    assert c.phase is Phase.IDLE  # nothing started: the client tries again later
    assert c.handle(text(type="resume_session", token="x")) == [TakeSeat(), TakeState("x")]


def test_keepalive_blames_only_a_client_that_does_not_read():
    k = Keepalive(interval=1.0, timeout=2.0, now=0.0)
    assert k.tick(1.0, holding=False, frames_sent=0, awaits_reading=False) is None
    k.heard(1.5)
    assert k.tick(4.0, holding=False, frames_sent=0, awaits_reading=False) is None
    assert k.tick(5.0, holding=False, frames_sent=0, awaits_reading=False) == Close(1011, "keepalive ping timeout")
    held = Keepalive(interval=1.0, timeout=2.0, now=0.0)
    for t in range(1, 10):  # held back by the server, frames going out: never blamed
        assert held.tick(float(t), holding=True, frames_sent=t, awaits_reading=True) is None
    for t in range(10, 13):  # held, frames waiting and none going out: silence counts
        assert held.tick(float(t), holding=True, frames_sent=9, awaits_reading=True) is None
    assert held.tick(13.0, holding=True, frames_sent=9, awaits_reading=True) is not None


# ---- the face (revision 7): each client's own name set, smile and binary layout ------------------------------

def face_of(action: SendFrames):
    """The face channel an action's frames carry (None: none), and the `channels` message before them."""
    ch = action.channels.get("face")
    return (ch.labels if ch is not None else None), (json.loads(action.layout) if action.layout else None)


def test_json_frames_carry_the_servers_face_and_binary_frames_only_once_asked():
    from dimgestor.face.names import ARKIT, names_of

    vrm0 = names_of("vrm0")
    json_client, old_binary = (client(seats_of(max_sessions=4, face="vrm0", joints=3)),
                               client(seats_of(max_sessions=4, face="vrm0", joints=3)))
    old_binary.handle(text(type="hello", encoding="binary"))
    assert face_of(json_client.handle(Broadcast(2))[0]) == (vrm0, None)  # nothing asked: the server's set
    assert old_binary.handle(Broadcast(2)) == [SendFrames(None, "binary")]  # revision 5's frames for an old client

    c = old_binary
    assert c.handle(text(type="hello", encoding="binary", face="arkit")) == []  # said with the next frames
    first, later = c.handle(Broadcast(2))[0], c.handle(Broadcast(1))[0]
    labels, layout = face_of(first)
    assert labels == ARKIT and layout == {"type": "channels", "channels": [
        {"name": "face", "size": 52, "offset": 28 + 16 * 3, "labels": list(ARKIT),
         "description": "face blendshape weights 0..1, arkit names"}]}
    assert face_of(later) == (ARKIT, None)  # the layout is told once
    c.handle(text(type="hello", encoding="json"))  # (a hello without `face` keeps it)
    assert face_of(c.handle(Broadcast(1))[0]) == (ARKIT, None) and c.handle(Broadcast(1))[0].encoding == "json"

    # an unknown set: bad_message listing the known ones; nothing of that hello applies, the client goes on
    bad = c.handle(text(type="hello", encoding="binary", face="vrm2"))
    assert kinds(bad) == ["bad_message"] and all(s in sent(bad)[0]["message"] for s in ("vrm0", "vrm1", "arkit",
                                                                                         "oculus", "none"))
    assert c.encoding == "json" and face_of(c.handle(Broadcast(1))[0]) == (ARKIT, None)

    c.handle(text(type="hello", face="none"))  # no face at all, and an empty layout
    assert face_of(c.handle(Broadcast(1))[0]) == (None, {"type": "channels", "channels": []})
    c.handle(text(type="hello", encoding="binary"))
    assert c.handle(Broadcast(1)) == [SendFrames(None, "binary")]


def test_own_frames_follow_the_clients_set_and_a_faceless_server_ignores_the_ask():
    c = client(seats_of(max_sessions=4, face="arkit", joints=2))
    c.handle(text(type="hello", face="oculus", timing=True))
    audio_in(c, 160)
    assert c.handle(Broadcast(3)) == []  # a client with audio of its own follows its own frames only
    send = c.handle(Frames(count=2, backlog_s=0.0, window="w"))[0]
    assert send.window == "w" and face_of(send)[0][:2] == ("viseme_sil", "viseme_PP")
    assert face_of(send)[1]["channels"][0]["size"] == 17

    plain = client(seats_of(max_sessions=4, face=None, joints=2))  # --face none: ignored, no `channels` message
    plain.handle(text(type="hello", encoding="binary", face="arkit"))
    assert plain.handle(Broadcast(1)) == [SendFrames(None, "binary")]
    plain.handle(text(type="hello", encoding="json"))
    assert plain.handle(Broadcast(1)) == [SendFrames(None, "json")]


def test_smile_goes_to_the_clients_own_sessions_only():
    c = client(seats_of(max_sessions=4, face="vrm0"))
    assert c.handle(text(type="hello", smile=0.75)) == []  # no session yet: its next one starts with it
    assert audio_in(c, 160)[1] == StartSession(1, 16000, None, None, smile=0.75)
    assert c.handle(text(type="hello", smile=0)) == [SetSmile(0.0)]  # the running session, from its next frames
    for bad in (1.5, -0.1, "big", True, None):
        assert kinds(c.handle(text(type="hello", smile=bad))) == ["bad_message"]
    assert c.smile == 0.0
    c.handle(text(type="audio_end"))
    c.handle(SessionEnded(frames=4))
    assert audio_in(c, 160)[1].smile == 0.0


def test_every_event_has_its_handler():
    """`handle` dispatches on the event's type through one table: every `Event` is in it, nothing else, each to a
    method of the machine."""
    import typing

    from streamer.client_events import Event
    from streamer.client_session import HANDLERS

    assert set(HANDLERS) == set(typing.get_args(Event))
    assert all(callable(getattr(ClientSession, name)) for name in HANDLERS.values())
