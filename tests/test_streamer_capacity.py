"""Admission by capacity (issue 52, item 2): a new session is admitted only while the sessions already admitted stay
in real time; beyond that its audio gets `busy` with `retry_after_s`, and `/readyz` says how many more faces fit.
Seven clients asking for a face beside one talker once put every one of them 9-19 s behind."""
import asyncio
import json
import re
import time

import pytest

from streamer import client_session as S
from streamer.capacity import FACE_SETTLE_S, Admission, FaceCost
from streamer.health import Readiness, RealtimeLoad
from helpers.serve import serve
from helpers.talkers import Talker, readyz


class FakeClock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


def _busy_for(load: RealtimeLoad, clock: FakeClock, fraction: float, seconds: float = 10.0) -> None:
    """Real-time work on the inference thread for `fraction` of the last `seconds`."""
    for _ in range(int(seconds * 10)):
        load.began(True)
        clock.t += 0.1 * fraction
        load.ended()
        clock.t += 0.1 * (1 - fraction)


def test_faces_are_admitted_while_they_fit_beside_the_measured_load():
    clock = FakeClock()
    ready = Readiness(RealtimeLoad(window_s=10.0, now=clock))
    admission = Admission(ready, FaceCost(0.1), lanes=1, max_load=0.8, now=clock)
    _busy_for(ready.load, clock, 0.3)  # the talkers admitted so far: 0.3 of the thread
    assert admission.faces_left() == 5  # (0.8 - 0.3) / 0.1
    admitted = 0
    while admission.refusal(face=True) is None:  # a crowd at once: each face admitted counts 1.5x until it is in
        admission.admitted(face=True)            # the measured load (FACE_SETTLE_S)
        admitted += 1
    assert admitted == 3 and admission.faces_left() == 0  # 0.5 - 3 x 0.15 leaves room for none
    why = admission.refusal(face=True)
    assert why.startswith("this worker is at capacity for faces (0.10 s of compute a second each, real-time load "
                          "0.30, limit 0.8)") and 'hello.face "none"' in why
    assert admission.refusal(face=False) is None  # a session without a face costs the batch little more
    clock.t += FACE_SETTLE_S  # ... by then the three are in the load: 0.3 + 3 x 0.1
    _busy_for(ready.load, clock, 0.6)
    assert admission.faces_left() == 2 and admission.refusal(face=True) is None
    assert ready.check() == (True, "ready: real-time load 0.60; room for 2 more faces")
    _busy_for(ready.load, clock, 0.8)
    assert admission.faces_left() == 0 and admission.refusal(face=True) is not None


def test_no_session_is_admitted_while_the_worker_is_not_ready():
    clock = FakeClock()
    ready = Readiness(RealtimeLoad(window_s=10.0, now=clock))
    admission = Admission(ready, None, now=clock)
    assert admission.refusal(face=False) is None and admission.faces_left() is None  # (no face made here)
    _busy_for(ready.load, clock, 0.95)
    assert admission.refusal(face=False) == ("this worker is at capacity (real-time load 0.95 over the last 10 s "
                                             "(limit 0.9): inference cannot keep real time): try again after "
                                             "retry_after_s")
    ready.lags = lambda: [(clock.t - 20.0, 20.0, 3.0)]  # and a talker 3 s behind
    _busy_for(ready.load, clock, 0.2)
    assert "1 real-time client 3.0 s behind" in admission.refusal(face=False)


def test_a_face_cost_is_measured_at_start_and_learnt_from_the_faces_made():
    pytest.importorskip("pocketsphinx")
    from dimgestor.face import FaceOptions

    cost = FaceCost()
    assert 0.01 < cost.measure(FaceOptions(), 20, 0.3, seconds=1.0) < 4.0  # seconds of compute a second of speech
    first = cost.value
    for _ in range(40):
        cost.add(0.05, 0.1)  # what the sessions' faces took on a busier machine: 0.5 s a second (followed quickly)
    assert abs(cost.value - 0.5) < 0.01 * first + 1e-3
    for _ in range(40):
        cost.add(0.01, 0.1)  # ... and then 0.1: followed slowly
    assert 0.2 < cost.value < 0.5


def test_the_machine_answers_busy_with_retry_after_s_and_takes_no_seat_at_capacity():
    from streamer.client_events import Audio, Decoded, Refused, Send

    class Full:
        retry_after_s = 5.0

        def __init__(self):
            self.admitted_faces = []

        def refusal(self, face):
            return "this worker is at capacity for faces (...)" if face else None

        def admitted(self, face):
            self.admitted_faces.append(face)

        def freed(self, face):
            self.admitted_faces.remove(face)

    full = Full()
    seats = S.Seats(S.Terms(max_sessions=4, face="arkit"), full)
    face = S.ClientSession(seats, new_token=lambda: "t")
    face.handle(S.Text(json.dumps({"type": "hello", "face": "arkit"})))
    face.handle(Audio(b"\0\0" * 1600))
    out = face.handle(Decoded())
    assert [type(a) for a in out] == [Refused, S.Log, Send] and out[0] == Refused("capacity")
    assert json.loads(out[2].message) == {"type": "error", "code": "busy", "retry_after_s": 5.0,
                                          "message": "this worker is at capacity for faces (...)"}
    plain = S.ClientSession(seats, new_token=lambda: "t")
    plain.handle(Audio(b"\0\0" * 1600))
    started = plain.handle(Decoded())
    assert started[0] == S.TakeSeat(face=False)
    seats.carry_out(started[0])
    assert seats.taken == 1 and full.admitted_faces == [False]
    seats.carry_out(S.FreeSeat(False))
    assert seats.taken == 0 and full.admitted_faces == []


@pytest.mark.timeout(180)
def test_faces_beyond_capacity_are_told_busy_and_everyone_admitted_keeps_real_time(tiny_checkpoint):
    """A talker alone (its quiet p95), then eight clients asking for a face, each in real time: those admitted and
    the talker keep their latency (p95 within 1.5x the quiet one, or 0.2 s more on a shared machine: the full suite
    beside it once made an admitted face 0.29 s against 0.12 quiet; overloaded, they were 1-19 s); the others are told
    `busy` with `retry_after_s`, no more of them admitted than /readyz said had room; and one that tries again
    once the crowd has gone is admitted."""
    pytest.importorskip("pocketsphinx")
    s = serve(tiny_checkpoint, "--source", "ws", "--steps", "2", "--status-every", "0")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    http = re.sub(r"^ws", "http", url.rstrip("/")) + "/"  # (/readyz on the WebSocket's port)
    crowd_s, quiet_s = 8.0, 3.0

    async def run():
        talker = Talker(url, quiet_s + crowd_s + 3.0, seed=2)
        task = asyncio.create_task(talker.run())
        await asyncio.sleep(1.0 + quiet_s)
        quiet = (talker.t0 + 1.0, time.monotonic())
        room = await asyncio.get_running_loop().run_in_executor(None, readyz, http)
        crowd = [Talker(url, crowd_s, seed=10 + k, face="arkit") for k in range(8)]
        tasks = [asyncio.create_task(c.run()) for c in crowd]
        await asyncio.sleep(crowd_s)
        span = (time.monotonic() - crowd_s + 1.0, time.monotonic())
        await asyncio.gather(*tasks, task)
        again = Talker(url, 2.0, seed=30, face="arkit")
        await again.run()
        return talker, quiet, room, crowd, span, again

    try:
        talker, quiet, room, crowd, span, again = asyncio.run(run())
    finally:
        s.proc.terminate()
        s.finish(10)
    fit = int(re.search(r"room for (\d+) more face", room[1]).group(1))
    refused = [c for c in crowd if any(e["code"] == "busy" for e in c.errors)]
    admitted = [c for c in crowd if c not in refused]
    assert all(e.get("retry_after_s", 0) > 0 for c in refused for e in c.errors if e["code"] == "busy")
    assert len(admitted) <= fit and len(admitted) + len(refused) == 8, (fit, len(admitted), room)
    assert len(refused) >= 8 - fit
    bound = max(1.5 * talker.percentile(*quiet), talker.percentile(*quiet) + 0.2)
    print(f"room for {fit} faces; {len(admitted)} admitted, {len(refused)} told busy; talker p95 quiet "
          f"{talker.percentile(*quiet):.3f} s, with the crowd {talker.percentile(*span):.3f} s; admitted faces' p95 "
          f"{[round(c.percentile(*span), 3) for c in admitted]}")
    for who in [talker, *admitted]:
        assert who.percentile(*span) <= bound, (who.percentile(*span), talker.percentile(*quiet), fit, len(admitted))
        assert not who.errors, who.errors
    assert not again.errors and again.end is not None and again.end["frames"] == 40
