// Protocol v1 (revision 2) helpers without DOM or three.js, so they also run under node (clients/web/tests/).

/** Decode a DGF1 binary frame: "DGF1" | u32 index | f64 pts | f32[3] root | f32[J*4] wxyz, little-endian. */
export function decodeBinaryFrame(buf) {
  const dv = new DataView(buf);
  const magic = String.fromCharCode(...new Uint8Array(buf, 0, Math.min(4, buf.byteLength)));
  if (magic !== 'DGF1' || buf.byteLength < 28 || (buf.byteLength - 28) % 16 !== 0)
    throw new Error(`bad binary frame (${buf.byteLength} bytes, magic ${JSON.stringify(magic)})`);
  const n = (buf.byteLength - 28) / 16;
  const rotations = new Array(n);
  for (let j = 0, o = 28; j < n; j++, o += 16)
    rotations[j] = [dv.getFloat32(o, true), dv.getFloat32(o + 4, true), dv.getFloat32(o + 8, true),
                    dv.getFloat32(o + 12, true)];
  return { type: 'frame', index: dv.getUint32(4, true), pts: dv.getFloat64(8, true),
           root: [dv.getFloat32(16, true), dv.getFloat32(20, true), dv.getFloat32(24, true)], rotations };
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
