// Web Worker of the local mode (local-engine.js): onnxruntime-web's WebAssembly backend runs the exported frame
// step (`dimgestor export-onnx`: frame_step.onnx + manifest.json) off the page's thread, driven by
// FrameStepStream (frame-step-stream.js, the mirror of Python's). Messages in, one at a time in order:
//   {type: 'init', base, threads, seed}   load base + manifest.json and its graph (and face_step.onnx, the face's
//                                         listener, when the export has it) -> {type: 'ready', face, ...}
//   {type: 'push', samples}               16 kHz mono Float32Array -> {type: 'frames', frames, faces, runMs, samples}
//   {type: 'finish'}                      the end of the audio -> {type: 'frames', ..., final: true}
//   {type: 'reset', seed}                 a new stream (same session) -> {type: 'reset'}
//   {type: 'bench', calls}                `calls` calls on a fresh stream of noise -> {type: 'bench', ms: [...]}
// Import maps do not reach workers: onnxruntime-web is imported by its path under node_modules/.
import * as ort from './node_modules/onnxruntime-web/dist/ort.wasm.min.mjs';
import { FrameStepStream } from './frame-step-stream.js';
import { FaceStepStream } from './face-step-stream.js';

let session = null, manifest = null, stream = null, seed = 0;
// The face's listener (face_step.onnx beside the body's graph, when the export has it and its calls match): null
// without one, and the frames carry no face.
let faceSession = null, faceManifest = null, faceStream = null;
let queue = Promise.resolve();
let latest = 0;  // the newest stream the page has asked for (its messages carry `stream`)

function runOn(s) {
  return async (feeds) => {
    const tensors = {};
    for (const [name, t] of Object.entries(feeds))
      tensors[name] = t instanceof ort.Tensor ? t : new ort.Tensor(t.dtype, t.data, t.dims);
    return s.run(tensors);
  };
}
const run = (feeds) => runOn(session)(feeds);
const runFace = (feeds) => runOn(faceSession)(feeds);

async function loadFace(get) {
  // An export without the face (export-onnx --no-face, or an older one) streams the body only.
  try {
    faceManifest = await get('face_manifest.json', 'json');
  } catch {
    return 'no face_manifest.json beside the model';
  }
  if (faceManifest.samples_per_call !== manifest.call.samples_per_call || faceManifest.fps !== manifest.call.fps) {
    faceManifest = null;
    return 'the face graph was exported for other calls than the model\'s';
  }
  faceSession = await ort.InferenceSession.create(await get(faceManifest.graph, 'arrayBuffer'),
                                                  { executionProviders: ['wasm'], graphOptimizationLevel: 'all' });
  return null;
}

async function init({ base, threads, seed: s }) {
  ort.env.wasm.numThreads = threads || 0;  // 0: onnxruntime-web's default (1 unless the page is cross-origin isolated)
  const t0 = performance.now();
  const get = async (name, as) => {
    const r = await fetch(new URL(name, base));
    if (!r.ok) throw new Error(`${new URL(name, base)}: HTTP ${r.status} (export the model there: streamer web)`);
    return r[as]();
  };
  manifest = await get('manifest.json', 'json');
  const graph = await get(manifest.graph, 'arrayBuffer');
  session = await ort.InferenceSession.create(graph, { executionProviders: ['wasm'], graphOptimizationLevel: 'all' });
  const noFace = await loadFace(get);
  seed = s || 0;
  const loadMs = performance.now() - t0;
  // The first calls compile and allocate (several times a call's usual time): made here, on a throwaway stream,
  // they do not make the first live frames late (which would grow the viewer's playout buffer for good).
  const t1 = performance.now();
  const warm = new FrameStepStream(manifest, run, seed);
  await warm.push(new Float32Array(warm.chunk * (warm.warmup + 2)));
  if (faceSession) await new FaceStepStream(faceManifest, runFace).push(new Float32Array(warm.chunk * 4));
  newStreams();
  return { type: 'ready', loadMs, warmMs: performance.now() - t1, threads: ort.env.wasm.numThreads,
           crossOriginIsolated: self.crossOriginIsolated, sampler: manifest.sampler, call: manifest.call,
           face: !noFace, noFace };
}

function newStreams() {
  stream = new FrameStepStream(manifest, run, seed);
  faceStream = faceSession ? new FaceStepStream(faceManifest, runFace) : null;
}

/** Each frame's face (null without the face's listener): the face is heard before the body's frame is made. */
function facesOf(frames, first) {
  return frames.map((_, k) => (faceStream ? faceStream.take(first + k) : null));
}

async function push(samples, of) {
  // A stream replaced since this was sent (a second WAV dropped): answered, not run.
  if (of < latest) return { type: 'frames', frames: [], runMs: 0, samples: samples.length, skipped: true };
  const runMs = stream.runMs + (faceStream ? faceStream.runMs : 0);
  if (faceStream) await faceStream.push(samples);
  const first = stream.framesOut;
  const frames = await stream.push(samples);
  const faces = facesOf(frames, first);
  return { type: 'frames', frames, faces, runMs: stream.runMs + (faceStream ? faceStream.runMs : 0) - runMs,
           samples: samples.length };
}

async function finish() {
  const runMs = stream.runMs + (faceStream ? faceStream.runMs : 0);
  if (faceStream) {  // the silence the body's finish pads with (the face needs no more: it hears less far ahead)
    const c = manifest.call, T = Math.floor((stream.samplesIn * c.fps) / c.sample_rate);
    const need = T ? (Math.ceil(T / stream.perCall) + stream.warmup) * stream.chunk : 0;
    await faceStream.push(new Float32Array(Math.max(need - stream.samplesIn, 0)));
  }
  const first = stream.framesOut;
  const frames = await stream.finish();
  return { type: 'frames', frames, faces: facesOf(frames, first),
           runMs: stream.runMs + (faceStream ? faceStream.runMs : 0) - runMs, samples: 0, final: true };
}

async function bench(calls) {
  // A fresh stream fed whole calls of noise: the time of every call, the warm-up ones included.
  const s = new FrameStepStream(manifest, run, seed);
  const samples = new Float32Array(s.chunk);
  const ms = [];
  for (let i = 0; i < calls; i++) {
    for (let k = 0; k < samples.length; k++) samples[k] = 0.1 * Math.sin(0.05 * (k + i * samples.length)) * Math.random();
    const t0 = performance.now();
    await s.push(samples);
    ms.push(performance.now() - t0);
  }
  return { type: 'bench', ms, samplesPerCall: s.chunk, sampleRate: manifest.call.sample_rate };
}

const handlers = {
  init, push: (m) => push(m.samples, m.stream ?? latest), finish: () => finish(), bench: (m) => bench(m.calls),
  reset: (m) => { seed = m.seed ?? seed; newStreams(); return { type: 'reset' }; },
};

self.onmessage = (e) => {
  const msg = e.data;
  if (msg.stream > latest) latest = msg.stream;  // (at once: pushes queued for an older stream are skipped)
  queue = queue.then(async () => {
    try {
      const handler = handlers[msg.type];
      if (!handler) throw new Error(`unknown message ${msg.type}`);
      self.postMessage({ id: msg.id, ...(await handler(msg)) });
    } catch (err) {
      self.postMessage({ id: msg.id, type: 'error', message: err.message || String(err) });
    }
  });
};
