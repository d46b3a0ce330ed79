"""PyMO-style motion features: layout, inverse, resampling, streaming decode, continuity, mirroring."""

import json

import bvh as pypi_bvh
import numpy as np
import pytest

from dimgestor import rotations as R
from dimgestor.bvh import BvhMotion, forward_kinematics, read_bvh, write_bvh
from dimgestor.features import (
    ROOT_COLUMNS, FeatureSpec, PoseDecoder, RootState, arm_columns, decode_features, features_to_motion,
    mirror_features, mirror_motion,
    mirror_name, mix_arms, motion_to_features, resample_pose,
)
from dimgestor.training.synthetic import synthetic_motion, synthetic_skeleton


def start_of(motion):
    """Root ground position and heading of the first frame, to decode back in place."""
    heading, _ = R.split_heading(motion.rotations()[0, 0])
    return motion.translations()[0, 0], float(heading)


def decode(features, motion, spec):
    pos, heading = start_of(motion)
    return features_to_motion(features, motion.skeleton, spec, start_pos=pos, start_heading=heading)


def reference_fk(motion, fps=20.0):
    rot, trans = resample_pose(motion.rotations(), motion.translations(), motion.frame_time, fps)
    return forward_kinematics(motion.skeleton, rot, trans)


def test_spec_layout_and_dict_round_trip():
    sk = synthetic_skeleton()
    spec = FeatureSpec().resolve(sk)
    assert spec.joints == tuple(sk.names[1:])  # every non-root joint, in skeleton order
    assert spec.dim == 6 + 3 * 12 == len(spec.columns)
    assert spec.columns[:7] == ["root_dx", "root_dz", "root_dyaw", "root_y", "root_tilt_x", "root_tilt_z", "Spine_rx"]
    assert FeatureSpec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec
    assert spec.to_dict()["columns"] == spec.columns
    assert FeatureSpec.from_dict(FeatureSpec().to_dict()) == FeatureSpec()  # unresolved: "all joints"
    with pytest.raises(ValueError, match="not in the skeleton"):
        FeatureSpec(joints=("Tail",)).resolve(sk)
    with pytest.raises(ValueError, match="unresolved"):
        FeatureSpec().dim


def test_features_inverse_features_is_identity():
    motion = synthetic_motion(seconds=6.0, fps=20.0, seed=3)
    spec = FeatureSpec()
    f = motion_to_features(motion, spec)
    f2 = motion_to_features(features_to_motion(f, motion.skeleton, spec), spec)
    np.testing.assert_allclose(f2, f, atol=1e-4)


def test_bvh_to_features_to_bvh_reproduces_joint_positions(tmp_path):
    motion = synthetic_motion(seconds=6.0, fps=20.0, seed=4)
    spec = FeatureSpec().resolve(motion.skeleton)
    out = tmp_path / "back.bvh"
    write_bvh(out, decode(motion_to_features(motion, spec), motion, spec))
    back = read_bvh(out)
    assert back.num_frames == motion.num_frames and back.frame_time == pytest.approx(0.05)
    assert np.abs(forward_kinematics(back) - forward_kinematics(motion)).max() < 1e-2
    other = pypi_bvh.Bvh(out.read_text())  # an independent parser reads what we wrote
    assert other.get_joints_names() == motion.skeleton.names
    assert other.nframes == motion.num_frames and other.frame_time == pytest.approx(0.05)


def test_velocities_are_per_frame_in_the_root_heading_frame():
    sk = synthetic_skeleton()
    T = 40
    values = np.zeros((T, sk.num_channels))
    values[:, 0] = 1.5 * np.arange(T)  # +X, 1.5 cm per frame at 20 fps
    values[:, 1] = 95.0
    values[:, 5] = 90.0  # Yrotation of the ZXY root: heading 90 deg turns +Z (forward) into +X
    f = motion_to_features(BvhMotion(sk, 0.05, values))
    np.testing.assert_allclose(f[1:, 0], 0.0, atol=1e-6)  # no sideways motion
    np.testing.assert_allclose(f[1:, 1], 1.5, atol=1e-5)  # forward, per frame
    np.testing.assert_allclose(f[:, [2, 4, 5]], 0.0, atol=1e-6)  # no turning, no tilt
    np.testing.assert_allclose(f[:, 3], 95.0)
    np.testing.assert_allclose(f[0, :2], 0.0)


@pytest.mark.parametrize("src_fps", [30.0, 60.0, 100.0, 120.0, 24.0, 59.94])
def test_resampling_matches_the_motion_sampled_at_20fps(src_fps):
    seconds = 4.0
    src = synthetic_motion(seconds, src_fps, seed=5)  # the same analytic motion at another rate
    direct = synthetic_motion(seconds, 20.0, seed=5)
    f = motion_to_features(src)
    assert len(f) == int(src.duration * 20 + 1e-6)  # the same duration, at 20 fps
    n = min(len(f), direct.num_frames)
    positions = forward_kinematics(decode(f, src, FeatureSpec()))[:n]
    err = np.abs(positions - forward_kinematics(direct)[:n]).max()
    assert err < 0.5, f"interpolation error {err:.4f} cm"
    assert np.abs(positions - reference_fk(src)[: len(positions)]).max() < 1e-2


def test_frames_that_coincide_with_source_frames_are_exact():
    src = synthetic_motion(4.0, 60.0, seed=6)
    every_third = BvhMotion(src.skeleton, 0.05, src.values[::3])
    np.testing.assert_allclose(motion_to_features(src), motion_to_features(every_third), atol=1e-5)


def test_pose_decoder_in_chunks_equals_all_at_once_and_features_to_motion():
    motion = synthetic_motion(5.0, 20.0, seed=7)
    spec = FeatureSpec().resolve(motion.skeleton)
    f = motion_to_features(motion, spec)
    whole = PoseDecoder(motion.skeleton, spec, start_pos=(3.0, 0.0, -2.0), start_heading=0.4).decode(f)
    dec = PoseDecoder(motion.skeleton, spec, start_pos=(3.0, 0.0, -2.0), start_heading=0.4)
    parts = [dec.decode(f[a:b]) for a, b in [(0, 1), (1, 8), (8, 8), (8, 21), (21, len(f))]]
    np.testing.assert_allclose(np.concatenate([p.root_pos for p in parts]), whole.root_pos, atol=1e-9)
    np.testing.assert_allclose(np.concatenate([p.rotations for p in parts]), whole.rotations, atol=1e-12)
    assert whole.rotations.shape == (len(f), motion.skeleton.num_joints, 4)
    m = features_to_motion(f, motion.skeleton, spec, start_pos=(3.0, 0.0, -2.0), start_heading=0.4)
    np.testing.assert_allclose(m.translations()[:, 0], whole.root_pos, atol=1e-5)
    assert np.abs(np.abs(np.sum(m.rotations() * whole.rotations, -1)) - 1).max() < 1e-9


@pytest.mark.parametrize("root", ["tether", "lock"])
def test_root_modes_decode_in_chunks_like_all_at_once(root):
    motion = synthetic_motion(5.0, 20.0, seed=7)
    spec = FeatureSpec().resolve(motion.skeleton)
    f = motion_to_features(motion, spec)
    kw = dict(start_pos=(3.0, 0.0, -2.0), start_heading=0.4, root=root, tether_s=0.5)
    whole = PoseDecoder(motion.skeleton, spec, **kw).decode(f)
    dec = PoseDecoder(motion.skeleton, spec, **kw)
    parts = [dec.decode(f[a:b]) for a, b in [(0, 1), (1, 8), (8, 8), (8, 21), (21, len(f))]]
    np.testing.assert_allclose(np.concatenate([p.root_pos for p in parts]), whole.root_pos, atol=1e-9)
    np.testing.assert_allclose(np.concatenate([p.rotations for p in parts]), whole.rotations, atol=1e-12)
    m = features_to_motion(f, motion.skeleton, spec, **kw)
    np.testing.assert_allclose(m.translations()[:, 0], whole.root_pos, atol=1e-4)
    free = PoseDecoder(motion.skeleton, spec, start_pos=(3.0, 0.0, -2.0), start_heading=0.4).decode(f)
    np.testing.assert_allclose(whole.root_pos[:, 1], free.root_pos[:, 1])  # height always from the features
    # the joints below the root keep their rotations
    np.testing.assert_allclose(whole.rotations[:, 1:], free.rotations[:, 1:], atol=1e-12)


def test_tether_removes_a_steady_walk_and_spin_and_lock_stands_still():
    sk = synthetic_motion(1.0, 20.0, seed=1).skeleton
    spec = FeatureSpec().resolve(sk)
    f = np.zeros((20 * 60, spec.dim))  # one minute walking forward at 1 unit/s, turning at 0.1 rad/s
    f[:, 1], f[:, 2], f[:, 3] = 1.0 / 20, 0.1 / 20, 90.0
    free = PoseDecoder(sk, spec).decode(f)
    tether = PoseDecoder(sk, spec, root="tether", tether_s=2.0).decode(f)
    lock = PoseDecoder(sk, spec, start_pos=(1.0, 0.0, 2.0), start_heading=0.3, root="lock").decode(f)
    ground = lambda p: np.linalg.norm(p.root_pos[:, [0, 2]], axis=1)
    assert ground(free).max() > 15  # walked away (a circle of radius 10)
    # a steady drift is the model's bias, not a gesture: tether removes it from the first frame on
    assert ground(tether).max() < 1e-9
    np.testing.assert_allclose([R.split_heading(q)[0] for q in tether.rotations[:, 0]], 0.0, atol=1e-9)
    np.testing.assert_allclose(lock.root_pos[:, [0, 2]], np.tile([1.0, 2.0], (len(f), 1)))
    heading = [R.split_heading(q)[0] for q in lock.rotations[[0, -1], 0]]
    np.testing.assert_allclose(heading, 0.3, atol=1e-9)
    with pytest.raises(ValueError, match="root must be one of"):
        PoseDecoder(sk, spec, root="glued")


def test_tether_keeps_a_turn_and_a_step_then_returns_to_the_start():
    sk = synthetic_motion(1.0, 20.0, seed=1).skeleton
    spec = FeatureSpec().resolve(sk)
    f = np.zeros((20 * 40, spec.dim))
    f[:, 3] = 90.0
    f[200:210, 2] = np.radians(90) / 10  # a quarter turn in half a second at 10 s
    f[400:420, 1] = 30.0 / 20            # a step forward of 30 units in one second at 20 s
    pose = PoseDecoder(sk, spec, root="tether", tether_s=5.0).decode(f)
    heading = np.degrees([R.split_heading(q)[0] for q in pose.rotations[:, 0]])
    assert heading[210] > 60                     # the turn is made
    assert abs(heading[390]) < 0.25 * heading[210]  # and faded back towards the start
    ground = np.linalg.norm(pose.root_pos[:, [0, 2]], axis=1)
    assert ground[420] > 18 and ground[-1] < 0.25 * ground[420]


def test_tether_faces_the_start_on_average_whatever_the_spin():
    """A model that spins steadily at any rate (plus noise), for a minute: mean |heading| under 30 degrees."""
    sk = synthetic_motion(1.0, 20.0, seed=1).skeleton
    spec = FeatureSpec().resolve(sk)
    rng = np.random.default_rng(0)
    for deg_per_s in (-90, 10, 34, 180):
        f = np.zeros((20 * 60, spec.dim))
        f[:, 2] = np.radians(deg_per_s + 40 * rng.standard_normal(len(f))) / 20
        f[:, 3] = 90.0
        dec = PoseDecoder(sk, spec, root="tether", tether_s=5.0)
        pose = [dec.decode(f[i:i + 4]) for i in range(0, len(f), 4)]  # live: window by window
        rot = np.concatenate([p.rotations[:, 0] for p in pose])
        heading = np.degrees(np.unwrap([R.split_heading(q)[0] for q in rot]))
        assert np.abs(heading).mean() < 30, (deg_per_s, np.abs(heading).mean())


def test_spinning_motion_gives_continuous_features():
    motion = synthetic_motion(6.0, 30.0, seed=8)
    t = np.arange(motion.num_frames) / 30.0
    sk = motion.skeleton
    motion.values[:, 5] = 400.0 * t  # root yaw: more than six full turns
    hand = sk.channel_starts[sk.index("LeftHand")]
    motion.values[:, hand:hand + 3] = 0.0
    motion.values[:, hand] = 300.0 * t  # the hand spins about one axis, five turns
    f = motion_to_features(motion)
    jumps = np.abs(np.diff(f[:, 4:], axis=0)).max()  # tilt and joint exp maps
    assert jumps < 0.5, f"exp-map jump of {jumps:.2f} rad between frames"
    np.testing.assert_allclose(f[1:, 2], np.radians(400.0) / 20, atol=2e-3)  # steady heading rate
    assert np.abs(forward_kinematics(decode(f, motion, FeatureSpec())) - reference_fk(motion)).max() < 1e-2


def test_joint_subset_and_rest_pose_for_the_others():
    motion = synthetic_motion(3.0, 20.0, seed=9)
    spec = FeatureSpec(joints=("Spine", "LeftArm", "RightArm")).resolve(motion.skeleton)
    f = motion_to_features(motion, spec)
    assert f.shape == (60, 6 + 9)
    back = features_to_motion(f, motion.skeleton, spec)
    head = back.skeleton.channel_starts[back.skeleton.index("Head")]
    np.testing.assert_allclose(back.values[:, head:head + 3], 0.0, atol=1e-9)
    np.testing.assert_allclose(motion_to_features(back, spec), f, atol=1e-4)


def test_mirroring_swaps_sides_and_reflects():
    assert [mirror_name(n) for n in ["LeftArm", "RightHandThumb1", "L_Hand", "mixamorig:LHand", "hand.r", "Spine", "Lumbar"]] == [
        "RightArm", "LeftHandThumb1", "R_Hand", "mixamorig:RHand", "hand.l", "Spine", "Lumbar"]
    motion = synthetic_motion(4.0, 20.0, seed=10)
    sk = motion.skeleton
    spec = FeatureSpec().resolve(sk)
    mirrored = mirror_motion(motion)
    p, pm = forward_kinematics(motion), forward_kinematics(mirrored)
    left, right = sk.index("LeftHand"), sk.index("RightHand")
    np.testing.assert_allclose(pm[:, left], p[:, right] * [-1, 1, 1], atol=1e-6)
    f = motion_to_features(motion, spec)
    np.testing.assert_allclose(mirror_features(f, spec), motion_to_features(mirrored, spec), atol=1e-4)
    np.testing.assert_array_equal(mirror_features(mirror_features(f, spec), spec), f)
    assert np.abs(mirror_features(f, spec) - f).max() > 0.1


def test_arm_mixing_puts_one_arms_motion_on_both_sides_and_leaves_the_rest():
    motion = synthetic_motion(4.0, 20.0, seed=11)
    sk = motion.skeleton
    spec = FeatureSpec().resolve(sk)
    f = motion_to_features(motion, spec)
    left, right = arm_columns(spec, sk)
    joints = list(spec._resolved())
    names = lambda cols: {joints[(c - len(ROOT_COLUMNS)) // 3] for c in cols}  # noqa: E731
    assert "LeftHand" in names(left) and "RightHand" in names(right) and "LeftArm" in names(left)
    assert not {"LeftUpLeg", "RightUpLeg", "Spine", "Head"} & (names(left) | names(right))  # legs hang from the root
    for side, kept in (("left", "LeftHand"), ("right", "RightHand")):
        mixed = mix_arms(f, spec, sk, side)
        p = forward_kinematics(features_to_motion(mixed, sk, spec))
        p0 = forward_kinematics(features_to_motion(f, sk, spec))
        k = sk.index(kept)
        np.testing.assert_allclose(p[:, k], p0[:, k], atol=1e-6)  # that arm as it was
        others = np.setdiff1d(np.arange(f.shape[1]), np.concatenate([left, right]))
        np.testing.assert_array_equal(mixed[:, others], f[:, others])  # root, spine, head and legs untouched
        other_side = right if side == "left" else left
        np.testing.assert_allclose(mixed[:, other_side], mirror_features(f, spec)[:, other_side])
        assert np.abs(mixed - f).max() > 0.1
    # mirroring the left arm's copy gives the right-arm copy of the mirrored motion
    np.testing.assert_allclose(mirror_features(mix_arms(f, spec, sk, "left"), spec),
                               mix_arms(mirror_features(f, spec), spec, sk, "right"), atol=1e-6)
    with pytest.raises(ValueError, match="side"):
        mix_arms(f, spec, sk, "both")


def test_zeggs_round_trip_after_resampling(zeggs_dir):
    motion = read_bvh(zeggs_dir / "067_Speech_2_x_1_0.bvh")
    spec = FeatureSpec().resolve(motion.skeleton)
    assert len(spec.joints) == 74  # full body, fingers included
    f = motion_to_features(motion, spec)
    assert f.shape == (1376, spec.dim) and f.dtype == np.float32
    # Exp maps stay continuous on real data: wherever the rotation itself moves less than 5 degrees
    # between frames, so does its exp map (this sample also has a few genuine flips of ~170 degrees).
    q = R.expmap_to_quat(f[:, 6:].reshape(len(f), -1, 3).astype(np.float64))
    step = 2 * np.arccos(np.clip(np.abs(np.sum(q[1:] * q[:-1], -1)), 0, 1))
    jump = np.linalg.norm(np.diff(f[:, 6:].reshape(len(f), -1, 3), axis=0), axis=-1)
    assert jump[step < np.radians(5)].max() < 0.5
    err = np.abs(forward_kinematics(decode(f, motion, spec)) - reference_fk(motion)).max()
    assert err < 1e-2, f"FK error {err:.5f} cm"


def test_facing_heading_is_bounded_round_trips_and_decodes_in_chunks():
    from dimgestor.features import heading_track

    motion = synthetic_motion(seconds=8.0, fps=20.0, seed=5)  # it turns while it gestures
    vel, fac = FeatureSpec(), FeatureSpec(heading="facing")
    fv, ff = motion_to_features(motion, vel), motion_to_features(motion, fac)
    assert fac.resolve(motion.skeleton).columns[2] == "root_yaw"
    np.testing.assert_allclose(np.delete(ff, 2, axis=1), np.delete(fv, 2, axis=1), atol=1e-6)  # only heading differs
    np.testing.assert_allclose(heading_track(ff, fac), heading_track(fv, vel), atol=1e-5)  # the same turning
    assert abs(np.degrees(np.mean(ff[:, 2]))) < 2.0  # relative to the clip's mean facing
    # features -> motion -> features: the same up to where "forward" is (a constant on the heading column)
    back = motion_to_features(features_to_motion(ff, motion.skeleton, fac), fac)
    np.testing.assert_allclose(np.delete(back, 2, axis=1), np.delete(ff, 2, axis=1), atol=1e-4)
    shift = back[:, 2] - ff[:, 2]
    assert np.ptp(shift) < 1e-4
    # a streamed decode equals the whole, and the decoded heading is the start's plus the feature
    dec = PoseDecoder(motion.skeleton, fac, start_heading=0.4)
    whole = PoseDecoder(motion.skeleton, fac, start_heading=0.4).decode(ff)
    parts = [dec.decode(ff[a:b]) for a, b in [(0, 1), (1, 17), (17, 17), (17, len(ff))]]
    np.testing.assert_allclose(np.concatenate([p.root_pos for p in parts]), whole.root_pos, atol=1e-9)
    np.testing.assert_allclose(np.concatenate([p.rotations for p in parts]), whole.rotations, atol=1e-12)
    heading, _ = R.split_heading(whole.rotations[:, 0])
    np.testing.assert_allclose(np.unwrap(heading), 0.4 + ff[:, 2], atol=1e-5)
    # a model's error in the heading stays an error: a constant offset is a constant turn, never a spin
    off = ff.copy()
    off[:, 2] += 0.1
    h_off, _ = R.split_heading(PoseDecoder(motion.skeleton, fac).decode(off).rotations[:, 0])
    h, _ = R.split_heading(PoseDecoder(motion.skeleton, fac).decode(ff).rotations[:, 0])
    np.testing.assert_allclose(np.unwrap(h_off) - np.unwrap(h), 0.1, atol=1e-6)
    # mirroring reflects the facing too
    np.testing.assert_allclose(mirror_features(ff, fac.resolve(motion.skeleton))[:, 2], -ff[:, 2])


@pytest.mark.parametrize("lam", [0.5, 0.9, 0.99, 0.999])
def test_the_tethers_leaky_sum_adds_as_scipy_lfilter_does_bit_for_bit(lam):
    """The root tether's y_n = lam y_{n-1} + u_n is a loop (no scipy.signal import, ~1 s of CPU that a server's
    first frames paid), with lfilter's sums in lfilter's order: the same root, bit for bit."""
    from scipy.signal import lfilter

    from dimgestor.features import leaky_cumsum

    rng = np.random.default_rng(int(lam * 1000))
    u, prev = rng.normal(size=500), float(rng.normal())
    assert np.array_equal(leaky_cumsum(u, prev, lam), lfilter([1.0], [1.0, -lam], u, zi=[lam * prev])[0])
    assert np.array_equal(leaky_cumsum(u[:0], prev, lam), np.zeros(0))


def test_a_pose_decoder_refuses_a_bad_tether_when_made_and_decodes_as_decode_features():
    """`PoseDecoder` checks its root settings when made (not at its first window), and its windows, with the spec
    resolved once, are `decode_features`' own: the same poses and root state."""
    sk = synthetic_motion(1.0, 20.0, seed=1).skeleton
    spec = FeatureSpec()  # unresolved: both resolve it
    with pytest.raises(ValueError, match="tether_s"):
        PoseDecoder(sk, spec, root="tether", tether_s=0.0)
    with pytest.raises(ValueError, match="root must be"):
        PoseDecoder(sk, spec, root="float")
    f = np.random.default_rng(3).standard_normal((30, spec.resolve(sk).dim)) * 0.2
    dec = PoseDecoder(sk, spec, start_pos=(1.0, 0.0, 2.0), start_heading=0.3, root="tether", tether_s=2.0)
    got = [dec.decode(f[a:a + 3]) for a in range(0, 30, 3)]
    start = RootState(1.0, 2.0, 0.3)
    want, state = decode_features(f, sk, spec, start, "tether", 2.0, start)
    np.testing.assert_allclose(np.concatenate([p.rotations for p in got]), want.rotations, atol=1e-12)
    np.testing.assert_allclose(np.concatenate([p.root_pos for p in got]), want.root_pos, atol=1e-12)
    assert dec.state.heading == pytest.approx(state.heading) and dec.state.x == pytest.approx(state.x)
