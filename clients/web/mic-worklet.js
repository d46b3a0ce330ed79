// AudioWorklet that hands the microphone out in fixed-size mono chunks. Runs on the audio thread. With
// processorOptions.viaPort the page gives it a MessagePort to the socket worker (socket-worker.js), which converts
// to the declared wire format and sends: the chunks never wait for the page's main thread; chunks made before that
// port comes are kept and go first. Without it (local mode, local-engine.js) the chunks go on the node's own port.
const EARLY_MAX = 50;  // chunks kept before the port comes (1 s of 20 ms chunks); beyond it the oldest go

class MicChunker extends AudioWorkletProcessor {
  constructor(options) {
    super();
    // ~20 ms chunks: small enough for low latency, large enough to keep message overhead low.
    this.size = (options.processorOptions && options.processorOptions.chunkSamples) || 960;
    this.buf = new Float32Array(this.size);
    this.fill = 0;
    this.out = options.processorOptions && options.processorOptions.viaPort ? null : this.port;  // where chunks go
    this.early = [];   // chunks made before it came
    this.port.onmessage = (e) => {
      if (!(e.data && e.data.port)) return;
      this.out = e.data.port;
      for (const c of this.early) this.out.postMessage(c, [c.buffer]);
      this.early = [];
    };
  }

  process(inputs) {
    const input = inputs[0];
    if (!input || input.length === 0) return true;  // no device data this quantum
    const ch0 = input[0];
    for (let i = 0; i < ch0.length; i++) {
      // Downmix to mono: the protocol declares channels: 1.
      let s = ch0[i];
      if (input.length > 1) { for (let c = 1; c < input.length; c++) s += input[c][i]; s /= input.length; }
      this.buf[this.fill++] = s;
      if (this.fill === this.size) {
        if (this.out) this.out.postMessage(this.buf, [this.buf.buffer]);
        else if (this.early.push(this.buf) > EARLY_MAX) this.early.shift();
        this.buf = new Float32Array(this.size);
        this.fill = 0;
      }
    }
    return true;
  }
}

registerProcessor('mic-chunker', MicChunker);
