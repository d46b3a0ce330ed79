// The face's listener (`dimgestor export-onnx`: face_step.onnx + face_manifest.json) driven as a stream, beside
// the body's FrameStepStream in the local mode (local-worker.js): the same whole calls of 16 kHz samples, each
// call numbered on the stream's clock (`frame`), every state carried from one call's outputs to the next's
// inputs. A call gives the 15 visemes' chances and the jaw's opening of `frames_per_call` face frames; they are
// kept by frame index until the body's frame of that index is made (the body looks further ahead: its frame i
// comes later than the face's). `mouth` turns them into the VRM 1.0 mouth shapes as the server's face does
// (dimgestor/face/stream.py `_mouth_heard`, names.py's vowels); blinks, brows and the loudness scale are the
// server's only. No DOM and no ONNX Runtime here: the caller gives `run(feeds) -> outputs`, so it runs under node.

const ARRAYS = { float32: Float32Array, float64: Float64Array, int64: BigInt64Array };
export const VISEMES = ['sil', 'PP', 'FF', 'TH', 'DD', 'kk', 'CH', 'SS', 'nn', 'RR', 'aa', 'E', 'I', 'O', 'U'];
// A vowel viseme's shape is weighed by the vowel's height; each viseme as the five vowel shapes (names.py).
const SHAPE_WEIGHT = { aa: 1, E: 0.75, I: 0.5, O: 0.75, U: 0.5 };
const VOWEL_OF = {
  sil: {}, PP: {}, FF: { ih: 0.2 }, TH: { ee: 0.25 }, DD: { ee: 0.2, ih: 0.1 }, kk: { ee: 0.2, aa: 0.1 },
  CH: { ou: 0.2, ih: 0.1 }, SS: { ih: 0.25 }, nn: { ee: 0.2, ih: 0.1 }, RR: { oh: 0.2, ou: 0.2 },
  aa: { aa: 1 }, E: { ee: 1 }, I: { ih: 1 }, O: { oh: 1 }, U: { ou: 1 },
};

function initial(entry) {
  const n = entry.shape.reduce((a, b) => a * b, 1);
  const Array_ = ARRAYS[entry.dtype];
  if (!Array_) throw new Error(`face manifest state ${entry.input}: dtype ${entry.dtype} is not supported`);
  const data = Array.isArray(entry.init) ? Array_.from(entry.init) : new Array_(n).fill(Number(entry.init));
  return { data, dims: entry.shape.slice(), dtype: entry.dtype };
}

/** The mouth of one face frame as VRM 1.0 expressions {aa, ih, ou, ee, oh} (0..1) and ARKit's jawOpen. */
export function mouth(visemes, opening) {
  const p = Array.from(visemes);
  let best = 0;
  for (let k = 1; k < p.length; k++) if (p[k] > p[best]) best = k;
  const closed = VISEMES[best] === 'PP' ? 0.2 : 1;  // lips shut on M, B, P
  const out = { aa: 0, ih: 0, ou: 0, ee: 0, oh: 0 };
  VISEMES.forEach((v, k) => {
    const w = p[k] * (SHAPE_WEIGHT[v] ?? 1) * closed;
    for (const [shape, x] of Object.entries(VOWEL_OF[v])) out[shape] += w * x;
  });
  for (const k of Object.keys(out)) out[k] = Math.min(1, Math.max(0, out[k]));
  out.jawOpen = Math.min(1, Math.max(0, opening * (1 - p[VISEMES.indexOf('PP')]) * closed));
  return out;
}

export class FaceStepStream {
  /** manifest: face_manifest.json; run: async (feeds) -> outputs by name. */
  constructor(manifest, run) {
    if (manifest.format !== 1) throw new Error(`face manifest format ${manifest.format}: this page reads 1`);
    this.manifest = manifest;
    this.run = run;
    this.chunk = manifest.samples_per_call;
    this.perCall = manifest.frames_per_call;
    this.tensors = Object.fromEntries(manifest.state.map((s) => [s.input, initial(s)]));
    this.pending = new Float32Array(0);
    this.calls = 0;
    this.faces = new Map();  // face frame index -> its mouth, until taken
    this.runMs = 0;
  }

  /** Mono float32 16 kHz samples (any length): the calls they complete are run. */
  async push(samples) {
    const audio = new Float32Array(this.pending.length + samples.length);
    audio.set(this.pending);
    audio.set(samples, this.pending.length);
    const whole = audio.length - (audio.length % this.chunk);
    this.pending = audio.slice(whole);
    const m = this.manifest;
    for (let i = 0; i < whole / this.chunk; i++) {
      const n = this.calls;
      const feeds = {
        samples: { data: audio.slice(i * this.chunk, (i + 1) * this.chunk), dims: [1, this.chunk], dtype: 'float32' },
        frame: { data: BigInt64Array.of(BigInt(n * m.frame.per_call + m.frame.offset)), dims: [1], dtype: 'int64' },
        ...this.tensors,
      };
      const t0 = performance.now();
      const r = await this.run(feeds);
      this.runMs += performance.now() - t0;
      this.calls++;
      for (const s of m.state) this.tensors[s.input] = r[s.output];
      const V = VISEMES.length;
      for (let f = 0; f < this.perCall; f++) {
        const index = m.face_frames.first + n * this.perCall + f;
        if (index >= 0) this.faces.set(index, mouth(r.visemes.data.subarray(f * V, (f + 1) * V), r.opening.data[f]));
      }
    }
  }

  /** Face frame `index`'s mouth (and forget it and older ones); null if not heard yet. */
  take(index) {
    const face = this.faces.get(index) ?? null;
    for (const k of this.faces.keys()) if (k <= index) this.faces.delete(k);
    return face;
  }
}
