// Test driver: FrameRing (../frame-ring.js) between a writer and a reader that share its memory, as the socket
// worker and the page do; tests/test_clients_web.py checks the output.
// usage: node frame_ring_check.mjs JOINTS SCRIPT   (lines: "write N" frames written from the next index | "take")
// Prints one JSON line per take: {frames: [{index, pts, root, rotations}], at: [...], binary: [...]}; and one
// {event: "misfit", written} for a frame of the wrong joint count (the writer must refuse it).
import { readFileSync } from 'node:fs';
import { FrameRing } from '../frame-ring.js';

const joints = Number(process.argv[2]);
const writer = FrameRing.create(joints);
const reader = new FrameRing(writer.sab, joints);  // the page's view of the same memory
let next = 0;
const frame = (i, n) => ({ index: i, pts: i / 20, root: [i, -i, 0.5],
                           rotations: Array.from({ length: n }, (_, j) => [1, j, -i, 0.25]) });
for (const line of readFileSync(process.argv[3], 'utf8').split('\n')) {
  const [op, a] = line.trim().split(/\s+/);
  if (op === 'write') for (let k = 0; k < Number(a); k++, next++) writer.write(frame(next, joints), next % 2 === 1, 1000 + next);
  else if (op === 'misfit') console.log(JSON.stringify({ event: 'misfit', written: writer.write(frame(next, joints + 1), false, 0) }));
  else if (op === 'take') {
    const got = reader.take();
    console.log(JSON.stringify({ event: 'take', frames: got.map(([f]) => f), at: got.map(([, at]) => at),
                                 binary: got.map(([, , b]) => b) }));
  }
}
