// Normalized motion features -> the pose the viewer draws: the browser's port of the checkpoint's denormalization
// (`Bundle.denormalize`: f * std + mean in float32) and of `dimgestor.features.PoseDecoder` (the root
// integrated frame by frame in "free", "tether" or "lock" mode, exp-map joint angles to quaternions w, x, y, z).
// No DOM: it also runs under node (clients/web/tests/pose_decoder_check.mjs, against Python's numbers).
//
// Feature row layout (dimgestor/features.py): root_dx, root_dz, root_dyaw (or root_yaw when heading is
// "facing"), root_y, root_tilt_x, root_tilt_z, then (rx, ry, rz) for every kept joint.

const ROOT_COLUMNS = 6;
const ROOT_MODES = ['free', 'tether', 'lock'];

/** Hamilton product a * b of quaternions [w, x, y, z] (apply b first, then a). */
export function quatMul(a, b) {
  const [aw, ax, ay, az] = a, [bw, bx, by, bz] = b;
  return [aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
          aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw];
}

/** A rotation vector (axis * angle) -> unit quaternion [w, x, y, z] (dimgestor.rotations.expmap_to_quat). */
export function expmapToQuat(x, y, z) {
  const angle = Math.hypot(x, y, z);
  // sin(angle/2) / angle -> 1/2 - angle^2/48 near zero.
  const s = angle < 1e-6 ? 0.5 - (angle * angle) / 48 : Math.sin(angle / 2) / angle;
  return [Math.cos(angle / 2), x * s, y * s, z * s];
}

export class PoseDecoder {
  /**
   * spec: {mean, std (D numbers), joints (the skeleton index of each kept joint, feature order), numJoints,
   * heading ("velocity" | "facing"), fps}; root: "free" | "tether" | "lock"; tetherS: tether's time constant.
   */
  constructor(spec, root = 'tether', tetherS = 5) {
    if (!ROOT_MODES.includes(root)) throw new Error(`root must be one of ${ROOT_MODES.join(', ')}, got ${root}`);
    if (root === 'tether' && !(tetherS > 0)) throw new Error(`tetherS must be > 0, got ${tetherS}`);
    const dim = ROOT_COLUMNS + 3 * spec.joints.length;
    if (spec.mean.length !== dim || spec.std.length !== dim)
      throw new Error(`mean/std have ${spec.mean.length}/${spec.std.length} values for ${dim} feature columns`);
    Object.assign(this, { spec, root, tetherS, dim });
    this.lam = root === 'free' ? 1 : Math.exp(-1 / (spec.fps * tetherS));
    this.nAvg = spec.fps * tetherS;
    this.state = { x: 0, z: 0, heading: 0, drift: [0, 0, 0], frames: 0 };  // the frame before the next one
  }

  /** A normalized row -> the denormalized features, in float32 arithmetic as Python's (float32 mean and std). */
  denormalize(row) {
    const { mean, std } = this.spec;
    if (row.length !== this.dim) throw new Error(`a frame of ${row.length} features, expected ${this.dim}`);
    return Array.from(row, (v, d) => Math.fround(Math.fround(v * std[d]) + mean[d]));
  }

  /** One normalized frame -> {root: [x, y, z] file units, rotations: [[w, x, y, z] per skeleton joint]}. */
  decode(row) {
    const f = this.denormalize(row);
    const s = this.state, facing = this.spec.heading === 'facing';
    let x, z, heading;
    if (this.root === 'lock') {
      [x, z, heading] = [0, 0, 0];  // the anchor: the start
    } else {
      const u = [f[0], f[1], facing ? 0 : f[2]];
      let drift = s.drift, frames = s.frames;
      if (this.root === 'tether') {  // minus the running mean: any steady walk or spin is removed
        frames += 1;
        drift = drift.map((m, i) => m + (u[i] - m) / Math.min(frames, this.nAvg));
        for (let i = 0; i < 3; i++) u[i] -= drift[i];
      }
      // The anchor (start) is 0 in x, z and heading; "free" integrates plainly (lam = 1).
      heading = facing ? f[2] : this.lam * s.heading + u[2];
      const c = Math.cos(s.heading), sn = Math.sin(s.heading);  // rotate by +h_prev about Y
      x = this.lam * s.x + (c * u[0] + sn * u[1]);
      z = this.lam * s.z + (-sn * u[0] + c * u[1]);
      this.state = { x, z, heading, drift, frames };
    }
    const rotations = Array.from({ length: this.spec.numJoints }, () => [1, 0, 0, 0]);
    const yaw = [Math.cos(heading / 2), 0, Math.sin(heading / 2), 0];
    rotations[0] = quatMul(yaw, expmapToQuat(f[4], 0, f[5]));
    this.spec.joints.forEach((j, k) => {
      const i = ROOT_COLUMNS + 3 * k;
      rotations[j] = expmapToQuat(f[i], f[i + 1], f[i + 2]);
    });
    return { root: [x, f[3], z], rotations, features: f };
  }
}
