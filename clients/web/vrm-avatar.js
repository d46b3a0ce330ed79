// Your own avatar: a VRM (0.x or 1.0) loaded with three's GLTFLoader and @pixiv/three-vrm, driven through its
// normalized humanoid bones from the streamed skeleton.
//
// Retargeting, in world space: each humanoid bone b has a joint in the streamed skeleton (hello.humanoid).
// With S the joint's rest world rotation and G its world rotation now, D = G S^-1 is how far the joint turned
// from rest. The VRM bone (rest world rotation R, rest direction v towards its chain child) is first aligned
// onto the skeleton's rest direction s by the swing A (v -> s), then turned by D:  W = D A R.  At rest the VRM
// takes the skeleton's rest pose; bones it lacks or the skeleton lacks stay at their rest relative to the
// parent. Both rest poses face the same way after F, the yaw from the skeleton's facing to the VRM's.
// Where the skeleton has joints between a bone's joint and its chain child's (the spine's Spine1, a second neck
// joint), their turns bend the skeleton's chain but not the VRM's one bone: D is then followed by the swing that
// takes D s onto the skeleton's direction now, so the bone points where the skeleton's chain does (a no-op where
// the child's joint is the joint's own child).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { VRMLoaderPlugin, VRMUtils } from '@pixiv/three-vrm';
import { vrmExpressions } from './face.js';

/** Unity HumanBodyBones name (the hello's humanoid keys) -> three-vrm's humanoid bone name (VRM 1.0 naming). */
export function vrmBoneName(unity) {
  const thumb = { ThumbProximal: 'ThumbMetacarpal', ThumbIntermediate: 'ThumbProximal' };
  const m = /^(Left|Right)(ThumbProximal|ThumbIntermediate)$/.exec(unity);
  const name = m ? m[1] + thumb[m[2]] : unity;
  return name[0].toLowerCase() + name.slice(1);
}

// For each bone, the chain children whose direction defines it, in order of preference.
const NEXT = {
  hips: ['spine'], spine: ['chest', 'upperChest', 'neck'], chest: ['upperChest', 'neck'], upperChest: ['neck'],
  neck: ['head'],
};
for (const S of ['left', 'right']) {
  Object.assign(NEXT, {
    [`${S}Shoulder`]: [`${S}UpperArm`], [`${S}UpperArm`]: [`${S}LowerArm`], [`${S}LowerArm`]: [`${S}Hand`],
    [`${S}Hand`]: [`${S}MiddleProximal`, `${S}IndexProximal`], [`${S}UpperLeg`]: [`${S}LowerLeg`],
    [`${S}LowerLeg`]: [`${S}Foot`], [`${S}Foot`]: [`${S}Toes`],
    [`${S}ThumbMetacarpal`]: [`${S}ThumbProximal`], [`${S}ThumbProximal`]: [`${S}ThumbDistal`],
  });
  for (const f of ['Index', 'Middle', 'Ring', 'Little'])
    Object.assign(NEXT, { [`${S}${f}Proximal`]: [`${S}${f}Intermediate`], [`${S}${f}Intermediate`]: [`${S}${f}Distal`] });
}

/** Parse a .vrm file's bytes into a VRM (throws with a readable message when it is not one). */
export async function parseVrm(arrayBuffer) {
  const loader = new GLTFLoader();
  loader.register((parser) => new VRMLoaderPlugin(parser));
  const gltf = await loader.parseAsync(arrayBuffer, '');
  const vrm = gltf.userData.vrm;
  if (!vrm || !vrm.humanoid) throw new Error('not a VRM: the glTF has no VRM humanoid extension');
  VRMUtils.removeUnnecessaryVertices(gltf.scene);
  VRMUtils.rotateVRM0(vrm);  // VRM 0.x faces -Z; turn it to face +Z like VRM 1.0
  vrm.scene.traverse((o) => { if (o.isMesh) { o.frustumCulled = false; o.castShadow = true; } });
  return vrm;
}

export class VrmAvatar {
  /**
   * vrm: from parseVrm, already added to the scene; source: {joints (Object3D per skeleton joint, at rest),
   * humanoid (hello map), forward (THREE.Vector3, rest facing), scale (file units -> metres)}.
   */
  constructor(vrm, source) {
    this.vrm = vrm;
    this.name = (vrm.meta && (vrm.meta.name || vrm.meta.title)) || 'VRM';
    this.metaVersion = vrm.meta ? vrm.meta.metaVersion : '?';
    const { joints, humanoid } = source;
    vrm.scene.updateMatrixWorld(true);
    joints[0].parent.updateMatrixWorld(true);
    const jointIndex = new Map(joints.map((o, j) => [o.name, j]));
    const srcPos = (j) => joints[j].getWorldPosition(new THREE.Vector3());
    const node = (b) => vrm.humanoid.getNormalizedBoneNode(b);

    // The VRM's facing at rest, from its own bones (robust to files that do not follow the convention).
    const wp = (b) => node(b).getWorldPosition(new THREE.Vector3());
    const vrmLeft = node('leftUpperLeg') && node('rightUpperLeg') ? wp('leftUpperLeg').sub(wp('rightUpperLeg')) : new THREE.Vector3(1, 0, 0);
    const vrmFwd = new THREE.Vector3().crossVectors(vrmLeft, new THREE.Vector3(0, 1, 0)).setY(0).normalize();
    const srcFwd = source.forward.clone().setY(0).normalize();
    this.F = new THREE.Quaternion().setFromUnitVectors(srcFwd, vrmFwd);
    this.Finv = this.F.clone().invert();

    // Every VRM bone, parents before children; the skeleton's joint where it has one.
    const srcJoint = {};
    for (const [unity, joint] of Object.entries(humanoid || {}))
      if (jointIndex.has(joint)) srcJoint[vrmBoneName(unity)] = jointIndex.get(joint);
    this.bones = [];
    const byNode = new Map();
    const depth = (n) => { let d = 0; for (let o = n; o; o = o.parent) d++; return d; };
    const order = Object.keys(vrm.humanoid.humanBones).filter((b) => node(b))
      .sort((a, b) => depth(node(a)) - depth(node(b)));
    for (const b of order) {
      const n = node(b);
      if (!n) continue;
      const j = srcJoint[b];
      const R = n.getWorldQuaternion(new THREE.Quaternion());
      let A = new THREE.Quaternion();
      let chord = null;  // (the skeleton's rest direction to the chain child's joint, and that joint)
      const child = (NEXT[b] || []).find((c) => node(c) && srcJoint[c] !== undefined);
      if (child && j !== undefined) {
        const v = wp(child).sub(wp(b)).normalize();
        const s = srcPos(srcJoint[child]).sub(srcPos(j)).applyQuaternion(this.F).normalize();
        if (v.lengthSq() > 0.5 && s.lengthSq() > 0.5) {
          A.setFromUnitVectors(v, s);
          if (joints[srcJoint[child]].parent !== joints[j]) chord = { s, joint: srcJoint[child] };
        }
      } else {
        const p = byNode.get(n.parent);
        if (p) A = p.A.clone();  // a leaf bone keeps its parent's alignment (a fingertip stays in line)
      }
      const entry = { name: b, node: n, joint: j, R, A, chord, S: j !== undefined ? joints[j].getWorldQuaternion(new THREE.Quaternion()) : null,
                      parentRest: n.parent.getWorldQuaternion(new THREE.Quaternion()), W: R.clone() };
      entry.Sinv = entry.S ? entry.S.clone().invert() : null;
      this.bones.push(entry);
      byNode.set(n, entry);
    }
    this.byNode = byNode;
    this.srcJointOf = srcJoint;

    // Root motion: the hips follow the skeleton root's displacement from rest, scaled by the hip heights.
    const hips = byNode.get(node('hips'));
    this.hips = hips;
    this.hipsRest = wp('hips');
    this.hipsRestLocal = hips.node.position.clone();
    this.hipsParentInv = hips.node.parent.matrixWorld.clone().invert();
    this.srcRootRest = hips.joint !== undefined ? srcPos(hips.joint) : null;
    this.rootScale = this.srcRootRest && this.srcRootRest.y > 1e-3 ? this.hipsRest.y / this.srcRootRest.y : 1;
  }

  /** Pose the VRM like the streamed skeleton's joints are now (call after applying a frame). */
  drive(joints, dt) {
    const D = new THREE.Quaternion(), G = new THREE.Quaternion(), parentW = new THREE.Quaternion();
    const swing = new THREE.Quaternion(), from = new THREE.Vector3(), to = new THREE.Vector3(), at = new THREE.Vector3();
    for (const e of this.bones) {
      const p = this.byNode.get(e.node.parent);
      parentW.copy(p ? p.W : e.parentRest);
      if (e.joint === undefined) {  // the skeleton lacks this bone: keep its rest relative to its parent
        e.W.copy(parentW).multiply(e.parentRest.clone().invert().multiply(e.R));
      } else {
        joints[e.joint].getWorldQuaternion(G);
        D.copy(G).multiply(e.Sinv);                                 // rotation from rest, skeleton world
        D.premultiply(this.F).multiply(this.Finv);                  // ... in the VRM's world
        if (e.chord) {  // joints between: point along the skeleton's chain as it is now
          joints[e.chord.joint].getWorldPosition(to).sub(joints[e.joint].getWorldPosition(at)).applyQuaternion(this.F);
          from.copy(e.chord.s).applyQuaternion(D);
          if (to.lengthSq() > 1e-12) D.premultiply(swing.setFromUnitVectors(from, to.normalize()));
        }
        e.W.copy(D).multiply(e.A).multiply(e.R);
      }
      e.node.quaternion.copy(parentW).invert().multiply(e.W);
    }
    if (this.srcRootRest) {
      const now = joints[this.hips.joint].getWorldPosition(new THREE.Vector3());
      const target = now.sub(this.srcRootRest).applyQuaternion(this.F).multiplyScalar(this.rootScale).add(this.hipsRest);
      this.hips.node.position.copy(target.applyMatrix4(this.hipsParentInv));
    }
    this.vrm.update(dt);
  }

  /** Show a frame's face (revision 7; null: at rest) through the VRM's preset expressions, VRM 1.0 names for 0.x and
   *  1.0 models alike (three-vrm maps 0.x presets A, Blink_L, ... onto them); applied by the next drive(). The
   *  values set, by name, are kept in `expressions` (presets the model lacks are left out). */
  setFace(face) {
    const em = this.vrm.expressionManager;
    this.expressions = {};
    if (!em) return;
    for (const [name, w] of Object.entries(vrmExpressions(face))) {
      if (!em.getExpression(name)) continue;
      em.setValue(name, w);
      this.expressions[name] = w;
    }
  }

  /** World positions (metres) of the VRM's raw humanoid bones, by VRM bone name (for tests and tools). */
  boneWorldPositions() {
    this.vrm.scene.updateMatrixWorld(true);
    const out = {};
    for (const b of Object.keys(this.vrm.humanoid.humanBones)) {
      const n = this.vrm.humanoid.getRawBoneNode(b);
      if (n) out[b] = n.getWorldPosition(new THREE.Vector3()).toArray();
    }
    return out;
  }

  dispose() {
    this.vrm.scene.removeFromParent();
    VRMUtils.deepDispose(this.vrm.scene);
  }
}
