// Test driver: PlayoutClock (../av-clock.js) on a schedule of frame arrivals and display refreshes.
// usage: node av_clock_check.mjs SCHEDULE
//   (lines: "margin S" | "slack S" | "bursts WINDOW_S FRAME_S" | "page S" | "arrive PTS T" | "time T")
// Prints one JSON line per "time" ({t, pts, offset, horizon}) and a last line with the clock's counters;
// tests/test_clients_playout.py checks them.
import { readFileSync } from 'node:fs';
import { PlayoutClock } from '../av-clock.js';

const clock = new PlayoutClock();
for (const line of readFileSync(process.argv[2], 'utf8').split('\n')) {
  const [op, a, b] = line.trim().split(/\s+/);
  if (op === 'margin') clock.setBaseMargin(Number(a));
  else if (op === 'bursts') clock.setBursts(Number(a), Number(b));
  else if (op === 'slack') clock.setSlack(Number(a));
  else if (op === 'page') clock.pageS = Number(a);
  else if (op === 'arrive') clock.arrive(Number(a), Number(b));
  else if (op === 'time') {
    const pts = clock.time(Number(a));
    console.log(JSON.stringify({ t: Number(a), pts, offset: clock.offset, horizon: clock.horizon() }));
  }
}
console.log(JSON.stringify({ underruns: clock.underruns, catchUps: clock.catchUps, marginS: clock.marginS }));
