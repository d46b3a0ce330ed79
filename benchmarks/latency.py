"""Speech -> motion latency, end to end and part by part (issue 24, item 1).

Two paths, each fed a stimulus with onsets at known places (tone bursts after silence):

talk  real Chromium, its fake microphone playing the stimulus, the web viewer's Talk button, against
      `dimgestor serve --source ws`. benchmarks/latency_probe.js stamps on the page's clock when each microphone
      chunk reached the viewer's socket worker and was sent, when each frame arrived there (as the playout clock
      is told of it: the worker's stamp for frames read from shared memory) and which pts every
      requestAnimationFrame presented; the server's `timing` messages (protocol revision 5) say when each window's audio had arrived,
      when inference began and when its frames were sent, related to the page's clock by the pong with the
      shortest round trip. total = onset reached the page -> the first requestAnimationFrame presenting its pts.
vmc   `dimgestor serve --source mic --vmc` with the virtual microphone (tests/helpers/virtual_mic.py) playing the stimulus
      in real time, a UDP receiver stamping the bundles: total = onset played -> the bundle of the first frame at
      or after the onset's pts received (server side, one clock: time.monotonic of this machine).

Parts, for an onset at pts p whose pose needs frame j (the first at or after p; the pose at p is interpolated
towards it) made by a window whose audio ends at E: capture (the audio at E said -> sent; vmc: played ->
arrived at the server), network up (sent -> arrived at the server, its decoding included), lookahead (the hello's
lookahead_s: frame j needs the audio up to pts_j + lookahead_s), frame (pts_j - p), window (the rest of the
window's audio, E - pts_j - lookahead_s), queue (arrived -> inference began), compute (-> frames queued to the
client), network down (-> arrival at the page), playout (-> the rAF that presents p; vmc: the pacer's jitter buffer
-> the bundle received). The parts add up to the total up to the jitter of the page's microphone clock (reported
per onset as `slack_ms`; vmc: exact, one clock).

    .venv/bin/python benchmarks/latency.py --window-ms 100 --out benchmarks/results/latency_default_100ms.json
    .venv/bin/python benchmarks/latency.py --checkpoint /work/main/runs/live --window-ms 100 --name live ...
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import struct
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
import wave
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))
from benchmarks.common import code_version, describe_device, load_average, utc_now, write_json  # noqa: E402

PROBE = Path(__file__).resolve().parent / "latency_probe.js"
PARTS = {"talk": ["capture", "network_up", "lookahead", "frame", "window", "queue", "compute", "network_down",
                  "playout"],
         "vmc": ["capture", "lookahead", "frame", "window", "queue", "compute", "pacing"]}
RATE = 48000
METHOD = {
    "talk": "onset = the first microphone sample above 0.05 after 0.3 s of quiet; said = when the viewer's socket "
            "worker got its chunk (the least delayed chunk within 5 s dates the stream: the device's and the worklet's own buffers "
            "before that are not seen); total = said -> the first requestAnimationFrame presenting the onset's pts "
            "(the compositor's frame after it is not seen); the server's stamps are related to the page's clock by "
            "the pong with the shortest round trip (min_rtt_ms), so network up vs down is split within half of it",
    "vmc": "onset played = when pacat was given that sample, paced in real time; the stream's onset found in the "
           "server's own captured audio (the server runs in the benchmark's process: one clock); capture = played -> "
           "the server had it, through the virtual microphone (pacat, PulseAudio, PortAudio: a real device's input "
           "latency replaces it); server_side = total - capture, what the mic -> VMC target is about",
    "parts": "lookahead = the hello's lookahead_s; frame = the onset to the first frame at or after it; window = "
             "the rest of that frame's window's audio; queue = audio arrived -> inference began; compute -> frames "
             "queued; then network down and playout (talk) or the VMC pacer and UDP (vmc); slack = total - parts",
}
# An onset: |x| > ONSET after QUIET_S below QUIET (latency_probe.js finds the first sample above ONSET). QUIET is
# above the 16 kHz resampler's ringing just before a burst (up to 0.01 at these bursts). A burst's first samples
# may land between QUIET and ONSET (where the resampler's grid cuts its first period): up to RISE_S of them.
ONSET, QUIET, QUIET_S, RISE_S = 0.05, 0.03, 0.3, 0.005
WARMUP_S = 4.0  # onsets earlier than this on the stream's clock are left out (the playout clock is settling)
SAID_SPAN_S = 5.0  # the least delayed microphone chunk within this of a moment dates it (as the viewer does)


def stimulus(seconds: float, period_s: float = 1.37, burst_s: float = 0.4,
             lead_s: float = 1.0) -> tuple[np.ndarray, list[float]]:
    """Tone bursts (a voiced 160 Hz tone with harmonics, full level from its first sample) every `period_s`
    after `lead_s` of silence: the samples at RATE and the onset times (s). The period is no multiple of a frame
    or a window, so the onsets fall at every phase of them."""
    x = np.zeros(int(seconds * RATE), np.float32)
    t = np.arange(int(burst_s * RATE)) / RATE
    tone = np.sin(2 * np.pi * 160 * t) + 0.5 * np.sin(2 * np.pi * 320 * t + 1.0)
    burst = 0.3 * tone * np.minimum(1, (burst_s - t) / 0.05)  # a 50 ms fade out: one onset per burst
    onsets = []
    for start in np.arange(lead_s, seconds - burst_s, period_s):
        a = int(start * RATE)
        x[a : a + len(burst)] = burst
        onsets.append(start)
    return x, onsets


def write_wav(path: Path, x: np.ndarray) -> Path:
    pcm = np.clip(np.round(x * 32767), -32768, 32767).astype("<i2")
    with wave.open(str(path), "wb") as w:
        w.setnchannels(1), w.setsampwidth(2), w.setframerate(RATE)
        w.writeframes(pcm.tobytes())
    return path


def detect_onsets(x: np.ndarray, rate: int) -> list[int]:
    """Sample indices where |x| first exceeds ONSET after QUIET_S below QUIET and at most RISE_S between."""
    out, run, quiet_before, rising = [], 0, 0, 0
    need, rise = int(QUIET_S * rate), int(RISE_S * rate)
    for i, a in enumerate(np.abs(x)):
        if a < QUIET:
            run += 1
            continue
        if run:  # the quiet stretch before this sample, and how many rising samples since
            quiet_before, rising, run = run, 0, 0
        if a > ONSET:
            if quiet_before >= need and rising <= rise:
                out.append(i)
            quiet_before = 0
        else:
            rising += 1
    return out


def jitter(transits: list[float]) -> dict:
    """How much later than the least late a window's first frame came (ms): what a playout buffer must absorb."""
    x = np.asarray(transits) - min(transits)
    out = {q: round(float(np.percentile(x, int(q[1:]))), 1) for q in ("p50", "p90", "p99")}
    return out | {"max": round(float(x.max()), 1)}


def summary(rows: list[dict], keys: list[str]) -> dict:
    return {k: {"median_ms": round(float(np.median([r[k] for r in rows])), 1),
                "p90_ms": round(float(np.percentile([r[k] for r in rows], 90)), 1)} for k in keys}


def serve_args(a, source: str) -> list[str]:
    args = ["--source", source, "--window-ms", str(a.window_ms), "--status-every", "0"]
    if a.checkpoint:
        args += ["--checkpoint", a.checkpoint]
    if a.steps:
        args += ["--steps", str(a.steps)]
    return args


# ---------------------------------------------------------------- talk: Chromium, fake microphone, the viewer

def run_talk(a, tmp: Path) -> dict:
    from helpers.serve import Serve
    from helpers.browser import CHROMIUM, Browser

    if not CHROMIUM:
        return {"skipped": "chromium not installed"}
    x, _ = stimulus(a.seconds + 30)  # Chromium's fake microphone loops its file: longer than the run
    wav = write_wav(tmp / "stimulus.wav", x)
    s = Serve(*serve_args(a, "ws"), "--ws", "127.0.0.1:0")
    browser = None
    try:
        url = s.wait_for(r"WebSocket\s+ws://(\S+)", 180).group(1)
        browser = Browser(tmp, "about:blank", (f"--window-size={a.page_size}", "--use-fake-ui-for-media-stream",
                                               "--use-fake-device-for-media-stream",
                                               f"--use-file-for-fake-audio-capture={wav}"))
        browser.call("Page.enable")
        browser.call("Page.addScriptToEvaluateOnNewDocument", source=PROBE.read_text())
        browser.call("Page.navigate", url=f"http://{url}?avatar={a.avatar}")
        browser.wait_for("window.dimgestor && window.dimgestor.hello && !document.getElementById('talk').disabled",
                         60, "hello and an enabled Talk button")
        browser.eval("document.getElementById('talk').click()", user_gesture=True)
        browser.wait_for("window.dimgestor.talking && window.dimgestor.audioChunksSent > 10", 30, "microphone chunks sent")
        got = {"sends": [], "texts": [], "arrive": [], "shown": []}
        hud, t_start = [], time.monotonic()
        while time.monotonic() < t_start + a.seconds:
            for _ in range(4):
                browser.eval("window.__latency.ping()")
                time.sleep(0.25)
            part = browser.eval("window.__latency.take()")
            for k in got:
                got[k] += part[k]
            got["mic_rate"] = part["mic_rate"]
            if time.monotonic() > t_start + WARMUP_S + 1:  # the viewer's readout, as the onsets after the warm-up
                hud.append(browser.eval("[performance.now(), window.dimgestor.delayMs, "
                                        "window.dimgestor.delayMeasured]"))
        hello = browser.eval("window.dimgestor.hello")
        page = browser.eval("({underruns: window.dimgestor.clock.underruns, margin_s: window.dimgestor.clock.marginS, "
                            "dropped: window.dimgestor.audioChunksDropped, errors: window.dimgestor.errors, "
                            "avatar: window.dimgestor.avatar, drawing: window.dimgestor.drawing || null})")
    finally:
        if browser is not None:
            browser.close()
        s.proc.terminate()
        s.finish(30)
    if a.raw:
        write_json(a.raw, {"got": got, "hello": hello})
    result = analyse_talk(got, hello)
    measured = [h for h in hud if h[1] is not None and h[2]]
    result["hud_ms"] = {"median_ms": round(float(np.median([h[1] for h in measured])), 1) if measured else None,
                        "samples": len(measured), "measured": bool(measured)}
    result["page"] = page
    return result


def clock_offset_ms(texts: list) -> tuple[float, float]:
    """Server seconds -> page ms: page = server_s * 1000 - offset; from the pongs with the shortest round trips."""
    pongs = []
    for at, text in texts:
        m = json.loads(text)
        if m.get("type") == "pong" and "t" in m and "server_time_s" in m:
            pongs.append((at - m["t"], m["server_time_s"] * 1000 - (at + m["t"]) / 2))
    if not pongs:
        raise RuntimeError("no pong with server_time_s: the server predates protocol revision 5")
    pongs.sort()
    best = pongs[: max(3, len(pongs) // 10)]
    return float(np.median([o for _, o in best])), float(best[0][0])


def analyse_talk(got: dict, hello: dict) -> dict:
    rate, fps, lookahead = got["mic_rate"], hello["fps"], hello["lookahead_s"]
    offset, rtt = clock_offset_ms(got["texts"])
    page = lambda server_s: server_s * 1000 - offset  # noqa: E731
    timings = [json.loads(t) for _, t in got["texts"] if '"timing"' in t]
    sends = got["sends"]
    ends = np.cumsum([r[1] for r in sends])  # samples sent up to and including each message

    # When each moment of the audio was captured, on the page's clock: the microphone runs in real time, so it is
    # the stream time plus the smallest (arrival - stream time) of the chunks around it (the least delayed chunk;
    # a busy page delays the others: that delay is capture). The viewer's readout uses the same rule.
    starts = np.asarray([r[2] - e / rate * 1000 if r[2] is not None else np.inf for r, e in zip(sends, ends)])
    times = ends / rate

    def said(x: float) -> float:
        near = np.abs(times - x) <= SAID_SPAN_S
        return float(np.min(starts[near])) + x * 1000

    def sent(x: float) -> float | None:
        """When the message carrying the audio at stream time x (s) was sent."""
        i = int(np.searchsorted(ends, x * rate - 1e-6))
        return sends[i][0] if i < len(sends) else None

    arrival = {}
    for pts, at in got["arrive"]:
        arrival.setdefault(round(pts * fps), at)
    shown = np.asarray(got["shown"]) if got["shown"] else np.zeros((0, 2))
    rows, quiet = [], 0.0
    for i, (_, n, at, onset, peak) in enumerate(sends):
        was_quiet, quiet = quiet, (quiet + n / rate if peak < QUIET else 0.0)
        if onset < 0 or at is None or was_quiet < QUIET_S:
            continue
        p = (ends[i] - n + onset) / rate
        if p < WARMUP_S:
            continue
        j = math.ceil(p * fps - 1e-9)
        w = next((w for w in timings if w["first"] <= j < w["first"] + w["frames"]), None)
        later = np.nonzero(shown[:, 1] >= p - 1e-9)[0] if len(shown) else []
        sent_e = sent(w["audio_until_s"]) if w else None
        if w is None or not len(later) or j not in arrival or sent_e is None:
            continue
        drawn, E = shown[later[0], 0], w["audio_until_s"]
        said_p, said_e = said(p), said(E)
        row = {"pts_s": round(p, 4), "total": drawn - said_p,
               "capture": sent_e - said_e, "network_up": page(w["arrived_s"]) - sent_e,
               "lookahead": lookahead * 1000, "frame": (j / fps - p) * 1000,
               "window": (E - j / fps - lookahead) * 1000,
               "queue": (w["dispatched_s"] - w["arrived_s"]) * 1000,
               "compute": (w["sent_s"] - w["dispatched_s"]) * 1000,
               "network_down": arrival[j] - page(w["sent_s"]), "playout": drawn - arrival[j]}
        row["slack"] = row["total"] - sum(row[k] for k in PARTS["talk"])
        rows.append({k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()})
    if not rows:
        raise RuntimeError(f"no onset measured ({len(sends)} chunks sent, {len(timings)} timings, "
                           f"{len(got['shown'])} rAFs)")
    rafs = np.diff(shown[:, 0]) if len(shown) > 1 else np.zeros(1)
    transits = [arrival[w["first"]] - w["first"] / fps * 1000 for w in timings
                if w["first"] in arrival and w["first"] / fps >= WARMUP_S]
    return {"onsets": len(rows), "parts": summary(rows, PARTS["talk"]), "arrival_jitter_ms": jitter(transits),
            "total": summary(rows, ["total"])["total"],
            "slack": summary(rows, ["slack"])["slack"], "min_rtt_ms": round(rtt, 2),
            "raf_interval_ms": {"median_ms": round(float(np.median(rafs)), 1),
                                "p90_ms": round(float(np.percentile(rafs, 90)), 1)},
            "lookahead_s": lookahead, "window_ms": hello.get("window_ms"), "rows": rows}


# ---------------------------------------------------------------- vmc: virtual microphone, UDP receiver

def osc_times(datagram: bytes) -> list[float]:
    """The /VMC/Ext/T values in an OSC bundle (big-endian float after its ',f' type tag)."""
    out, key = [], b"/VMC/Ext/T\x00\x00,f\x00\x00"
    for m in re.finditer(re.escape(key), datagram):
        out.append(struct.unpack(">f", datagram[m.end() : m.end() + 4])[0])
    return out


class Feeder(threading.Thread):
    """Plays samples into the virtual microphone's sink in real time through pacat (10 ms buffer): sample i is
    played at `t0 + i / RATE` on time.monotonic (plus pacat's buffer, at most its 10 ms). Start it once `ready()`:
    pacat's stream is connected (before, what it is given waits in its pipe and plays late)."""

    def __init__(self, x: np.ndarray, env: dict, sink: str = "mic48", block: int = RATE // 100):
        super().__init__(daemon=True)
        self.x, self.block, self.t0, self.env = x, block, None, env
        self.proc = subprocess.Popen(["pacat", "--playback", f"--device={sink}", f"--rate={RATE}", "--channels=1",
                                      "--format=float32le", "--latency-msec=10", "--raw", "--client-name=feeder"],
                                     stdin=subprocess.PIPE, env=env)

    def ready(self, timeout: float = 30.0) -> None:
        """Wait until the sink has pacat's stream (its client named `feeder`)."""
        deadline = time.monotonic() + timeout
        while b"feeder" not in subprocess.run(["pactl", "list", "sink-inputs"], env=self.env,
                                              capture_output=True).stdout:
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"pacat did not connect to the virtual microphone (exit {self.proc.poll()})")
            time.sleep(0.05)

    def run(self):
        self.t0 = time.monotonic() + 0.05
        for k in range(0, len(self.x), self.block):
            wait = self.t0 + k / RATE - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            self.proc.stdin.write(self.x[k : k + self.block].astype("<f4").tobytes())
            self.proc.stdin.flush()
        self.proc.stdin.close()
        self.proc.wait(10)


class TappedSource:
    """The server's microphone source, unchanged, keeping what it yields (stream time, samples, arrival); calls
    `on_first()` when it has the first chunk (the microphone is capturing)."""

    def __init__(self, source, on_first=None):
        self.source, self.chunks, self.on_first = source, [], on_first

    def __getattr__(self, name):
        return getattr(self.source, name)

    async def __aiter__(self):
        async for chunk in self.source:
            self.chunks.append(chunk)
            if len(self.chunks) == 1 and self.on_first:
                self.on_first()
            yield chunk


class WindowStamps:
    """A sink beside VMC: when each window's frames were handed to the sinks, and that window's `WindowTiming`."""

    def __init__(self, session):
        self.session, self.windows = session, []

    async def open(self) -> None:
        pass

    def send(self, frames) -> None:
        if frames and self.session.stats.window is not None:
            self.windows.append({"first": frames[0].index, "frames": len(frames), "sent_s": time.monotonic(),
                                 **vars(self.session.stats.window)})

    async def close(self, drain: bool = True) -> None:
        pass

    def describe(self) -> str:
        return ""

    def status(self) -> str:
        return ""


def run_vmc(a, tmp: Path) -> dict:
    """The server in this process (its source and sinks watched from inside: the stream's clock and
    time.monotonic are the server's own), the virtual microphone playing the stimulus, a UDP receiver."""
    import asyncio

    import pytest
    from helpers.udp_capture import UdpCapture
    from helpers.virtual_mic import missing, virtual_mic

    if why := missing():
        return {"skipped": f"no virtual microphone: {why}"}
    x, file_onsets = stimulus(a.seconds)
    udp = UdpCapture()
    bundles: list[tuple[float, float]] = []
    udp.on_datagram = lambda data, at: bundles.extend((t, at) for t in osc_times(data))
    udp.start()
    try:
        with virtual_mic(tmp / "vmic") as vmic:
            import sounddevice

            os.environ.update(vmic.env)  # PortAudio in this process must find this PulseAudio: start it again
            sounddevice._terminate()
            sounddevice._initialize()
            from dimgestor_app.cli import build_parser
            from streamer.options import ServeOptions
            from streamer.server import build, run

            argv = ["serve", *serve_args(a, "mic"), "--input-device", "pulse", "--rate", str(RATE), "--no-ws",
                    "--vmc", f"127.0.0.1:{udp.port}", "--max-seconds", str(a.seconds + 1)]
            if a.vmc_jitter_ms is not None:
                argv += ["--vmc-jitter-ms", str(a.vmc_jitter_ms)]
            args = vars(build_parser().parse_args(argv))
            p = build(ServeOptions.parse(**{k: v for k, v in args.items() if k in ServeOptions.model_fields}))
            # The sound starts once pacat is connected and the microphone captures: started earlier, every burst
            # reached the server late by those start-up times (0.8-1.2 s on a loaded machine), counted as capture.
            feeder = Feeder(np.concatenate([np.zeros(RATE // 2, np.float32), x]), vmic.env)
            feeder.ready()
            p.source = TappedSource(p.source, on_first=feeder.start)
            stamps = WindowStamps(p.session)
            p.sinks.insert(0, stamps)
            asyncio.run(run(p))
            if feeder.ident is not None:
                feeder.join(30)
            if feeder.proc.poll() is None:
                feeder.proc.terminate()
    except pytest.skip.Exception as e:
        return {"skipped": str(e)}
    finally:
        udp.stop = True
    hello = {"fps": p.bundle.feature_spec.fps, "lookahead_s": p.session.lookahead_s, "window_ms": a.window_ms}
    if feeder.t0 is None:
        raise RuntimeError("the server's microphone gave no audio: nothing was played")
    played = [feeder.t0 + 0.5 + f for f in file_onsets]
    vmc = next(s for s in p.sinks if hasattr(s, "pacer"))
    if a.raw:
        chunks = [[c.t_start, c.arrival, float(np.abs(c.samples).max())] for c in p.source.chunks]
        write_json(a.raw.with_suffix(".vmc.json"), {"hello": hello, "timings": stamps.windows, "played": played,
                                                    "bundles": bundles, "chunks": chunks})
    return {**analyse_vmc(hello, stamps.windows, p.source.chunks, bundles, played),
            "vmc_jitter_buffer_ms": vmc.jitter_s * 1000, "vmc_sent": vmc.sent, "vmc_dropped": vmc.dropped}


def analyse_vmc(hello: dict, timings: list, chunks: list, bundles: list, played: list[float]) -> dict:
    from dimgestor.audio import SAMPLE_RATE

    fps, lookahead = hello["fps"], hello["lookahead_s"]
    x = np.concatenate([c.samples for c in chunks])
    heard = [chunks[0].t_start + i / SAMPLE_RATE for i in detect_onsets(x, SAMPLE_RATE)]  # on the stream's clock
    sent = {}
    for t, at in bundles:
        sent.setdefault(round(t * fps), at)
    # Each onset heard is the latest one played before the server had it (the capture delay is below a period).
    rows = []
    for p in heard:
        j = math.ceil(p * fps - 1e-9)
        w = next((w for w in timings if w["first"] <= j < w["first"] + w["frames"]), None)
        if w is None or j not in sent or p < WARMUP_S:
            continue
        captured = w["arrived_s"] - (w["audio_until_s"] - p)
        before = [t for t in played if t <= captured]
        if not before:
            continue
        t_played = before[-1]
        E = w["audio_until_s"]
        row = {"pts_s": round(p, 4), "total": (sent[j] - t_played) * 1000,
               "capture": (w["arrived_s"] - (t_played + E - p)) * 1000,
               "lookahead": lookahead * 1000, "frame": (j / fps - p) * 1000, "window": (E - j / fps - lookahead) * 1000,
               "queue": (w["dispatched_s"] - w["arrived_s"]) * 1000,
               "compute": (w["sent_s"] - w["dispatched_s"]) * 1000,
               "pacing": (sent[j] - w["sent_s"]) * 1000}
        row["slack"] = row["total"] - sum(row[k] for k in PARTS["vmc"])
        rows.append({k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()})
    if not rows:
        raise RuntimeError(f"no onset measured ({len(heard)} heard, {len(played)} played, {len(timings)} timings, "
                           f"{len(sent)} frames sent over VMC)")
    for row in rows:  # what the target is about: the server's part, from the onset's arrival to the bundle sent
        row["server_side"] = round(row["total"] - row["capture"], 2)
    transits = [(w["sent_s"] - w["first"] / fps) * 1000 for w in timings if w["first"] / fps >= WARMUP_S]
    return {"onsets": len(rows), "parts": summary(rows, PARTS["vmc"]), "made_jitter_ms": jitter(transits),
            "total": summary(rows, ["total"])["total"],
            "server_side": summary(rows, ["server_side"])["server_side"],
            "slack": summary(rows, ["slack"])["slack"], "lookahead_s": lookahead, "window_ms": hello.get("window_ms"),
            "rows": rows}


# ---------------------------------------------------------------- plot, main

def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bars = [(f"{r['path']}\n{textwrap.fill(r['model'], 22)}\n{r['window_ms']} ms", r) for r in runs if "parts" in r]
    fig, ax = plt.subplots(figsize=(max(4, 1.6 * len(bars) + 2), 4.5))
    keys = list(dict.fromkeys(k for _, r in bars for k in r["parts"]))
    colors = plt.cm.tab10(np.linspace(0, 1, 10))
    for i, (label, r) in enumerate(bars):
        bottom = 0.0
        for c, k in enumerate(keys):
            v = r["parts"].get(k, {}).get("median_ms", 0.0)
            ax.bar(i, v, bottom=bottom, color=colors[c % 10], label=k if i == 0 or k not in PARTS["talk"] else None)
            bottom += v
        ax.plot([i - 0.4, i + 0.4], [r["total"]["median_ms"]] * 2, "k-", lw=2)
        ax.text(i, r["total"]["median_ms"] + 8, f"{r['total']['median_ms']:.0f}", ha="center", fontsize=8)
    handles, labels = ax.get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    ax.legend(uniq.values(), uniq.keys(), fontsize=7, loc="upper left", bbox_to_anchor=(1, 1))
    ax.set_xticks(range(len(bars)), [b for b, _ in bars], fontsize=7)
    ax.set_ylabel("ms (median per part; black: median total)")
    ax.axhline(400, color="r", ls="--", lw=0.8)
    ax.set_title("speech -> motion latency by part", fontsize=9)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", help="checkpoint directory (default: the embedded default model)")
    ap.add_argument("--name", default=None, help="the model's name in the results (default: the checkpoint's)")
    ap.add_argument("--window-ms", type=int, default=100)
    ap.add_argument("--steps", type=int, default=None, help="DDIM steps K (default: the checkpoint's)")
    ap.add_argument("--seconds", type=float, default=40.0, help="how long each path runs")
    ap.add_argument("--paths", nargs="+", default=["talk", "vmc"], choices=["talk", "vmc"])
    ap.add_argument("--vmc-jitter-ms", type=float, default=None, help="passed to the server (default: its own)")
    ap.add_argument("--page-size", default="480,320", help="the browser window (software WebGL draws every pixel "
                                                           "on the CPU: a large page is slow on a small machine)")
    ap.add_argument("--avatar", default="mannequin", choices=["mannequin", "skeleton"],
                    help="the viewer's look while talking (its Avatar menu; the skeleton is far cheaper to draw)")
    ap.add_argument("--note", default=None, help="a remark stored with each run (e.g. what was changed)")
    ap.add_argument("--raw", type=Path, help="also write the talk path's raw stamps here (to re-analyse)")
    ap.add_argument("--out", type=Path, required=True, help="JSON to write; merged with it when it exists (one "
                                                            "entry per path, model and window); the plot beside it")
    a = ap.parse_args(argv)
    name = a.name or (Path(a.checkpoint).name if a.checkpoint else "default")
    previous = json.loads(a.out.read_text()) if a.out.exists() else {"runs": []}
    runs = previous["runs"]
    for path in a.paths:
        load = load_average()
        with tempfile.TemporaryDirectory(prefix="latency-") as tmp:
            r = (run_talk if path == "talk" else run_vmc)(a, Path(tmp))
        r = {"path": path, "model": name, "checkpoint": a.checkpoint, "window_ms": a.window_ms, "steps": a.steps,
             "avatar": a.avatar if path == "talk" else None,
             "seconds": a.seconds, "vmc_jitter_ms": a.vmc_jitter_ms if path == "vmc" else None,
             "note": a.note, "device": describe_device("cpu"), "code_version": code_version(), "date": utc_now(),
             "load_avg_before": load, "load_avg_after": load_average(), **r}
        if "skipped" in r:
            print(f"{path}: skipped: {r['skipped']}")
        else:
            print(f"{path} {name} {a.window_ms} ms: total {r['total']}"
                  + (f" (server side {r['server_side']})" if "server_side" in r else "")
                  + f" over {r['onsets']} onsets; "
                  + ", ".join(f"{k} {v['median_ms']}" for k, v in r["parts"].items()))
        runs = [x for x in runs if (x["path"], x["model"], x["window_ms"]) != (path, name, a.window_ms)] + [r]
    write_json(a.out, {"benchmark": "latency", "method": METHOD, "runs": runs})
    plot(runs, a.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
