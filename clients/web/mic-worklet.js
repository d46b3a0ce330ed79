// AudioWorklet that hands the microphone to the page in fixed-size mono chunks.
// Runs on the audio thread; the page converts to the declared wire format and sends.
class MicChunker extends AudioWorkletProcessor {
  constructor(options) {
    super();
    // ~20 ms chunks: small enough for low latency, large enough to keep message overhead low.
    this.size = (options.processorOptions && options.processorOptions.chunkSamples) || 960;
    this.buf = new Float32Array(this.size);
    this.fill = 0;
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
        this.port.postMessage(this.buf, [this.buf.buffer]);
        this.buf = new Float32Array(this.size);
        this.fill = 0;
      }
    }
    return true;
  }
}

registerProcessor('mic-chunker', MicChunker);
