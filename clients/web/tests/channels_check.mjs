// Test driver: recorded server messages (NNNNNN.json / NNNNNN.bin in a folder, as clients/python/client.py --save
// keeps them) decoded as the socket worker does (protocol.js, binary frames laid out by the hello) and passed
// through a FrameRing made from the hello, as the page reads them; tests/test_clients_channels.py checks the output.
// usage: node channels_check.mjs FOLDER   Prints one JSON line per frame: {file, index, rotations, channels, ring}.
import { readdirSync, readFileSync } from 'node:fs';
import { join } from 'node:path';
import { decodeBinaryFrame } from '../protocol.js';
import { FrameRing } from '../frame-ring.js';

const folder = process.argv[2];
let hello = null, ring = null;
for (const name of readdirSync(folder).sort()) {
  const bytes = readFileSync(join(folder, name));
  let f;
  if (name.endsWith('.bin')) f = decodeBinaryFrame(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.length), hello);
  else {
    const msg = JSON.parse(bytes.toString('utf8'));
    if (msg.type === 'hello') { hello = msg; ring = FrameRing.create(msg.skeleton.joints.length, msg.channels); continue; }
    if (msg.type !== 'frame') continue;
    f = msg;
  }
  ring.write(f, name.endsWith('.bin'), 0);
  const [[back]] = ring.take();
  console.log(JSON.stringify({ file: name, index: f.index, rotations: f.rotations, channels: f.channels || null,
                               ring: back.channels || null }));
}
