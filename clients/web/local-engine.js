// Local mode of the viewer (`?local=MODEL_URL`, e.g. `?local=model/`): the model runs in this browser, no server
// inference. A Web Worker (local-worker.js) runs the exported frame step with onnxruntime-web (WebAssembly) and
// carries its state; here the frames are denormalized and decoded to poses (pose-decoder.js) and handed to the
// viewer as protocol messages (hello, frame, status: docs/protocol.md), so the same playout clock, mannequin
// and VRM code draw them. Audio: the microphone (Talk: captured by mic-worklet.js in an AudioContext running at
// the model's 16 kHz, the browser resampling) or a dropped WAV file (played through the model in real time, its
// sound handed to the viewer with each chunk, as a server's source audio: the viewer plays it on the frames' playout
// clock, source-audio.js). A second drop replaces the first: its stream, frames and sound.
//
// The model folder holds what `streamer web` writes: frame_step.onnx + manifest.json (`dimgestor export-onnx`)
// and web.json (the hello the server would send for this checkpoint, the feature layout, the root mode).
//
// window.dimgestorLocal (for scripts and tests): ready (a promise), info, rtf, runMs, audioS (answered by the
// worker), capturedS (from the microphone), backlogS, droppedS, streamAt (when the stream now began, page ms),
// framesMade, runWav(url | File, {realtime, seed, sound}) -> {normalized, root, rotations, rtf}, startMic(),
// stopMic(), bench(calls) -> per-call ms.
import { PoseDecoder } from './pose-decoder.js';

const MAX_BACKLOG_S = 2;   // microphone audio waiting for the worker beyond this is dropped (counted)
const RTF_WINDOW = 50;     // pushes the shown real-time factor is averaged over
const WAV_CHUNK_S = 0.1;   // a dropped WAV goes to the worker in chunks this long, paced in real time

/** hooks: {onMessage(json), say(text), fail(text), setState(state, detail), api (window.dimgestor), talkButton,
 *  beginStream({talk, sound, windowS}), sourceAudio({rate, pts, samples}, at ms), noteSaid(pts, at ms)}. */
export async function startLocal(base, hooks) {
  const engine = new LocalEngine(new URL(base || 'model/', location.href), hooks);
  window.dimgestorLocal = engine;
  engine.ready = engine.start();
  engine.ready.catch((e) => hooks.fail(`local inference: ${e.message}`));
  return engine;
}

class LocalEngine {
  constructor(base, hooks) {
    Object.assign(this, { base, hooks });
    this.worker = null;
    this.pending = new Map();  // message id -> {resolve, reject}
    this.nextId = 0;
    this.info = null;
    this.rtfPushes = [];       // [runMs, audio ms] of the last RTF_WINDOW pushes
    this.rtf = null;
    this.runMs = 0;
    this.audioS = 0;
    this.droppedS = 0;         // microphone audio dropped because the worker was MAX_BACKLOG_S behind
    this.backlog = 0;          // samples sent to the worker and not answered yet
    this.capturedS = 0;        // microphone audio captured (the worklet's chunks), sent or dropped
    this.framesMade = 0;
    this.lastCallMs = null;
    this.mic = null;
    this.record = null;        // {normalized, root, rotations, face} while runWav collects the frames it makes
    this.source = null;        // 'mic' | 'wav' | null
    this.stream = 0;           // the stream now: answers for an older one (replaced by a drop) are dropped
    this.wavRun = 0;           // the WAV run now: an older run's pacing stops when a new one starts
    this.pushedS = 0;          // audio of this stream sent to the worker (the pts it has reached)
  }

  async start() {
    const { hooks } = this;
    hooks.setState('local', ': loading');
    document.getElementById('url').textContent = 'runs locally in this browser (WebAssembly): no server inference';
    const latency = document.getElementById('latency');  // the HUD's "latency (server)" row: the model's time here
    latency.previousElementSibling.textContent = 'inference (local)';
    latency.previousElementSibling.title = 'the model\'s time for the last push of audio, in this browser';
    const get = async (name) => {
      const r = await fetch(new URL(name, this.base));
      if (!r.ok) throw new Error(`${new URL(name, this.base)}: HTTP ${r.status} (serve it with: streamer web)`);
      return r.json();
    };
    const [web, manifest] = await Promise.all([get('web.json'), get('manifest.json')]);
    this.web = web;
    this.fps = manifest.call.fps;
    this.rate = manifest.call.sample_rate;
    this.spec = { ...web.features, mean: manifest.checkpoint.mean, std: manifest.checkpoint.std };
    hooks.onMessage(JSON.stringify(web.hello));
    this.worker = new Worker(new URL('./local-worker.js', import.meta.url), { type: 'module' });
    this.worker.onmessage = (e) => this.answer(e.data);
    this.worker.onerror = (e) => hooks.fail(`local inference worker: ${e.message}`);
    const params = new URLSearchParams(location.search);
    this.info = await this.call({ type: 'init', base: this.base.href, threads: Number(params.get('threads') || 0),
                                  seed: Number(params.get('seed') || 0) });
    this.newStream();
    hooks.setState('local');
    hooks.talkButton.disabled = false;
    hooks.say(`local model loaded in ${(this.info.loadMs / 1000).toFixed(1)} s (K = ${this.info.sampler.steps}, ` +
              `${this.info.call.frames_per_call * 1000 / this.fps} ms windows, ${this.info.threads} thread(s)): ` +
              'press Talk or drop a WAV file');
    addEventListener('drop', (e) => this.onDrop(e), true);  // before the viewer's (VRM) handler
    return this.info;
  }

  call(msg, transfer = []) {
    const id = ++this.nextId;
    return new Promise((resolve, reject) => {
      this.pending.set(id, { resolve, reject });
      this.worker.postMessage({ ...msg, id }, transfer);
    });
  }

  answer(msg) {
    const p = this.pending.get(msg.id);
    if (!p) return;
    this.pending.delete(msg.id);
    if (msg.type === 'error') p.reject(new Error(msg.message));
    else p.resolve(msg);
  }

  /** A fresh stream in the worker and the viewer (`sound`: the audio pushed is played there too). */
  newStream(seed, sound = false) {
    this.stream++;
    this.streamAt = performance.now();
    this.decoder = new PoseDecoder(this.spec, this.web.root, this.web.tether_s);
    this.framesMade = 0;
    this.pushedS = 0;
    this.rtfPushes = [];
    if (this.hooks.beginStream) {
      const windowS = this.info ? this.info.call.frames_per_call / this.fps : null;
      this.hooks.beginStream({ talk: this.source === 'mic', sound, windowS });
    }
    return this.worker ? this.call({ type: 'reset', seed, stream: this.stream }) : null;
  }

  /** 16 kHz samples to the model; its frames go to the viewer (and to `record`). */
  async push(samples, finish = false) {
    const n = finish ? 0 : samples.length;  // (read before the buffer is transferred to the worker)
    const stream = this.stream;
    this.backlog += n;
    this.pushedS += n / this.rate;
    let r;
    try {
      r = finish ? await this.call({ type: 'finish', stream })
        : await this.call({ type: 'push', samples, stream }, [samples.buffer]);
    } finally {
      this.backlog -= n;
    }
    this.runMs += r.runMs;
    this.audioS += r.samples / this.rate;
    if (r.samples) {
      this.rtfPushes.push([r.runMs, (1000 * r.samples) / this.rate]);
      if (this.rtfPushes.length > RTF_WINDOW) this.rtfPushes.shift();
      const [run, audio] = this.rtfPushes.reduce((a, [x, y]) => [a[0] + x, a[1] + y], [0, 0]);
      this.rtf = run / audio;
    }
    if (stream !== this.stream) return 0;  // a stream replaced meanwhile: its last frames are not shown
    r.frames.forEach((row, k) => this.emit(row, r.faces ? r.faces[k] : null));
    if (r.runMs > 0) this.lastCallMs = r.runMs;  // (a push shorter than a call may complete none)
    this.hooks.onMessage(JSON.stringify({ type: 'status', rtf: this.rtf, latency_ms: this.lastCallMs, local: true }));
    return r.frames.length;
  }

  emit(row, face = null) {
    const index = this.framesMade++;
    const pose = this.decoder.decode(row);
    if (this.record) {
      this.record.normalized.push(Array.from(row));
      this.record.root.push(pose.root);
      this.record.rotations.push(pose.rotations);
      this.record.face.push(face);
    }
    this.hooks.onMessage(JSON.stringify({ type: 'frame', index, pts: index / this.fps, root: pose.root,
                                          rotations: pose.rotations, ...(face ? { face } : {}) }));
  }

  // ---------------------------------------------------------------- a WAV file
  /** A WAV (URL or File) through the model: as fast as it goes (realtime false) or paced like live audio, its
   *  sound played with the frames (`sound`, paced only). A run started meanwhile replaces this one: its pacing
   *  stops and it returns what it made so far (`replaced`). */
  async runWav(source, { realtime = false, seed, sound = false } = {}) {
    await this.ready;
    if (this.source === 'mic') throw new Error('busy: the microphone is running (stop it first)');
    // Read and parsed before anything running is replaced: a file that cannot be read stops nothing.
    const bytes = source instanceof Blob ? await source.arrayBuffer() : await (await fetch(source)).arrayBuffer();
    const audio = await wavTo16k(bytes, this.rate);
    if (this.source === 'mic') throw new Error('busy: the microphone is running (stop it first)');
    const run = ++this.wavRun;
    this.source = 'wav';
    const record = this.record = { normalized: [], root: [], rotations: [], face: [] };
    const t0 = performance.now(), runMs0 = this.runMs;
    sound = sound && realtime;
    let pushed = 0;
    try {
      await this.newStream(seed, sound);
      // As fast as it goes: all of it in one message (the worker still calls the graph window by window).
      const chunk = realtime ? Math.round(WAV_CHUNK_S * this.rate) : audio.length;
      const pushes = [];
      const due = (i) => t0 + (1000 * Math.min(i + chunk, audio.length)) / this.rate;  // its last sample's time
      for (let i = 0; i < audio.length && run === this.wavRun;) {
        if (realtime) {  // pace: a chunk is "heard" when its last sample's time has come
          await new Promise((res) => setTimeout(res, Math.max(0, due(i) - performance.now())));
          if (run !== this.wavRun) break;
        }
        // Every chunk due by now: a page busy drawing wakes late (a software-drawn page's frame can take 250 ms),
        // and one chunk a wake would fall behind real time.
        do {
          const piece = audio.slice(i, i + chunk);
          // Its sound goes to the viewer as it is heard, with its pts, before its frames (as a server's source audio).
          if (sound) this.hooks.sourceAudio({ rate: this.rate, pts: i / this.rate, samples: piece.slice() }, due(i));
          pushed += piece.length;  // (before the push transfers its buffer to the worker)
          pushes.push(this.push(piece));  // (not awaited: the worker takes them in order)
          i += chunk;
        } while (realtime && i < audio.length && due(i) <= performance.now());
      }
      if (run === this.wavRun) pushes.push(this.push(null, true));
      await Promise.all(pushes);
      return { ...record, rtf: (this.runMs - runMs0) / ((1000 * audio.length) / this.rate), samples: pushed,
               replaced: run !== this.wavRun };
    } finally {
      if (run === this.wavRun) {
        this.record = null;
        this.source = null;
      }
    }
  }

  onDrop(e) {
    const file = e.dataTransfer && e.dataTransfer.files[0];
    if (!file || !/\.wav$/i.test(file.name)) return;  // (a .vrm goes on to the viewer's handler)
    e.preventDefault();
    e.stopImmediatePropagation();
    document.getElementById('drop').classList.remove('show');
    this.hooks.say(`${file.name}: generating locally, in real time`);
    this.runWav(file, { realtime: true, sound: true }).then(
      (r) => r.replaced || this.hooks.say(`${file.name}: ${r.normalized.length} frames made here, real-time factor ${r.rtf.toFixed(2)}`),
      (err) => this.hooks.say(`${file.name}: ${err.message}`));
  }

  // ---------------------------------------------------------------- the microphone
  toggleMic() { return this.mic ? this.stopMic() : this.startMic(); }

  async startMic() {
    await this.ready;
    if (this.source) throw new Error(`busy: the ${this.source} is running`);
    const { hooks } = this;
    const stream = await navigator.mediaDevices.getUserMedia(
      { audio: { channelCount: 1, echoCancellation: true, noiseSuppression: true, autoGainControl: true } });
    const ctx = new AudioContext({ sampleRate: this.rate });  // the browser resamples the microphone to 16 kHz
    this.mic = { stream, ctx, node: null };
    this.source = 'mic';
    await this.newStream();
    await ctx.resume();
    await ctx.audioWorklet.addModule(new URL('./mic-worklet.js', import.meta.url));
    // 100 ms chunks, one call's audio: one message each way per call (the main thread also draws, often slowly).
    const chunkSamples = this.info.call.samples_per_call;
    const node = new AudioWorkletNode(ctx, 'mic-chunker', { processorOptions: { chunkSamples } });
    let last = Promise.resolve();
    node.port.onmessage = (e) => {  // each chunk to the worker at once (it takes them in order, answers in order)
      this.capturedS += e.data.length / this.rate;
      if (this.backlog / this.rate > MAX_BACKLOG_S) { this.droppedS += e.data.length / this.rate; return; }
      // Said when it reached the page, its last sample at the pts of all the audio sent (the speech -> motion
      // readout, as talking to a server; a chunk the page got late reads least delayed among the last 5 s).
      this.hooks.noteSaid(this.pushedS + e.data.length / this.rate, performance.now());
      last = this.push(e.data).catch((err) => hooks.fail(`local inference: ${err.message}`));
    };
    const silence = ctx.createGain();  // the node must reach the destination to be pulled; never heard
    silence.gain.value = 0;
    ctx.createMediaStreamSource(stream).connect(node);
    node.connect(silence).connect(ctx.destination);
    this.mic.node = node;
    this.mic.last = () => last;
    hooks.api.talking = true;
    hooks.api.audioRate = ctx.sampleRate;
    hooks.talkButton.textContent = 'Stop';
    hooks.talkButton.classList.add('on');
    hooks.say('talking: the model runs here, in this browser');
  }

  async stopMic() {
    if (!this.mic) return;
    const { stream, ctx, node, last } = this.mic;
    this.mic = null;
    stream.getTracks().forEach((t) => t.stop());
    node.disconnect();
    await ctx.close();
    await last();
    await this.push(null, true);
    this.source = null;
    this.hooks.api.talking = false;
    this.hooks.talkButton.textContent = 'Talk';
    this.hooks.talkButton.classList.remove('on');
  }

  get backlogS() { return this.backlog / this.rate; }

  /** Per-call milliseconds of `calls` calls on a fresh stream (the benchmark's hook). */
  async bench(calls) {
    await this.ready;
    return this.call({ type: 'bench', calls });
  }
}

/** A WAV file's bytes -> mono float32 samples at `rate`: PCM16 / float32 parsed here exactly as dimgestor's
 * read_wav does (int16 / 32768, channels averaged); another sample rate goes through the browser's resampler. */
export async function wavTo16k(bytes, rate) {
  const dv = new DataView(bytes);
  const tag = (o) => String.fromCharCode(dv.getUint8(o), dv.getUint8(o + 1), dv.getUint8(o + 2), dv.getUint8(o + 3));
  if (bytes.byteLength < 12 || tag(0) !== 'RIFF' || tag(8) !== 'WAVE') throw new Error('not a WAV file (no RIFF/WAVE header)');
  let fmt = null, data = null;
  for (let pos = 12; pos + 8 <= bytes.byteLength;) {
    const id = tag(pos), size = dv.getUint32(pos + 4, true);
    if (id === 'fmt ') fmt = { format: dv.getUint16(pos + 8, true), channels: dv.getUint16(pos + 10, true),
                               rate: dv.getUint32(pos + 12, true), bits: dv.getUint16(pos + 22, true) };
    if (id === 'data') data = [pos + 8, Math.min(size, bytes.byteLength - pos - 8)];
    pos += 8 + size + (size % 2);
  }
  if (!fmt || !data) throw new Error('a WAV file without fmt or data chunk');
  const pcm16 = fmt.format === 1 && fmt.bits === 16, f32 = fmt.format === 3 && fmt.bits === 32;
  if (!(pcm16 || f32) || fmt.rate !== rate) {  // anything else: the browser decodes and resamples it
    const decoded = await new OfflineAudioContext(1, 1, rate).decodeAudioData(bytes.slice(0));
    const n = Math.round((decoded.duration * rate));
    const off = new OfflineAudioContext(1, n, rate);
    const src = off.createBufferSource();
    src.buffer = decoded;
    src.connect(off.destination);
    src.start();
    return (await off.startRendering()).getChannelData(0).slice();
  }
  const width = fmt.bits / 8, n = Math.floor(data[1] / (width * fmt.channels));
  const out = new Float32Array(n);
  for (let i = 0; i < n; i++) {
    let s = 0;
    for (let c = 0; c < fmt.channels; c++) {
      const o = data[0] + (i * fmt.channels + c) * width;
      s += pcm16 ? dv.getInt16(o, true) / 32768 : dv.getFloat32(o, true);
    }
    out[i] = s / fmt.channels;
  }
  return out;
}
