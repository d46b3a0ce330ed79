"""Rotation helpers: Euler (BVH order) <-> quaternion (w, x, y, z) <-> matrix <-> exponential map.

Vectorised numpy over any leading shape, radians throughout (the BVH layer converts degrees).
Euler angles are intrinsic as BVH uses them: for the order "ZXY" the angles (a, b, c) mean
R = Rz(a) @ Rx(b) @ Ry(c), i.e. the channel order is the multiplication order. Rotations act on
column vectors; a quaternion q and its negation -q are the same rotation.
"""

from __future__ import annotations

import numpy as np

AXES = {"X": 0, "Y": 1, "Z": 2}
_EPS = 1e-12


def _check_order(order: str) -> tuple[int, ...]:
    order = order.upper()
    if not order or any(a not in AXES for a in order):
        raise ValueError(f"rotation order must be made of X, Y, Z, got {order!r}")
    return tuple(AXES[a] for a in order)


# ---- quaternion algebra --------------------------------------------------------------------------


def quat_identity(shape: tuple[int, ...] = ()) -> np.ndarray:
    q = np.zeros(shape + (4,))
    q[..., 0] = 1.0
    return q


def quat_normalize(q: np.ndarray) -> np.ndarray:
    return q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), _EPS)


def quat_conj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b (apply b first, then a)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4)."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_from_axis_angle(axis: int, angle: np.ndarray) -> np.ndarray:
    angle = np.asarray(angle, dtype=np.float64)
    q = np.zeros(angle.shape + (4,))
    q[..., 0] = np.cos(angle / 2)
    q[..., 1 + axis] = np.sin(angle / 2)
    return q


# ---- Euler ---------------------------------------------------------------------------------------


def euler_to_quat(angles: np.ndarray, order: str) -> np.ndarray:
    """Intrinsic Euler angles (..., len(order)) in radians -> unit quaternions (..., 4)."""
    axes = _check_order(order)
    angles = np.asarray(angles, dtype=np.float64)
    if angles.shape[-1] != len(axes):
        raise ValueError(f"order {order!r} needs {len(axes)} angles, got shape {angles.shape}")
    q = quat_from_axis_angle(axes[0], angles[..., 0])
    for k in range(1, len(axes)):
        q = quat_mul(q, quat_from_axis_angle(axes[k], angles[..., k]))
    return q


def matrix_to_euler(m: np.ndarray, order: str) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> intrinsic Euler angles (..., 3) for a Tait-Bryan order.

    For R = R_i(a) R_j(b) R_k(c) with s = +1 for cyclic orders (XYZ, YZX, ZXY) and -1 otherwise:
    sin b = s R[i,k], tan a = -s R[j,k] / R[k,k], tan c = -s R[i,j] / R[i,i]. At gimbal lock
    (cos b ~ 0) c is set to 0 and a is read from column j.
    """
    i, j, k = _check_order(order)
    if len({i, j, k}) != 3:
        raise ValueError(f"only Tait-Bryan orders (three distinct axes) are supported, got {order!r}")
    s = 1.0 if (i, j, k) in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) else -1.0
    m = np.asarray(m, dtype=np.float64)
    cos_b = np.hypot(m[..., i, i], m[..., i, j])
    b = np.arctan2(s * m[..., i, k], cos_b)
    a = np.arctan2(-s * m[..., j, k], m[..., k, k])
    c = np.arctan2(-s * m[..., i, j], m[..., i, i])
    locked = cos_b < 1e-9
    if np.any(locked):
        a = np.where(locked, np.arctan2(s * m[..., k, j], m[..., j, j]), a)
        c = np.where(locked, 0.0, c)
    return np.stack([a, b, c], axis=-1)


def quat_to_euler(q: np.ndarray, order: str) -> np.ndarray:
    return matrix_to_euler(quat_to_matrix(q), order)


# ---- matrices ------------------------------------------------------------------------------------


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    q = quat_normalize(np.asarray(q, dtype=np.float64))
    w, x, y, z = np.moveaxis(q, -1, 0)
    m = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrices -> unit quaternions with w >= 0 (Shepperd: largest pivot per element)."""
    m = np.asarray(m, dtype=np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # Four candidate solutions, each well conditioned when its pivot is large.
    cands = np.stack(
        [
            np.stack([1 + m00 + m11 + m22, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            np.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            np.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]], -1),
            np.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )
    pivots = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = quat_normalize(q)
    return np.where(q[..., :1] < 0, -q, q)


# ---- exponential map -----------------------------------------------------------------------------


def quat_to_expmap(q: np.ndarray) -> np.ndarray:
    """Unit quaternions -> rotation vectors axis * angle with angle in [0, pi] (the shorter way)."""
    q = quat_normalize(np.asarray(q, dtype=np.float64))
    q = np.where(q[..., :1] < 0, -q, q)
    sin_half = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, q[..., :1])
    # angle / sin(angle/2) -> 2 as angle -> 0; the series keeps full precision near identity.
    small = sin_half < 1e-6
    scale = np.where(small, 2.0 + angle**2 / 12.0, angle / np.where(small, 1.0, sin_half))
    return q[..., 1:] * scale


def expmap_to_quat(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    small = angle < 1e-6
    # sin(angle/2) / angle -> 1/2 - angle^2/48 near zero.
    scale = np.where(small, 0.5 - angle**2 / 48.0, np.sin(angle / 2) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(angle / 2), v * scale], axis=-1)


# ---- continuity and interpolation ----------------------------------------------------------------


def quat_continuity(q: np.ndarray, axis: int = 0) -> np.ndarray:
    """Flip signs along `axis` so consecutive quaternions have a non-negative dot product."""
    q = np.moveaxis(np.asarray(q, dtype=np.float64), axis, 0)
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    flips = np.concatenate([np.ones((1,) + dots.shape[1:]), np.where(dots < 0, -1.0, 1.0)])
    signs = np.cumprod(flips, axis=0)
    return np.moveaxis(q * signs[..., None], 0, axis)


def expmap_continuity(v: np.ndarray, axis: int = 0) -> np.ndarray:
    """Choose, per frame, the rotation vector of the same rotation closest to the previous choice.

    All rotation vectors of one rotation are u * s with s = angle + 2 pi k for its unit axis u;
    |u s - p| is smallest for s nearest to u . p, which fixes k in closed form. The choice depends
    on the previous frame's choice, so this is a recurrence over time (vectorised over the rest).
    """
    v = np.moveaxis(np.asarray(v, dtype=np.float64), axis, 0)
    angle = np.linalg.norm(v, axis=-1)
    u = v / np.maximum(angle, _EPS)[..., None]
    two_pi = 2.0 * np.pi
    out = np.empty_like(v)
    prev = v[0]
    out[0] = prev
    for t in range(1, len(v)):
        # At (numerically) identity the axis is noise: keep the previous axis, so a full turn
        # continues as 2 pi along the spin instead of jumping to an arbitrary direction.
        prev_norm = np.linalg.norm(prev, axis=-1, keepdims=True)
        keep = (angle[t] < 1e-6)[..., None] & (prev_norm > 1e-6)
        ut = np.where(keep, prev / np.maximum(prev_norm, _EPS), u[t])
        k = np.round((np.sum(ut * prev, axis=-1) - angle[t]) / two_pi)
        prev = ut * (angle[t] + two_pi * k)[..., None]
        out[t] = prev
    return np.moveaxis(out, 0, axis)


def quat_slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation along the shorter arc; t broadcasts against the leading shape."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6  # nearly equal: linear interpolation is exact to rounding
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    return quat_normalize(w0 * q0 + w1 * q1)


def yaw_quat(angle: np.ndarray) -> np.ndarray:
    """Rotation by `angle` radians about +Y (the BVH up axis)."""
    return quat_from_axis_angle(1, angle)


def split_heading(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q = yaw_quat(heading) * tilt, with tilt a swing whose axis lies in the XZ plane.

    The twist about Y is the projection of q onto (w, y); the remainder has no Y component.
    Returns (heading radians in [-pi, pi), tilt quaternion).
    """
    q = np.asarray(q, dtype=np.float64)
    heading = 2.0 * np.arctan2(q[..., 2], q[..., 0])
    heading = np.mod(heading + np.pi, 2 * np.pi) - np.pi
    tilt = quat_mul(quat_conj(yaw_quat(heading)), q)
    return heading, tilt
