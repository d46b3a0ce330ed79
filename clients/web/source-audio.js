// The server source's audio (DGA1 messages, docs/protocol.md) played through Web Audio in sync with the motion.
//
// Picture and sound follow one clock (av-clock.js): the pts presented at local time `now` is `now - offset`.
// Audio chunks carry the pts of their first sample, so the audio of pts p is scheduled to be *heard* at local
// time p + offset: the AudioContext's output timestamp maps the page's clock to the context's. Sound is
// scheduled only as far as the clock's horizon (the newest frame there is), in pieces butted together sample
// for sample, so it never runs ahead of a picture waiting for late frames; when the clock moves (it rebuilt its
// buffer after an underrun, or caught up) the schedule is made afresh from the pts presented now.
const RESYNC_S = 0.03;
const SOONEST_S = 0.005;  // a piece starts no sooner than this after the context's current time
const LEAD_SPARE_S = 0.02; // the page's time from reading the clock to scheduling the sound (leadS)
const KEEP_S = 10;     // audio kept after its time (for rescheduling after a clock move), seconds
const PLAYED_KEPT = 4096; // pieces kept in `played` (about two minutes of sound)

export class SourceAudio {
  constructor() {
    this.ctx = null;
    this.gain = null;
    this.chunks = [];     // {pts, end, rate, buffer}, in pts order
    this.playing = [];    // {src, chunk}
    this.next = null;     // context time where the last scheduled piece ends
    this.until = null;    // pts where the last scheduled piece ends
    this.offset = null;   // the clock offset the schedule was made for
    this.muted = false;
    this.paused = false;
    this.chunksReceived = 0;
    this.samplesScheduled = 0;
    // What was scheduled to play, piece by piece, for whoever checks what was heard (the tests, against a
    // recording): {at: context time it starts, pts: the pts it starts at, dur: s, late: s of it not played at its
    // start because the page came late (a whole piece: dur 0), ahead: s from the context's time then to `at` (the
    // audio thread starts a piece later than `at` if it hears of it after that), stop: context time it was
    // stopped (null: not)}.
    this.played = [];
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
    const c = { pts: chunk.pts, end: chunk.pts + chunk.samples.length / chunk.rate, rate: chunk.rate, buffer };
    const last = this.chunks[this.chunks.length - 1];
    if (last && c.pts < last.pts - 1) this.clear();  // the source started over: a new audio clock
    this.chunks.push(c);
    this.chunksReceived++;
  }

  /** Forget everything (a new stream or connection). */
  clear() {
    this.stopAll();
    this.chunks = [];
    this.offset = null;
  }

  stopAll() {
    const t = this.ctx ? this.ctx.currentTime : null;
    for (const p of this.playing) {
      try { p.src.stop(); } catch (e) { /* already ended */ }
      p.src.disconnect();
      if (p.log.stop === null && t < p.log.at + p.log.dur) p.log.stop = t;
    }
    this.playing = [];
    this.next = null;
    this.until = null;
  }

  /** Schedule afresh from the pts presented now (the context's clock stood still, or the clock moved). */
  reset() { this.stopAll(); }

  /**
   * Follow the shared clock: `offset` = local seconds minus pts (null: no frames yet), `horizon` = the pts
   * the sound may be scheduled up to (the newest frame; while the picture holds, where it holds).
   */
  sync(offset, now, horizon) {
    if (offset === null) { if (this.offset !== null) { this.stopAll(); this.offset = null; } return; }
    while (this.chunks.length && this.chunks[0].end < now - offset - KEEP_S) this.chunks.shift();
    if (this.offset === null || Math.abs(offset - this.offset) > RESYNC_S) {
      this.offset = offset;
      this.stopAll();
    }
    if (this.paused || !this.ctx || this.ctx.state !== 'running') return;
    const from = this.until !== null ? this.until : now - offset;
    if (horizon !== null && horizon > from) this.scheduleRange(from, horizon);
  }

  /** Context time at which the page's clock (performance.now() seconds) reads `t`, as heard at the output. */
  contextTimeAt(t) {
    const ctx = this.ctx;
    const ts = ctx.getOutputTimestamp ? ctx.getOutputTimestamp() : null;
    if (ts && ts.performanceTime > 0) return ts.contextTime + (t - ts.performanceTime / 1000);
    return ctx.currentTime + (t - performance.now() / 1000) - (ctx.outputLatency || ctx.baseLatency || 0);
  }

  /** The pts where the scheduled sound ended, when it has played out though there is sound after it (the page
   *  came back later than the sound it had scheduled lasted: av-clock.js soundStopped); otherwise null. */
  ranOutAt() {
    if (this.next === null || this.paused || !this.ctx || this.ctx.state !== 'running') return null;
    if (this.next > this.ctx.currentTime + SOONEST_S) return null;
    const until = this.until;
    return this.chunks.some((c) => c.end > until + 1e-3) ? until : null;
  }

  /** How much later than local time `now` sound scheduled now can be heard at the soonest (s): the output's
   *  latency, and a little; 0 while no sound plays. */
  leadS(now) {
    if (this.paused || !this.ctx || this.ctx.state !== 'running') return 0;
    return Math.max(0, this.ctx.currentTime + SOONEST_S - this.contextTimeAt(now)) + LEAD_SPARE_S;
  }

  /** The pts being heard now (null when nothing is scheduled). */
  heardPts(now) {
    if (!this.ctx || this.offset === null || !this.playing.length) return null;
    return now - this.offset;
  }

  /** Schedule the audio of pts [from, to) that is there; `until` moves to where the audio there ends. */
  scheduleRange(from, to) {
    for (const c of this.chunks) {
      if (c.end <= from) continue;
      if (c.pts >= to) break;
      // Whole samples of this chunk: a piece ends where the next one starts, sample for sample.
      const i0 = Math.max(0, Math.round((from - c.pts) * c.rate));
      const i1 = Math.min(c.buffer.length, Math.round((to - c.pts) * c.rate));
      if (i1 > i0) this.schedulePiece(c, i0, i1);
      from = c.pts + i1 / c.rate;
      this.until = from;
    }
  }

  schedulePiece(c, i0, i1) {
    const ctx = this.ctx;
    let when = this.contextTimeAt(c.pts + i0 / c.rate + this.offset);
    if (this.next !== null && Math.abs(when - this.next) < RESYNC_S) when = this.next;  // butt-join
    const dur = (i1 - i0) / c.rate;
    this.next = when + dur;
    const soonest = ctx.currentTime + SOONEST_S;
    const pts = c.pts + i0 / c.rate;
    if (when + dur <= soonest) {  // already past
      this.log({ at: when, pts, dur: 0, late: dur, ahead: when - ctx.currentTime, stop: null });
      return;
    }
    const skip = Math.max(0, soonest - when);
    const src = ctx.createBufferSource();
    src.buffer = c.buffer;
    src.connect(this.gain);
    src.start(when + skip, i0 / c.rate + skip, dur - skip);
    const entry = { src, chunk: c, log: this.log({ at: when + skip, pts: pts + skip, dur: dur - skip, late: skip,
                                                   ahead: when + skip - ctx.currentTime, stop: null }) };
    this.playing.push(entry);
    src.onended = () => { const i = this.playing.indexOf(entry); if (i >= 0) this.playing.splice(i, 1); };
    this.samplesScheduled += Math.round((dur - skip) * c.rate);
  }

  log(piece) {
    this.played.push(piece);
    if (this.played.length > PLAYED_KEPT) this.played.splice(0, this.played.length - PLAYED_KEPT);
    return piece;
  }
}
