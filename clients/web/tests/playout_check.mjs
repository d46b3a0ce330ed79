// Test driver: FramePlayout (../playout.js) on recorded frames and a schedule of arrivals and samples.
// usage: node playout_check.mjs FOLDER SCHEDULE   (schedule lines: "push K T" | "sample T" | "delay S")
// Prints one JSON line per sample; tests/test_clients_playout.py compares the three clients' outputs.
import { readFileSync, readdirSync } from 'node:fs';
import { join } from 'node:path';
import { FramePlayout } from '../playout.js';
import { decodeBinaryFrame } from '../protocol.js';

const [folder, schedule] = process.argv.slice(2);
const frames = readdirSync(folder).sort().flatMap((name) => {
  const bytes = readFileSync(join(folder, name));
  if (name.endsWith('.bin')) return [decodeBinaryFrame(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.length))];
  const msg = JSON.parse(bytes.toString('utf8'));
  return msg.type === 'frame' ? [msg] : [];
});
const playout = new FramePlayout();
for (const line of readFileSync(schedule, 'utf8').split('\n')) {
  const [op, a, b] = line.trim().split(/\s+/);
  if (op === 'delay') playout.delayS = Number(a);
  else if (op === 'push') playout.push(frames[Number(a)], Number(b));
  else if (op === 'sample') {
    const s = playout.sample(Number(a));
    console.log(JSON.stringify(s ? { index: s.index, pts: s.pts, root: s.root, rotations: s.rotations } : null));
  }
}
console.error(`reanchors ${playout.reanchors}`);
