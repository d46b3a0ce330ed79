// The server source's audio (DGA1 messages, docs/protocol.md) played through Web Audio in sync with the motion.
//
// Frames are shown at local time pts + offset (playout.js). Audio chunks carry the pts of their first sample, so
// chunk k is scheduled to be *heard* at pts_k + offset: the AudioContext's output timestamp maps the page's clock
// to the context's. Consecutive chunks are butted together (no clicks from clock jitter) unless the mapping moved
// by more than RESYNC_S; when the playout clock jumps (late frames, pause) everything is rescheduled.
const RESYNC_S = 0.03;
const KEEP_S = 10;     // audio kept after its time (for rescheduling after a clock jump), seconds

export class SourceAudio {
  constructor() {
    this.ctx = null;
    this.gain = null;
    this.chunks = [];     // {pts, end, buffer}, in pts order
    this.playing = [];    // {src, chunk}
    this.next = null;     // context time where the last scheduled chunk ends
    this.offset = null;   // the playout offset the schedule was made for
    this.muted = false;
    this.paused = false;
    this.chunksReceived = 0;
    this.samplesScheduled = 0;
  }

  /** The AudioContext, created on first use (browsers start it suspended without a user gesture). */
  context() {
    if (!this.ctx) {
      this.ctx = new AudioContext({ latencyHint: 'interactive' });
      this.gain = this.ctx.createGain();
      this.gain.gain.value = this.muted ? 0 : 1;
      this.gain.connect(this.ctx.destination);
    }
    return this.ctx;
  }

  /** Resume after a user gesture; true when sound can play. */
  async unlock() {
    const ctx = this.context();
    if (ctx.state === 'suspended' && !this.paused) {
      await ctx.resume().catch(() => {});
      this.reset();  // the context's clock stood still while suspended: schedule afresh
    }
    return ctx.state === 'running';
  }

  get blocked() { return !!this.ctx && this.ctx.state === 'suspended' && !this.paused; }

  setMuted(muted) {
    this.muted = muted;
    if (this.gain) this.gain.gain.setTargetAtTime(muted ? 0 : 1, this.ctx.currentTime, 0.01);
  }

  async setPaused(paused) {
    this.paused = paused;
    if (!this.ctx) return;
    if (paused) await this.ctx.suspend();
    else { await this.ctx.resume().catch(() => {}); this.reset(); }
  }

  /** A decoded DGA1 chunk {rate, pts, samples (Float32Array)}. */
  push(chunk) {
    const ctx = this.context();
    const buffer = ctx.createBuffer(1, chunk.samples.length, chunk.rate);
    buffer.copyToChannel(chunk.samples, 0);
    const c = { pts: chunk.pts, end: chunk.pts + chunk.samples.length / chunk.rate, buffer };
    const last = this.chunks[this.chunks.length - 1];
    if (last && c.pts < last.pts - 1) this.clear();  // the source started over: a new audio clock
    this.chunks.push(c);
    this.chunksReceived++;
    if (this.offset !== null) this.schedule(c);
  }

  /** Forget everything (a new stream or connection). */
  clear() {
    this.stopAll();
    this.chunks = [];
    this.offset = null;
  }

  stopAll() {
    for (const p of this.playing) { try { p.src.stop(); } catch (e) { /* already ended */ } p.src.disconnect(); }
    this.playing = [];
    this.next = null;
  }

  reset() { this.stopAll(); if (this.offset !== null) this.chunks.forEach((c) => this.schedule(c)); }

  /** Follow the playout clock: `offset` = local seconds minus pts (null: no frames yet). */
  sync(offset, now) {
    if (offset === null) { if (this.offset !== null) { this.stopAll(); this.offset = null; } return; }
    while (this.chunks.length && this.chunks[0].end < now - offset - KEEP_S) this.chunks.shift();
    if (this.offset === null || Math.abs(offset - this.offset) > RESYNC_S) {
      this.offset = offset;
      this.reset();
    }
  }

  /** Context time at which the page's clock (performance.now() seconds) reads `t`, as heard at the output. */
  contextTimeAt(t) {
    const ctx = this.ctx;
    const ts = ctx.getOutputTimestamp ? ctx.getOutputTimestamp() : null;
    if (ts && ts.performanceTime > 0) return ts.contextTime + (t - ts.performanceTime / 1000);
    return ctx.currentTime + (t - performance.now() / 1000) - (ctx.outputLatency || ctx.baseLatency || 0);
  }

  /** The pts being heard now (null when nothing is scheduled). */
  heardPts(now) {
    if (!this.ctx || this.offset === null || !this.playing.length) return null;
    return now - this.offset;
  }

  schedule(c) {
    const ctx = this.ctx;
    if (this.paused || ctx.state === 'closed') return;
    let when = this.contextTimeAt(c.pts + this.offset);
    if (this.next !== null && Math.abs(when - this.next) < RESYNC_S) when = this.next;  // butt-join
    const dur = c.buffer.duration;
    const soonest = ctx.currentTime + 0.005;
    if (when + dur <= soonest) return;  // already past
    const skip = Math.max(0, soonest - when);
    const src = ctx.createBufferSource();
    src.buffer = c.buffer;
    src.connect(this.gain);
    src.start(when + skip, skip);
    const entry = { src, chunk: c };
    this.playing.push(entry);
    src.onended = () => { const i = this.playing.indexOf(entry); if (i >= 0) this.playing.splice(i, 1); };
    this.samplesScheduled += Math.round((dur - skip) * c.buffer.sampleRate);
    this.next = when + dur;
  }
}
