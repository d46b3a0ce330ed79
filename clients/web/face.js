// The face on the page (protocol revision 7), without DOM or three.js so it also runs under node (clients/web/tests/).
// A frame's `face` is {name: weight 0..1} in the name set the page asked for in its hello (FACE_SET); the avatars
// read it here: a VRM's expressions by their VRM 1.0 preset names (three-vrm takes those for 0.x models too), the
// mannequin's jaw and eyelids. Weights in another set (a server that sends its own default, vrm0) read the same.
export const FACE_SET = 'vrm1';

// The VRM 0.x preset names as VRM 1.0 names them (three-vrm's expressionManager knows the 1.0 names only).
const VRM0_TO_VRM1 = { A: 'aa', I: 'ih', U: 'ou', E: 'ee', O: 'oh', Blink: 'blink', Blink_L: 'blinkLeft',
                       Blink_R: 'blinkRight', Joy: 'happy' };
export const VRM_EXPRESSIONS = ['aa', 'ih', 'ou', 'ee', 'oh', 'blink', 'blinkLeft', 'blinkRight', 'happy'];
const VOWELS = [['aa', 'A', 'viseme_aa'], ['ih', 'I', 'viseme_I'], ['ou', 'U', 'viseme_U'], ['ee', 'E', 'viseme_E'],
                ['oh', 'O', 'viseme_O']];

const clamp01 = (x) => Math.min(1, Math.max(0, Number(x) || 0));

/** The face between two frames' faces, u of the way from a to b (linear per name, as the pose's root); a name
 *  only one of them has is held from that one. null when neither has a face. */
export function lerpFace(a, b, u) {
  if (!a || !b) return a || b || null;
  const out = {};
  for (const k of Object.keys(a)) out[k] = k in b ? a[k] + (b[k] - a[k]) * u : a[k];
  for (const k of Object.keys(b)) if (!(k in out)) out[k] = b[k];
  return out;
}

/** A binary frame's face channel (values in the layout's order) as {label: value}; null without labels. */
export function faceFromValues(values, labels) {
  if (!values || !Array.isArray(labels) || labels.length !== values.length) return null;
  const out = {};
  labels.forEach((name, i) => { out[name] = values[i]; });
  return out;
}

/** The face as VRM 1.0 preset expressions {aa, ih, ou, ee, oh, blink, blinkLeft, blinkRight, happy}, from vrm1 or
 *  vrm0 names (other sets: the mouth's opening as `aa` and the blinks). */
export function vrmExpressions(face) {
  const out = Object.fromEntries(VRM_EXPRESSIONS.map((n) => [n, 0]));
  if (!face) return out;
  let known = false;
  for (const [name, w] of Object.entries(face)) {
    const n = VRM0_TO_VRM1[name] || name;
    if (n in out) { out[n] = clamp01(w); known = true; }
  }
  if (!known) {  // arkit / oculus names
    const m = mouthOf(face);
    const both = Math.min(m.blinkLeft, m.blinkRight);
    Object.assign(out, { aa: m.jaw, blink: both, blinkLeft: m.blinkLeft - both, blinkRight: m.blinkRight - both,
                         happy: m.smile });
  }
  return out;
}

/** What a simple head shows of the face: {jaw (0 closed .. 1 wide open), blinkLeft, blinkRight (1 closed),
 *  smile}. The jaw is ARKit's jawOpen where the set has it, else the vowel shapes' sum (each vowel's weight is
 *  its height: an open A 1, a close I 0.4; consonants add a little of their nearest vowel; M, B, P none). */
export function mouthOf(face) {
  if (!face) return { jaw: 0, blinkLeft: 0, blinkRight: 0, smile: 0 };
  const w = (n) => clamp01(face[n]);
  const jaw = 'jawOpen' in face ? w('jawOpen')
    : clamp01(VOWELS.reduce((s, names) => s + Math.max(...names.map(w)), 0));
  const both = Math.max(w('blink'), w('Blink'));
  const left = 'eyeBlinkLeft' in face ? w('eyeBlinkLeft') : clamp01(both + Math.max(w('blinkLeft'), w('Blink_L')));
  const right = 'eyeBlinkRight' in face ? w('eyeBlinkRight') : clamp01(both + Math.max(w('blinkRight'), w('Blink_R')));
  const smile = Math.max(w('happy'), w('Joy'), (w('mouthSmileLeft') + w('mouthSmileRight')) / 2);
  return { jaw, blinkLeft: left, blinkRight: right, smile };
}
