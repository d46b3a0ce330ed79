// Speech -> motion, measured: how long after a moment of speech was said its pose is on screen. Without DOM or
// sockets, so it also runs under node (clients/web/tests/).
//
// Every moment of speech has a stream time (its pts) and a local time when it was said. Talking, our own
// microphone chunks tell it (a chunk's last sample was said when the page got it); watching the server's source,
// the server's `timing` messages do (protocol revision 5: when each window's audio had arrived at the server, on
// its clock, related to ours by the pong with the shortest round trip), or else the source audio's arrival. The
// least delayed of the last SAID_S dates the speech (the others were held up on the way: by a busy page, the
// network), as benchmarks/latency.py does. The pose of pts t is presented at local time t + offset (the playout
// clock) and drawn at the page's next frame: on average half a page frame later.
export const SAID_S = 5;
const PONGS_S = 60;  // the best pong of this long relates the clocks (they drift far less than a round trip)

export class SpeechToMotion {
  constructor() { this.reset(); }

  reset() {
    this.said = [];           // [local time (s), local time - pts (s)] of recent speech
    this.serverOffset = null; // server seconds - local seconds, from the best pong
    this.bestRtt = Infinity;
    this.pongs = [];          // [local time, rtt, offset] of the last SAID_S * 4 seconds
  }

  /** A moment of speech at stream time `pts` was said at local time `at` (s). */
  noteSaid(pts, at) {
    this.said.push([at, at - pts]);
    while (this.said.length && this.said[0][0] < at - SAID_S) this.said.shift();
  }

  /** A pong to our ping sent at `sentAt` came at `now` (s) with the server's clock `serverTimeS`. */
  notePong(sentAt, now, serverTimeS) {
    if (typeof serverTimeS !== 'number') return;
    this.pongs.push([now, now - sentAt, serverTimeS - (sentAt + now) / 2]);
    while (this.pongs.length > 1 && this.pongs[0][0] < now - PONGS_S) this.pongs.shift();
    const best = this.pongs.reduce((a, b) => (b[1] < a[1] ? b : a));
    this.bestRtt = best[1];
    this.serverOffset = best[2];
  }

  /** A `timing` message: the audio up to `audio_until_s` had arrived at the server at `arrived_s`. */
  noteTiming(msg) {
    if (this.serverOffset === null || typeof msg.arrived_s !== 'number') return false;
    this.noteSaid(msg.audio_until_s, msg.arrived_s - this.serverOffset);
    return true;
  }

  /** Speech -> motion in ms at local time `now`, for the playout clock's `offset` (local - pts, s) and the page's
   *  mean frame interval `pageFrameS`; null until both are known. */
  totalMs(offset, pageFrameS, now) {
    while (this.said.length && this.said[0][0] < now - SAID_S) this.said.shift();
    if (offset === null || !this.said.length) return null;
    let least = Infinity;
    for (const [, o] of this.said) least = Math.min(least, o);
    return (offset - least + pageFrameS / 2) * 1000;
  }
}
