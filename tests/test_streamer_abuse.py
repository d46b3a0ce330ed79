"""One client cannot hurt another: `streamer serve` under abusive clients, watched by two bystanders.

One server (a subprocess, a tiny model, a looping WAV broadcast in real time) runs through a quiet
phase and then one phase per abusive pattern. Throughout, a watcher follows the broadcast (its largest
gap between frames is measured) and a talker streams its own audio in real time (the latency of each
of its frames: arrival minus the moment its audio was complete; the median per phase).
"""

import asyncio
import json
import multiprocessing
import time

import numpy as np
import pytest
from websockets.asyncio.client import connect

from helpers.serve import serve
from helpers.streamer_abusers import PATTERNS, abuse
from helpers.talkers import Talker

pytestmark = pytest.mark.timeout(150)
PHASE_S = 3.0
CHUNK_S = 0.05


class Watcher:
    def __init__(self):
        self.arrivals: list[float] = []

    async def run(self, url, stop):
        async with connect(url) as c:
            while not stop.is_set():
                try:
                    m = await asyncio.wait_for(c.recv(), 0.5)
                except asyncio.TimeoutError:
                    continue
                if json.loads(m)["type"] == "frame":
                    self.arrivals.append(time.monotonic())

    def max_gap(self, t0, t1):
        t = [a for a in self.arrivals if t0 <= a <= t1]
        return float(max(np.diff([t0, *t, t1])))


def test_abusive_clients_do_not_hurt_bystanders(tiny_checkpoint, wav):
    s = serve(tiny_checkpoint, "--source", str(wav), "--loop", "--status-every", "0")
    url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
    spawn = multiprocessing.get_context("spawn")

    async def phase(name=None):
        """(start, end) of one phase: quiet, or one abuser running in its own process (measured once it abuses)."""
        if name is None:
            t = time.monotonic()
            await asyncio.sleep(PHASE_S)
            return t + 0.5, time.monotonic()
        started = spawn.Event()
        abuser = spawn.Process(target=abuse, args=(name, url, PHASE_S, started), daemon=True)
        abuser.start()
        while not started.is_set():  # connected and abusing
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.5)
        t = time.monotonic()
        await asyncio.sleep(PHASE_S - 0.5)
        span = t, time.monotonic()
        while abuser.is_alive():
            await asyncio.sleep(0.1)
        return span

    def within(name, quiet, span):
        # The watcher's largest gap: under 0.5 s (~0.22 quiet here: a 200 ms window's frames come together), or
        # under 2x the quiet phase's on a machine that stretches it by itself (beside two busy loops, quiet phases
        # of one run gave 0.25-0.48 s with no abuser, and odd_rates 0.30-0.33 s between them).
        # The talker: 2x the quiet latency, plus 25 ms for what a shared 2-core machine's scheduler adds to a
        # ~60 ms median on its own (seen: 124 ms against 2 x 58 ms under a load average of 8, with no abuser
        # effect elsewhere)
        # Rigs (issue 52): the talker's 95th percentile too, within 1.5x the quiet one's (+25 ms, as above): a valid
        # rig re-sent in a loop once made it 10x (its fitting, ~35 ms, on the event loop).
        return (watcher.max_gap(*span) < max(0.5, 2 * watcher.max_gap(*quiet))
                and talker.median(*span) <= 2 * talker.median(*quiet) + 0.025
                and ("rig" not in name or talker.percentile(*span) <= 1.5 * talker.percentile(*quiet) + 0.025))

    async def run():
        stop = asyncio.Event()
        bystanders = [asyncio.create_task(watcher.run(url, stop)), asyncio.create_task(talker.run())]
        await asyncio.sleep(1.0)  # settle
        trials = {name: [] for name in PATTERNS}  # per pattern: (quiet span, abused span) pairs
        quiet = await phase()
        for name in PATTERNS:
            trials[name].append((quiet, await phase(name)))
            if not within(name, *trials[name][-1]):
                # A 3 s phase on a shared machine can be stretched by other work (CI saw a talker median of
                # 320 ms against 68 ms quiet once, with the watcher slowed too, in a run that no other run
                # repeated): measure that pattern once more against a quiet phase just before it. An abuser
                # that does hurt the bystanders fails both times.
                quiet = await phase()
                trials[name].append((quiet, await phase(name)))
        stop.set()
        talker.stop.set()
        await asyncio.gather(*bystanders, return_exceptions=True)
        return trials

    watcher, talker = Watcher(), Talker(url, 120.0, chunk_s=CHUNK_S, binary=False, finish=False)  # stopped at the end
    trials = asyncio.run(run())
    s.proc.terminate()
    assert s.finish(10) == 0, s.output
    report = {
        name: [(round(watcher.max_gap(*q), 3), round(talker.median(*q), 3), round(talker.percentile(*q), 3),
                round(watcher.max_gap(*a), 3), round(talker.median(*a), 3), round(talker.percentile(*a), 3))
               for q, a in pairs]
        for name, pairs in trials.items()
    }
    print("per pattern and trial: quiet max watcher gap s, quiet median and p95 talker latency s; abused: max "
          "watcher gap s, median and p95 talker latency s:", report)
    print("server output:\n" + s.output)
    for name, pairs in trials.items():
        assert any(within(name, *pair) for pair in pairs), f"{name} hurt the bystanders in every trial: {report[name]} ({report})"
    assert not talker.errors, talker.errors[:3]
    assert "Traceback" not in s.output and len(s.output.splitlines()) < 20, s.output[-3000:]  # no log floods
