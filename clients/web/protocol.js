// Protocol v1 helpers without DOM or three.js, so they also run under node (clients/web/tests/).

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
