// The one clock that the picture and the server source's sound both follow: at local time `now` (seconds,
// performance.now() / 1000) the pts presented is `now - offset`; frames are sampled there (playout.js) and
// source audio is scheduled to be heard there (source-audio.js).
//
// The offset is a jitter buffer sized from the lateness seen: each frame's transit (arrival - pts) is noted,
// and the offset sits a margin above the largest transit of the last WINDOW_S. When the frame for `now` has not
// come (an underrun: the server fell behind), the clock holds at the newest frame, picture and sound together,
// and resumes once the buffer is rebuilt to the new worst lateness plus the margin (also when the page was busy
// and the clock passed its newest frame unseen: the next frame's arrival tells); underruns that keep coming
// grow the margin. When the lateness has stayed far below the buffer for a whole window (a stall is over), the
// clock catches up; and once REPEAT_S pass without an underrun a grown margin shrinks a step (/ GROW) every
// REPEAT_S back to its base, the buffer with it where the lateness of the last WINDOW_S allows: what underruns
// took is given back, as live use needs. Moves are rare, so the sound does not jump at every late burst, and
// while it holds nothing plays: what is heard at audio time t is always the frame with pts t.
//
// The page schedules sound only when it runs, as far as the horizon: a page busier than that lead (a starved
// machine drawing at 1 fps) comes back after the sound it scheduled has played out, frames and sound there all
// along. That is the page's own lateness, and it holds like an underrun (soundStopped): sound and picture resume
// where the sound stopped, and the time the page came late counts as lateness, so the buffer covers it.
//
// The stream starts at its first frame however long the page took to present it, with a buffer set from the
// frames that came before that. A stream's first message may be the tail of a window (a model that looks ahead
// has only a few frames' audio at first: 2 of 4 with 350 ms), whose frames are later than their pts by less
// than a whole window's first frame will be: the lateness expected is the newest of them plus the burst's span
// (one window less one frame), when that is more than the first's. A busy page learns of arrivals up to one of
// its own frames late (the socket worker has them sooner, but a software-rendered page on a loaded machine draws at
// ~5 fps and reads its messages between drawings), so the start's buffer also holds the page's longest recent
// frame (`pageS`).
const WINDOW_S = 10;       // lateness is remembered this long
const MARGIN_MAX_S = 2;    // the margin grows at most to this
const GROW = 1.5;          // margin x GROW when underruns come within REPEAT_S of each other
const REPEAT_S = 20;
const SLACK_S = 0.5;       // catch up when the buffer exceeds lateness + margin by more than this (and a margin)
const AHEAD_S = 8;         // frames further ahead than margin + this: the clock jumps to them (a fast source;
                           // playout.js keeps 256 frames, 12.8 s at 20 fps). A page that was busy for seconds
                           // when the stream began keeps its start, and catches up by the SLACK_S rule later

export class PlayoutClock {
  /** `baseMarginS`: the buffer above the worst lateness when nothing went wrong (one window + network). */
  constructor(baseMarginS = 0.3) {
    this.baseMarginS = baseMarginS;
    this.slackS = SLACK_S;  // spare buffer kept rather than skipping ahead (setSlack)
    this.burstS = 0;  // frames come in bursts this long (first to last pts): setBursts
    this.pageS = 0;   // the page's longest recent frame interval (s), kept current by the page
    this.startLeadS = 0;  // sound scheduled now is heard this much later at the soonest (the page keeps it current)
    this.reset();
  }

  /** A new stream: forget everything. */
  reset() {
    this.offset = null;       // local seconds minus pts; null before the first frame
    this.firstPts = null;     // the stream's first frame, until it has been presented
    this.firstTransit = null; // and its transit
    this.marginS = this.baseMarginS;
    this.transits = [];       // [arrival, transit] of recent frames (transit = arrival - pts), arrival order
    this.holdAt = null;       // pts the clock stands at while it waits for late frames
    this.newestPts = null;
    this.lastUnderrun = -Infinity;
    this.shrunkAt = -Infinity; // when the margin last shrank a step
    this.changedAt = null;    // when the offset last moved
    this.underruns = 0;
    this.soundHolds = 0;      // of which the page came back too late to go on with the sound (soundStopped)
    this.catchUps = 0;
  }

  setBaseMargin(s) {
    this.marginS = Math.max(this.marginS - this.baseMarginS + s, s);
    this.baseMarginS = s;
  }

  /** Catch up when the buffer has held more than `s` (and a margin) above lateness + margin for WINDOW_S.
   *  Watching with the sound: SLACK_S, as a catch-up skips that much sound. Talking (no sound played back):
   *  small, or spare buffer from the start (the page's slow first frames, `pageS`) stays as latency for good. */
  setSlack(s) { this.slackS = s; }

  /** Frames come in bursts: one inference window of `windowS` seconds, frames `frameS` apart. */
  setBursts(windowS, frameS) { this.burstS = Math.max(0, windowS - frameS); }

  /** The worst transit (seconds) of the frames that arrived in the last WINDOW_S. */
  lateness() {
    let worst = -Infinity;
    for (const [, tr] of this.transits) worst = Math.max(worst, tr);
    return worst;
  }

  /** A frame with `pts` arrived at local time `now`. */
  arrive(pts, now) {
    if (this.newestPts !== null && pts < this.newestPts - 1) this.reset();  // the pts went back: a new stream
    const transit = now - pts;
    this.transits.push([now, transit]);
    while (this.transits.length && this.transits[0][0] < now - WINDOW_S) this.transits.shift();
    // The clock passed the newest frame before this one came, unseen (the page was busy): that was an underrun.
    if (this.offset !== null && this.holdAt === null && this.firstPts === null && now - this.offset > this.newestPts)
      this.underrun(now);
    this.newestPts = this.newestPts === null ? pts : Math.max(this.newestPts, pts);
    if (this.offset === null) { this.firstPts = pts; this.firstTransit = transit; }
    if (this.firstPts !== null) {  // not presented yet: the start's buffer from the frames so far (see above)
      const expected = Math.max(this.firstTransit, transit + this.burstS);
      this.move(expected + this.marginS + Math.min(this.pageS, MARGIN_MAX_S), now);
      return;
    }
    if (this.holdAt !== null) return;
    const ahead = pts - (now - this.offset);
    if (ahead > this.marginS + AHEAD_S) { this.move(transit + this.marginS, now); this.catchUps++; return; }
    // No underrun for REPEAT_S: the margin shrinks a step towards its base, and the buffer with it.
    if (this.marginS > this.baseMarginS && now - Math.max(this.lastUnderrun, this.shrunkAt) > REPEAT_S) {
      this.marginS = Math.max(this.baseMarginS, this.marginS / GROW);
      this.shrunkAt = now;
      const target = this.lateness() + this.marginS;
      if (target < this.offset) { this.move(target, now); this.catchUps++; }
      return;
    }
    // Caught up after a stall: lateness has stayed far below the buffer for a whole window.
    const spare = this.offset - this.lateness() - this.marginS;
    if (spare > Math.max(this.slackS, this.marginS) && now - this.changedAt > WINDOW_S) {
      this.move(this.offset - spare, now);
      this.marginS = Math.max(this.baseMarginS, this.marginS / GROW);
      this.catchUps++;
    }
  }

  move(offset, now) { this.offset = offset; this.changedAt = now; }

  /** The pts to present at local time `now` (null before any frame); holds while the frames are late. */
  time(now) {
    if (this.offset === null) return null;
    if (this.firstPts !== null) {  // the first presentation starts at the first frame, however busy the page was,
      // and where its sound can still be heard from its first sample
      if (now + this.startLeadS - this.offset > this.firstPts) this.move(now + this.startLeadS - this.firstPts, now);
      this.firstPts = null;
    }
    if (this.holdAt !== null) {
      // Resume when the newest lateness (the frames that came during the hold included) has its margin again.
      const offset = now - this.holdAt;
      if (this.newestPts > this.holdAt && offset >= this.lateness() + this.marginS) {
        this.move(offset, now);
        this.holdAt = null;
      } else return this.holdAt;
    }
    const t = now - this.offset;
    if (t > this.newestPts) { this.underrun(now); return this.holdAt; }  // the frame for now has not come
    return t;
  }

  /** Hold at `pts` (the newest frame) until the buffer is rebuilt; underruns in a row grow the margin. */
  underrun(now, pts = this.newestPts) {
    if (now - this.lastUnderrun < REPEAT_S) this.marginS = Math.min(this.marginS * GROW, MARGIN_MAX_S);
    this.lastUnderrun = now;
    this.underruns++;
    this.holdAt = pts;
  }

  /** The sound scheduled up to `pts` had played out when the page came back at `now`, though there was more:
   *  hold there and note `now - pts` as lateness (see above). True when the clock holds for it. */
  soundStopped(pts, now) {
    if (this.offset === null || this.firstPts !== null || this.holdAt !== null || pts >= now - this.offset) return false;
    this.transits.push([now, now - pts]);
    this.soundHolds++;
    this.underrun(now, pts);
    return true;
  }

  /** How far the sound may be scheduled (pts): never past the frames there are, nothing new while holding. */
  horizon() { return this.holdAt !== null ? this.holdAt : this.newestPts; }
}
