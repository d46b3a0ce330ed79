"""The web viewer's speech -> motion readout is measured, not estimated, and agrees with benchmarks/latency.py: in
real Chromium, talking through the fake microphone (tone bursts with known onsets) to a tiny-model server, the
HUD's number equals the benchmark's onset -> pose-on-screen total within what the page's own frames allow; and
watching the server's source (a file), the readout is measured from the server's `timing` messages. The numbers
themselves are the benchmark's business (benchmarks/results/latency.json), not this test's."""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from helpers.browser import CHROMIUM, THREE_JS, Browser
from helpers.clients import REPO, live_server

sys.path.insert(0, str(REPO / "benchmarks"))
import latency  # noqa: E402

pytestmark = [pytest.mark.timeout(300),
              pytest.mark.skipif(not CHROMIUM, reason="chromium not installed (Debian: apt-get install chromium)"),
              pytest.mark.skipif(not THREE_JS.exists(), reason="the viewer's npm dependencies are not installed "
                                 "(make setup runs npm ci in clients/web)")]


def test_readout_dates_speech_by_its_least_delayed_moment_and_the_best_pong(tmp_path):
    """clients/web/latency.js under node: speech said is dated by the least delayed of the last 5 s; `timing`
    counts only once a pong related the clocks, through the pong with the shortest round trip; the total is the
    playout offset minus that, plus half a page frame."""
    node = shutil.which("node")
    if not node:
        pytest.skip("node not installed (Debian: apt-get install nodejs)")
    script = tmp_path / "latency.txt"
    script.write_text("\n".join([
        "total 2.0 0.02 10.0",             # nothing said yet: no total
        "said 1.0 10.1", "said 1.1 10.5",  # said at pts + 9.1, then + 9.4 (a busy page): the least delayed counts
        "total 9.5 0.02 10.6",             # 9.5 - 9.1 + 0.01 = 0.41 s
        "said 8.0 20.0",                   # 7 s later: the early ones are forgotten, pts + 12.0
        "total 12.3 0 20.0",
        "timing 3.0 100.0",                # no pong yet: the server's clock is unknown
        "pong 30.0 30.2 130.0", "pong 40.0 40.02 140.51",  # offsets 99.9 and 100.5; the second's round trip is shorter
        "timing 22.0 122.0",               # arrived at 122.0 - 100.5 = 21.5 local: said at pts - 0.5
        "total 0.2 0 21.5"]))              # least delayed: 21.5 - 22.0 = -0.5 -> 0.2 + 0.5 = 0.7 s
    r = subprocess.run([node, str(REPO / "clients/web/tests/latency_check.mjs"), str(script)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    out = [json.loads(line) for line in r.stdout.splitlines()]
    totals = [o["total_ms"] for o in out if o["event"] == "total"]
    assert totals[0] is None and totals[1] == pytest.approx(410) and totals[2] == pytest.approx(300)
    assert totals[3] == pytest.approx(700)
    timings = [o["timing_used"] for o in out if o["event"] == "timing"]
    assert timings == [False, True] and out[-1]["server_offset"] == pytest.approx(100.5)


def test_talk_readout_equals_the_benchmarks_onset_to_screen_total(tmp_path, checkpoint):
    a = argparse.Namespace(checkpoint=str(checkpoint), steps=1, window_ms=100, seconds=14.0, page_size="480,320",
                           avatar="mannequin", raw=None)
    r = latency.run_talk(a, tmp_path)
    assert r["page"]["errors"] == [] and r["onsets"] >= 3
    assert r["hud_ms"]["measured"] and r["hud_ms"]["samples"] >= 3
    # The readout dates speech and presents poses as the benchmark does; what differs is when within a page frame
    # the onset falls (the readout takes half a frame) and how the playout clock moved between its samples and the
    # onsets: one page frame (p90), the page's arrival jitter (p90) and how far the playout buffer itself moved
    # over the run (the spread of the onsets' playout part: an underrun on a loaded machine grows it between the
    # readout's samples and the onsets) bound it, plus 30 ms.
    playout = [row["playout"] for row in r["rows"]]
    moved = float(np.percentile(playout, 90) - np.percentile(playout, 10))
    tolerance = r["raf_interval_ms"]["p90_ms"] + r["arrival_jitter_ms"]["p90"] + moved + 30
    assert abs(r["hud_ms"]["median_ms"] - r["total"]["median_ms"]) <= tolerance, (r["hud_ms"], r["total"], tolerance)


def test_watching_a_file_the_readout_is_measured_from_the_servers_timing(tmp_path, checkpoint):
    wav = latency.write_wav(tmp_path / "bursts.wav", latency.stimulus(20)[0])
    with live_server(tmp_path, str(wav), checkpoint, http=True, loop=True) as server:
        browser = Browser(tmp_path, server.http_url + "?sound=off", ("--window-size=480,320",))
        try:
            browser.wait_for("window.dimgestor && window.dimgestor.timingSeen && window.dimgestor.delayMeasured", 60,
                             "a measured readout from the server's timing")
            hello = browser.eval("window.dimgestor.hello")
            readouts = []
            for _ in range(6):
                browser.wait_for("window.dimgestor.delayMs !== null", 10, "a readout")
                readouts.append(browser.eval("window.dimgestor.delayMs"))
                assert browser.eval("document.getElementById('delay').textContent").endswith(" ms")
                assert "≈" not in browser.eval("document.getElementById('delay').textContent")
                browser.eval("new Promise((r) => setTimeout(r, 500))")
        finally:
            browser.close()
    # A file source's audio "arrives" as it is due (paced in real time), so the readout is at least the model's
    # lookahead and a window; it is bounded by the page's playout buffer on top of that.
    assert np.median(readouts) >= 1000 * hello["lookahead_s"] + hello["window_ms"] - 60
