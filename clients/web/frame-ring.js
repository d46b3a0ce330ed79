// Frames from the socket worker to the page through shared memory (a SharedArrayBuffer: needs a cross-origin
// isolated page), without DOM so it also runs under node (clients/web/tests/). The worker writes each frame into
// the next of SLOTS slots and then advances `head` (Atomics); the page reads the slots from where it stopped up to
// head whenever it draws. A page that fell more than SLOTS frames behind loses the oldest (its frame gaps count
// them). Slot: index, pts, arrival (ms, page clock), flags (1: binary, 2: has a face), root[3], rotations[J][w, x,
// y, z], then the values of each channel of the layout (revision 6: hello.channels, in order; revision 7: a
// `channels` message's), then the face's weights by `faceLabels` (revision 7: a frame's `face`), as float64.
// A ring has one layout: when the frames' channels or face names change the worker makes a new ring.
export const SLOTS = 256;  // 12.8 s at 20 fps
const HEAD = 4;            // fields before the root
const BINARY = 1, FACE = 2;

const slotSize = (joints, channels, faceLabels) =>
  HEAD + 3 + 4 * joints + channels.reduce((n, c) => n + c.size, 0) + faceLabels.length;

export class FrameRing {
  constructor(sab, joints, channels = [], faceLabels = []) {
    this.sab = sab;
    this.joints = joints;
    this.channels = (channels || []).map((c) => ({ name: c.name, size: c.size }));
    this.faceLabels = (faceLabels || []).slice();
    this.slot = slotSize(joints, this.channels, this.faceLabels);
    this.head = new Int32Array(sab, 0, 1);  // frames written so far
    this.x = new Float64Array(sab, 8, SLOTS * this.slot);
    this.read = 0;                          // frames read so far (the page's side)
  }

  /** A ring for frames of `joints` joints, the layout's `channels` and a face of `faceLabels` (the worker's side;
   *  its `sab` goes to the page, which makes its own FrameRing of the same joints, channels and face labels). */
  static create(joints, channels = [], faceLabels = []) {
    const chans = channels || [], labels = faceLabels || [];
    return new FrameRing(new SharedArrayBuffer(8 + 8 * SLOTS * slotSize(joints, chans, labels)), joints, chans, labels);
  }

  /** Whether a frame's face has this ring's names (a frame without a face fits any ring). */
  fitsFace(f) {
    if (!f.face) return true;
    const names = Object.keys(f.face);
    return names.length === this.faceLabels.length && names.every((n, i) => n === this.faceLabels[i]);
  }

  /** Put a frame in (the worker); false when it does not fit the ring's joints or face names (then it goes another
   *  way). */
  write(f, binary, at) {
    if (f.rotations.length !== this.joints || f.root.length !== 3 || !this.fitsFace(f)) return false;
    const n = Atomics.load(this.head, 0);
    const x = this.x;
    let o = (n % SLOTS) * this.slot;
    x[o] = f.index; x[o + 1] = f.pts; x[o + 2] = at; x[o + 3] = (binary ? BINARY : 0) | (f.face ? FACE : 0);
    o += HEAD;
    for (let i = 0; i < 3; i++) x[o++] = f.root[i];
    for (const q of f.rotations) for (let i = 0; i < 4; i++) x[o++] = q[i];
    for (const c of this.channels) {  // a frame without the channel (or with too few values) holds zeros
      const v = (f.channels && f.channels[c.name]) || [];
      for (let i = 0; i < c.size; i++) x[o++] = Number(v[i]) || 0;
    }
    for (const name of this.faceLabels) x[o++] = f.face ? Number(f.face[name]) || 0 : 0;
    Atomics.store(this.head, 0, n + 1);
    return true;
  }

  /** The frames written since the last call (the page), oldest first: [{type, index, pts, root, rotations,
   *  channels?, face?}, at, binary]. Frames overwritten before they were read are skipped. */
  take() {
    const head = Atomics.load(this.head, 0);
    if (head - this.read >= SLOTS) this.read = head - SLOTS + 1;  // (the slot being written next is not read)
    const out = [];
    const x = this.x;
    for (; this.read < head; this.read++) {
      let o = (this.read % SLOTS) * this.slot;
      const f = { type: 'frame', index: x[o], pts: x[o + 1], root: [x[o + 4], x[o + 5], x[o + 6]], rotations: [] };
      const at = x[o + 2], flags = x[o + 3];
      o += HEAD + 3;
      for (let j = 0; j < this.joints; j++, o += 4) f.rotations.push([x[o], x[o + 1], x[o + 2], x[o + 3]]);
      if (this.channels.length) f.channels = {};
      for (const c of this.channels) {
        f.channels[c.name] = Array.from(x.subarray(o, o + c.size));
        o += c.size;
      }
      if (flags & FACE) {
        f.face = {};
        for (const name of this.faceLabels) f.face[name] = x[o++];
      }
      out.push([f, at, (flags & BINARY) !== 0]);
    }
    return out;
  }
}
