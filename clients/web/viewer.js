// dimgestor browser viewer: protocol v1 client (docs/protocol.md), three.js stick figure, microphone.
//
// Page parameters: ?ws=ws://host:port/  (override the server's /config.json)
//                  ?token=T             (when the server requires one)
//                  ?encoding=binary     (DGF1 binary frames instead of JSON)
//                  ?audio=float32       (microphone wire format; default pcm16)
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/OrbitControls.js';
import { FramePlayout } from './playout.js';
import { decodeBinaryFrame } from './protocol.js';

const params = new URLSearchParams(location.search);
const ENCODING = params.get('encoding') === 'binary' ? 'binary' : 'json';
const AUDIO_FORMAT = params.get('audio') === 'float32' ? 'float32' : 'pcm16';
const UNIT_TO_M = { m: 1, cm: 0.01, mm: 0.001 };
const MAX_SEND_BUFFER = 1 << 20;  // bytes queued in the socket before mic chunks are dropped

const $ = (id) => document.getElementById(id);
const ui = { state: $('state'), frames: $('frames'), fps: $('fps'), latency: $('latency'), rtt: $('rtt'),
             rtf: $('rtf'), buffer: $('buffer'), dropped: $('dropped'), clients: $('clients'), talk: $('talk'),
             message: $('message'), url: $('url') };

// Everything a test or the console may want to read.
const api = window.dimgestor = {
  state: 'connecting', url: null, hello: null, status: null, ended: null, errors: [],
  framesReceived: 0, binaryFramesReceived: 0, lastFrame: null, shownFrame: null, bufferMs: null,
  gaps: 0, fps: 0, rttMs: null,
  talking: false, audioRate: null, audioChunksSent: 0, audioChunksDropped: 0,
  jointNames: () => (api.hello ? api.hello.skeleton.joints.slice() : []),
  jointWorldPositions, talk: () => startTalk(), stopTalk: () => stopTalk(),
};

// ---------------------------------------------------------------- scene
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x1d2127);
scene.add(new THREE.HemisphereLight(0xffffff, 0x444455, 2.0));
const sun = new THREE.DirectionalLight(0xffffff, 1.5);
sun.position.set(2, 4, 3);
scene.add(sun);
scene.add(new THREE.GridHelper(10, 20, 0x888888, 0x3a3f47));  // 10 m floor, 50 cm cells

const camera = new THREE.PerspectiveCamera(40, innerWidth / innerHeight, 0.01, 100);
camera.position.set(0, 1.2, 4);
let renderer = null;
let controls = null;
try {
  renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(devicePixelRatio);
  renderer.setSize(innerWidth, innerHeight);
  $('view').appendChild(renderer.domElement);
  controls = new OrbitControls(camera, renderer.domElement);
  controls.target.set(0, 1, 0);
} catch (e) {
  // Joints are still tracked (jointWorldPositions works); only drawing is lost.
  say(`WebGL unavailable: ${e.message}`);
}
addEventListener('resize', () => {
  camera.aspect = innerWidth / innerHeight;
  camera.updateProjectionMatrix();
  if (renderer) renderer.setSize(innerWidth, innerHeight);
});

const figure = new THREE.Group();  // holds the skeleton in file units, scaled to metres
scene.add(figure);
let joints = [];                   // one Object3D per joint, in skeleton order
let roots = [];                    // indices of joints whose parent is -1
const boneMaterial = new THREE.MeshLambertMaterial({ color: 0xd9b38c });
const jointMaterial = new THREE.MeshLambertMaterial({ color: 0x5b8def });

function buildSkeleton(sk) {
  const { joints: names, parents, offsets } = sk;
  const rest = sk.rest_rotations || names.map(() => [1, 0, 0, 0]);
  if (parents.length !== names.length || offsets.length !== names.length || rest.length !== names.length)
    throw new Error(`hello.skeleton: ${names.length} joints but ${parents.length} parents, ` +
                    `${offsets.length} offsets, ${rest.length} rest rotations`);
  figure.clear();
  joints = names.map((name, j) => {
    const o = new THREE.Object3D();
    o.name = name;
    o.position.fromArray(offsets[j]);
    o.quaternion.set(rest[j][1], rest[j][2], rest[j][3], rest[j][0]);  // wire order is w, x, y, z
    return o;
  });
  roots = [];
  parents.forEach((p, j) => {
    if (p < 0) { roots.push(j); figure.add(joints[j]); }
    else if (p < names.length) joints[p].add(joints[j]);
    else throw new Error(`hello.skeleton: joint ${names[j]} has parent ${p} out of range`);
  });
  const scale = UNIT_TO_M[sk.units] ?? 0.01;
  if (!(sk.units in UNIT_TO_M)) say(`unknown skeleton units "${sk.units}", assuming cm`);
  figure.scale.setScalar(scale);

  // Size the capsules from the rest-pose height so any unit or skeleton looks alike.
  figure.updateMatrixWorld(true);
  const box = new THREE.Box3();
  joints.forEach((o) => box.expandByPoint(o.getWorldPosition(new THREE.Vector3())));
  const height = Math.max(box.max.y - box.min.y, 1e-3) / scale;  // file units
  const radius = 0.015 * height;
  const up = new THREE.Vector3(0, 1, 0);
  parents.forEach((p, j) => {
    const off = new THREE.Vector3().fromArray(offsets[j]);
    const len = off.length();
    const ball = p < 0 ? radius : Math.min(0.7 * radius, 0.35 * len);
    if (ball > 1e-6) joints[j].add(new THREE.Mesh(new THREE.SphereGeometry(ball, 12, 8), jointMaterial));
    if (p < 0 || len < 1e-6) return;
    const r = Math.min(radius, 0.2 * len);
    const bone = new THREE.Mesh(new THREE.CapsuleGeometry(r, Math.max(len - 2 * r, 1e-4), 4, 10), boneMaterial);
    bone.position.copy(off).multiplyScalar(0.5);
    bone.quaternion.setFromUnitVectors(up, off.normalize());
    joints[p].add(bone);
  });
  const center = box.getCenter(new THREE.Vector3());
  const h = box.max.y - box.min.y;
  if (controls) controls.target.set(center.x, center.y, center.z);
  camera.position.set(center.x + 0.3 * h, center.y + 0.15 * h, center.z + 2.6 * h);
  camera.lookAt(center);
}

function applyFrame(f) {
  if (f.rotations.length !== joints.length) {
    fail(`frame ${f.index}: ${f.rotations.length} rotations for ${joints.length} joints`);
    return;
  }
  // The root's local position is the frame's root position (file units, BVH space = three.js space).
  for (const j of roots) joints[j].position.set(f.root[0], f.root[1], f.root[2]);
  for (let j = 0; j < joints.length; j++) {
    const q = f.rotations[j];
    joints[j].quaternion.set(q[1], q[2], q[3], q[0]);
  }
}

// Frames are shown at their presentation time, not on arrival (they come in bursts): see playout.js.
const playout = new FramePlayout();
api.playout = playout;

function showPose() {
  const now = performance.now() / 1000;
  const pose = playout.sample(now);
  if (!pose || pose === api.shownFrame || !joints.length) return;
  applyFrame(pose);
  api.shownFrame = pose;
  const newest = playout.queue[playout.queue.length - 1];
  api.bufferMs = (newest.pts - (now - playout.offset)) * 1000;
}
setInterval(showPose, 50);  // keeps the pose current when the tab is hidden and rAF stops

/** World positions of every joint in metres (three.js = BVH space), skeleton order. */
function jointWorldPositions() {
  figure.updateMatrixWorld(true);
  const v = new THREE.Vector3();
  return joints.map((o) => o.getWorldPosition(v).toArray());
}

const figureCenter = new THREE.Vector3();
function render() {
  requestAnimationFrame(render);
  showPose();
  if (!renderer) return;
  if (joints.length) {
    // Follow the figure (root motion can walk it out of view): ease the orbit target onto its centre.
    figure.updateMatrixWorld(true);
    figureCenter.set(0, 0, 0);
    const v = new THREE.Vector3();
    for (const o of joints) figureCenter.add(o.getWorldPosition(v));
    figureCenter.divideScalar(joints.length);
    const step = figureCenter.sub(controls.target).multiplyScalar(0.2);
    controls.target.add(step);
    camera.position.add(step);
  }
  controls.update();
  renderer.render(scene, camera);
}
render();

// ---------------------------------------------------------------- protocol
let ws = null;
let mode = 'view';                 // 'view': watch the server's source; 'talk': own session fed by the mic
let reconnectTimer = null;
let reconnectDelay = 1000;
let pingSentAt = null;
let lastIndex = -1;
const arrivals = [];                // frame arrival times (ms) over the last second, for the fps readout

async function resolveUrl() {
  let url = params.get('ws');
  let tokenRequired = false;
  if (!url) {
    try {
      const r = await fetch(new URL('config.json', location.href), { cache: 'no-store' });
      if (r.ok) { const c = await r.json(); url = c.ws_url; tokenRequired = !!c.token_required; }
    } catch (e) { /* opened from disk or another server: fall back below */ }
  }
  if (!url) url = `ws://${location.hostname || 'localhost'}:8765/`;
  const u = new URL(url);
  // A server bound to every interface advertises 0.0.0.0, which a browser cannot dial.
  if (['0.0.0.0', '[::]', '::'].includes(u.hostname) && location.hostname) u.hostname = location.hostname;
  const token = params.get('token');
  if (token) u.searchParams.set('token', token);
  else if (tokenRequired) say('the server requires a token: open this page with ?token=...');
  return u.toString();
}

function connect(audio = null) {
  clearTimeout(reconnectTimer);
  if (ws) { const old = ws; ws = null; old.close(1000, 'reconnect'); }
  mode = audio ? 'talk' : 'view';
  lastIndex = -1;
  playout.offset = null;  // whatever this connection sends starts a new playout clock
  pingSentAt = null;
  const sock = new WebSocket(api.url);
  sock.binaryType = 'arraybuffer';
  ws = sock;
  setState('connecting');
  sock.onopen = () => {
    if (sock !== ws) return;
    const hello = { type: 'hello', protocol: 1, encoding: ENCODING };
    if (audio) hello.audio = audio;
    sock.send(JSON.stringify(hello));
    reconnectDelay = 1000;
    setState('open');
  };
  sock.onmessage = (ev) => { if (sock === ws) onMessage(ev.data); };
  sock.onclose = (ev) => {
    if (sock !== ws) return;  // a socket we replaced on purpose
    ws = null;
    setState('closed', ev.code === 1000 ? '' : ` (code ${ev.code}${ev.reason ? ': ' + ev.reason : ''})`);
    if (api.talking) stopMic();
    // Keep trying: the server may be restarting. A 401 (bad token) also lands here as code 1006.
    reconnectTimer = setTimeout(() => connect(null), reconnectDelay);
    reconnectDelay = Math.min(reconnectDelay * 2, 10000);
  };
}

function onMessage(data) {
  if (typeof data !== 'string') {
    try { onFrame(decodeBinaryFrame(data)); api.binaryFramesReceived++; } catch (e) { fail(e.message); }
    return;
  }
  let msg;
  try { msg = JSON.parse(data); } catch (e) { fail(`unparsable message: ${data.slice(0, 80)}`); return; }
  switch (msg.type) {
    case 'hello':
      if (msg.protocol !== 1) say(`server speaks protocol ${msg.protocol}; this page expects 1`);
      api.hello = msg;
      try { buildSkeleton(msg.skeleton); } catch (e) { fail(e.message); return; }
      // Buffer one inference window (frames come in bursts of that length) plus some network jitter.
      playout.delayS = (msg.window_ms ? msg.window_ms / 1000 : 0.25) + 0.06;
      ui.talk.disabled = !(msg.audio && msg.audio.accepts) && !api.talking;
      if (!api.talking) ui.talk.title = msg.audio && msg.audio.accepts ? 'Talk to the avatar' : 'this server takes no audio';
      break;
    case 'frame': onFrame(msg); break;
    case 'status': api.status = msg; break;
    case 'pong': if (pingSentAt !== null) { api.rttMs = performance.now() - pingSentAt; pingSentAt = null; } break;
    case 'error':
      api.errors.push(msg);
      say(`server error ${msg.code}: ${msg.message}`);
      // The server will not take (more of) our audio: stop the microphone and watch again.
      if (mode === 'talk' && ['busy', 'audio_disabled', 'internal'].includes(msg.code)) {
        stopMic();
        reconnectTimer = setTimeout(() => connect(null), 1000);
      }
      break;
    case 'end':
      api.ended = msg;
      say(`source ended after ${msg.frames} frames`);
      // A finished talk session goes back to watching the server's own source.
      if (mode === 'talk' && !api.talking) reconnectTimer = setTimeout(() => connect(null), 500);
      break;
    default: break;  // newer message types are ignored, as the protocol asks
  }
}

function onFrame(f) {
  if (!joints.length) return;  // frames before hello cannot be placed
  if (lastIndex >= 0 && f.index > lastIndex + 1) api.gaps += f.index - lastIndex - 1;
  lastIndex = f.index;
  api.framesReceived++;
  api.lastFrame = f;
  const now = performance.now();
  arrivals.push(now);
  while (arrivals.length && arrivals[0] < now - 1000) arrivals.shift();
  playout.push(f, now / 1000);
}

// ---------------------------------------------------------------- microphone
let mic = null;

async function startTalk() {
  if (api.talking) return stopTalk();
  ui.talk.disabled = true;
  try {
    if (!navigator.mediaDevices) throw new Error('needs a secure context: open the page via localhost or https');
    const stream = await navigator.mediaDevices.getUserMedia(
      { audio: { channelCount: 1, echoCancellation: true, noiseSuppression: true, autoGainControl: true } });
    const ctx = new AudioContext();
    mic = { stream, ctx, node: null };  // set now, so a failure below still releases the microphone
    await ctx.resume();
    const src = ctx.createMediaStreamSource(stream);
    const chunkSamples = Math.round(ctx.sampleRate * 0.02);
    let node;
    if (ctx.audioWorklet) {
      await ctx.audioWorklet.addModule(new URL('./mic-worklet.js', import.meta.url));
      node = new AudioWorkletNode(ctx, 'mic-chunker', { processorOptions: { chunkSamples } });
      node.port.onmessage = (e) => sendAudio(e.data);
    } else {  // older browsers: the deprecated main-thread path
      node = ctx.createScriptProcessor(2048, 1, 1);
      node.onaudioprocess = (e) => sendAudio(new Float32Array(e.inputBuffer.getChannelData(0)));
    }
    src.connect(node);
    node.connect(ctx.destination);  // keeps the node pulled; its output is silence
    mic.node = node;
    api.talking = true;
    api.audioRate = ctx.sampleRate;
    // Our own session: a fresh connection whose hello declares the audio we will send.
    connect({ rate: ctx.sampleRate, format: AUDIO_FORMAT, channels: 1 });
    ui.talk.textContent = 'Stop';
    ui.talk.classList.add('on');
    say(`talking: ${ctx.sampleRate} Hz ${AUDIO_FORMAT}`);
  } catch (e) {
    stopMic();
    say(`microphone: ${e.message}`);
  } finally {
    ui.talk.disabled = false;
  }
}

function stopTalk() {
  if (!api.talking) return;
  stopMic();
  if (ws && ws.readyState === WebSocket.OPEN) {
    ws.send(JSON.stringify({ type: 'audio_end' }));
    say('audio ended; waiting for the last gestures');
  } else {
    connect(null);  // the talk connection never opened: nothing to wait for
  }
}

function stopMic() {
  if (mic) {
    mic.stream.getTracks().forEach((t) => t.stop());
    if (mic.node) mic.node.disconnect();
    mic.ctx.close();
    mic = null;
  }
  api.talking = false;
  ui.talk.textContent = 'Talk';
  ui.talk.classList.remove('on');
}

function sendAudio(f32) {
  if (!api.talking || mode !== 'talk' || !ws || ws.readyState !== WebSocket.OPEN) return;
  if (ws.bufferedAmount > MAX_SEND_BUFFER) { api.audioChunksDropped++; return; }  // bounded, counted
  let buf;
  if (AUDIO_FORMAT === 'float32') {
    buf = new ArrayBuffer(f32.length * 4);
    const dv = new DataView(buf);
    for (let i = 0; i < f32.length; i++) dv.setFloat32(i * 4, f32[i], true);
  } else {
    buf = new ArrayBuffer(f32.length * 2);
    const dv = new DataView(buf);
    for (let i = 0; i < f32.length; i++) dv.setInt16(i * 2, Math.round(Math.max(-1, Math.min(1, f32[i])) * 32767), true);
  }
  ws.send(buf);
  api.audioChunksSent++;
}

ui.talk.addEventListener('click', () => startTalk());

// ---------------------------------------------------------------- HUD
function setState(s, detail = '') {
  api.state = s;
  ui.state.textContent = s + detail;
  ui.state.className = s;
}
function say(text) { ui.message.textContent = text; }
function fail(text) { api.errors.push({ code: 'client', message: text }); say(text); }
const fmt = (x, d = 1) => (typeof x === 'number' && isFinite(x) ? x.toFixed(d) : '-');

setInterval(() => {
  const s = api.status || {};
  api.fps = arrivals.length;
  ui.frames.textContent = api.framesReceived;
  ui.fps.textContent = `${api.fps}` + (api.hello ? ` / ${api.hello.fps}` : '');
  ui.latency.textContent = s.latency_ms !== undefined ? `${fmt(s.latency_ms, 0)} ms` : '-';
  ui.rtt.textContent = api.rttMs !== null ? `${fmt(api.rttMs, 0)} ms` : '-';
  ui.buffer.textContent = api.bufferMs !== null ? `${fmt(api.bufferMs, 0)} ms` : '-';
  ui.rtf.textContent = fmt(s.rtf, 2);
  ui.dropped.textContent = `${s.dropped ?? '-'} / ${api.gaps}`;
  ui.clients.textContent = s.clients ?? '-';
}, 250);

setInterval(() => {  // round trip on the same socket as the frames
  if (ws && ws.readyState === WebSocket.OPEN && pingSentAt === null) {
    pingSentAt = performance.now();
    ws.send(JSON.stringify({ type: 'ping' }));
  }
}, 2000);

resolveUrl().then((url) => {
  api.url = url;
  ui.url.textContent = url.replace(/token=[^&]+/, 'token=…');
  connect(null);
});
