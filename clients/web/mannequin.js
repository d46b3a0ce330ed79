// The built-in avatar: a stylised mannequin built at load time from the hello's skeleton and humanoid map.
// Every body part is a smooth primitive attached to the joint that carries it (segment-attached, so limbs
// stay rigid and ball joints cover the bends), sized from the skeleton's own proportions. Parts are laid out
// in the rest pose's world space and then expressed in their joint's frame, so any rest_rotations work.
import * as THREE from 'three';
import { RoundedBoxGeometry } from 'three/addons/geometries/RoundedBoxGeometry.js';

const MATERIALS = {
  body: new THREE.MeshStandardMaterial({ color: 0xe8e2d8, roughness: 0.5, metalness: 0.0 }),
  joint: new THREE.MeshStandardMaterial({ color: 0x47505f, roughness: 0.35, metalness: 0.1 }),
  hair: new THREE.MeshStandardMaterial({ color: 0x2e2724, roughness: 0.75 }),
  eye: new THREE.MeshStandardMaterial({ color: 0x14171c, roughness: 0.15 }),
  lips: new THREE.MeshStandardMaterial({ color: 0xb86f62, roughness: 0.6 }),
  mouth: new THREE.MeshStandardMaterial({ color: 0x3a1414, roughness: 0.9 }),
  shoe: new THREE.MeshStandardMaterial({ color: 0x39404c, roughness: 0.6 }),
};
const X = new THREE.Vector3(1, 0, 0), Y = new THREE.Vector3(0, 1, 0), Z = new THREE.Vector3(0, 0, 1);
const FINGERS = ['Thumb', 'Index', 'Middle', 'Ring', 'Little'];
const PHALANGES = ['Proximal', 'Intermediate', 'Distal'];

/** Segments for a curve drawn with `n` at full detail: at least `min`. */
const segments = (n, detail, min = 3) => Math.max(min, Math.round(n * detail));

/** A capsule from y=0 to y=len whose radius tapers from r0 to r1 (a lathe: smooth, no seams). */
function taperedCapsule(len, r0, r1, detail = 1) {
  const pts = [];
  const n = segments(10, detail, 2);
  for (let i = 0; i <= n; i++) {  // bottom cap
    const a = -Math.PI / 2 + (i / n) * (Math.PI / 2);
    pts.push(new THREE.Vector2(Math.max(r0 * Math.cos(a), 1e-4), r0 * Math.sin(a)));
  }
  for (let i = 0; i <= n; i++) {  // top cap
    const a = (i / n) * (Math.PI / 2);
    pts.push(new THREE.Vector2(Math.max(r1 * Math.cos(a), 1e-4), len + r1 * Math.sin(a)));
  }
  return new THREE.LatheGeometry(pts, segments(28, detail, 6));
}

/**
 * A closed tube along y from y0 to y1 whose elliptical cross-section is prof(y) = [rx, rz], its ends rounded over
 * capBottom / capTop. Pieces that share a cross-section where they meet join without a seam.
 */
function profiledTube(y0, y1, prof, capBottom, capTop, detail = 1) {
  const rings = segments(16, detail, 4), around = segments(36, detail, 8);
  const ys = [];  // [y, shrink] per ring: caps are quarter ellipses, so the ends close smoothly
  const capRings = segments(8, detail, 2);
  for (let i = capRings; i > 0; i--) { const a = (i / capRings) * Math.PI / 2; ys.push([y0 - capBottom * Math.sin(a), Math.cos(a)]); }
  for (let i = 0; i <= rings; i++) ys.push([y0 + ((y1 - y0) * i) / rings, 1]);
  for (let i = 1; i <= capRings; i++) { const a = (i / capRings) * Math.PI / 2; ys.push([y1 + capTop * Math.sin(a), Math.cos(a)]); }
  const pos = [];
  for (const [y, k] of ys) {
    const [rx, rz] = prof(Math.min(Math.max(y, y0), y1));
    for (let j = 0; j < around; j++) {
      const a = (j / around) * Math.PI * 2;
      pos.push(Math.max(k, 1e-3) * rx * Math.cos(a), y, Math.max(k, 1e-3) * rz * Math.sin(a));
    }
  }
  const index = [];
  for (let i = 0; i + 1 < ys.length; i++)
    for (let j = 0; j < around; j++) {
      const a = i * around + j, b = i * around + ((j + 1) % around), c = a + around, d = b + around;
      index.push(a, c, b, b, c, d);
    }
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.Float32BufferAttribute(pos, 3));
  g.setIndex(index);
  g.computeVertexNormals();
  return g;
}

/**
 * Build the mannequin's meshes onto `joints` (Object3Ds in skeleton order, at rest). Returns the meshes, the
 * rest pose's facing and its face: {meshes, forward, up, left, bounds (Box3, file units), face}; face.set({jaw,
 * blinkLeft, blinkRight}) (0..1, face.js mouthOf) opens the mouth and closes the eyelids, face.state is what it
 * shows (a skeleton without a head: nothing to show, the state still kept). `detail` (0..1] scales the curves'
 * segments: a software renderer's cost follows the triangles (1: ~113k, 0.4: ~18k).
 */
export function buildMannequin(skeleton, humanoid, joints, detail = 1) {
  const SPHERE = new THREE.SphereGeometry(1, segments(40, detail, 8), segments(24, detail, 6));
  const names = skeleton.joints, parents = skeleton.parents;
  const index = new Map(names.map((n, j) => [n, j]));
  const bone = (b) => (humanoid && humanoid[b] !== undefined && index.has(humanoid[b]) ? index.get(humanoid[b]) : -1);

  // Rest pose in world (figure) space, file units.
  const root = joints[parents.indexOf(-1)].parent;
  root.updateMatrixWorld(true);
  const rootInv = root.matrixWorld.clone().invert();
  const rest = joints.map((o) => new THREE.Matrix4().multiplyMatrices(rootInv, o.matrixWorld));
  const restInv = rest.map((m) => m.clone().invert());
  const P = (j) => new THREE.Vector3().setFromMatrixPosition(rest[j]);
  const has = (b) => bone(b) >= 0;
  const at = (b) => P(bone(b));
  const children = names.map(() => []);
  parents.forEach((p, j) => { if (p >= 0) children[p].push(j); });

  const bounds = new THREE.Box3();
  joints.forEach((_, j) => bounds.expandByPoint(P(j)));

  // Facing: up from the hips to the head, left from the right leg (or arm) to the left one.
  const up = has('Hips') && has('Head') ? at('Head').sub(at('Hips')).normalize() : Y.clone();
  let left = X.clone();
  for (const [l, r] of [['LeftUpperLeg', 'RightUpperLeg'], ['LeftUpperArm', 'RightUpperArm']])
    if (has(l) && has(r)) { left = at(l).sub(at(r)).normalize(); break; }
  const forward = new THREE.Vector3().crossVectors(left, up).normalize();
  left.crossVectors(up, forward).normalize();

  // One size unit: a 170 cm adult's centimetre, from the upper arm (else legs, else the skeleton's height).
  let u = (bounds.max.y - bounds.min.y) / 160;
  if (has('LeftUpperArm') && has('LeftLowerArm')) u = at('LeftUpperArm').distanceTo(at('LeftLowerArm')) / 28.5;
  else if (has('LeftUpperLeg') && has('LeftLowerLeg')) u = at('LeftUpperLeg').distanceTo(at('LeftLowerLeg')) / 40;

  const meshes = [];
  const basis = new THREE.Matrix4().makeBasis(left, up, forward);  // body frame: x left, y up, z forward
  /** Attach `geometry` to joint j with a world transform given as position, rotation matrix and scale. */
  function add(j, geometry, material, pos, rot = basis, scale = new THREE.Vector3(1, 1, 1)) {
    if (j < 0) return null;
    const world = new THREE.Matrix4().compose(pos, new THREE.Quaternion().setFromRotationMatrix(rot), scale);
    const mesh = new THREE.Mesh(geometry, material);
    new THREE.Matrix4().multiplyMatrices(restInv[j], world).decompose(mesh.position, mesh.quaternion, mesh.scale);
    mesh.castShadow = true;
    mesh.receiveShadow = true;
    joints[j].add(mesh);
    meshes.push(mesh);
    if (pos.y + scale.y > bounds.max.y) bounds.max.y = pos.y + scale.y;  // the head's top, above its joint
    return mesh;
  }
  const ellipsoid = (j, c, rx, ry, rz, material = MATERIALS.body, rot = basis) =>
    add(j, SPHERE, material, c, rot, new THREE.Vector3(rx, ry, rz));
  /** A limb from world point a to b on joint j, oriented so its lathe axis runs a -> b. */
  function limb(j, a, b, r0, r1, material = MATERIALS.body) {
    const d = new THREE.Vector3().subVectors(b, a);
    const len = d.length();
    if (len < 1e-6) return null;
    const rot = new THREE.Matrix4().makeRotationFromQuaternion(new THREE.Quaternion().setFromUnitVectors(Y, d.normalize()));
    return add(j, taperedCapsule(len, r0, r1, detail), material, a, rot);
  }
  const ball = (j, r, material = MATERIALS.joint) => ellipsoid(j, P(j), r, r, r, material);
  const along = (a, b, t) => new THREE.Vector3().lerpVectors(a, b, t);
  const done = new Set();  // joints whose segment is already shaped

  // ---- torso: one smooth body from the crotch to the shoulders, cut into a piece per spine joint (so it bends
  // with the spine); neighbouring pieces share their cross-section where they meet, and overlap to cover bends.
  const hips = bone('Hips');
  const neck = bone('Neck');
  if (hips >= 0) {
    const hipHalf = has('LeftUpperLeg') ? at('LeftUpperLeg').distanceTo(at('Hips')) : 10 * u;
    const chain = [];  // spine joints from the hips up to (not including) the neck
    if (neck >= 0) for (let a = parents[neck]; a >= 0 && a !== hips; a = parents[a]) chain.unshift(a);
    const shoulderHalf = has('LeftUpperArm') && has('RightUpperArm') ? at('LeftUpperArm').distanceTo(at('RightUpperArm')) / 2 : 18 * u;
    const top = neck >= 0 ? P(neck) : P(hips).addScaledVector(up, 50 * u);
    const seg = [hips, ...chain];
    const ends = [...seg.map(P), top];
    const lengths = ends.slice(1).map((p, i) => p.distanceTo(ends[i]));
    const total = lengths.reduce((x, y) => x + y, 0) || 1;
    // Half width and half depth along the torso, h = 0 at the hips joint, 1 at the neck: hips, waist, ribcage, chest.
    const keys = [[0, hipHalf + 4 * u, 9.2 * u], [0.3, 11.8 * u, 8.4 * u], [0.62, Math.max(shoulderHalf * 0.78, 13.5 * u), 9.8 * u],
                  [0.86, Math.max(shoulderHalf * 0.92, 15 * u), 9.6 * u], [1, Math.max(shoulderHalf * 0.8, 13 * u), 8 * u]];
    const profile = (h) => {
      let k = 0;
      while (k + 2 < keys.length && h > keys[k + 1][0]) k++;
      const [h0, x0, z0] = keys[k], [h1, x1, z1] = keys[k + 1];
      const t = THREE.MathUtils.smoothstep(THREE.MathUtils.clamp((h - h0) / (h1 - h0), 0, 1), 0, 1);
      return [x0 + (x1 - x0) * t, z0 + (z1 - z0) * t];
    };
    const overlap = 4 * u;
    // The pelvis: below the hips joint, upright in the body's frame, narrowing down to the crotch.
    const [px, pz] = profile(0);
    const pelvis = (y) => { const k = 1 + 0.025 * Math.min(y, 0) / u; return [px * k, pz * (0.5 + 0.5 * k)]; };
    add(hips, profiledTube(-7 * u, overlap, pelvis, 6 * u, 0, detail), MATERIALS.body, P(hips));
    let h = 0;
    seg.forEach((j, i) => {
      const a = ends[i], b = ends[i + 1], len = lengths[i];
      const h0 = h, h1 = h + len / total;
      h = h1;
      if (len < 1e-6) return;
      const first = i === 0, last = i === seg.length - 1;
      // The piece's frame: y along the spine segment, x towards the body's left, z forward.
      const yAxis = new THREE.Vector3().subVectors(b, a).normalize();
      const xAxis = left.clone().addScaledVector(yAxis, -left.dot(yAxis)).normalize();
      const zAxis = new THREE.Vector3().crossVectors(xAxis, yAxis);
      const rot = new THREE.Matrix4().makeBasis(xAxis, yAxis, zAxis);
      const y0 = first ? 0 : -overlap, y1 = last ? len : len + overlap;
      const prof = (y) => profile(h0 + (y / len) * (h1 - h0));
      add(j, profiledTube(y0, y1, prof, 0, last ? 5 * u : 0, detail), MATERIALS.body, a, rot);
      done.add(j);
    });
  }

  // ---- neck and head, with a face so facing reads at a glance, and speaks: a jaw and eyelids (revision 7's face)
  const face = { state: { jaw: 0, blinkLeft: 0, blinkRight: 0 }, set(m) { Object.assign(this.state, m); },
                 parts: { mouth: [], eyes: [] } };  // the meshes of each (to find them on screen)
  const head = bone('Head');
  if (neck >= 0) {
    for (let j = head >= 0 ? head : neck; j !== neck && j >= 0; j = parents[j]) {
      if (parents[j] >= 0 && parents[j] !== hips) limb(parents[j], P(parents[j]), P(j), 5.6 * u, 5 * u);
      done.add(parents[j]);
    }
  }
  if (head >= 0) {
    const c = P(head).addScaledVector(up, 6 * u).addScaledVector(forward, 1.2 * u);
    const R = { x: 8.2 * u, y: 11 * u, z: 9.8 * u };
    ellipsoid(head, c, R.x, R.y, R.z);
    const surface = (x, y) => {  // the point of the head's front surface at (x left, y up)
      const z = R.z * Math.sqrt(Math.max(0, 1 - (x / R.x) ** 2 - (y / R.y) ** 2));
      return c.clone().addScaledVector(left, x).addScaledVector(up, y).addScaledVector(forward, z);
    };
    const lids = [];
    for (const s of [1, -1]) {
      const e = surface(s * 3.1 * u, 1.2 * u).addScaledVector(forward, -0.35 * u);
      face.parts.eyes.push(ellipsoid(head, e, 1.05 * u, 1.35 * u, 0.8 * u, MATERIALS.eye));
      lids.push([e, ellipsoid(head, e, 1.2 * u, 1.45 * u, 0.95 * u)]);  // skin over the eye, coming down from above
      // (an open lid shrinks into the eye rather than being hidden: the avatar menu's toggle stays the only one)
      const brow = surface(s * 3.2 * u, 3.6 * u);
      const tilt = new THREE.Matrix4().makeRotationAxis(forward, s * 0.12).multiply(basis);
      ellipsoid(head, brow, 1.9 * u, 0.38 * u, 0.5 * u, MATERIALS.hair, tilt);
      ellipsoid(head, c.clone().addScaledVector(left, s * R.x * 0.97).addScaledVector(up, 0.5 * u), 1.0 * u, 2.6 * u, 1.7 * u);
    }
    ellipsoid(head, surface(0, -1.6 * u).addScaledVector(forward, 0.2 * u), 1.0 * u, 1.7 * u, 1.2 * u);  // nose
    // The mouth: an upper lip, a lower lip that drops with the jaw along the face, the dark of the mouth between.
    const upper = ellipsoid(head, surface(0, -5.1 * u), 2.3 * u, 0.42 * u, 0.6 * u, MATERIALS.lips);
    const inside = ellipsoid(head, surface(0, -5.4 * u), 1.9 * u, 0.3 * u, 0.6 * u, MATERIALS.mouth);
    const lower = ellipsoid(head, surface(0, -5.7 * u), 2.1 * u, 0.45 * u, 0.6 * u, MATERIALS.lips);
    face.parts.mouth.push(upper, inside, lower);
    const restInvHead = restInv[head];
    const place = (mesh, world, rx, ry, rz) => {  // a part moved on its joint (rigid: restInv has no scale)
      mesh.position.copy(world).applyMatrix4(restInvHead);
      mesh.scale.set(rx, ry, rz);
    };
    const JAW_DROP = 1.8 * u;  // the lower lip's travel at a wide open jaw
    face.set = function set(m) {
      Object.assign(this.state, m);
      const jaw = THREE.MathUtils.clamp(this.state.jaw, 0, 1);
      place(lower, surface(0, -5.7 * u - jaw * JAW_DROP), 2.1 * u, 0.45 * u, 0.6 * u);
      place(inside, surface(0, -5.4 * u - jaw * JAW_DROP / 2).addScaledVector(forward, -0.25 * u),
            1.9 * u * (1 - 0.25 * jaw), 0.3 * u + jaw * JAW_DROP / 2, 0.6 * u);
      lids.forEach(([e, lid], i) => {
        const b = THREE.MathUtils.clamp(i === 0 ? this.state.blinkLeft : this.state.blinkRight, 0, 1);
        if (b < 0.02) place(lid, e, 1e-3 * u, 1e-3 * u, 1e-3 * u);  // open: tucked away inside the eye
        else place(lid, e.clone().addScaledVector(up, (1 - b) * 1.4 * u), 1.2 * u, b * 1.45 * u, 0.95 * u);
      });
    };
    face.set({});
    // Hair: the top of a slightly larger ellipsoid, tipped back so the hairline sits above the brow.
    const hair = new THREE.SphereGeometry(1, segments(40, detail, 8), segments(20, detail, 5), 0, Math.PI * 2, 0, Math.PI * 0.56);
    const tip = new THREE.Matrix4().makeRotationAxis(left, -0.5).multiply(basis);
    add(head, hair, MATERIALS.hair, c.clone().addScaledVector(up, 0.4 * u).addScaledVector(forward, -0.3 * u), tip,
        new THREE.Vector3(R.x * 1.07, R.y * 1.04, R.z * 1.08));
    done.add(head);
  }

  // ---- arms and hands
  for (const side of ['Left', 'Right']) {
    const sh = bone(`${side}Shoulder`), ua = bone(`${side}UpperArm`), la = bone(`${side}LowerArm`), hand = bone(`${side}Hand`);
    if (sh >= 0 && ua >= 0) { limb(sh, P(sh), P(ua), 4.6 * u, 4.8 * u); done.add(sh); }
    if (ua >= 0) ball(ua, 5.4 * u, MATERIALS.body);
    if (ua >= 0 && la >= 0) { limb(ua, P(ua), P(la), 4.8 * u, 3.8 * u); ball(la, 3.7 * u); done.add(ua); }
    if (la >= 0 && hand >= 0) { limb(la, P(la), P(hand), 3.7 * u, 2.6 * u); ball(hand, 2.6 * u); done.add(la); }
    if (hand < 0) continue;
    const base = (f) => bone(`${side}${f}Proximal`);
    const idx = base('Index'), mid = base('Middle'), lit = base('Little') >= 0 ? base('Little') : base('Ring');
    if (mid >= 0) {
      const w = P(hand), m = P(mid);
      const ax = new THREE.Vector3().subVectors(m, w);
      const len = ax.length();
      ax.normalize();
      const across = idx >= 0 && lit >= 0 ? new THREE.Vector3().subVectors(P(idx), P(lit)) : forward.clone();
      const width = idx >= 0 && lit >= 0 ? across.length() + 2.4 * u : 8 * u;
      const normal = new THREE.Vector3().crossVectors(ax, across).normalize();
      across.crossVectors(normal, ax).normalize();
      const rot = new THREE.Matrix4().makeBasis(ax, normal, across);
      const palm = new RoundedBoxGeometry(1, 1, 1, segments(3, detail, 1), 0.45);
      add(hand, palm, MATERIALS.body, along(w, m, 0.55), rot, new THREE.Vector3(len * 1.05, 2.8 * u, width));
    }
    for (const f of FINGERS) {
      const chain = PHALANGES.map((ph) => bone(`${side}${f}${ph}`)).filter((j) => j >= 0);
      if (!chain.length) continue;
      const r = (f === 'Thumb' ? 1.25 : f === 'Little' ? 0.82 : 0.95) * u;
      if (f === 'Thumb') limb(hand, P(hand), P(chain[0]), 1.7 * u, r * 1.15);
      // The last phalanx ends at the skeleton's end joint if it has one, else continues its parent's direction.
      const last = chain[chain.length - 1];
      const tipJ = children[last].find((c) => P(c).distanceTo(P(last)) > 1e-3);
      const tipP = tipJ !== undefined ? P(tipJ)
        : P(last).add(new THREE.Vector3().subVectors(P(last), P(chain.length > 1 ? chain[chain.length - 2] : hand)).setLength(2.2 * u));
      chain.forEach((j, i) => {
        const b = i + 1 < chain.length ? P(chain[i + 1]) : tipP;
        const t = 1 - i * 0.08;
        limb(j, P(j), b, r * t, r * (t - 0.08));
        done.add(j);
      });
    }
    done.add(hand);
  }

  // ---- legs and feet
  for (const side of ['Left', 'Right']) {
    const ul = bone(`${side}UpperLeg`), ll = bone(`${side}LowerLeg`), ft = bone(`${side}Foot`), toe = bone(`${side}Toes`);
    if (ul >= 0 && ll >= 0) { limb(ul, P(ul), P(ll), 7.6 * u, 5.2 * u); ball(ll, 4.9 * u); done.add(ul); }
    if (ll >= 0 && ft >= 0) { limb(ll, P(ll), P(ft), 5.0 * u, 3.5 * u); ball(ft, 3.4 * u); done.add(ll); }
    if (ft < 0) continue;
    const a = P(ft);
    const ground = Math.min(a.y - 2 * u, Math.max(0, bounds.min.y - 9 * u));  // the rest pose's floor
    const toeP = toe >= 0 ? P(toe) : a.clone().addScaledVector(forward, 14 * u);
    const fwd = new THREE.Vector3().subVectors(toeP, a).projectOnPlane(Y).normalize();
    const side3 = new THREE.Vector3().crossVectors(Y, fwd).normalize();
    const rot = new THREE.Matrix4().makeBasis(side3, Y, fwd);
    const heel = a.clone().addScaledVector(fwd, -5 * u);
    const h = Math.max(a.y - ground + 2 * u, 5 * u);
    const body = new THREE.Vector3().lerpVectors(heel, toeP, 0.5).setY(ground + h / 2);
    add(ft, new RoundedBoxGeometry(1, 1, 1, segments(3, detail, 1), 0.35), MATERIALS.shoe, body, rot,
        new THREE.Vector3(9 * u, h, heel.distanceTo(toeP) + 2 * u));
    done.add(ft);
    if (toe >= 0) {
      const end = children[toe].map(P).find((p) => p.distanceTo(toeP) > 1e-3) || toeP.clone().addScaledVector(fwd, 7 * u);
      const len = toeP.distanceTo(end) + 1.5 * u;
      const c = along(toeP, end, 0.5).setY(ground + 2.2 * u);
      add(toe, new RoundedBoxGeometry(1, 1, 1, segments(3, detail, 1), 0.4), MATERIALS.shoe, c, rot, new THREE.Vector3(8.6 * u, 4.4 * u, len));
      done.add(toe);
    }
    bounds.min.y = Math.min(bounds.min.y, ground);
  }

  // ---- anything the map does not name (another skeleton's extra joints): a plain limb per bone
  parents.forEach((p, j) => {
    if (p < 0 || done.has(p) || P(j).distanceTo(P(p)) < 1e-3) return;
    limb(p, P(p), P(j), 3.2 * u, 2.6 * u);
  });
  return { meshes, forward, up, left, bounds, unit: u, face };
}
