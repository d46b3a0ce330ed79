// Flow control of the microphone (protocol revision 2, docs/protocol.md "Audio"), without DOM or sockets so it
// also runs under node (clients/web/tests/). Between a `slow_down` and its `resume` the server wants no audio:
// chunks are held, at most `holdS` seconds of them, and go out in order at `resume`. A live talker wants now,
// not what was said long ago, so beyond the bound the oldest chunks are dropped, and counted.

export const MIC_HOLD_S = 10;

export class AudioFlow {
  constructor(rate, holdS = MIC_HOLD_S) {
    this.rate = rate;
    this.maxSamples = Math.round(rate * holdS);
    this.paused = false;
    this.held = [];            // [chunk, samples] not sent yet, oldest first
    this.heldSamples = 0;
    this.droppedSamples = 0;   // held longer than the bound allows: gone
    this.droppedChunks = 0;
    this.pauses = 0;           // `slow_down` notices that paused us
    this.resumes = 0;
  }

  /** A chunk of `samples` sample frames was captured: the chunks to send now, in order (none while paused). */
  offer(chunk, samples) {
    this.held.push([chunk, samples]);
    this.heldSamples += samples;
    while (this.heldSamples > this.maxSamples && this.held.length > 1) {
      const [, n] = this.held.shift();
      this.heldSamples -= n;
      this.droppedSamples += n;
      this.droppedChunks++;
    }
    return this.paused ? [] : this.take();
  }

  /** The server said `slow_down`: hold what comes until `resume`. */
  slowDown() {
    if (!this.paused) this.pauses++;
    this.paused = true;
  }

  /** The server said `resume`: the held chunks, to send now. */
  resume() {
    if (this.paused) this.resumes++;
    this.paused = false;
    return this.take();
  }

  take() {
    const out = this.held.map(([c]) => c);
    this.held = [];
    this.heldSamples = 0;
    return out;
  }

  get heldS() { return this.heldSamples / this.rate; }
  get droppedS() { return this.droppedSamples / this.rate; }
}
