// The exported frame step (`dimgestor export-onnx`) driven as a stream, in JavaScript: the mirror of Python's
// `dimgestor.export.onnx_stream.FrameStepStream`, line for line, so the browser's frames equal ONNX Runtime's in Python.
// It buffers 16 kHz audio to whole calls (samples_per_call), numbers each call's first frame (below 0 during the
// warm-up, whose frames it drops), carries every state tensor from one call's outputs to the next call's inputs,
// pads the end with silence as `finish_step` does, and applies the same output filter (One Euro). No DOM and no
// ONNX Runtime here: the caller gives `run(feeds) -> outputs` (local-worker.js: onnxruntime-web's session), so it
// also runs under node (clients/web/tests/). Tensors are {data, dims, dtype} plain objects on both sides.

const ARRAYS = { float32: Float32Array, float64: Float64Array, int64: BigInt64Array };

/** A state entry of the manifest -> its starting tensor (every state starts as one constant; "nan" is NaN). */
export function initialTensor(entry) {
  const n = entry.shape.reduce((a, b) => a * b, 1);
  const Array_ = ARRAYS[entry.dtype];
  if (!Array_) throw new Error(`manifest state ${entry.input}: dtype ${entry.dtype} is not supported`);
  const fill = entry.init === 'nan' ? NaN : Number(entry.init);
  const data = new Array_(n);
  data.fill(entry.dtype === 'int64' ? BigInt(fill) : fill);
  return { data, dims: entry.shape.slice(), dtype: entry.dtype };
}

/** The One Euro filter (dimgestor.smoothing.OneEuroFilter) on (n, D) rows, carried from call to call. */
export class OneEuroFilter {
  constructor(fps, minCutoffHz, beta = 0, dCutoffHz = 1) {
    if (!(fps > 0 && minCutoffHz > 0 && dCutoffHz > 0 && beta >= 0))
      throw new Error(`OneEuroFilter needs fps, min cutoff and d cutoff > 0, beta >= 0`);
    Object.assign(this, { fps, minCutoffHz, beta, dCutoffHz });
    this.x = null;   // the last filtered frame (Float64Array), null before the first frame
    this.dx = null;  // its derivative, units per second
  }

  alpha(cutoffHz) { return 1 / (1 + this.fps / (2 * Math.PI * cutoffHz)); }

  /** Filters rows (arrays of D numbers) in place order; returns the filtered rows (Float64Array each). */
  step(rows) {
    const aD = this.alpha(this.dCutoffHz), aFixed = this.alpha(this.minCutoffHz);
    return rows.map((row) => {
      if (this.x === null) {  // the first frame passes unchanged
        this.x = Float64Array.from(row);
        this.dx = new Float64Array(row.length);
        return Float64Array.from(this.x);
      }
      for (let d = 0; d < row.length; d++) {
        if (this.beta === 0) { this.x[d] += aFixed * (row[d] - this.x[d]); continue; }
        this.dx[d] += aD * ((row[d] - this.x[d]) * this.fps - this.dx[d]);
        this.x[d] += this.alpha(this.minCutoffHz + this.beta * Math.abs(this.dx[d])) * (row[d] - this.x[d]);
      }
      return Float64Array.from(this.x);
    });
  }
}

/** The model config's output filter (`dimgestor.streaming.stream.make_smoother` with smoothing "config"), or
 *  null. */
export function configSmoother(config) {
  return config.smooth_hz ? new OneEuroFilter(config.fps, config.smooth_hz, config.smooth_beta || 0) : null;
}

export class FrameStepStream {
  /** manifest: the export's manifest.json; run: async (feeds) -> outputs by name; seed: the stream's noise seed. */
  constructor(manifest, run, seed = 0) {
    this.manifest = manifest;
    this.run = run;
    this.seed = BigInt(seed);
    this.config = manifest.checkpoint.config;
    const call = manifest.call;
    this.chunk = call.samples_per_call;
    this.warmup = call.warmup_calls;
    this.perCall = call.frames_per_call;
    this.dim = this.config.motion_dim;
    this.smoother = configSmoother(this.config);
    this.tensors = Object.fromEntries(manifest.state.map((s) => [s.input, initialTensor(s)]));
    this.pending = new Float32Array(0);  // samples not yet a whole call
    this.samplesIn = 0;
    this.calls = 0;
    this.framesOut = 0;
    this.finished = false;
    this.busy = false;
    this.runMs = 0;       // time spent in `run`, for the real-time factor
  }

  /** Mono float32 16 kHz samples (any length) -> the normalized frames (arrays of D floats) that became final. */
  async push(samples) {
    if (this.finished) throw new Error('push() after finish(): start a new stream');
    if (this.busy) throw new Error('push() while a push is running: await each push before the next');
    if (!(samples instanceof Float32Array)) throw new Error('audio must be a Float32Array of mono samples');
    this.busy = true;
    try {
      const audio = new Float32Array(this.pending.length + samples.length);
      audio.set(this.pending);
      audio.set(samples, this.pending.length);
      const whole = audio.length - (audio.length % this.chunk);
      this.pending = audio.slice(whole);
      this.samplesIn += samples.length;
      return await this.frames(audio.subarray(0, whole));
    } finally {
      this.busy = false;
    }
  }

  async frames(audio) {
    const out = [];
    const M = this.perCall;
    for (let i = 0; i < audio.length / this.chunk; i++) {
      const j = this.calls - this.warmup;  // this call makes frames [j M, (j + 1) M) (j < 0: warm-up)
      const feeds = {
        samples: { data: audio.slice(i * this.chunk, (i + 1) * this.chunk), dims: [1, this.chunk], dtype: 'float32' },
        seed: { data: BigInt64Array.of(this.seed), dims: [1], dtype: 'int64' },
        frame: { data: BigInt64Array.of(BigInt(j * M)), dims: [1], dtype: 'int64' },
        ...this.tensors,
      };
      const t0 = performance.now();
      const result = await this.run(feeds);
      this.runMs += performance.now() - t0;
      this.calls++;
      for (const s of this.manifest.state) this.tensors[s.input] = result[s.output];
      if (j < 0) continue;  // a warm-up call's frames are not real (the graph kept the denoiser's start state)
      const f = result.frames.data;
      for (let k = 0; k < M; k++) out.push(Float32Array.from(f.subarray(k * this.dim, (k + 1) * this.dim)));
    }
    const frames = this.smoother && out.length ? this.smoother.step(out).map((r) => Float32Array.from(r)) : out;
    this.framesOut += frames.length;
    return frames;
  }

  /** The end of the audio: silence up to the last frame's lookahead; the frames that follow (as finish_step). */
  async finish() {
    if (this.finished) return [];
    const c = this.config;
    const T = Math.floor((this.samplesIn * c.fps) / c.sample_rate);
    const need = T ? (Math.ceil(T / this.perCall) + this.warmup) * this.chunk : 0;  // until frame T - 1 exists
    const before = this.framesOut;
    const frames = await this.push(new Float32Array(Math.max(need - this.samplesIn, 0)));
    const kept = frames.slice(0, Math.max(T - before, 0));
    this.framesOut = before + kept.length;
    this.finished = true;
    return kept;
  }
}
