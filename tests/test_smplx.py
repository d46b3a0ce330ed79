"""BEAT2 / SMPL-X takes (issue 51, first part): read onto the SMPL-X skeleton, converted to BVH and back exactly,
joints where SMPL-X's own kinematics put them, the user's body model honoured, bad files refused by name."""

import numpy as np
import pytest

from dimgestor import rotations as R
from dimgestor import smplx
from dimgestor.bvh import BvhMotion, forward_kinematics, read_bvh
from dimgestor_app.cli import main

T, FPS = 40, 30


def take(seed: int = 0, frames: int = T) -> dict:
    """A synthetic BEAT2 take: smooth random joint rotations up to ~2.5 rad, a wandering root, float32 as shipped."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, frames)[:, None, None]
    axis = rng.normal(size=(1, 55, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = rng.uniform(0.2, 2.5, (1, 55, 1)) * np.sin(2 * np.pi * (t + rng.uniform(0, 1, (1, 55, 1))))
    poses = (axis * angle).reshape(frames, 165)
    trans = np.cumsum(rng.normal(0, 0.01, (frames, 3)), axis=0) + (0.1, 0.9, -0.2)
    return {"poses": poses.astype(np.float32), "trans": trans.astype(np.float32),
            "betas": rng.normal(size=300).astype(np.float32), "expressions": rng.normal(size=(frames, 100)).astype(np.float32),
            "model": np.array("smplx2020"), "gender": np.array("neutral"), "mocap_frame_rate": np.array(FPS)}


def save(path, fields: dict):
    np.savez(path, **fields)
    return path


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Radians between rotations given as axis-angle (..., 3)."""
    qa, qb = R.expmap_to_quat(a), R.expmap_to_quat(b)
    return 2 * np.arccos(np.clip(np.abs(np.sum(qa * qb, axis=-1)), 0, 1))


def direction(p: np.ndarray, skeleton, x: str, y: str) -> np.ndarray:
    """Unit vectors from joint x to joint y of world positions p (frames, joints, 3)."""
    v = p[:, skeleton.index(y)] - p[:, skeleton.index(x)]
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def smplx_joints(poses: np.ndarray, trans: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """SMPL-X's own joint kinematics (rotation matrices from axis-angle, each joint rotated about its parent from
    its rest position, the pelvis at rest + trans), written independently of the module under test."""
    def rodrigues(v):
        theta = np.linalg.norm(v, axis=-1)[..., None, None]
        k = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
        K = np.zeros(v.shape[:-1] + (3, 3))
        K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
        K = K - np.swapaxes(K, -1, -2)
        return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K

    rot = rodrigues(poses.reshape(len(poses), 55, 3).astype(np.float64))
    world_r, world_p = np.empty_like(rot), np.empty((len(poses), 55, 3))
    for j, p in enumerate(smplx.PARENTS):
        if p < 0:
            world_r[:, j], world_p[:, j] = rot[:, j], rest[j] + trans
        else:
            world_r[:, j] = world_r[:, p] @ rot[:, j]
            world_p[:, j] = world_p[:, p] + (world_r[:, p] @ (rest[j] - rest[p]))
    return world_p


def test_the_skeleton_is_smplx_tree_and_a_standing_adult():
    sk = smplx.skeleton()
    assert sk.num_joints == 55 and smplx.is_smplx(sk) and all(p < j for j, p in enumerate(sk.parents))
    assert [sk.names[sk.parents[sk.index(n)]] for n in ("left_wrist", "right_index1", "left_thumb3", "jaw")] == [
        "left_elbow", "right_wrist", "left_thumb2", "head"]
    assert [smplx.PARENTS[smplx.JOINTS.index(n)] for n in ("left_wrist", "jaw", "left_index1", "right_thumb3")] == [
        18, 15, 20, 53]  # SMPL-X's own indices: wrist under elbow 18, jaw under head 15, ...
    rest = forward_kinematics(sk, R.quat_identity((1, 55)))[0] / smplx.CM
    np.testing.assert_allclose(rest, smplx.GENERIC_REST[smplx.BVH_ORDER], atol=1e-12)
    left, right = rest[sk.index("left_wrist")], rest[sk.index("right_wrist")]
    assert left[0] > 0.5 and right[0] < -0.5 and abs(left[1] - rest[sk.index("left_shoulder"), 1]) < 1e-9  # T-pose
    assert 1.45 < rest[sk.index("left_eye"), 1] - rest[sk.index("left_foot"), 1] < 1.7  # eyes over the feet (m)


def test_a_take_is_read_where_smplx_kinematics_put_its_joints(tmp_path):
    fields = take(1)
    motion, extra = smplx.read_smplx(save(tmp_path / "a.npz", fields))
    assert motion.num_frames == T and motion.fps == FPS and extra["betas"].shape == (300,)
    ours = forward_kinematics(motion) / smplx.CM
    theirs = smplx_joints(fields["poses"], fields["trans"].astype(np.float64), smplx.GENERIC_REST)
    assert np.abs(ours - theirs[:, smplx.BVH_ORDER]).max() < 1e-7


def test_take_to_bvh_to_take_keeps_every_rotation_and_the_root(tmp_path):
    fields = take(2)
    src = save(tmp_path / "src.npz", fields)
    assert main(["convert", str(src), str(tmp_path / "mid.bvh")]) == 0
    assert main(["convert", str(tmp_path / "mid.bvh"), str(tmp_path / "back.npz")]) == 0
    with np.load(tmp_path / "back.npz", allow_pickle=False) as f:
        back = {k: f[k] for k in f.files}
    assert back["poses"].shape == (T, 165) and back["trans"].shape == (T, 3) and back["betas"].shape == (300,)
    assert back["expressions"].shape == (T, 100) and float(back["mocap_frame_rate"]) == FPS
    assert str(back["model"]) == "smplx2020" and str(back["gender"]) == "neutral"
    turn = angle_between(back["poses"].reshape(T, 55, 3), fields["poses"].reshape(T, 55, 3).astype(np.float64))
    assert turn.max() < 1e-4, turn.max()
    assert np.abs(back["trans"] - fields["trans"]).max() < 1e-5
    # and the BVH on the way is the same motion
    mid = read_bvh(tmp_path / "mid.bvh")
    assert smplx.is_smplx(mid.skeleton) and mid.num_frames == T and mid.fps == pytest.approx(FPS)
    assert np.abs(forward_kinematics(mid) / smplx.CM - smplx_joints(
        fields["poses"], fields["trans"].astype(np.float64), smplx.GENERIC_REST)[:, smplx.BVH_ORDER]).max() < 1e-6


def body_model(path, rng, vertices: int = 200):
    """A stand-in for a SMPL-X body-model file (the real one is the user's): a template, shape directions and a
    joint regressor whose rows average a few vertices."""
    template = smplx.GENERIC_REST[rng.integers(0, 55, vertices)] + rng.normal(0, 0.01, (vertices, 3))
    regressor = np.zeros((55, vertices))
    for j in range(55):
        regressor[j, rng.choice(vertices, 4, replace=False)] = 0.25
    shapedirs = rng.normal(0, 0.002, (vertices, 3, 400))
    np.savez(path, v_template=template, J_regressor=regressor, shapedirs=shapedirs, f=np.zeros((1, 3), np.int64))
    return path, template, regressor, shapedirs


def test_the_users_body_model_gives_the_takes_own_skeleton(tmp_path):
    rng = np.random.default_rng(5)
    path, template, regressor, shapedirs = body_model(tmp_path / "SMPLX_NEUTRAL_2020.npz", rng)
    fields = take(3)
    joints = regressor @ (template + shapedirs[..., :300] @ fields["betas"].astype(np.float64))
    np.testing.assert_allclose(smplx.body_model_joints(path, fields["betas"]), joints, atol=1e-12)
    src = save(tmp_path / "b.npz", fields)
    motion, _ = smplx.read_smplx(src, body_model=path)
    ours = forward_kinematics(motion) / smplx.CM
    theirs = smplx_joints(fields["poses"], fields["trans"].astype(np.float64), joints)
    assert np.abs(ours - theirs[:, smplx.BVH_ORDER]).max() < 1e-7
    # convert with it, and back: the take's own rotations and trans
    assert main(["convert", str(src), str(tmp_path / "b.bvh"), "--smplx-model", str(path)]) == 0
    assert main(["convert", str(tmp_path / "b.bvh"), str(tmp_path / "b2.npz")]) == 0
    with np.load(tmp_path / "b2.npz") as f:
        assert np.abs(f["trans"] - fields["trans"]).max() < 1e-5
        assert angle_between(f["poses"].reshape(T, 55, 3), fields["poses"].reshape(T, 55, 3).astype(float)).max() < 1e-4


@pytest.mark.parametrize("change, says", [
    (lambda f: f.pop("poses"), "no 'poses'"),
    (lambda f: f.pop("mocap_frame_rate"), "no 'mocap_frame_rate'"),
    (lambda f: f.update(poses=f["poses"][:, :156]), r"poses must be \(frames, 165\)"),
    (lambda f: f.update(trans=f["trans"][:-1]), r"trans must be \(40, 3\)"),
    (lambda f: f["poses"].__setitem__((7, 3), np.nan), "poses is not finite at frame 7"),
    (lambda f: f.update(mocap_frame_rate=np.array(0)), "mocap_frame_rate must be one positive number"),
])
def test_a_file_that_is_not_a_take_is_refused_by_name(tmp_path, capsys, change, says):
    fields = take(4)
    change(fields)
    path = save(tmp_path / "bad.npz", fields)
    with pytest.raises(smplx.SmplxError, match=says) as e:
        smplx.read_smplx(path)
    assert str(path) in str(e.value)
    assert main(["convert", str(path), str(tmp_path / "out.bvh")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {path}") and not (tmp_path / "out.bvh").exists()


def test_not_a_numpy_file_and_other_formats_are_refused(tmp_path, capsys):
    (tmp_path / "x.npz").write_text("not a zip")
    assert main(["convert", str(tmp_path / "x.npz"), str(tmp_path / "y.bvh")]) == 2
    assert "x.npz: not a SMPL-X take" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "x.npz"), str(tmp_path / "y.fbx")]) == 2
    assert "y.fbx: convert reads and writes .npz and .bvh" in capsys.readouterr().err


def test_a_motion_on_another_rig_is_not_written_as_smplx(tmp_path):
    sk = smplx.skeleton()
    other = type(sk)(["Hips", "Spine"], [-1, 0], np.zeros((2, 3)), [["Zrotation", "Xrotation", "Yrotation"]] * 2)
    motion = BvhMotion(other, 1 / 30, np.zeros((3, 6)))
    with pytest.raises(smplx.SmplxError, match="only a motion on the SMPL-X skeleton .* retarget it onto SMPL-X"):
        smplx.write_smplx(tmp_path / "o.npz", motion)


def test_train_reads_takes_beside_bvh_pairs_and_refuses_a_bad_take_by_name(tmp_path, capsys):
    """A folder holding a BEAT2 take (NAME.npz + NAME.wav) and a BVH pair on the same skeleton (a take converted)
    trains; a take that is not one is refused, naming it, before any training."""
    from dimgestor.audio import save_wav
    from dimgestor.streaming.checkpoint import load_checkpoint
    from dimgestor.training.synthetic import synthetic_speech

    data = tmp_path / "data"
    data.mkdir()
    for i in range(2):
        fields = take(10 + i, frames=FPS * 8)
        fields["poses"] *= 0.3
        save(data / f"take{i}.npz", fields)
        save_wav(data / f"take{i}.wav", synthetic_speech(8.0, seed=i), 16000)
    assert main(["convert", str(data / "take0.npz"), str(data / "take0.bvh")]) == 0
    (data / "take0.npz").unlink()  # (one motion file a clip)
    args = ["train", "--data", str(data), "--out", str(tmp_path / "run"), "--preset", "tiny", "--max-steps", "1",
            "--batch-size", "2", "--window-s", "4", "--no-progress", "--no-augment", "--no-mirror", "--speeds", "",
            "--no-arm-mix", "--valid-fraction", "0.25", "--valid-every", "0", "--cache-dir", str(tmp_path / "cache")]
    assert main(args) == 0
    assert smplx.is_smplx(load_checkpoint(tmp_path / "run").skeleton)
    bad = take(12, frames=FPS * 8)
    bad["poses"][5, 0] = np.inf
    save(data / "take2.npz", bad)
    save_wav(data / "take2.wav", synthetic_speech(8.0, seed=2), 16000)
    capsys.readouterr()
    assert main([*args[:4], str(tmp_path / "run2"), *args[5:]]) == 2
    err = capsys.readouterr()
    assert f"error: {data / 'take2.npz'}: poses is not finite at frame 5" in err.err and "step" not in err.out


def our_motion(frames: int = 30) -> BvhMotion:
    """Smooth random motion on the default model's skeleton (what `generate` and `serve --record` write)."""
    from dimgestor.streaming.checkpoint import load_checkpoint

    sk = load_checkpoint(None).skeleton
    rng = np.random.default_rng(7)
    t = np.arange(frames)[:, None, None] / 20
    q = R.expmap_to_quat(rng.uniform(0, 0.5, (1, sk.num_joints, 3)) * np.sin(2 * np.pi * t + rng.uniform(0, 6, (1, sk.num_joints, 3))))
    tr = np.broadcast_to(sk.offsets, (frames, sk.num_joints, 3)).copy()
    return BvhMotion.from_pose(sk, 1 / 20, q, tr)


def test_our_motion_written_as_a_take_moves_each_bone_as_ours_does(tmp_path):
    """`generate --out X.npz`'s writer: our skeleton's motion retargeted onto the generic SMPL-X skeleton; each
    arm and leg segment points where ours does (rest poses respected), and the file is a BEAT2 take."""
    from dimgestor.retarget.export import write_motion

    ours = our_motion()
    sk, frames = ours.skeleton, ours.num_frames
    assert "SMPL-X take on the generic SMPL-X skeleton" in write_motion(tmp_path / "t.npz", ours)
    with np.load(tmp_path / "t.npz", allow_pickle=False) as f:
        assert {k: f[k].shape for k in ("poses", "trans", "betas", "expressions")} == {
            "poses": (frames, 165), "trans": (frames, 3), "betas": (300,), "expressions": (frames, 100)}
        assert float(f["mocap_frame_rate"]) == 20
    take_motion, _ = smplx.read_smplx(tmp_path / "t.npz")
    a, b = forward_kinematics(ours), forward_kinematics(take_motion)
    for (x, y), (u, w) in [(("LeftArm", "LeftForeArm"), ("left_shoulder", "left_elbow")),
                           (("RightForeArm", "RightHand"), ("right_elbow", "right_wrist")),
                           (("LeftUpLeg", "LeftLeg"), ("left_hip", "left_knee")),
                           (("RightLeg", "RightFoot"), ("right_knee", "right_ankle"))]:
        cos = (direction(a, sk, x, y) * direction(b, take_motion.skeleton, u, w)).sum(-1)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1.0, (x, y)


def test_a_clip_with_two_motion_files_is_refused_by_name(tmp_path):
    from dimgestor.training.dataset import DatasetError, find_pairs

    for name in ("a.bvh", "a.npz", "a.wav"):
        (tmp_path / name).write_bytes(b"x")
    with pytest.raises(DatasetError, match=r"a\.npz: a\.bvh is beside it: one motion file a clip"):
        find_pairs(tmp_path)


def test_convert_retargets_a_bvh_on_another_rig_onto_smplx_and_refuses_one_it_cannot_map(tmp_path, capsys):
    """`serve --record`'s BVH (our skeleton) becomes a BEAT2 take with `convert`: the same take `generate --out
    X.npz` writes from that motion; a BVH whose bones name no body is refused, naming the file."""
    from dimgestor.bvh import write_bvh
    from dimgestor.retarget.export import write_motion

    ours = our_motion()
    write_bvh(tmp_path / "rec.bvh", ours)
    assert main(["convert", str(tmp_path / "rec.bvh"), str(tmp_path / "rec.npz")]) == 0
    assert "SMPL-X take on the generic SMPL-X skeleton" in capsys.readouterr().out
    write_motion(tmp_path / "direct.npz", read_bvh(tmp_path / "rec.bvh"))
    with np.load(tmp_path / "rec.npz") as a, np.load(tmp_path / "direct.npz") as b:
        assert sorted(a.files) == sorted(b.files) and all(np.array_equal(a[k], b[k]) for k in a.files)
    sk = smplx.skeleton()
    odd = type(sk)(["Foo", "Bar"], [-1, 0], np.array([[0, 0, 0], [0, 10, 0.0]]), [["Zrotation", "Xrotation", "Yrotation"]] * 2)
    write_bvh(tmp_path / "odd.bvh", BvhMotion(odd, 1 / 30, np.zeros((3, 6))))
    assert main(["convert", str(tmp_path / "odd.bvh"), str(tmp_path / "odd.npz")]) == 2
    assert f"{tmp_path / 'odd.bvh'}: its skeleton cannot be retargeted onto SMPL-X" in capsys.readouterr().err
    assert not (tmp_path / "odd.npz").exists()


def test_serve_records_a_take_beside_its_bvh(tiny_checkpoint, wav, tmp_path):
    """`serve --record OUT.npz`: OUT.bvh as the motion comes, and at the end the take `convert` makes of it."""
    from helpers.serve import WAV_SECONDS, serve

    s = serve(tiny_checkpoint, "--source", str(wav), "--fast", "--no-ws", "--steps", "1", "--record",
              str(tmp_path / "talk.npz"))
    assert s.finish() == 0, s.output
    assert f"wrote {tmp_path / 'talk.npz'} (BEAT2 / SMPL-X take on the generic SMPL-X skeleton" in s.output
    assert main(["convert", str(tmp_path / "talk.bvh"), str(tmp_path / "again.npz")]) == 0
    with np.load(tmp_path / "talk.npz") as a, np.load(tmp_path / "again.npz") as b:
        assert len(a["poses"]) == int(WAV_SECONDS * 20) and float(a["mocap_frame_rate"]) == 20
        assert all(np.array_equal(a[k], b[k]) for k in a.files)
