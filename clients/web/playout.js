// Playout buffer: the server computes motion window by window, so frames arrive in bursts (e.g. 4 frames
// every 200 ms). Showing each on arrival would animate at 5 fps; instead every frame is shown at its own
// presentation time, pts + offset on the local clock, interpolating between neighbours (root: linear,
// rotations: slerp). The same rules are in DimgestorPlayout.cs and DimgestorPlayout.h.
//
// offset is set when a stream starts (first frame shown `delay` seconds after it arrived), grows when a
// frame arrives too late to be shown on time, and shrinks when more than 2 x delay is buffered (so a
// server that caught up after a stall does not leave the viewer behind for good).
//
// The web viewer plays the source's sound too, and sound cannot jump at every late burst: it keeps the queue
// and interpolation here but takes its clock from av-clock.js (picture and sound on one clock, a jitter
// buffer sized from the lateness seen) through sampleAt(pts).
//
// A frame's face (revision 7) is interpolated with its pose at the same moment (linear per weight, face.js), so the
// face shown is always that of the pose shown.
import { lerpFace } from './face.js';

const MAX_QUEUE = 256;
const LATE_MARGIN_S = 0.02;

export class FramePlayout {
  constructor(delayS = 0.3) {
    this.delayS = delayS;
    this.queue = [];      // frames waiting or showing, in pts order
    this.offset = null;   // local seconds minus pts
    this.reanchors = 0;   // times the clock was moved because frames came late or piled up
  }

  /** Add a frame that arrived at local time `now` (seconds). */
  push(frame, now) {
    const last = this.queue[this.queue.length - 1];
    if (this.offset === null || (last && (frame.index < last.index || frame.pts <= last.pts))) {
      this.queue = [];    // a new stream (own audio session, --loop, reconnect): start its clock afresh
      this.offset = now - frame.pts + this.delayS;
    } else if (now - this.offset > frame.pts) {
      this.offset = now - frame.pts + LATE_MARGIN_S;  // late: show it now, and keep that much more buffer
      this.reanchors++;
    } else if (frame.pts - (now - this.offset) > 2 * this.delayS) {
      this.offset = now - frame.pts + this.delayS;    // too much buffered: catch up
      this.reanchors++;
    }
    this.queue.push(frame);
    if (this.queue.length > MAX_QUEUE) this.queue.shift();
  }

  /** The pose to show at local time `now`: {pts, index, root, rotations, face}, interpolated; null before any
   *  frame. (face: null when the frames carry none.) */
  sample(now) {
    return this.queue.length ? this.sampleAt(now - this.offset) : null;
  }

  /** The pose at presentation time `t` (for a clock kept outside, e.g. av-clock.js); null before any frame. */
  sampleAt(t) {
    const q = this.queue;
    if (!q.length) return null;
    while (q.length > 1 && q[1].pts <= t) q.shift();  // keep the last frame at or before t
    const a = q[0];
    const b = q[1];
    if (!b || t <= a.pts || b.rotations.length !== a.rotations.length) {
      return { pts: a.pts, index: a.index, root: a.root, rotations: a.rotations, face: a.face || null };  // hold
    }
    const u = (t - a.pts) / (b.pts - a.pts);
    return {
      pts: t, index: a.index,
      root: a.root.map((v, i) => v + (b.root[i] - v) * u),
      rotations: a.rotations.map((qa, j) => slerp(qa, b.rotations[j], u)),
      face: lerpFace(a.face, b.face, u),
    };
  }
}

/** Spherical interpolation of unit quaternions [w, x, y, z], along the shorter arc. */
export function slerp(a, b, u) {
  let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
  const s = dot < 0 ? -1 : 1;  // q and -q are the same rotation: take the nearer one
  dot *= s;
  let wa, wb;
  if (dot > 0.9995) { wa = 1 - u; wb = u; }  // nearly equal: linear is exact enough and avoids 0/0
  else {
    const th = Math.acos(dot), sin = Math.sin(th);
    wa = Math.sin((1 - u) * th) / sin;
    wb = Math.sin(u * th) / sin;
  }
  const r = [0, 1, 2, 3].map((i) => wa * a[i] + wb * s * b[i]);
  const n = Math.hypot(r[0], r[1], r[2], r[3]);
  return r.map((v) => v / n);
}
