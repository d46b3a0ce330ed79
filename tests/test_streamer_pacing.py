"""The Pacer: a playout clock that drops late items, never bursts, and recovers from any stall within resync_s."""

import numpy as np
import pytest

from streamer.pacing import Pacer

FPS = 20


def simulate(pacer, arrivals, until):
    """Run a paced sink on a virtual clock: arrivals [(t, pts)] -> sent [(t_sent, pts)]."""
    queue, sent, now, i = [], [], 0.0, 0
    arrivals = sorted(arrivals)
    while now < until:
        while i < len(arrivals) and arrivals[i][0] <= now:
            pacer.arrived(arrivals[i][1], arrivals[i][0])
            queue.append(arrivals[i][1])
            i += 1
        while queue:
            d = pacer.wait(queue[0], now)
            if d is None:
                queue.pop(0)
            elif d == 0:
                sent.append((now, queue.pop(0)))
            else:
                break
        now += 0.005
    return sent


def windows(t_start, t_end, latency=0.1, window=0.2, stalls=()):
    """A producer making 4 frames per 0.2 s window, `latency` after the window; during a stall (a, b) nothing
    comes out, and at b the backlog comes out at once (a file source catching up)."""
    out = []
    k = 0
    while True:
        t_done = (k + 1) * window + latency
        if t_done > t_end:
            return out
        for a, b in stalls:
            if a <= t_done < b:
                t_done = b
        out += [(t_done, (k * 4 + j) / FPS) for j in range(4)]
        k += 1


def catching_up(t_end, stall, speed, latency=0.1, window=0.2):
    """A producer stalled during `stall` (a, b) that then works through its backlog at `speed` x real time
    (a file source on a slow or busy machine), one 4-frame window at a time, until it is on time again."""
    out, done, k = [], 0.0, 0
    while (due := (k + 1) * window + latency) <= t_end:
        done = due if due < stall[0] else max(due, stall[1], done + window / speed)
        out += [(done, (k * 4 + j) / FPS) for j in range(4)]
        k += 1
    return out


def rate_after(sent, t0, t1):
    return sum(1 for t, _ in sent if t0 <= t < t1) / (t1 - t0)


def test_steady_stream_is_sent_at_pts_plus_a_constant_lag():
    p = Pacer(buffer_s=0.25)
    sent = simulate(p, windows(0, 10), 10)
    lags = [t - pts for t, pts in sent]
    assert max(lags) - min(lags) < 0.011  # the virtual clock's step
    assert p.stats.dropped_late == 0 and p.stats.resyncs == 0
    assert rate_after(sent, 2, 9) == pytest.approx(FPS, abs=0.5)


def test_a_stall_with_catch_up_drops_the_backlog_and_keeps_the_clock():
    p = Pacer(buffer_s=0.25)
    stalls = [(3 + 4 * i, 5.5 + 4 * i) for i in range(6)]  # 6 x 2.5 s pauses
    sent = simulate(p, windows(0, 30, stalls=stalls), 30)
    last = stalls[-1][1]
    assert rate_after(sent, last + 1.0, 30) >= 19
    base = sent[0][0] - sent[0][1]
    after = [t - pts - base for t, pts in sent if t > last + 1.0]
    assert max(after) <= 0.25 and min(after) > -0.02  # lag after the stalls: no more than before
    assert p.stats.dropped_late > 0
    t = np.array([t for t, _ in sent])
    in_half_s = np.searchsorted(t, t + 0.5) - np.arange(len(t))
    assert in_half_s.max() <= 0.5 * FPS + 0.1 * FPS + 1  # no burst: the rate plus what the tolerance lets through


def test_a_producer_that_falls_behind_for_good_is_followed_within_resync_s():
    """A live source that lost 3 s of audio: every later frame arrives 3 s later than before."""
    p = Pacer(buffer_s=0.25, resync_s=1.0)
    before = windows(0, 5)
    after = [(t + 3.0, pts) for t, pts in windows(5, 20) if t > 5]
    sent = simulate(p, before + after, 23)
    assert p.stats.resyncs == 1
    assert rate_after(sent, 8 + 1.2, 23) >= 19
    worst = max(t - pts for t, pts in after)  # the last of each window
    lag = [t - pts - worst for t, pts in sent if t > 10]
    assert max(lag) <= 0.25 + 0.011  # follows the producer: a jitter buffer after its latest arrivals


def test_a_producer_that_gets_faster_pulls_the_clock_in():
    p = Pacer(buffer_s=0.25, resync_s=1.0)
    slow = [(t + 1.0, pts) for t, pts in windows(0, 3)]  # a slow first second (warm-up), then fast
    fast = [(t, pts) for t, pts in windows(0, 15) if t > 4]
    sent = simulate(p, slow + fast, 20)
    assert p.stats.resyncs >= 1 and p.stats.dropped_late == 0  # pulled in by playing faster, nothing lost
    lag = [t - pts for t, pts in sent if t > 12]
    worst = max(t - pts for t, pts in fast)
    assert max(lag) - worst <= 0.25 + 0.011
    gaps = [b[0] - a[0] for a, b in zip(sent, sent[1:])]
    assert min(gaps) >= 0.8 / FPS - 0.011  # at most 1.2x speed while catching up


def test_a_slow_catch_up_after_a_stall_keeps_the_clock():
    """After a 2.5 s stall the backlog goes through at only 2x real time (2.5 s late for 2.5 s): the clock
    does not follow those late frames (it would keep their lag for as long as pulling it back takes)."""
    p = Pacer(buffer_s=0.25, resync_s=1.0)
    arrivals = catching_up(20, stall=(3.0, 5.5), speed=2.0)
    on_time = next(t for t, pts in arrivals if t > 5.5 and t - pts < 0.4)
    assert 7.5 < on_time < 8.5  # the producer is late for over 2 resync_s
    sent = simulate(p, arrivals, 20)
    assert p.stats.resyncs == 0 and p.stats.dropped_late > 0
    base = sent[0][0] - sent[0][1]
    after = [t - pts - base for t, pts in sent if t > on_time]
    assert max(after) <= 0.011 and min(after) > -0.011  # the lag of before the stall, at once
    assert rate_after(sent, on_time + 0.5, 20) >= 19


def test_a_producer_too_slow_to_catch_up_is_followed():
    """After the stall it goes only 1.2x real time (over 10 s to catch up): following it beats a long gap."""
    p = Pacer(buffer_s=0.25, resync_s=1.0, catchup_s=3.0)
    sent = simulate(p, catching_up(12, stall=(3.0, 5.5), speed=1.2), 12)
    assert p.stats.resyncs >= 1
    assert rate_after(sent, 5.5 + 1.5, 12) >= 19


def test_a_clock_far_behind_skips_to_the_producer():
    """The producer fell 3 s behind (the clock followed it), then is on time again: the clock moves back at
    once, dropping the frames in between, rather than playing 1.2x fast for 15 s with 3 s of lag."""
    p = Pacer(buffer_s=0.25, resync_s=1.0, skip_s=1.5)
    before = windows(0, 5)
    behind = [(t + 3.0, pts) for t, pts in windows(5, 10) if t > 5]
    again = [(t, pts) for t, pts in windows(0, 25) if t > 13.5]
    sent = simulate(p, before + behind + again, 25)
    assert p.stats.skips == 1 and p.stats.dropped_late > 0
    base = sent[0][0] - sent[0][1]
    after = [t - pts - base for t, pts in sent if t > 13.5 + 1.5]
    assert max(after) <= 0.011 and min(after) > -0.011
    assert rate_after(sent, 13.5 + 1.5, 25) >= 19


def test_reset_starts_a_new_stream():
    p = Pacer(buffer_s=0.1)
    p.arrived(0.0, 10.0)
    assert p.wait(0.0, 10.0) == pytest.approx(0.1)
    p.reset()
    p.arrived(0.0, 50.0)
    assert p.wait(0.0, 50.0) == pytest.approx(0.1)
    assert p.wait(0.0, 50.5) is None and p.stats.dropped_late == 1


def test_bad_settings_are_refused():
    with pytest.raises(ValueError):
        Pacer(buffer_s=-1)
    with pytest.raises(ValueError):
        Pacer(resync_s=0)
