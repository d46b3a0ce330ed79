// Test driver: SpeechToMotion (../latency.js) on a script of events; tests/test_clients_web_latency.py checks it.
// usage: node latency_check.mjs SCRIPT   (lines: "said PTS AT" | "pong SENT_AT NOW SERVER_S" |
//                                          "timing AUDIO_UNTIL_S ARRIVED_S" | "total OFFSET PAGE_FRAME_S NOW")
// Prints one JSON line per event: {event, total_ms (total only), server_offset, timing_used (timing only)}.
import { readFileSync } from 'node:fs';
import { SpeechToMotion } from '../latency.js';

const s = new SpeechToMotion();
for (const line of readFileSync(process.argv[2], 'utf8').split('\n')) {
  const [op, ...args] = line.trim().split(/\s+/);
  if (!op) continue;
  const [a, b, c] = args.map(Number);
  const out = { event: op };
  if (op === 'said') s.noteSaid(a, b);
  else if (op === 'pong') s.notePong(a, b, c);
  else if (op === 'timing') out.timing_used = s.noteTiming({ audio_until_s: a, arrived_s: b });
  else if (op === 'total') out.total_ms = s.totalMs(a, b, c);
  out.server_offset = s.serverOffset;
  console.log(JSON.stringify(out));
}
