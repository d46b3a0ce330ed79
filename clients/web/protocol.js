// Protocol v1 (revision 7) helpers without DOM or three.js, so they also run under node (clients/web/tests/).
import { faceFromValues } from './face.js';

/** Decode a DGF1 binary frame: "DGF1" | u32 index | f64 pts | f32[3] root | f32[J*4] wxyz | channels,
 *  little-endian. With the server's `hello`, J is its joint count and each of `hello.channels` (revision 6) is read
 *  at its offset into `channels: {name: [values]}`; bytes past the last listed channel are ignored. Without it,
 *  every byte after the header is a rotation (a frame without channels). `layout`: the channels the frames carry
 *  now when a `channels` message (revision 7) changed them since the hello. The "face" channel is also given as
 *  `face: {label: weight}`, as a JSON frame carries it. */
export function decodeBinaryFrame(buf, hello = null, layout = null) {
  const dv = new DataView(buf);
  const magic = String.fromCharCode(...new Uint8Array(buf, 0, Math.min(4, buf.byteLength)));
  const joints = hello && hello.skeleton && Array.isArray(hello.skeleton.joints) ? hello.skeleton.joints.length : null;
  const channels = Array.isArray(layout) ? layout : (hello && Array.isArray(hello.channels)) ? hello.channels : [];
  const n = joints === null ? (buf.byteLength - 28) / 16 : joints;
  const end = Math.max(28 + 16 * n, ...channels.map((c) => c.offset + 4 * c.size));
  if (magic !== 'DGF1' || buf.byteLength < 28 || !Number.isInteger(n) || buf.byteLength < end)
    throw new Error(`bad binary frame (${buf.byteLength} bytes, magic ${JSON.stringify(magic)})`);
  const rotations = new Array(n);
  for (let j = 0, o = 28; j < n; j++, o += 16)
    rotations[j] = [dv.getFloat32(o, true), dv.getFloat32(o + 4, true), dv.getFloat32(o + 8, true),
                    dv.getFloat32(o + 12, true)];
  const frame = { type: 'frame', index: dv.getUint32(4, true), pts: dv.getFloat64(8, true),
                  root: [dv.getFloat32(16, true), dv.getFloat32(20, true), dv.getFloat32(24, true)], rotations };
  if (channels.length) {
    frame.channels = {};
    for (const c of channels)
      frame.channels[c.name] = Array.from({ length: c.size }, (_, i) => dv.getFloat32(c.offset + 4 * i, true));
    const face = channels.find((c) => c.name === 'face');
    const named = face ? faceFromValues(frame.channels.face, face.labels) : null;
    if (named) frame.face = named;
  }
  return frame;
}

/** The magic of a binary message from the server: "DGF1" (frame) or "DGA1" (source audio). */
export function binaryKind(buf) {
  return buf.byteLength >= 4 ? String.fromCharCode(...new Uint8Array(buf, 0, 4)) : '';
}

/** Decode a DGA1 source-audio message: "DGA1" | u32 rate | f64 pts | i16[n], little-endian. */
export function decodeSourceAudio(buf) {
  if (binaryKind(buf) !== 'DGA1' || buf.byteLength < 16 || (buf.byteLength - 16) % 2 !== 0)
    throw new Error(`bad source audio message (${buf.byteLength} bytes)`);
  const dv = new DataView(buf);
  const n = (buf.byteLength - 16) / 2;
  const samples = new Float32Array(n);
  for (let i = 0; i < n; i++) samples[i] = dv.getInt16(16 + 2 * i, true) / 32767;
  return { rate: dv.getUint32(4, true), pts: dv.getFloat64(8, true), samples };
}
