"""BVH reading/writing, forward kinematics and the rotation helpers they rest on."""

import json

import bvh as pypi_bvh
import numpy as np
import pytest

from dimgestor import rotations as R
from dimgestor.bvh import BvhError, BvhMotion, Skeleton, forward_kinematics, read_bvh, write_bvh

ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]

# Mixed rotation orders, a 6-channel root with the position channels in a non-XYZ order,
# a 6-channel inner joint, End Sites, tabs and CRLF line ends.
MIXED_BVH = """HIERARCHY
ROOT Hips
{
\tOFFSET 0.0 90.0 0.0
\tCHANNELS 6 Xposition Zposition Yposition Zrotation Xrotation Yrotation
\tJOINT Spine
\t{
\t\tOFFSET 0.0 10.0 0.0
\t\tCHANNELS 3 XYZ_PLACEHOLDER
\t\tJOINT Head
\t\t{
\t\t\tOFFSET 0.0 15.0 1.0
\t\t\tCHANNELS 3 Zrotation Yrotation Xrotation
\t\t\tEnd Site
\t\t\t{
\t\t\t\tOFFSET 0.0 8.0 0.0
\t\t\t}
\t\t}
\t}
\tJOINT LeftUpLeg
\t{
\t\tOFFSET 9.0 -5.0 0.0
\t\tCHANNELS 6 Xposition Yposition Zposition Yrotation Zrotation Xrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0.0 -40.0 0.0
\t\t}
\t}
}
MOTION
Frames: 3
Frame Time: 0.0333333
1.0 2.0 90.0 10.0 -20.0 30.0 5.0 6.0 7.0 1.0 2.0 3.0 9.0 -5.0 0.0 40.0 -50.0 60.0
1.5 2.5 90.5 11.0 -21.0 31.0 5.5 6.5 7.5 1.5 2.5 3.5 9.0 -5.0 0.0 41.0 -51.0 61.0
2.0 3.0 91.0 12.0 -22.0 32.0 6.0 7.0 8.0 2.0 3.0 4.0 9.0 -5.0 0.0 42.0 -52.0 62.0
""".replace("XYZ_PLACEHOLDER", "Xrotation Yrotation Zrotation").replace("\n", "\r\n")


@pytest.fixture
def mixed_file(tmp_path):
    p = tmp_path / "mixed.bvh"
    p.write_bytes(MIXED_BVH.encode())
    return p


def axis_matrix(axis, a):
    c, s = np.cos(a), np.sin(a)
    return {"X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


# ---- rotations -----------------------------------------------------------------------------------


@pytest.mark.parametrize("order", ORDERS)
def test_euler_order_is_the_multiplication_order(order):
    a = np.array([0.3, -0.7, 1.1])
    expected = axis_matrix(order[0], a[0]) @ axis_matrix(order[1], a[1]) @ axis_matrix(order[2], a[2])
    np.testing.assert_allclose(R.quat_to_matrix(R.euler_to_quat(a, order)), expected, atol=1e-12)


@pytest.mark.parametrize("order", ORDERS)
def test_euler_quat_round_trip_including_gimbal_lock(order):
    rng = np.random.default_rng(1)
    a = rng.uniform(-np.pi, np.pi, (500, 3))
    a[:, 1] *= 0.5  # middle angle in (-pi/2, pi/2): the unique Tait-Bryan solution
    np.testing.assert_allclose(R.quat_to_euler(R.euler_to_quat(a, order), order), a, atol=1e-9)
    locked = np.array([0.4, np.pi / 2, -0.3])  # different angles, same rotation: compare rotations
    back = R.quat_to_euler(R.euler_to_quat(locked, order), order)
    np.testing.assert_allclose(R.quat_to_matrix(R.euler_to_quat(back, order)),
                               R.quat_to_matrix(R.euler_to_quat(locked, order)), atol=1e-7)


def test_matrix_and_expmap_round_trips():
    rng = np.random.default_rng(2)
    q = R.quat_normalize(rng.normal(size=(1000, 4)))
    same = lambda a, b: np.abs(np.abs(np.sum(a * b, -1)) - 1).max()  # noqa: E731
    assert same(R.matrix_to_quat(R.quat_to_matrix(q)), q) < 1e-12
    assert same(R.expmap_to_quat(R.quat_to_expmap(q)), q) < 1e-12
    assert np.linalg.norm(R.quat_to_expmap(q), axis=-1).max() <= np.pi + 1e-9
    tiny = np.array([1e-9, -2e-9, 3e-9])
    np.testing.assert_allclose(R.quat_to_expmap(R.expmap_to_quat(tiny)), tiny, rtol=1e-6)


def test_continuity_removes_sign_flips_and_2pi_jumps():
    angle = np.linspace(0, 6 * np.pi, 200)  # three full turns about a tilted axis
    axis = np.array([0.3, 0.9, 0.1]) / np.linalg.norm([0.3, 0.9, 0.1])
    q = np.concatenate([np.cos(angle / 2)[:, None], np.sin(angle / 2)[:, None] * axis], -1)
    canonical = R.matrix_to_quat(R.quat_to_matrix(q))  # w >= 0: flips sign every turn
    assert np.abs(np.diff(canonical, axis=0)).max() > 1.0
    smooth = R.quat_continuity(canonical)
    assert np.abs(np.diff(smooth, axis=0)).max() < 0.1
    v = R.quat_to_expmap(canonical)
    assert np.linalg.norm(np.diff(v, axis=0), axis=-1).max() > 3.0
    cont = R.expmap_continuity(v)
    assert np.linalg.norm(np.diff(cont, axis=0), axis=-1).max() < 0.1
    np.testing.assert_allclose(cont, angle[:, None] * axis, atol=1e-9)  # the unwrapped rotation vector


def test_expmap_continuity_picks_the_representation_closest_to_the_previous_frame():
    rng = np.random.default_rng(4)
    q = R.quat_continuity(R.quat_normalize(np.cumsum(rng.normal(scale=0.3, size=(300, 4)), axis=0)))
    v = R.expmap_continuity(R.quat_to_expmap(q))
    assert np.abs(np.abs(np.sum(R.expmap_to_quat(v) * q, -1)) - 1).max() < 1e-9  # same rotations
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    u = v / angle
    chosen = np.linalg.norm(v[1:] - v[:-1], axis=-1)
    for turn in (-2 * np.pi, 2 * np.pi):  # the same rotation one turn either way is never closer
        assert np.all(chosen <= np.linalg.norm(v[1:] + turn * u[1:] - v[:-1], axis=-1) + 1e-12)
    assert angle.max() > np.pi  # the walk wandered past pi, so the choice was exercised


def test_slerp_is_constant_speed_on_the_short_arc():
    q0 = R.euler_to_quat(np.array([0.0, 0.0, 0.0]), "XYZ")
    q1 = -R.euler_to_quat(np.array([0.0, 1.0, 0.0]), "XYZ")  # negated: slerp must take the short way
    t = np.linspace(0, 1, 5)
    out = R.quat_slerp(q0[None], q1[None], t)
    np.testing.assert_allclose(np.linalg.norm(R.quat_to_expmap(out), axis=-1), t, atol=1e-12)


def test_split_heading_recomposes_and_tilt_has_no_yaw():
    rng = np.random.default_rng(3)
    q = R.quat_normalize(rng.normal(size=(300, 4)))
    heading, tilt = R.split_heading(q)
    same = np.abs(np.sum(R.quat_mul(R.yaw_quat(heading), tilt) * q, -1))
    np.testing.assert_allclose(same, 1.0, atol=1e-12)
    np.testing.assert_allclose(tilt[:, 2], 0.0, atol=1e-12)


# ---- BVH -----------------------------------------------------------------------------------------


def test_reads_mixed_orders_six_channel_joints_end_sites_crlf(mixed_file):
    m = read_bvh(mixed_file)
    sk = m.skeleton
    assert sk.names == ["Hips", "Spine", "Head", "LeftUpLeg"]
    assert sk.parents == [-1, 0, 1, 0]
    assert [sk.rotation_order(j) for j in range(4)] == ["ZXY", "XYZ", "ZYX", "YZX"]
    assert sk.children(0) == [1, 3]
    assert sorted(sk.end_sites) == [2, 3]
    np.testing.assert_allclose(sk.end_sites[3], [0, -40, 0])
    assert m.values.shape == (3, 18) and m.frame_time == pytest.approx(0.0333333)
    np.testing.assert_allclose(m.translations()[1, 0], [1.5, 90.5, 2.5])  # X, Z, Y channel order honoured


def test_write_read_round_trip_and_independent_parser(mixed_file, tmp_path):
    m = read_bvh(mixed_file)
    out = tmp_path / "out.bvh"
    write_bvh(out, m)
    back = read_bvh(out)
    assert back.skeleton.same_topology(m.skeleton)
    np.testing.assert_allclose(back.values, m.values, atol=1e-4)
    np.testing.assert_allclose(back.skeleton.offsets, m.skeleton.offsets)
    assert back.frame_time == m.frame_time
    other = pypi_bvh.Bvh(out.read_text())
    assert other.get_joints_names() == m.skeleton.names
    assert other.nframes == 3 and other.frame_time == pytest.approx(m.frame_time)
    assert other.joint_channels("LeftUpLeg") == m.skeleton.channels[3]


def test_forward_kinematics_known_pose():
    sk = Skeleton(["root", "a", "b"], [-1, 0, 1], np.array([[0, 0, 0], [0, 0, 10], [0, 5, 0]]),
                  [["Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"],
                   ["Zrotation", "Xrotation", "Yrotation"], []])
    # root at (1,2,3) turned 90 deg about Y (+Z -> +X); a bent 90 deg about X (+Y -> +Z -> +X).
    m = BvhMotion(sk, 0.05, np.array([[1, 2, 3, 0, 90, 0, 0, 90, 0]]))
    np.testing.assert_allclose(forward_kinematics(m)[0], [[1, 2, 3], [11, 2, 3], [16, 2, 3]], atol=1e-12)


def test_pose_round_trip_through_from_pose(mixed_file):
    m = read_bvh(mixed_file)
    back = BvhMotion.from_pose(m.skeleton, m.frame_time, m.rotations(), m.translations())
    np.testing.assert_allclose(back.values, m.values, atol=1e-9)  # angles are in the principal range here


def test_skeleton_dict_is_json_safe(mixed_file):
    sk = read_bvh(mixed_file).skeleton
    back = Skeleton.from_dict(json.loads(json.dumps(sk.to_dict())))
    assert back.same_topology(sk)
    np.testing.assert_array_equal(back.offsets, sk.offsets)
    assert back.end_sites.keys() == sk.end_sites.keys()
    assert back == sk
    back.offsets[2, 1] += 0.01
    assert back != sk  # a different bone length is a different skeleton


@pytest.mark.parametrize(
    "mutate, line, words",
    [
        (lambda s: s.rsplit("\r\n", 2)[0] + "\r\n", 34, "ends after 2 of 3 frames"),
        (lambda s: s.split("MOTION")[0], 29, "no MOTION"),
        (lambda s: s.replace("OFFSET 0.0 15.0 1.0", "OFFSET 0.0 abc 1.0"), 12, "expected a number"),
        (lambda s: s.replace("Zrotation Yrotation Xrotation", "Zrotation Yrotation Wrotation"), 13, "unknown channel"),
        (lambda s: s.replace("91.0 12.0", "91.0"), 35, "17 values"),
        (lambda s: s.replace("HIERARCHY", "HIERARCHX"), 1, "not a BVH"),
    ],
)
def test_malformed_files_name_file_and_line(tmp_path, mutate, line, words):
    p = tmp_path / "bad.bvh"
    p.write_bytes(mutate(MIXED_BVH).encode())
    with pytest.raises(BvhError, match=rf"bad\.bvh:{line}: .*{words}"):
        read_bvh(p)


def _chain_bvh(n: int) -> str:
    """A chain of n joints, each the child of the one before, with two frames."""
    lines = ["HIERARCHY", "ROOT Hips", "{", "OFFSET 0 0 0",
             "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    for i in range(n - 1):
        lines += [f"JOINT j{i}", "{", "OFFSET 0 1 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    lines += ["End Site", "{", "OFFSET 0 1 0", "}", *["}"] * n, "MOTION", "Frames: 2", "Frame Time: 0.05"]
    return "\n".join(lines + [" ".join(["1"] * (3 + 3 * n))] * 2) + "\n"


def test_a_chain_deeper_than_the_recursion_limit_reads_and_writes_and_a_cut_one_names_its_line(tmp_path):
    """Nesting of any depth parses (no recursion: Python's limit stopped a 1,000-deep chain with a RecursionError)."""
    p = tmp_path / "deep.bvh"
    p.write_text(_chain_bvh(3_000))
    m = read_bvh(p)
    assert m.skeleton.num_joints == 3_000 and m.skeleton.parents[-1] == 2_998 and m.num_frames == 2
    write_bvh(tmp_path / "again.bvh", m)
    back = read_bvh(tmp_path / "again.bvh")
    assert back.skeleton == m.skeleton and np.array_equal(back.values, m.values)
    cut = _chain_bvh(3_000).replace("}\n" * 1_500, "", 1)  # half the closing braces gone
    p.write_text(cut)
    with pytest.raises(BvhError, match=r"deep\.bvh:\d+: expected JOINT, End Site or '}' inside 'j\d+', found 'MOTION'|"
                                       r"deep\.bvh:\d+: unexpected end of file"):
        read_bvh(p)


def test_zeggs_round_trip(zeggs_dir, tmp_path):
    m = read_bvh(zeggs_dir / "067_Speech_2_x_1_0.bvh")
    assert m.skeleton.num_joints == 75 and m.num_frames == 2065
    write_bvh(tmp_path / "z.bvh", m)
    back = read_bvh(tmp_path / "z.bvh")
    np.testing.assert_allclose(back.values, m.values, atol=1e-4)
    assert back.frame_time == m.frame_time
    np.testing.assert_allclose(forward_kinematics(back), forward_kinematics(m), atol=1e-4)


def test_a_bvh_written_in_pieces_is_the_text_of_it_written_at_once(tmp_path):
    """BvhWriter (generate's long recordings): Euler angles unwrapped across the pieces, so the file is write_bvh's
    of the whole motion, byte for byte, whatever the pieces; a count other than the header's is refused."""
    from dimgestor import rotations as R
    from dimgestor.bvh import BvhMotion, BvhWriter, Skeleton, write_bvh

    sk = Skeleton(["hips", "spine", "head"], [-1, 0, 1], np.array([[0, 90, 0], [0, 10, 0], [0, 20, 0]], float),
                  [["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"],
                   ["Zrotation", "Xrotation", "Yrotation"], ["Zrotation", "Xrotation", "Yrotation"]])
    T = 97
    angle = np.linspace(0, 6 * np.pi, T)  # turns round and round: the unwrapping is at work across the pieces
    axes = np.array([[0, 1, 0], [1, 0, 0], [0.6, 0.8, 0]])
    q = np.stack([R.expmap_to_quat(axes[j] * ((j + 1) * angle[:, None] % (2 * np.pi))) for j in range(3)], axis=1)
    t = np.broadcast_to(sk.offsets, (T, 3, 3)).copy()
    t[:, 0] = np.random.default_rng(0).standard_normal((T, 3))
    write_bvh(tmp_path / "whole.bvh", BvhMotion.from_pose(sk, 0.05, q, t))
    with BvhWriter(tmp_path / "pieces.bvh", sk, 0.05, T) as w:
        for a, b in [(0, 1), (1, 1), (1, 30), (30, 31), (31, 97)]:
            w.write(q[a:b], t[a:b])
    assert (tmp_path / "pieces.bvh").read_text() == (tmp_path / "whole.bvh").read_text()
    with pytest.raises(ValueError, match="96 frames written, the header says 97"):
        with BvhWriter(tmp_path / "short.bvh", sk, 0.05, T) as w:
            w.write(q[1:], t[1:])
