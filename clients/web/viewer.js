// dimgestor browser viewer: protocol v1 revision 7 client (docs/protocol.md), the built-in mannequin, your own
// VRM, the server source's audio in sync, and the microphone (Talk), paused by the server's flow control. The face
// (revision 7): the page asks for FACE_SET's names (face.js) and shows each frame's face with its pose.
//
// Page parameters: ?ws=ws://host:port/  (another server than the one this page came from)
//                  ?token=T             (when the server requires one)
//                  ?encoding=binary     (DGF1 binary frames instead of JSON)
//                  ?audio=float32       (microphone wire format; default pcm16)
//                  ?avatar=skeleton     (start with the skeleton instead of the mannequin)
//                  ?sound=off           (start muted)
//                  ?local=model/        (no server: the model runs in this browser, local-engine.js)
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { PlayoutClock } from './av-clock.js';
import { SpeechToMotion } from './latency.js';
import { FramePlayout } from './playout.js';
import { FrameRing } from './frame-ring.js';
import { MIC_HOLD_S } from './audio-flow.js';
import { buildMannequin } from './mannequin.js';
import { FACE_SET, mouthOf } from './face.js';
import { SourceAudio } from './source-audio.js';

const params = new URLSearchParams(location.search);
const ENCODING = params.get('encoding') === 'binary' ? 'binary' : 'json';
const AUDIO_FORMAT = params.get('audio') === 'float32' ? 'float32' : 'pcm16';
// A speaker of a model trained on several (revision 9, `hello.speakers`): ?speaker=NAME; an empty ?speaker= asks for
// none in particular; absent, the server's default.
const SPEAKER = params.has('speaker') ? (params.get('speaker') || null) : undefined;
const UNIT_TO_M = { m: 1, cm: 0.01, mm: 0.001 };
const LIVE_SLACK_S = 0.1;    // talking: spare buffer above that kept for 10 s is given back (av-clock.js setSlack)
const LIVE_MARGIN_S = 0.05;  // talking: the playout buffer above the lateness seen (benchmarks/latency.py)
const RESUME_WITHIN_MS = 10000;  // after a goaway: tries to resume this long before a fresh session
const FPS_WINDOW_MS = 5000;       // received fps is averaged over this long (frames come in bursts)

const $ = (id) => document.getElementById(id);
const ui = { state: $('state'), frames: $('frames'), fps: $('fps'), latency: $('latency'), rtt: $('rtt'),
             rtf: $('rtf'), buffer: $('buffer'), dropped: $('dropped'), clients: $('clients'), talk: $('talk'),
             message: $('message'), url: $('url'), delay: $('delay'), avatar: $('avatar'), sound: $('sound'),
             pause: $('pause'), resetView: $('reset-view'), loadVrm: $('load-vrm'), vrmFile: $('vrm-file'),
             drop: $('drop'), paused: $('paused') };

const sourceAudio = new SourceAudio();
let localSound = false;  // local mode (below): the stream is a dropped file, its sound played
// Everything a test or the console may want to read.
const ARRIVAL_LOG = 4000;  // frames (200 s at 20 fps)
const api = window.dimgestor = {
  state: 'connecting', url: null, hello: null, status: null, ended: null, errors: [],
  framesReceived: 0, binaryFramesReceived: 0, lastFrame: null, shownFrame: null, bufferMs: null,
  gaps: 0, fps: 0, rttMs: null, delayMs: null, delayMeasured: false, timingSeen: false,
  talking: false, audioRate: null, audioChunksSent: 0, audioChunksDropped: 0, micMonitorGain: null,
  audioFlow: null,  // the microphone's flow (socket-worker.js) while talking: paused, pauses, resumes, heldS, ...
  notices: [],      // slow_down / resume: the server's flow control, not errors
  handovers: 0, resumed: 0,  // goaway (the worker stopped) while talking; sessions resumed on another worker
  reconnects: 0,    // talk connections lost without a goaway, talked on in a fresh session
  arrivalLog: [],   // [arrival (s, page clock, when this thread could show it), pts] of the last ARRIVAL_LOG frames
  avatar: 'mannequin', vrm: null, paused: false, sourceAudio, renderMs: null, frameMs: null,
  jointNames: () => (api.hello ? api.hello.skeleton.joints.slice() : []),
  // The frame channels the server sends beside the pose (revision 6: hello.channels; revision 7: the latest
  // `channels` message, e.g. the face once asked for); a frame's values are in lastFrame.channels[name].
  channels: [],
  channelNames: () => api.channels.map((c) => c.name),
  // The face shown (revision 7: the shown frame's `face`, by name; null when the stream has none) and what the
  // mannequin makes of it: {jaw, blinkLeft, blinkRight, smile} (0..1); a VRM's expressions are api.vrm.expressions.
  face: null, mouth: { jaw: 0, blinkLeft: 0, blinkRight: 0, smile: 0 }, faceSet: FACE_SET,
  frameFace: () => frameFace(),
  faceBox: (part) => faceBox(part),
  jointWorldPositions, talk: () => startTalk(), stopTalk: () => stopTalk(),
  loadAvatarFile: (file) => loadAvatarFile(file), setAvatar: (m) => setAvatar(m), resetView: () => resetView(),
  setPaused: (p) => setPaused(p), setMuted: (m) => setMuted(m),
  facing: () => facing(), cameraPosition: () => camera.position.toArray(),
};

// ---------------------------------------------------------------- scene
const scene = new THREE.Scene();
scene.background = gradientTexture('#2a3039', '#111318');
scene.fog = new THREE.Fog(0x15181d, 8, 22);
scene.add(new THREE.HemisphereLight(0xdfe8ff, 0x3a3430, 1.1));
const key = new THREE.DirectionalLight(0xfff4e8, 2.4);  // key light from the front left, casting shadows
key.position.set(2.0, 4.0, 3.5);
key.castShadow = true;
// A software renderer (no GPU: SwiftShader, llvmpipe) draws every pixel on the CPU: there the viewer draws without
// MSAA and with a 512 shadow map (in headless Chromium beside other work: ~2 -> ~9 fps for the mannequin,
// benchmarks/results/latency_talk_worker.json; a page's messages wait for its drawing, README "Latency"). Its cost
// follows the canvas's pixels and the mannequin's triangles, not shadows or tone mapping (headless Chromium on two
// cores, 960x640, the mannequin streaming: 150 ms a drawing; at half the pixel density 85 ms; with 0.4 of the
// segments too, 39 ms), so there the canvas has half the page's pixel density, the mannequin fewer segments, and
// it is drawn at most SOFTWARE_FPS times a second (the stream's own frame rate): ~7 -> ~17-20 drawings a second,
// each for about a quarter of the CPU, and a page that no longer takes every core it can get.
const SOFTWARE_GL = softwareGl();
const SOFTWARE_PIXEL_RATIO = 0.5;
const SOFTWARE_FPS = 20;
const SOFTWARE_DETAIL = 0.4;  // the mannequin's curves with 0.4 of their segments (a frame's triangles: 226k -> 37k)
key.shadow.mapSize.setScalar(SOFTWARE_GL ? 512 : 1024);
Object.assign(key.shadow.camera, { left: -2, right: 2, top: 2.5, bottom: -0.5, near: 0.5, far: 12 });
key.shadow.bias = -0.0005;
key.shadow.normalBias = 0.02;
const lights = new THREE.Group();  // key, rim and fill turn with the framing: the avatar is lit from the camera's side
scene.add(lights, key.target);
lights.add(key);
const rim = new THREE.DirectionalLight(0x9fbaff, 1.6);  // cool rim from behind: separates it from the background
rim.position.set(-2.5, 3.0, -3.5);
lights.add(rim);
const fill = new THREE.DirectionalLight(0xffffff, 0.5);
fill.position.set(-3, 1.5, 2);
lights.add(fill);
const floor = new THREE.Mesh(new THREE.CircleGeometry(6, 64),
                             new THREE.MeshStandardMaterial({ color: 0x262b33, roughness: 0.95 }));
floor.rotation.x = -Math.PI / 2;
floor.receiveShadow = true;
scene.add(floor);
const grid = new THREE.GridHelper(12, 24, 0x4a5260, 0x323842);  // 50 cm cells
grid.position.y = 0.001;
grid.material.transparent = true;
grid.material.opacity = 0.5;
scene.add(grid);

const camera = new THREE.PerspectiveCamera(30, innerWidth / innerHeight, 0.01, 100);
camera.position.set(0, 1.2, 4);
let renderer = null;
let controls = null;
try {
  renderer = new THREE.WebGLRenderer({ antialias: !SOFTWARE_GL });
  renderer.setPixelRatio(SOFTWARE_GL ? SOFTWARE_PIXEL_RATIO * devicePixelRatio : devicePixelRatio);
  renderer.setSize(innerWidth, innerHeight);
  renderer.shadowMap.enabled = true;
  renderer.shadowMap.type = THREE.PCFSoftShadowMap;
  renderer.toneMapping = THREE.ACESFilmicToneMapping;
  $('view').appendChild(renderer.domElement);
  controls = new OrbitControls(camera, renderer.domElement);
  controls.target.set(0, 1, 0);
  controls.enableDamping = true;
  controls.addEventListener('start', () => { faceFollow = false; });  // the user takes the camera
} catch (e) {
  // Joints are still tracked (jointWorldPositions works); only drawing is lost.
  say(`WebGL unavailable: ${e.message}`);
}
addEventListener('resize', () => { fitViewport(); });
api.drawing = { softwareGl: SOFTWARE_GL, antialias: !SOFTWARE_GL, shadowMap: key.shadow.mapSize.x,
                pixelRatio: renderer ? renderer.getPixelRatio() : null, maxFps: SOFTWARE_GL ? SOFTWARE_FPS : null };

/** Whether WebGL here is a software renderer (its name says so); false when it cannot be told. */
function softwareGl() {
  try {
    const gl = document.createElement('canvas').getContext('webgl2') || document.createElement('canvas').getContext('webgl');
    if (!gl) return false;
    const info = gl.getExtension('WEBGL_debug_renderer_info');  // (Chromium masks gl.RENDERER itself)
    const name = String(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER));
    const lose = gl.getExtension('WEBGL_lose_context');
    if (lose) lose.loseContext();
    return /swiftshader|llvmpipe|softpipe|software/i.test(name);
  } catch (e) {
    return false;
  }
}

function gradientTexture(top, bottom) {
  const c = document.createElement('canvas');
  c.width = 2; c.height = 256;
  const g = c.getContext('2d');
  const grad = g.createLinearGradient(0, 0, 0, 256);
  grad.addColorStop(0, top);
  grad.addColorStop(1, bottom);
  g.fillStyle = grad;
  g.fillRect(0, 0, 2, 256);
  const t = new THREE.CanvasTexture(c);
  t.colorSpace = THREE.SRGBColorSpace;
  return t;
}

/** Keep the avatar centred in the part of the window the HUD does not cover. */
function fitViewport() {
  camera.aspect = innerWidth / innerHeight;
  const hud = $('hud').getBoundingClientRect();
  const shift = innerWidth > 2.5 * hud.right ? hud.right / 2 : 0;
  if (shift) camera.setViewOffset(innerWidth, innerHeight, -shift, 0, innerWidth, innerHeight);
  else camera.clearViewOffset();
  camera.updateProjectionMatrix();
  if (renderer) renderer.setSize(innerWidth, innerHeight);
}

// ---------------------------------------------------------------- the streamed skeleton and its looks
const figure = new THREE.Group();  // holds the skeleton in file units, scaled to metres
scene.add(figure);
let joints = [];                   // one Object3D per joint, in skeleton order
let roots = [];                    // indices of joints whose parent is -1
let looks = { mannequin: [], skeleton: [] };  // the meshes of each built-in look
let body = null;                   // buildMannequin's result: facing and bounds at rest
let skeletonScale = 0.01;
let vrmAvatar = null;              // a VrmAvatar when one is loaded
const boneMaterial = new THREE.MeshStandardMaterial({ color: 0xd9b38c, roughness: 0.6 });
const jointMaterial = new THREE.MeshStandardMaterial({ color: 0x5b8def, roughness: 0.5 });

function buildSkeleton(sk, humanoid) {
  const { joints: names, parents, offsets } = sk;
  const rest = sk.rest_rotations || names.map(() => [1, 0, 0, 0]);
  if (parents.length !== names.length || offsets.length !== names.length || rest.length !== names.length)
    throw new Error(`hello.skeleton: ${names.length} joints but ${parents.length} parents, ` +
                    `${offsets.length} offsets, ${rest.length} rest rotations`);
  figure.clear();
  figure.scale.setScalar(1);
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
  if (!(sk.units in UNIT_TO_M)) say(`unknown skeleton units "${sk.units}", assuming cm`);
  skeletonScale = UNIT_TO_M[sk.units] ?? 0.01;

  body = buildMannequin(sk, humanoid, joints, SOFTWARE_GL ? SOFTWARE_DETAIL : 1);
  looks = { mannequin: body.meshes, skeleton: buildStickFigure(sk) };
  figure.scale.setScalar(skeletonScale);
  if (vrmAvatar) attachVrm(vrmAvatar.vrm);  // a new skeleton (another server): retarget the VRM to it
  setAvatar(api.avatar);
  resetView();
  needFraming = true;  // again once the first frame shows how it stands
}

/** The debug look: a capsule per bone and a sphere per joint. */
function buildStickFigure(sk) {
  const meshes = [];
  const height = Math.max(body.bounds.max.y - body.bounds.min.y, 1e-3);
  const radius = 0.012 * height;
  const up = new THREE.Vector3(0, 1, 0);
  sk.parents.forEach((p, j) => {
    const off = new THREE.Vector3().fromArray(sk.offsets[j]);
    const len = off.length();
    const ball = p < 0 ? radius : Math.min(0.7 * radius, 0.35 * len);
    if (ball > 1e-6) {
      const m = new THREE.Mesh(new THREE.SphereGeometry(ball, 12, 8), jointMaterial);
      joints[j].add(m);
      meshes.push(m);
    }
    if (p < 0 || len < 1e-6) return;
    const r = Math.min(radius, 0.2 * len);
    const bone = new THREE.Mesh(new THREE.CapsuleGeometry(r, Math.max(len - 2 * r, 1e-4), 4, 10), boneMaterial);
    bone.position.copy(off).multiplyScalar(0.5);
    bone.quaternion.setFromUnitVectors(up, off.normalize());
    joints[p].add(bone);
    meshes.push(bone);
  });
  return meshes;
}

function setAvatar(mode) {
  if (mode === 'vrm' && !vrmAvatar) mode = 'mannequin';
  if (!['mannequin', 'skeleton', 'vrm'].includes(mode)) mode = 'mannequin';
  api.avatar = mode;
  looks.mannequin.forEach((m) => { m.visible = mode === 'mannequin'; });
  looks.skeleton.forEach((m) => { m.visible = mode === 'skeleton'; });
  if (vrmAvatar) vrmAvatar.vrm.scene.visible = mode === 'vrm';
  ui.avatar.value = mode;
}

/** The avatar's facing now: {forward (world, unit), toCamera (unit, horizontal), cos (their angle's cosine)}. */
function facing() {
  if (!body || !joints.length) return null;
  const hips = joints[roots[0]];
  const fwd = currentForward();
  const toCam = camera.position.clone().sub(hips.getWorldPosition(new THREE.Vector3())).setY(0).normalize();
  return { forward: fwd.toArray(), toCamera: toCam.toArray(), cos: fwd.dot(toCam) };
}

/** The avatar's forward direction now (horizontal, world): from where its left and right legs (or arms) and
 * its head are, like a person would judge it; the rest facing turned by the root where those are missing. */
function currentForward() {
  figure.updateMatrixWorld(true);
  const idx = (b) => api.hello.skeleton.joints.indexOf((api.hello.humanoid || {})[b]);
  const pos = (j) => joints[j].getWorldPosition(new THREE.Vector3());
  let fwd = null;
  for (const [l, r] of [['LeftUpperLeg', 'RightUpperLeg'], ['LeftUpperArm', 'RightUpperArm']]) {
    const [jl, jr, jh, jt] = [idx(l), idx(r), idx('Hips'), idx('Head')];
    if (jl < 0 || jr < 0) continue;
    const left = pos(jl).sub(pos(jr));
    const up = jh >= 0 && jt >= 0 ? pos(jt).sub(pos(jh)) : new THREE.Vector3(0, 1, 0);
    fwd = left.cross(up).setY(0);
    break;
  }
  if (!fwd) fwd = body.forward.clone().applyQuaternion(joints[roots[0]].getWorldQuaternion(new THREE.Quaternion())).setY(0);
  return fwd.lengthSq() > 1e-9 ? fwd.normalize() : body.forward.clone();
}

/** A close-up of the head from the front (key F): the face, as it speaks; R frames the whole body again. */
function frameFace() {
  if (!body || !joints.length) return;
  const jh = api.hello.skeleton.joints.indexOf((api.hello.humanoid || {}).Head);
  if (jh < 0) return;
  resetView();  // the lights and framing of the whole body first, then closer along the same line
  figure.updateMatrixWorld(true);
  const vrmHead = vrmAvatar && api.avatar === 'vrm' ? vrmAvatar.vrm.humanoid.getNormalizedBoneNode('head') : null;
  const headAt = (vrmHead || joints[jh]).getWorldPosition(new THREE.Vector3());
  // About a head and neck in view: 36 of the mannequin's centimetres, or a fifth of the VRM's height.
  const size = vrmHead ? 0.2 * (vrmAvatar.restBounds.max.y - vrmAvatar.restBounds.min.y) : 36 * body.unit * skeletonScale;
  const target = headAt.add(new THREE.Vector3(0, size * 0.2, 0));
  const dir = camera.position.clone().sub(controls ? controls.target : target).setY(0).normalize();
  const dist = size / 2 / Math.tan(THREE.MathUtils.degToRad(camera.fov) / 2);
  camera.position.copy(target).addScaledVector(dir, dist);
  if (controls) { controls.target.copy(target); controls.update(); }
  camera.lookAt(target);
  followFrom = joints[roots[0]].getWorldPosition(new THREE.Vector3());
}

/** Where the mannequin's 'mouth' or 'eyes' are on screen now: [x0, y0, x1, y1] in CSS pixels (for tests and tools). */
function faceBox(part) {
  if (!body) return null;
  figure.updateMatrixWorld(true);
  const box = new THREE.Box3();
  for (const m of body.face.parts[part] || []) box.expandByObject(m);
  if (box.isEmpty()) return null;
  let [x0, y0, x1, y1] = [Infinity, Infinity, -Infinity, -Infinity];
  for (let i = 0; i < 8; i++) {
    const p = new THREE.Vector3(i & 1 ? box.max.x : box.min.x, i & 2 ? box.max.y : box.min.y,
                                i & 4 ? box.max.z : box.min.z).project(camera);
    const x = (p.x + 1) / 2 * innerWidth, y = (1 - p.y) / 2 * innerHeight;
    [x0, y0, x1, y1] = [Math.min(x0, x), Math.min(y0, y), Math.max(x1, x), Math.max(y1, y)];
  }
  return [Math.floor(x0), Math.floor(y0), Math.ceil(x1), Math.ceil(y1)];
}

/** Put the camera in front of the avatar as it stands now, the whole body in view. */
function resetView() {
  if (!body) return;
  fitViewport();
  const s = skeletonScale;
  const box = body.bounds.clone();
  box.min.multiplyScalar(s); box.max.multiplyScalar(s);
  if (vrmAvatar && api.avatar === 'vrm') box.copy(vrmAvatar.restBounds);
  const height = box.max.y - Math.min(box.min.y, 0);
  const center = new THREE.Vector3(0, Math.min(box.min.y, 0) + height * 0.5, 0);
  const hips = joints[roots[0]].getWorldPosition(new THREE.Vector3());
  center.x = hips.x; center.z = hips.z;
  const fov = THREE.MathUtils.degToRad(camera.fov);
  const fit = Math.max(height * 1.2, (box.max.x - box.min.x) * 0.55 / camera.aspect);
  const dist = fit / 2 / Math.tan(fov / 2);
  const fwd = currentForward();
  lights.rotation.y = Math.atan2(fwd.x, fwd.z);
  lights.position.set(center.x, 0, center.z);
  key.target.position.set(center.x, 0, center.z);
  camera.position.copy(center).addScaledVector(fwd, dist).add(new THREE.Vector3(0, height * 0.04, 0));
  if (controls) { controls.target.copy(center); controls.update(); }
  camera.lookAt(center);
  followFrom = hips.clone();
  faceFollow = true;
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
  applyFace(f.face || null);
}

/** The frame's face on the avatars: the mannequin's jaw and eyelids, a VRM's expressions (null: at rest). */
function applyFace(face) {
  api.face = face;
  api.mouth = mouthOf(face);
  if (body) body.face.set(api.mouth);
  if (vrmAvatar) vrmAvatar.setFace(face);
}

// Frames are shown at their presentation time, not on arrival (they come in bursts): playout.js keeps them and
// interpolates; av-clock.js is the one clock of picture and sound (a jitter buffer sized from the lateness seen).
const playout = new FramePlayout();
let ring = null;  // the stream's FrameRing (shared memory with the socket worker) when the page is isolated
const clock = new PlayoutClock();
api.playout = playout;
api.clock = clock;
let lastShowAt = performance.now();
let needFraming = false;

function showPose() {
  takeRing();  // the frames the socket worker has by now, whatever messages wait behind this drawing
  const nowMs = performance.now();
  const dt = (nowMs - lastShowAt) / 1000;
  lastShowAt = nowMs;
  if (api.paused) return;
  const now = nowMs / 1000;
  clock.startLeadS = sourceAudio.leadS(now);
  let t = clock.time(now);
  const ranOut = sourceAudio.ranOutAt();  // the page came too late to go on with the sound: hold there too
  if (ranOut !== null && clock.soundStopped(ranOut, now)) t = clock.time(now);
  sourceAudio.sync(clock.offset, now, clock.horizon());
  const pose = t === null ? null : playout.sampleAt(t);
  if (!pose || !joints.length) return;
  if (pose !== api.shownFrame) {
    applyFrame(pose);
    api.shownFrame = pose;
    api.shownAt = now;
    api.bufferMs = (clock.newestPts - t) * 1000;
    if (needFraming) { needFraming = false; resetView(); }
  }
  if (vrmAvatar && api.avatar === 'vrm') {
    figure.updateMatrixWorld(true);
    vrmAvatar.drive(joints, Math.min(dt, 0.1));
  }
}
setInterval(showPose, 50);  // keeps the pose current when the tab is hidden and rAF stops

/** World positions of every joint in metres (three.js = BVH space), skeleton order. */
function jointWorldPositions() {
  figure.updateMatrixWorld(true);
  const v = new THREE.Vector3();
  return joints.map((o) => o.getWorldPosition(v).toArray());
}

let followFrom = null;  // where the hips were when the view was last framed: the camera follows them from there
let faceFollow = true;  // the camera keeps in front of the avatar as it turns, until the user moves the view
const FACE_FOLLOW_S = 0.8;
let lastRender = performance.now();
const PAGE_FRAMES_MS = 2000;
const pageFrames = [];  // [time, interval] of the page's frames in the last PAGE_FRAMES_MS

function render() {
  // (a software renderer: the next drawing is asked for once its share of a second has passed, less half a display
  // frame, as display frames come a little before or after their period)
  const wait = SOFTWARE_GL && renderer ? 1000 / SOFTWARE_FPS - 8 - (performance.now() - lastRender) : 0;
  if (wait > 0) { setTimeout(() => requestAnimationFrame(render), wait); return; }
  requestAnimationFrame(render);
  showPose();
  if (!renderer) return;
  const t = performance.now(), dt = Math.min((t - lastRender) / 1000, 0.5);
  api.frameMs = api.frameMs === null ? t - lastRender : 0.9 * api.frameMs + 0.1 * (t - lastRender);
  // The clock's start holds the page's longest frame of late: a busy page reads posted frames up to that late, and
  // the sound of a stream's first frame must be scheduled before it is due (a late start skips the sound's first
  // moment). Talking from the shared ring neither holds: the page has every frame that came before it draws, and
  // there is no sound; the allowance would stay as latency until the 10 s give-back.
  pageFrames.push([t, t - lastRender]);
  while (pageFrames[0][0] < t - PAGE_FRAMES_MS) pageFrames.shift();
  clock.pageS = ring && api.talking ? 0 : Math.max(...pageFrames.map(([, d]) => d)) / 1000;
  lastRender = t;
  if (joints.length && followFrom && faceFollow && api.shownFrame && !api.paused) {
    // Orbit towards the avatar's front: the model turns as it talks, and a viewer wants to see its face.
    const fwd = currentForward();
    const arm = camera.position.clone().sub(controls.target);
    const diff = Math.atan2(Math.sin(Math.atan2(fwd.x, fwd.z) - Math.atan2(arm.x, arm.z)),
                            Math.cos(Math.atan2(fwd.x, fwd.z) - Math.atan2(arm.x, arm.z)));
    const turn = diff * (1 - Math.exp(-dt / FACE_FOLLOW_S));
    arm.applyAxisAngle(new THREE.Vector3(0, 1, 0), turn);
    camera.position.copy(controls.target).add(arm);
    lights.rotation.y += turn;
  }
  if (joints.length && followFrom) {
    // Follow the avatar across the floor (root motion), not up and down.
    const hips = joints[roots[0]].getWorldPosition(new THREE.Vector3());
    const step = hips.sub(followFrom).setY(0).multiplyScalar(0.1);
    followFrom.add(step);
    controls.target.add(step);
    camera.position.add(step);
    lights.position.add(step);
    key.target.position.add(step);
  }
  controls.update();
  const r0 = performance.now();
  renderer.render(scene, camera);
  api.renderMs = api.renderMs === null ? performance.now() - r0 : 0.9 * api.renderMs + 0.1 * (performance.now() - r0);
}
fitViewport();
render();

// ---------------------------------------------------------------- your own avatar (VRM)
let vrmModule = null;  // loaded on first use: the page starts without it

async function loadAvatarFile(file) {
  if (!/\.(vrm|glb)$/i.test(file.name)) { say(`${file.name}: not a .vrm file`); return false; }
  say(`loading ${file.name} …`);
  try {
    vrmModule = vrmModule || await import('./vrm-avatar.js');
    const vrm = await vrmModule.parseVrm(await file.arrayBuffer());
    if (vrmAvatar) vrmAvatar.dispose();
    attachVrm(vrm);
    const opt = ui.avatar.querySelector('option[value="vrm"]') || ui.avatar.appendChild(new Option('', 'vrm'));
    opt.textContent = `${vrmAvatar.name} (VRM ${vrmAvatar.metaVersion})`;
    setAvatar('vrm');
    resetView();
    say(`${file.name}: ${vrmAvatar.name}, VRM ${vrmAvatar.metaVersion}, ${vrmAvatar.bones.filter((b) => b.joint !== undefined).length} bones driven`);
    return true;
  } catch (e) {
    api.errors.push({ code: 'vrm', message: `${file.name}: ${e.message}` });
    say(`${file.name}: cannot load this avatar (${e.message})`);
    return false;
  }
}

function attachVrm(vrm) {
  if (!joints.length) throw new Error('wait for the server\'s hello before loading an avatar');
  // Retarget against the rest pose: put the skeleton at rest while the VRM measures it.
  const saved = joints.map((o) => [o.position.clone(), o.quaternion.clone()]);
  const sk = api.hello.skeleton;
  const rest = sk.rest_rotations || sk.joints.map(() => [1, 0, 0, 0]);
  joints.forEach((o, j) => { o.position.fromArray(sk.offsets[j]); o.quaternion.set(rest[j][1], rest[j][2], rest[j][3], rest[j][0]); });
  figure.updateMatrixWorld(true);
  scene.add(vrm.scene);
  vrmAvatar = new vrmModule.VrmAvatar(vrm, { joints, humanoid: api.hello.humanoid, forward: body.forward });
  vrm.scene.updateMatrixWorld(true);
  vrmAvatar.restBounds = new THREE.Box3().setFromObject(vrm.scene);
  joints.forEach((o, j) => { o.position.copy(saved[j][0]); o.quaternion.copy(saved[j][1]); });
  figure.updateMatrixWorld(true);
  api.vrm = vrmAvatar;
}

ui.loadVrm.addEventListener('click', () => ui.vrmFile.click());
ui.vrmFile.addEventListener('change', () => { if (ui.vrmFile.files[0]) loadAvatarFile(ui.vrmFile.files[0]); ui.vrmFile.value = ''; });
addEventListener('dragover', (e) => { e.preventDefault(); ui.drop.classList.add('show'); });
addEventListener('dragleave', (e) => { if (!e.relatedTarget) ui.drop.classList.remove('show'); });
addEventListener('drop', (e) => {
  e.preventDefault();
  ui.drop.classList.remove('show');
  const file = e.dataTransfer && e.dataTransfer.files[0];
  if (file) loadAvatarFile(file);
});
ui.avatar.addEventListener('change', () => { setAvatar(ui.avatar.value); resetView(); });

// ---------------------------------------------------------------- protocol
// The WebSocket lives in a Web Worker (socket-worker.js): the microphone's audio goes up and frames come down
// (parsed, and stamped on arrival) without waiting for this thread's drawing. Here: which connection is current
// and what its messages mean for the page.
let link = null;                   // the socket worker, made at the first connect
let connId = 0;                    // the current connection: the worker's events of older ones are ignored
let connOpen = false;
let connOpened = false;            // the current connection opened at some point
let mode = 'view';                 // 'view': watch the server's source; 'talk': own session fed by the mic
let reconnectTimer = null;
let reconnectDelay = 1000;
let pingSentAt = null;
let lastIndex = -1;
const arrivals = [];                // frame arrival times (ms) over the last FPS_WINDOW_MS, for the fps readout
const speech = new SpeechToMotion(); // when each moment of the speech was said: the measured speech -> motion

// The page and the WebSocket share one port (streamer serve answers both): connect to the page's own origin.
function socketUrl() {
  const given = params.get('ws');
  const scheme = location.protocol === 'https:' ? 'wss' : 'ws';  // behind a TLS proxy
  const u = new URL(given || (location.host ? `${scheme}://${location.host}/` : 'ws://localhost:8765/'));
  // A server bound to every interface may be named 0.0.0.0, which a browser cannot dial.
  if (['0.0.0.0', '[::]', '::'].includes(u.hostname) && location.hostname) u.hostname = location.hostname;
  const token = params.get('token');
  if (token) u.searchParams.set('token', token);
  return u.toString();
}

// ---- hand-over (protocol revision 3): a worker that stops sends `goaway` with a resume token; our session goes
// on on another worker (the same URL: a balancer picks one) from the sample its state covers. The socket worker
// keeps the audio we sent lately, holds the microphone meanwhile and re-sends at session_resumed.
let handover = null;  // {token, since (ms)} from a goaway until session_resumed (or a fresh session)

function socketWorker() {
  if (!link) {
    link = new Worker(new URL('./socket-worker.js', import.meta.url), { type: 'module' });
    link.onmessage = (e) => fromWorker(e.data);
    link.onerror = (e) => fail(`socket worker: ${e.message}`);
    link.postMessage({ type: 'init', pageOrigin: performance.timeOrigin });
  }
  return link;
}

/** Close the current connection on purpose (its close event is then ignored: no reconnect from it). */
function dropConnection(reason) {
  connId++;
  connOpen = false;
  if (link) link.postMessage({ type: 'close', code: 1000, reason });
}

/** Frames from the shared ring: this thread has them the moment it looks, so the socket worker's arrival stamp is
 *  when they could be shown (posted frames are later: when this thread got round to their message). */
function takeRing() {
  if (ring) for (const [f, at, binary] of ring.take()) { onFrame(f, at, at); if (binary) api.binaryFramesReceived++; }
}

function fromWorker(m) {
  if (m.type === 'mic') { onMicReport(m); return; }
  if (m.id !== connId) return;  // a connection replaced since
  takeRing();  // frames the worker had before this message come first
  if (m.ring) ring = new FrameRing(m.ring, m.layout.joints, m.layout.channels, m.layout.faceLabels);
  switch (m.type) {
    case 'ring': break;  // the frames go to a new ring from here on (another layout)
    case 'open': onOpen(); break;
    case 'close': onClose(m); break;
    case 'frame': onFrame(m.frame, m.at, performance.now()); if (m.binary) api.binaryFramesReceived++; break;
    case 'sourceAudio': onSourceAudio(m.chunk, m.at); break;
    case 'message': onParsed(m.msg, m.at); break;
    case 'bad': fail(m.message); break;
    default: fail(`socket worker: unknown event ${JSON.stringify(m.type)}`);
  }
}

function connect(audio = null, resume = null) {
  clearTimeout(reconnectTimer);
  endPending = false;
  mode = audio ? 'talk' : 'view';
  pingSentAt = null;
  if (!resume) {  // a resumed session goes on: its frames, clocks and audio continue where they were
    handover = null;
    resetStream();
  }
  if (resume) takeRing();  // the old stream's last frames: the resumed one goes on from them
  ring = null;
  connId++;
  connOpen = connOpened = false;
  // Watching: ask for the source's audio too (servers without it ignore the field). Talking: never, so nothing
  // but the avatar answers the microphone. Each window's `timing` (revision 5) dates the speech for the speech ->
  // motion readout. The worker sends it (and resume_session) when the socket opens.
  // The face (revision 7) in FACE_SET's names, in JSON and binary frames alike; older servers ignore the field.
  const hello = { type: 'hello', protocol: 1, encoding: ENCODING, source_audio: !audio, timing: true, face: FACE_SET };
  if (audio) hello.audio = audio;
  if (SPEAKER !== undefined) hello.speaker = SPEAKER;
  socketWorker().postMessage({ type: 'connect', id: connId, url: api.url, hello, resume: resume ? resume.token : null });
  setState('connecting');
}

/** Forget the stream shown so far: whatever comes next starts a new playout clock, sound and speech readout. */
function resetStream() {
  lastIndex = -1;
  playout.offset = null;
  playout.queue = [];
  clock.reset();
  sourceAudio.clear();
  speech.reset();
  api.timingSeen = false;
  arrivals.length = 0;
}

/** The playout buffer for this `mode`, frames coming in bursts of `windowS` (null: not said) at `fps`. Talking:
 *  only what the lateness may still grow by above the worst lateness of late (which already holds a window's
 *  burst; underruns grow it, av-clock.js), spare buffer given back; watching with the sound: one window plus
 *  network jitter, so the sound seldom pauses. */
function sizePlayout(windowS, fps) {
  playout.delayS = mode === 'talk' ? LIVE_MARGIN_S : (windowS || 0.25) + 0.06;
  clock.setBaseMargin(playout.delayS);
  clock.setSlack(mode === 'talk' ? LIVE_SLACK_S : 0.5);
  clock.setBursts(windowS || 0.2, 1 / (fps || 20));
}

function onOpen() {
  connOpen = connOpened = true;
  reconnectDelay = 1000;
  setState('open');
}

function onClose(ev) {
  connOpen = false;
  connId++;  // this connection is over: nothing more of it counts
  if (handover && api.talking) {  // the worker stopped (1012 after goaway): resume on another, at once
    setState('moving');
    reconnectTimer = setTimeout(() => resumeOrRestart(), 50);
    return;
  }
  setState('closed', ev.code === 1000 ? '' : ` (code ${ev.code}${ev.reason ? ': ' + ev.reason : ''})`);
  if (api.talking && connOpened) {  // our worker went away (killed, or stopped without a state store): talk on in
    api.reconnects++;               // a fresh session on whichever worker answers (a failed try stops the mic below)
    say('connection lost: talking on in a fresh session');
    reconnectTimer = setTimeout(() => connect(api.talkFormat), 250);  // (the held audio is the old session's)
    return;
  }
  // A refused handshake (a 401 for a missing token) reaches a page only as a close before open.
  if (!connOpened && !params.get('token')) say('cannot connect: if the server requires a token, open this page with ?token=...');
  if (api.talking) stopMic();
  // Keep trying: the server may be restarting. A 401 (bad token) also lands here as code 1006.
  reconnectTimer = setTimeout(() => connect(null), reconnectDelay);
  reconnectDelay = Math.min(reconnectDelay * 2, 10000);
}

function resumeOrRestart() {
  if (!api.talking) { handover = null; connect(null); return; }
  if (performance.now() - handover.since < RESUME_WITHIN_MS) { connect(api.talkFormat, handover); return; }
  say('could not resume our session on another worker: a fresh one starts');
  connect(api.talkFormat);  // (the socket worker drops what was held: it belongs to the old session)
}

/** A message as JSON text (local mode: local-engine.js hands its messages here). */
function onMessage(data) {
  let msg;
  try { msg = JSON.parse(data); } catch (e) { fail(`unparsable message: ${data.slice(0, 80)}`); return; }
  onParsed(msg, performance.now());
}

/** A parsed message from the server that arrived at `at` (ms, page clock). */
function onParsed(msg, at) {
  switch (msg.type) {
    case 'hello':
      if (msg.protocol !== 1) say(`server speaks protocol ${msg.protocol}; this page expects 1`);
      api.hello = msg;
      api.channels = Array.isArray(msg.channels) ? msg.channels : [];
      try { buildSkeleton(msg.skeleton, msg.humanoid); } catch (e) { fail(e.message); return; }
      sizePlayout(msg.window_ms ? msg.window_ms / 1000 : null, msg.fps);
      ui.talk.disabled = !(msg.audio && msg.audio.accepts) && !api.talking;
      if (!api.talking) ui.talk.title = msg.audio && msg.audio.accepts ? 'Talk to the avatar' : 'this server takes no audio';
      ui.sound.disabled = !msg.source_audio || mode === 'talk';
      updateSoundButton();
      if (msg.source === 'ws' && mode === 'view' && !api.talking) {
        say('This server has no audio of its own: press Talk and speak.');
        ui.talk.classList.add('hint');
      } else ui.talk.classList.remove('hint');
      break;
    case 'frame': onFrame(msg, at, at); break;
    case 'channels':  // revision 7: the channels binary frames carry from the next frame on (the socket worker reads them)
      if (Array.isArray(msg.channels)) api.channels = msg.channels;
      break;
    case 'status': api.status = msg; break;
    case 'pong':
      if (typeof msg.t === 'number') speech.notePong(msg.t / 1000, at / 1000, msg.server_time_s);
      if (pingSentAt !== null && typeof msg.t === 'number') { api.rttMs = at - msg.t; pingSentAt = null; }
      break;
    case 'timing':  // watching: the server says when the audio arrived (talking: our own chunks say it better)
      if (mode === 'view' && speech.noteTiming(msg)) api.timingSeen = true;
      break;
    case 'goaway':  // revision 3: this worker is stopping; our session's state is saved under the token
      if (mode === 'talk' && api.talking && msg.resume_token) {
        handover = { token: msg.resume_token, since: performance.now() };
        api.handovers++;  // (the socket worker holds the microphone until session_resumed)
        say('the server is restarting: moving our session to another worker');
      }
      break;
    case 'session_resumed':
      if (mode === 'talk' && handover) {
        handover = null;
        api.resumed++;  // (the socket worker re-sent our audio from msg.samples)
        setState('open');
        say('our session moved to another worker: talking again');
      }
      break;
    case 'error':
      if (handover && ['busy', 'resume_failed'].includes(msg.code)) {  // during a hand-over
        api.notices.push(msg);
        if (msg.code === 'resume_failed') handover.since = -Infinity;  // the token is spent: a fresh session
        dropConnection('resume elsewhere');
        reconnectTimer = setTimeout(() => resumeOrRestart(), msg.code === 'busy' ? 200 : 0);
        break;
      }
      if (msg.code === 'face_withheld') {  // a notice: this session talks without a face (the worker is at capacity)
        api.notices.push(msg);
        say('the server has no room for another face now: the avatar talks without one until the next session');
        break;
      }
      if (msg.code === 'slow_down') {  // a notice, nothing was lost: hold the microphone until `resume`
        api.notices.push(msg);
        if (mode === 'talk' && api.audioFlow) {  // (the socket worker holds the microphone already)
          say(`the server asks us to slow down: holding the microphone until it resumes (at most ${MIC_HOLD_S} s)`);
        }
        break;
      }
      api.errors.push(msg);
      say(`server error ${msg.code}: ${msg.message}`);
      // The server will not take (more of) our audio: stop the microphone and watch again.
      if (mode === 'talk' && ['busy', 'audio_disabled', 'internal'].includes(msg.code)) {
        stopMic();
        reconnectTimer = setTimeout(() => connect(null), 1000);
      }
      break;
    case 'resume':  // revision 2: the server takes our audio again (ignored while only watching)
      api.notices.push(msg);
      if (mode === 'talk' && api.audioFlow) {  // (the socket worker sent what it held, and audio_end if due)
        if (endPending) { endPending = false; say('audio ended; waiting for the last gestures'); }
        else if (api.talking) say(`the server resumed (backlog ${fmt(msg.backlog_s)} s): talking again`);
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

/** A frame that arrived at `now` (ms, page clock) and could be shown from `usable` on (ms). */
function onFrame(f, now, usable) {
  if (!joints.length) return;  // frames before hello cannot be placed
  if (lastIndex >= 0 && f.index > lastIndex + 1) api.gaps += f.index - lastIndex - 1;
  lastIndex = f.index;
  api.framesReceived++;
  api.lastFrame = f;
  arrivals.push(now);
  while (arrivals.length && arrivals[0] <= now - FPS_WINDOW_MS) arrivals.shift();
  // The playout clock takes when this thread could show the frame: a posted frame reaches a page busy drawing up
  // to one of its own frames after the socket worker got it, and that is lateness too; the ring's, no later.
  playout.push(f, usable / 1000);
  clock.arrive(f.pts, usable / 1000);
  api.arrivalLog.push([usable / 1000, f.pts]);
  if (api.arrivalLog.length > ARRIVAL_LOG) api.arrivalLog.splice(0, api.arrivalLog.length - ARRIVAL_LOG);
}

function onSourceAudio(chunk, at) {
  // The server releases source audio as it is spoken (a file source is paced in real time), so its arrival
  // tells when each moment of the speech happened, on our clock.
  if (!api.timingSeen) speech.noteSaid(chunk.pts + chunk.samples.length / chunk.rate, at / 1000);
  sourceAudio.push(chunk);
}

// ---------------------------------------------------------------- sound, pause, view
function updateSoundButton() {
  const available = api.hello && (api.hello.source_audio || localSound) && mode === 'view';
  ui.sound.textContent = !available ? 'No sound' : sourceAudio.muted ? 'Sound off' : sourceAudio.blocked ? 'Sound: click' : 'Sound on';
  ui.sound.classList.toggle('on', !!available && !sourceAudio.muted);
}

function setMuted(muted) { sourceAudio.setMuted(muted); updateSoundButton(); }

async function setPaused(paused) {
  api.paused = paused;
  ui.pause.textContent = paused ? 'Resume' : 'Pause';
  ui.pause.classList.toggle('on', paused);
  ui.paused.classList.toggle('show', paused);
  await sourceAudio.setPaused(paused);
}

ui.sound.addEventListener('click', async () => {
  if (sourceAudio.blocked) await sourceAudio.unlock();  // the click is the gesture the browser waits for
  else setMuted(!sourceAudio.muted);
  updateSoundButton();
});
ui.pause.addEventListener('click', () => setPaused(!api.paused));
ui.resetView.addEventListener('click', () => resetView());
addEventListener('pointerdown', () => { if (sourceAudio.blocked) sourceAudio.unlock().then(updateSoundButton); });
addEventListener('keydown', (e) => {
  if (e.target.tagName === 'INPUT' || e.target.tagName === 'SELECT') return;
  if (e.key === ' ') { e.preventDefault(); setPaused(!api.paused); }
  else if (e.key === 'r' || e.key === 'R') resetView();
  else if (e.key === 'f' || e.key === 'F') frameFace();
  else if (e.key === 'm' || e.key === 'M') setMuted(!sourceAudio.muted);
});
if (params.get('sound') === 'off') setMuted(true);
if (params.get('avatar')) api.avatar = params.get('avatar');

// ---------------------------------------------------------------- microphone
let mic = null;

async function startTalk() {
  if (api.talking) return stopTalk();
  ui.talk.disabled = true;
  ui.talk.classList.remove('hint');
  try {
    if (!navigator.mediaDevices) throw new Error('needs a secure context: open the page via localhost or https');
    const stream = await navigator.mediaDevices.getUserMedia(
      { audio: { channelCount: 1, echoCancellation: true, noiseSuppression: true, autoGainControl: true } });
    const ctx = new AudioContext();
    mic = { stream, ctx, node: null };  // set now, so a failure below still releases the microphone
    await ctx.resume();
    const src = ctx.createMediaStreamSource(stream);
    const chunkSamples = Math.round(ctx.sampleRate * 0.02);
    const toWorker = new MessageChannel();  // the microphone's chunks -> the socket worker, not through this thread
    let node;
    if (ctx.audioWorklet) {
      await ctx.audioWorklet.addModule(new URL('./mic-worklet.js', import.meta.url));
      node = new AudioWorkletNode(ctx, 'mic-chunker', { processorOptions: { chunkSamples, viaPort: true } });
      node.port.postMessage({ port: toWorker.port1 }, [toWorker.port1]);
    } else {  // older browsers: the deprecated main-thread path
      node = ctx.createScriptProcessor(2048, 1, 1);
      node.onaudioprocess = (e) => toWorker.port1.postMessage(new Float32Array(e.inputBuffer.getChannelData(0)));
    }
    socketWorker().postMessage({ type: 'mic', port: toWorker.port2, rate: ctx.sampleRate, format: AUDIO_FORMAT },
                               [toWorker.port2]);
    // The node must reach the destination to be pulled; a zero gain makes sure the microphone is never heard.
    const silence = ctx.createGain();
    silence.gain.value = 0;
    src.connect(node);
    node.connect(silence).connect(ctx.destination);
    api.micMonitorGain = silence.gain.value;
    mic.node = node;
    api.talking = true;
    api.audioRate = ctx.sampleRate;
    api.audioFlow = { paused: false, pauses: 0, resumes: 0, heldS: 0, droppedS: 0, droppedChunks: 0 };
    // Our own session: a fresh connection whose hello declares the audio we will send.
    api.talkFormat = { rate: ctx.sampleRate, format: AUDIO_FORMAT, channels: 1 };
    connect(api.talkFormat);
    ui.talk.textContent = 'Stop';
    ui.talk.classList.add('on');
    updateSoundButton();
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
  if (connOpen) {
    link.postMessage({ type: 'audioEnd' });  // the socket worker sends it after what it holds (at `resume`)
    if (api.audioFlow && api.audioFlow.paused) {
      endPending = true;
      say('stopped; the server has us paused: the last audio and audio_end go when it resumes');
    } else say('audio ended; waiting for the last gestures');
  } else {
    connect(null);  // the talk connection never opened: nothing to wait for
  }
}

let endPending = false;  // stopped talking while paused: audio_end waits for `resume` (after the held audio)

function stopMic() {
  if (mic) {
    mic.stream.getTracks().forEach((t) => t.stop());
    if (mic.node) mic.node.disconnect();
    mic.ctx.close();
    mic = null;
  }
  if (link) link.postMessage({ type: 'micStop' });
  api.talking = false;
  ui.talk.textContent = 'Talk';
  ui.talk.classList.remove('on');
}

/** The socket worker's account of the microphone: counts, flow state, and when the chunk it took was said. */
function onMicReport(m) {
  api.audioChunksSent = m.sent;
  api.audioChunksDropped = m.dropped;
  if (api.audioFlow) Object.assign(api.audioFlow, m.flow);
  if (!api.talking || mode !== 'talk') return;
  // Our own speech: the chunk's last sample was said when the worker got it, at pts = the samples up to it.
  if (m.said) speech.noteSaid(m.said[0], m.said[1]);
  if (m.startedDropping) say(`paused by the server for over ${MIC_HOLD_S} s: dropping the oldest microphone audio (counted)`);
}

ui.talk.addEventListener('click', () => (local ? local.toggleMic().catch((e) => say(`microphone: ${e.message}`)) : startTalk()));

// ---------------------------------------------------------------- HUD
function setState(s, detail = '') {
  api.state = s;
  ui.state.textContent = s + detail;
  ui.state.className = s;
}
function say(text) { ui.message.textContent = text; }
function fail(text) { api.errors.push({ code: 'client', message: text }); say(text); }
const fmt = (x, d = 1) => (typeof x === 'number' && isFinite(x) ? x.toFixed(d) : '-');

/** Speech -> motion: how long after a moment of speech was said its gesture is on screen (latency.js). */
function speechToMotionMs() {
  const offset = clock.offset;
  if (offset === null) return null;
  const measured = speech.totalMs(offset, (api.frameMs || 0) / 1000, performance.now() / 1000);
  if (measured !== null) {
    api.delayMeasured = true;
    return measured;
  }
  // Estimated (a server before revision 5 without source audio): the model's lookahead, one window of audio,
  // the server's latency and our playout buffer.
  const h = api.hello || {}, s = api.status || {};
  api.delayMeasured = false;
  return ((h.lookahead_s || 0) + (h.window_ms || 0) / 1000 + (s.latency_ms || 0) / 1000 + clock.marginS) * 1000;
}

/**
 * Frames received per second over the last FPS_WINDOW_MS (null until 1 s is seen). Frames come in bursts of one
 * inference window, so the rate is taken from the first burst's arrival to the last one's, the first burst left
 * out (its frames were made before the span began): a count over a fixed window would swing by a whole burst.
 */
function receivedFps(now) {
  while (arrivals.length && arrivals[0] <= now - FPS_WINDOW_MS) arrivals.shift();
  if (arrivals.length < 2) return null;
  const t0 = arrivals[0];
  let first = 1;
  while (first < arrivals.length && arrivals[first] - t0 < 30) first++;
  const last = arrivals[arrivals.length - 1];
  const span = now - last > 1000 ? now - t0 : last - t0;  // no frames for a while: that time counts too
  return span >= 1000 ? ((arrivals.length - first) * 1000) / span : null;
}

setInterval(() => {
  const s = api.status || {};
  const now = performance.now();
  const fps = receivedFps(now);
  api.fps = fps ?? 0;
  api.delayMs = speechToMotionMs();
  ui.frames.textContent = api.framesReceived;
  ui.fps.textContent = (fps !== null ? fmt(fps, 0) : '-') + (api.hello ? ` / ${api.hello.fps}` : '');
  ui.delay.textContent = api.delayMs !== null ? `${api.delayMeasured ? '' : '≈ '}${fmt(api.delayMs, 0)} ms` : '-';
  ui.latency.textContent = s.latency_ms !== undefined ? `${fmt(s.latency_ms, 0)} ms` : '-';
  ui.rtt.textContent = api.rttMs !== null ? `${fmt(api.rttMs, 0)} ms` : '-';
  ui.buffer.textContent = api.bufferMs !== null ? `${fmt(api.bufferMs, 0)} ms` : '-';
  ui.rtf.textContent = fmt(s.rtf, 2);
  ui.dropped.textContent = `${s.dropped ?? '-'} / ${api.gaps}`;
  ui.clients.textContent = s.clients ?? '-';
  updateSoundButton();
}, 250);

setInterval(() => {  // round trip on the same socket as the frames
  if (connOpen && pingSentAt === null) {
    pingSentAt = performance.now();
    link.postMessage({ type: 'ping' });  // the worker stamps it as it sends it
  }
}, 2000);

// Local mode (?local=MODEL_URL): no server; local-engine.js runs the model here and hands its frames to onMessage,
// a dropped WAV's sound to onSourceAudio (played on the playout clock, as the server's source) and, talking, when
// each microphone chunk reached the page (the speech -> motion readout, as talking to a server).
let local = null;

/** Local mode: a new stream starts (the microphone when `talk`, else a file), frames in `windowS` bursts. */
function beginLocalStream({ talk, sound, windowS }) {
  mode = talk ? 'talk' : 'view';
  localSound = !!sound;
  resetStream();
  sizePlayout(windowS, api.hello && api.hello.fps);
  ui.sound.disabled = !localSound;
  updateSoundButton();
}
if (params.has('local')) {
  import('./local-engine.js').then(async (m) => {
    local = await m.startLocal(params.get('local'), { onMessage, say, fail, setState, api, talkButton: ui.talk,
                                                      beginStream: beginLocalStream, sourceAudio: onSourceAudio,
                                                      noteSaid: (pts, at) => speech.noteSaid(pts, at / 1000) });
    api.talk = () => local.toggleMic();
    api.stopTalk = () => local.stopMic();
  }).catch((e) => fail(`local inference: ${e.message}`));
} else {
  api.url = socketUrl();
  ui.url.textContent = api.url.replace(/token=[^&]+/, 'token=…');
  connect(null);
}
