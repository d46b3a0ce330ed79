// Test driver: recorded server messages (NNNNNN.json / NNNNNN.bin, as clients/python/client.py --save keeps them)
// read as the socket worker reads them (protocol.js; a `channels` message, revision 7, changes the binary frames'
// layout from the next frame on), passed through a FrameRing as the page reads them (a new ring when the layout or
// the face's names change), then played out (playout.js) at each frame's pts and halfway to the next, and read by the
// avatars (face.js); tests/test_clients_web_face.py checks the output.
// usage: node face_check.mjs FOLDER
// Prints one JSON line per frame: {event: "frame", file, index, face, ring, mouth, vrm}; then one per sample:
// {event: "sample", pts, index, face}.
import { readdirSync, readFileSync } from 'node:fs';
import { join } from 'node:path';
import { decodeBinaryFrame } from '../protocol.js';
import { FrameRing } from '../frame-ring.js';
import { FramePlayout } from '../playout.js';
import { mouthOf, vrmExpressions } from '../face.js';

const folder = process.argv[2];
let hello = null, layout = null, ring = null;
const frames = [];
const newRing = (labels) => { ring = FrameRing.create(hello.skeleton.joints.length, layout, labels); };
for (const name of readdirSync(folder).sort()) {
  const bytes = readFileSync(join(folder, name));
  let f;
  if (name.endsWith('.bin')) f = decodeBinaryFrame(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.length), hello, layout);
  else {
    const msg = JSON.parse(bytes.toString('utf8'));
    if (msg.type === 'hello') { hello = msg; layout = msg.channels; newRing([]); continue; }
    if (msg.type === 'channels') {
      layout = msg.channels;
      const face = layout.find((c) => c.name === 'face');
      newRing(face ? face.labels : ring.faceLabels);
      continue;
    }
    if (msg.type !== 'frame') continue;
    f = msg;
  }
  if (!ring.fitsFace(f)) newRing(Object.keys(f.face));
  if (!ring.write(f, name.endsWith('.bin'), 0)) throw new Error(`${name}: the ring refused the frame`);
  const [[back]] = ring.take();
  frames.push(back);
  console.log(JSON.stringify({ event: 'frame', file: name, index: f.index, face: f.face || null, ring: back.face || null,
                               mouth: mouthOf(back.face), vrm: vrmExpressions(back.face) }));
}
const playout = new FramePlayout();
playout.offset = 0;
playout.queue = frames.slice();
for (let i = 0; i < frames.length; i++) {
  for (const t of i + 1 < frames.length ? [frames[i].pts, (frames[i].pts + frames[i + 1].pts) / 2] : [frames[i].pts]) {
    const s = playout.sampleAt(t);
    console.log(JSON.stringify({ event: 'sample', pts: s.pts, index: s.index, face: s.face }));
  }
}
