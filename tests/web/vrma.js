// A VRM avatar played by a VRM Animation (.vrma) the way an application does it with @pixiv/three-vrm-animation:
// GLTFLoader with VRMLoaderPlugin and VRMAnimationLoaderPlugin, createVRMAnimationClip, an AnimationMixer.
// tests/helpers/vrma_browser.py drives it: vrmaCheck.load(vrmUrl, vrmaUrl), then vrmaCheck.pose(t) per time.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { VRMLoaderPlugin, VRMUtils } from '@pixiv/three-vrm';
import { VRMAnimationLoaderPlugin, createVRMAnimationClip } from '@pixiv/three-vrm-animation';

const message = document.getElementById('message');
const errors = [];
const warnings = [];  // three-vrm-animation says what it ignores or doubts (a translation track on a non-hips bone...)
window.addEventListener('error', (e) => { errors.push(String(e.message)); message.textContent = e.message; });
window.addEventListener('unhandledrejection', (e) => { errors.push(String(e.reason)); message.textContent = e.reason; });
const warn = console.warn.bind(console);
console.warn = (...args) => { warnings.push(args.map(String).join(' ')); warn(...args); };

const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setSize(innerWidth, innerHeight);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x15181d);
const camera = new THREE.PerspectiveCamera(35, innerWidth / innerHeight, 0.1, 20);
camera.position.set(0, 0.9, 3.4);  // in front of an avatar facing +Z, all of its 1.6 m in view
camera.lookAt(0, 0.85, 0);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 2.0));
const sun = new THREE.DirectionalLight(0xffffff, 2.0);
sun.position.set(1, 2, 3);
scene.add(sun);

const loader = new GLTFLoader();
loader.register((parser) => new VRMLoaderPlugin(parser));
loader.register((parser) => new VRMAnimationLoaderPlugin(parser));

const nextFrame = () => new Promise((resolve) => requestAnimationFrame(() => resolve()));
let vrm, mixer, action;

let gltfScene, gltfMixer, gltfAction;

window.vrmaCheck = {
  errors, warnings,

  /** A plain glTF (ours: a skinned skeleton with one animation) as a three.js application loads it. */
  async loadGltf(url) {
    const gltf = await loader.loadAsync(url);
    gltfScene = gltf.scene;
    scene.add(gltfScene);
    gltfMixer = new THREE.AnimationMixer(gltfScene);
    gltfAction = gltfMixer.clipAction(gltf.animations[0]);
    gltfAction.setLoop(THREE.LoopOnce);
    gltfAction.clampWhenFinished = true;
    return { duration: gltf.animations[0].duration, animations: gltf.animations.length };
  },

  /** Its bones' world positions at t seconds, drawn. */
  async gltfPose(t) {
    gltfAction.reset().play();
    gltfMixer.setTime(t);
    gltfScene.updateMatrixWorld(true);
    const bones = {};
    gltfScene.traverse((o) => { if (o.isBone) bones[o.name] = o.getWorldPosition(new THREE.Vector3()).toArray(); });
    renderer.render(scene, camera);
    await nextFrame();
    await nextFrame();
    return bones;
  },

  async load(vrmUrl, vrmaUrl) {
    vrm = (await loader.loadAsync(vrmUrl)).userData.vrm;
    VRMUtils.rotateVRM0(vrm);  // VRM 0.x faces -Z; turned to face +Z like VRM 1.0, as viewers do
    scene.add(vrm.scene);
    const vrmAnimation = (await loader.loadAsync(vrmaUrl)).userData.vrmAnimations[0];
    const clip = createVRMAnimationClip(vrmAnimation, vrm);
    mixer = new THREE.AnimationMixer(vrm.scene);
    action = mixer.clipAction(clip);
    action.setLoop(THREE.LoopOnce);  // t = duration is the last key, not the first again
    action.clampWhenFinished = true;
    return {
      metaVersion: vrm.meta.metaVersion, duration: clip.duration, tracks: clip.tracks.map((t) => t.name),
      restHipsPosition: vrmAnimation.restHipsPosition.toArray(),
    };
  },

  /** The pose at t seconds, drawn: each humanoid bone's raw node in world space, and the expressions' weights. */
  async pose(t) {
    action.reset().play();  // a clamped action stays paused at its end; each time starts from a fresh one
    mixer.setTime(t);
    vrm.update(0);  // normalized bones -> raw bones
    vrm.scene.updateMatrixWorld(true);
    const bones = {};
    for (const name of Object.keys(vrm.humanoid.humanBones)) {
      const node = vrm.humanoid.getRawBoneNode(name);
      if (node) bones[name] = node.getWorldPosition(new THREE.Vector3()).toArray();
    }
    const expressions = {};  // the avatar's expressions as the clip set them (none without an expression track)
    if (vrm.expressionManager)
      for (const e of vrm.expressionManager.expressions) expressions[e.expressionName] = e.weight;
    renderer.render(scene, camera);
    await nextFrame();  // on screen before the screenshot
    await nextFrame();
    return { bones, expressions };
  },
};
