"""What a page plays against what it shows: a recorder on the page's sound output, the frame on screen with
the audio clock at that moment, what the page scheduled to play, and the comparisons of the recorded sound with
them (the sound is what the page scheduled of the source, the source time heard at each read, late arrivals a
playout clock cannot hide)."""

from __future__ import annotations

import numpy as np

# Records what the page's sound output plays (its master gain node), sample by sample, with the context frame
# of each render quantum: an AudioWorklet on the page's own AudioContext.
RECORDER = """(async () => {
  const audio = window.dimgestor.sourceAudio, ctx = audio.context();
  const code = `registerProcessor('rec', class extends AudioWorkletProcessor {
    process(inputs) { const x = inputs[0][0]; this.port.postMessage({frame: currentFrame, x: x ? x.slice() : null,
                      n: 128}); return true; } });`;
  await ctx.audioWorklet.addModule(URL.createObjectURL(new Blob([code], {type: 'text/javascript'})));
  const node = new AudioWorkletNode(ctx, 'rec');
  window.rec = {start: null, blocks: []};
  node.port.onmessage = (e) => { if (window.rec.start === null) window.rec.start = e.data.frame;
                                 window.rec.blocks.push(e.data); };
  audio.gain.connect(node);
  node.connect(ctx.destination);
  return ctx.sampleRate;
})()"""

RECORDING = """(() => {
  const r = window.rec, n = r.blocks.length ? r.blocks[r.blocks.length - 1].frame + 128 - r.start : 0;
  const pcm = new Int16Array(n);
  for (const b of r.blocks) if (b.x) for (let i = 0; i < b.x.length; i++)
    pcm[b.frame - r.start + i] = Math.max(-32768, Math.min(32767, Math.round(b.x[i] * 32767)));
  let s = ''; const u8 = new Uint8Array(pcm.buffer);
  for (let i = 0; i < u8.length; i += 8192) s += String.fromCharCode(...u8.subarray(i, i + 8192));
  const missed = [];  // [from, to) frames of the recording where the recorder got no block (its thread starved)
  for (let i = 1; i < r.blocks.length; i++) if (r.blocks[i].frame > r.blocks[i - 1].frame + 128)
    missed.push([r.blocks[i - 1].frame + 128 - r.start, r.blocks[i].frame - r.start]);
  return {start: r.start, pcm: btoa(s), missed};
})()"""


# A read of the frame on screen: its pts, and where the audio context's output was when the page picked it.
# `out` is that context time as the browser's output timestamp puts it (the context time at the output and the page
# time it is heard there, extrapolated to the pick); `t - lat - drawing` says the same from the context's current
# time read later (null `out`: the browser gives no timestamp). The timestamp is the better of the two on a loaded
# machine: the audio thread renders late there, its current time stands behind the page's clock by as much, and a
# read from it puts the heard sound earlier than it was (CI saw reads 0.06-0.13 s off that way, all one sign).
SHOWN_NOW = """new Promise((done) => requestAnimationFrame(() => {
  const c = window.dimgestor.sourceAudio.ctx;
  const k = window.dimgestor.clock;
  const ts = c.getOutputTimestamp ? c.getOutputTimestamp() : null;
  const shownAt = window.dimgestor.shownAt;
  done({t: c.currentTime, lat: c.outputLatency || 0, pts: window.dimgestor.shownFrame.pts,
        drawing: performance.now() / 1000 - shownAt, jumps: k.catchUps + k.underruns, held: k.holdAt !== null,
        out: ts && ts.performanceTime > 0 ? ts.contextTime + shownAt - ts.performanceTime / 1000 : null});
}))"""


def heard_pts(played: np.ndarray, idx: int, source: np.ndarray, near: float, search_s: float = 2.0) -> float | None:
    """The source time (s, on the looped clip's clock) that `played` has around index idx (16 kHz), looked for
    within `search_s` of `near`; None where it is silent or matches nothing well."""
    from scipy.signal import correlate

    half = 800  # 50 ms each side
    seg = played[idx - half : idx + half] if idx >= half else np.zeros(0, np.float32)
    if len(seg) < 2 * half or np.sqrt(np.mean(seg**2)) < 0.02:
        return None
    lo = int((near - search_s) * 16000) - half
    ext = np.take(source, np.arange(lo, lo + int(2 * search_s * 16000) + 2 * half), mode="wrap")
    energy = np.convolve(ext**2, np.ones(2 * half), "valid")
    corr = correlate(ext, seg, mode="valid", method="fft") / (np.linalg.norm(seg) * np.sqrt(energy) + 1e-9)
    k = int(np.argmax(corr))
    return (lo + k + half) / 16000 if corr[k] > 0.8 else None


def steady(samples) -> list[dict]:
    """The SHOWN_NOW reads where the clock was going: not holding (nothing plays then, by design), and neither
    caught up nor held since the read before (recovering from a stall, counted apart; a hold that began before
    the read before and ended since counts too (the underrun counter moved before that read, so only the read
    before's `held` tells). CI saw one read 0.9 s off among 18 within 9 ms in a run with 4 underruns.)"""
    return [s for prev, s in zip([None] + samples[:-1], samples)
            if not s.get("held") and (prev is None or (s["jumps"] == prev["jumps"] and not prev.get("held")))]


def voiced_at(source: np.ndarray, pts: float, level: float = 0.05) -> bool:
    """Whether the looped clip (16 kHz) speaks clearly within 50 ms of `pts` (s)."""
    k = int(pts * 16000)
    return float(np.sqrt(np.mean(np.take(source, np.arange(k - 800, k + 800), mode="wrap") ** 2))) > level


def missed16(rec: dict, rate: int) -> list[tuple[int, int]]:
    """The stretches (16 kHz indices) the recorder missed: no block came for them, so they read as silence."""
    return [(int(a * 16000 / rate), int(b * 16000 / rate)) for a, b in rec.get("missed", [])]


def recorded_around(missed: list[tuple[int, int]], idx: int, half: int = 1600) -> bool:
    """Whether the recorder missed nothing within `half` samples (16 kHz) of idx."""
    return not any(a < idx + half and b > idx - half for a, b in missed)


def heard_index(read: dict, start_s: float) -> int:
    """The index (16 kHz) into the recording, its first sample at context time `start_s`, of what the output played
    when the page picked the frame a SHOWN_NOW read saw."""
    at = read["out"] if read.get("out") is not None else read["t"] - read["lat"] - read.get("drawing", 0)
    return int((at - start_s) * 16000)


def timestamp_minus_current_time(samples) -> list[float]:
    """For each steady read with an output timestamp: where it puts the output at the pick less where the context's
    current time (read later, less the output latency and the page's time since the pick) puts it (s). The two
    estimates of one moment differ by the audio thread's lateness, a little; much more says the timestamp, which
    the page's schedule and this test's reads both go by, is not the output's clock."""
    return [s["out"] - (s["t"] - s["lat"] - s["drawing"]) for s in steady(samples) if s.get("out") is not None]


def shown_minus_heard(samples, played16: np.ndarray, start_s: float, source: np.ndarray,
                      missed: list[tuple[int, int]] = ()) -> list[float]:
    """For each steady SHOWN_NOW read: the pts on screen minus the source time heard when the page picked it (s),
    found from the recorded sound (`played16`, 16 kHz, its first sample at context time `start_s`); silent moments
    left out. (The time the page then took to draw it is the renderer's: on a starved machine SwiftShader takes
    0.1 s and more.) Reads left out too: where the recorder missed blocks (`missed`, from missed16) between the
    pick and the read, or around what was heard. There the audio context skipped render quanta, so its clock
    jumped ahead of the page's between the two, and "the context time of the pick" (the read's time less the
    page's time since the pick) lands as far after what was really heard as the skip was long."""
    sync = []
    for s in steady(samples):
        read_idx = int((s["t"] - s["lat"] - start_s) * 16000)
        heard_idx = heard_index(s, start_s)  # index into played16
        if any(a < max(read_idx, heard_idx) + 800 and b > min(read_idx, heard_idx) - 800 for a, b in missed):
            continue
        heard = heard_pts(played16, heard_idx, source, near=s["pts"])
        if heard is not None:
            sync.append(s["pts"] - heard)
    return sync


def late_arrivals(log, margin_s: float, window_s: float = 10.0, apart_s: float = 1.0) -> int:
    """How often frames came later than every frame of the `window_s` before them by more than `margin_s`
    (transit = arrival - pts, as the page's playout clock sees it): the stalls a playout clock cannot hide,
    late frames less than `apart_s` after the last one counting as one. log: [arrival s, pts] in arrival order."""
    events, last, seen = 0, -float("inf"), []
    for arrival, pts in log:
        transit = arrival - pts
        seen = [(a, t) for a, t in seen if a >= arrival - window_s]
        if seen and transit > max(t for _, t in seen) + margin_s:
            events += arrival - last > apart_s
            last = arrival
        seen.append((arrival, transit))
    return events


# What the page scheduled to play, piece by piece (source-audio.js `played`): where each piece starts on the
# audio context's clock, the pts it starts at, how long it plays, what of it the page skipped because it came
# late, and when it was stopped.
PLAYED = "window.dimgestor.sourceAudio.played"
STOP_TAKES_S = 0.03  # how long after the page's `stop()` (its context time then) the sound may still play
START_TAKES_S = 0.1  # a piece scheduled less than this ahead may start later than the page asked: the audio
#                      thread hears of it late on a loaded machine (seen: 50 ms asked 5 ms ahead, as 0.86 correlation)


def streams(pieces: list[dict]) -> list[list[dict]]:
    """The pieces split where the pts starts over (a new stream: a second drop): back by more than a second (as
    source-audio.js tells a new audio clock) to within a second of where the stream began. A stream whose clock
    moved (a hold, a catch-up) is scheduled again from the pts heard then: back by as much as the page had
    scheduled ahead (seconds, where the frames run ahead), but not to the stream's start; it stays one stream."""
    out: list[list[dict]] = []
    for p in pieces:
        start = p["pts"] - p["late"]
        if not out or (start < out[-1][-1]["pts"] + out[-1][-1]["dur"] - 1.0
                       and start < out[-1][0]["pts"] - out[-1][0]["late"] + 1.0):
            out.append([])
        out[-1].append(p)
    return out


def as_scheduled(pieces: list[dict], start_s: float, n: int, source: np.ndarray, wrap: bool = False,
                 edge: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the pieces make at 16 kHz over `n` samples of a recording whose first sample is at context time
    `start_s`, where that is certain: not within `edge` samples of a piece's start or end (the output
    interpolates across them), nor where a stopped piece may still play (STOP_TAKES_S after the page's stop), nor
    where a piece scheduled less than START_TAKES_S ahead may play (it may start that much later); and where a
    piece plays."""
    expected, unsure, covered = np.zeros(n, np.float32), np.zeros(n, bool), np.zeros(n, bool)
    for p in pieces:
        if p["dur"] <= 0:
            continue
        a = round((p["at"] - start_s) * 16000)
        b = round((p["at"] + p["dur"] - start_s) * 16000)
        if p["stop"] is not None and p["stop"] < p["at"] + p["dur"]:
            stop = round((p["stop"] - start_s) * 16000)
            b = min(b, stop + round(STOP_TAKES_S * 16000))
            unsure[max(0, stop) : max(0, b)] = True
        if b <= max(a, 0) or a >= n:
            continue
        k = round(p["pts"] * 16000)
        idx = np.arange(k, k + b - a)
        piece = np.take(source, idx, mode="wrap") if wrap else np.where(idx < len(source),
                                                                       source[np.clip(idx, 0, len(source) - 1)], 0)
        lo, hi = max(a, 0), min(b, n)
        expected[lo:hi] += piece[lo - a : hi - a]
        covered[lo:hi] = True
        if p.get("ahead", np.inf) < START_TAKES_S:
            unsure[lo : max(0, b + round(START_TAKES_S * 16000))] = True
        unsure[max(0, a - edge) : max(0, a + edge)] = True
        unsure[max(0, b - edge) : max(0, b + edge)] = True
    return expected, ~unsure, covered


def assert_played_as_scheduled(played16: np.ndarray, start_s: float, pieces: list[dict], source: np.ndarray,
                               t0: float, seconds: float, missed: list[tuple[int, int]] = (), wrap: bool = False
                               ) -> float:
    """What the recording holds from context time t0 on, until `seconds` of scheduled sound have been compared
    (or to its end), is what the page scheduled there: the source's audio at each piece's pts, at the piece's
    time, and silence between pieces (the page's holds, its catch-ups and what it skipped for coming late are all
    in `pieces`). Compared where that is certain (as_scheduled) and the recorder got every block (`missed`, from
    missed16). Returns the correlation."""
    expected, sure, covered = as_scheduled(pieces, start_s, len(played16), source, wrap)
    for m0, m1 in missed:
        sure[max(0, m0 - 128) : max(0, m1 + 128)] = False
    a = max(0, round((t0 - start_s) * 16000))
    counted = np.cumsum(sure[a:] & covered[a:])
    b = a + (int(np.searchsorted(counted, round(seconds * 16000))) + 1 if counted[-1] >= seconds * 16000 else
             len(counted))
    x, e = played16[a:b][sure[a:b]], expected[a:b][sure[a:b]]
    t1 = start_s + b / 16000
    assert counted[b - a - 1] >= min(seconds * 16000, 0.25 * (b - a)), (
        f"too little of {t0:.2f}-{t1:.2f} s was recorded and certain to compare ({counted[b - a - 1] / 16000:.2f} s)")
    assert np.linalg.norm(e) > 0, f"the page scheduled no sound at {t0:.2f}-{t1:.2f} s"
    corr = float(np.dot(x, e) / (np.linalg.norm(x) * np.linalg.norm(e) + 1e-9))
    gain = float(np.dot(x, e) / (np.dot(e, e) + 1e-9))
    print(f"played {t0 - start_s:.3f}-{t1 - start_s:.3f} s of the recording: as scheduled with "
          f"correlation {corr:.3f}, gain {gain:.2f}, over {len(x) / 16000:.2f} s")
    assert corr > 0.9 and 0.5 < gain < 2.0, (
        f"the played sound is not what the page scheduled (correlation {corr:.2f}, gain {gain:.2f})")
    return corr
