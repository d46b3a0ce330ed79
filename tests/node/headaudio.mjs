// HeadAudio (npm @met4citizen/headaudio, pinned in this folder's package.json), its own code unchanged, run offline in Node on
// a recording: the AudioWorklet processor is fed 128-sample blocks as a browser's audio thread feeds it, its
// messages reach the node as they would, and the node's animation `update` runs every 10 ms of audio (a browser's
// animation loop). Writes each 10 ms step's 15 Oculus viseme weights.
//
//   node headaudio.mjs SPEECH.f32 RATE OUT.json      (SPEECH.f32: mono float32 samples at RATE Hz)
//
// Only what the library needs of the Web Audio API is given here (AudioWorkletProcessor, registerProcessor,
// sampleRate, AudioWorkletNode with its port and parameters); its model is read from the package's dist/.
import { readFileSync, writeFileSync } from "node:fs";
import { MessageChannel } from "node:worker_threads";
import { createRequire } from "node:module";
import path from "node:path";

const [input, rateArg, output] = process.argv.slice(2);
const rate = Number(rateArg);
const samples = new Float32Array(readFileSync(input).buffer.slice(0));

globalThis.sampleRate = rate;
let nextPort = null;
const processors = {};
globalThis.AudioWorkletProcessor = class {
  constructor() { this.port = nextPort; }
};
globalThis.registerProcessor = (name, cls) => { processors[name] = cls; };
globalThis.AudioWorkletNode = class {
  constructor(context, name, options = {}) {
    const channel = new MessageChannel();
    this.port = channel.port1;
    nextPort = channel.port2;
    const Processor = processors[name];
    this.processor = new Processor(options);
    nextPort = null;
    // the parameters as the audio thread hands them to process(): each one's value, given or default
    this.parameterValues = {};
    this.parameters = new Map();
    for (const d of Processor.parameterDescriptors) {
      const value = options.parameterData?.[d.name] ?? d.defaultValue;
      this.parameterValues[d.name] = new Float32Array([value]);
      this.parameters.set(d.name, { value });
    }
  }
};
globalThis.fetch = async (location) => {  // the model file, from disk
  const bytes = readFileSync(location);
  return { ok: true, arrayBuffer: async () => bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength) };
};

const require = createRequire(import.meta.url);
const root = path.dirname(require.resolve("@met4citizen/headaudio/package.json"));
await import(path.join(root, "modules", "headworklet.mjs"));
const { HeadAudio } = await import(path.join(root, "modules", "headaudio.mjs"));

const flush = () => new Promise((resolve) => setImmediate(() => setImmediate(resolve)));
const node = new HeadAudio({ sampleRate: rate });  // default settings, as the README's node is made
await node.loadModel(path.join(root, "dist", "model-en-mixed.bin"));
await flush();

const names = node.visemeNames;
const values = Object.fromEntries(names.map((n) => [n, 0]));
node.onvalue = (key, value) => { values[key] = value; };
const BLOCK = 128, STEP = rate / 100;
const steps = [];
let fed = 0;
for (let k = 1; k * STEP <= samples.length; k++) {
  while (fed + BLOCK <= k * STEP) {  // the audio thread's blocks up to this step's time
    node.processor.process([[samples.subarray(fed, fed + BLOCK)]], [], node.parameterValues);
    fed += BLOCK;
  }
  await flush();  // its messages (viseme events) reach the node
  node.update(10);
  steps.push(names.map((n) => values[n]));
}
writeFileSync(output, JSON.stringify({ library: "@met4citizen/headaudio", step_s: 0.01, visemes: names, steps }));
process.exit(0);  // (the message ports would keep Node running)
