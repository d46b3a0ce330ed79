// Test driver: AudioFlow (../audio-flow.js) on a script of events; tests/test_clients_web.py checks the output.
// usage: node audio_flow_check.mjs RATE HOLD_S SCRIPT   (lines: "chunk ID SAMPLES" | "slow_down" | "resume")
// Prints one JSON line per event: {event, sent: [IDs sent now], paused, held_s, dropped_s, dropped_chunks}.
import { readFileSync } from 'node:fs';
import { AudioFlow } from '../audio-flow.js';

const flow = new AudioFlow(Number(process.argv[2]), Number(process.argv[3]));
for (const line of readFileSync(process.argv[4], 'utf8').split('\n')) {
  const [op, a, b] = line.trim().split(/\s+/);
  if (!op) continue;
  const sent = op === 'chunk' ? flow.offer(a, Number(b)) : op === 'slow_down' ? (flow.slowDown(), []) : flow.resume();
  console.log(JSON.stringify({ event: op, sent, paused: flow.paused, held_s: flow.heldS, dropped_s: flow.droppedS,
                               dropped_chunks: flow.droppedChunks, pauses: flow.pauses, resumes: flow.resumes }));
}
