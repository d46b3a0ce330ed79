// Test driver: PlayoutClock (../av-clock.js) on a schedule of frame arrivals and display refreshes.
// usage: node av_clock_check.mjs SCHEDULE
//   (lines: "margin S" | "slack S" | "bursts WINDOW_S FRAME_S" | "page S" | "lead S" | "arrive PTS T" | "time T" | "turn T")
// "turn T" is one turn of the page with sound (viewer.js showPose): the clock read, the sound scheduled up to its
// horizon (the source's audio there all along), a hold where that sound had played out before the turn.
// Prints one JSON line per "time" or "turn" ({t, pts, offset, horizon}) and a last line with the clock's
// counters; tests/test_clients_playout.py checks them.
import { readFileSync } from 'node:fs';
import { PlayoutClock } from '../av-clock.js';

const clock = new PlayoutClock();
let until = null;          // "turn": the pts the sound is scheduled up to (null: nothing scheduled)
let scheduledWith = null;  // and the clock offset it was scheduled with
for (const line of readFileSync(process.argv[2], 'utf8').split('\n')) {
  const [op, a, b] = line.trim().split(/\s+/);
  if (op === 'margin') clock.setBaseMargin(Number(a));
  else if (op === 'bursts') clock.setBursts(Number(a), Number(b));
  else if (op === 'slack') clock.setSlack(Number(a));
  else if (op === 'page') clock.pageS = Number(a);
  else if (op === 'lead') clock.startLeadS = Number(a);
  else if (op === 'arrive') clock.arrive(Number(a), Number(b));
  else if (op === 'time') {
    const pts = clock.time(Number(a));
    console.log(JSON.stringify({ t: Number(a), pts, offset: clock.offset, horizon: clock.horizon() }));
  } else if (op === 'turn') {
    const now = Number(a);
    let pts = clock.time(now);
    if (until !== null && until + scheduledWith <= now && clock.soundStopped(until, now)) pts = clock.time(now);
    if (clock.offset !== scheduledWith) { until = null; scheduledWith = clock.offset; }  // scheduled afresh
    if (pts !== null && clock.horizon() > (until === null ? pts : until)) until = clock.horizon();
    console.log(JSON.stringify({ t: now, pts, offset: clock.offset, horizon: clock.horizon(), until }));
  }
}
console.log(JSON.stringify({ underruns: clock.underruns, soundHolds: clock.soundHolds, catchUps: clock.catchUps,
                             marginS: clock.marginS }));
