"""One model from several rigs' data (issue 51): clips on other skeletons retargeted onto the training one, speakers
in equal turns, and an optional speaker condition that `generate --speaker`, `serve --speaker` and an ONNX export of
one speaker (`export-onnx --speaker`) play."""

import json
from collections import Counter

import numpy as np
import pytest
import torch
from test_smplx import FPS, direction, save, take

from dimgestor import smplx
from dimgestor.audio import save_wav
from dimgestor.bvh import forward_kinematics, read_bvh
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.training.dataset import DatasetError, GestureDataset, retarget_onto, speaker_of
from dimgestor.training.synthetic import make_synthetic_pair, synthetic_speech
from dimgestor.training.train import BalancedOrder
from dimgestor_app.cli import main

TRAIN = ["--preset", "tiny", "--max-steps", "2", "--batch-size", "2", "--window-s", "2", "--no-progress",
         "--no-augment", "--no-mirror", "--speeds", "", "--no-arm-mix", "--valid-fraction", "0.25", "--valid-every", "0"]


def calm_take(seed: int, seconds: float) -> dict:
    fields = take(seed, frames=int(FPS * seconds))
    fields["poses"] *= 0.3  # (within what a body does, so the retargeted arms stay readable)
    return fields


@pytest.fixture(scope="module")
def two_rigs(tmp_path_factory):
    """zeggs/: a BVH pair on the synthetic (ZEGGS-named) skeleton; beat2/: two BEAT2 takes of one speaker."""
    root = tmp_path_factory.mktemp("rigs")
    make_synthetic_pair(root / "zeggs", "001_Neutral_0", seconds=8.0, seed=0)
    (root / "beat2").mkdir()
    for i in range(2):
        name = f"2_scott_0_{i + 1}_{i + 1}"
        save(root / "beat2" / f"{name}.npz", calm_take(20 + i, 4.0))
        save_wav(root / "beat2" / f"{name}.wav", synthetic_speech(4.0, seed=5 + i), 16000)
    return root


def test_a_clips_speaker_is_beats_name_else_its_sub_folder_else_its_folder():
    assert speaker_of("2_scott_0_1_1", "beat2") == "scott"
    assert speaker_of("sub/10_kieks_1_3_3", "x") == "kieks"
    assert speaker_of("alice/take3", "x") == "alice"
    assert speaker_of("067_Speech_2_x_1_0", "zeggs") == "zeggs"  # (ZEGGS' own naming is not BEAT's)


def test_clips_of_another_rig_are_retargeted_onto_the_first_clips_skeleton(two_rigs, tmp_path):
    ds = GestureDataset([two_rigs / "zeggs", two_rigs / "beat2"], window_s=2.0, use_cache=False)
    ours = read_bvh(two_rigs / "zeggs" / "001_Neutral_0.bvh").skeleton
    assert ds.skeleton == ours and ds.retargeted == ["beat2/2_scott_0_1_1", "beat2/2_scott_0_2_2"]
    assert [p.name for p in ds.pairs][0] == "zeggs/001_Neutral_0" and ds.speakers == ["scott", "zeggs"]
    assert "2 clips retargeted onto the training skeleton, 2 speakers" in ds.summary()
    assert all(np.isfinite(ds[i]["motion"]).all() for i in range(len(ds)))
    # the other way round: the takes' SMPL-X skeleton trains, and the BVH is the one carried
    other = GestureDataset([two_rigs / "beat2", two_rigs / "zeggs"], window_s=2.0, use_cache=False)
    assert smplx.is_smplx(other.skeleton) and other.retargeted == ["zeggs/001_Neutral_0"]
    named = GestureDataset([two_rigs / "zeggs", two_rigs / "beat2"], window_s=2.0, use_cache=False,
                           skeleton=two_rigs / "beat2" / "2_scott_0_1_1.npz")
    assert smplx.is_smplx(named.skeleton) and named.motion_dim == other.motion_dim


def test_a_retargeted_take_moves_each_arm_segment_as_the_take_does(two_rigs):
    """Rest poses respected: the SMPL-X take carried onto the ZEGGS-named skeleton (an upper body) points each arm
    segment where SMPL-X's own kinematics point it (within 5 degrees, 95th percentile, as the issue asks of a real take)."""
    src, _ = smplx.read_smplx(two_rigs / "beat2" / "2_scott_0_1_1.npz")
    onto = read_bvh(two_rigs / "zeggs" / "001_Neutral_0.bvh").skeleton
    moved = retarget_onto(src, onto, two_rigs / "beat2" / "2_scott_0_1_1.npz", "zeggs")
    a, b = forward_kinematics(src), forward_kinematics(moved)
    for (u, w), (x, y) in [(("left_shoulder", "left_elbow"), ("LeftArm", "LeftForeArm")),
                           (("right_elbow", "right_wrist"), ("RightForeArm", "RightHand")),
                           (("left_elbow", "left_wrist"), ("LeftForeArm", "LeftHand")),
                           (("right_shoulder", "right_elbow"), ("RightArm", "RightForeArm"))]:
        cos = (direction(a, src.skeleton, u, w) * direction(b, onto, x, y)).sum(-1)
        assert np.percentile(np.degrees(np.arccos(np.clip(cos, -1, 1))), 95) < 5.0, (x, y)


def test_a_rig_that_cannot_be_matched_is_refused_naming_both_files(two_rigs, tmp_path):
    from dimgestor.bvh import BvhMotion, Skeleton, write_bvh

    data = tmp_path / "d"
    bvh, _ = make_synthetic_pair(data, "b", seconds=3.0, seed=1)
    m = read_bvh(bvh)
    sk = m.skeleton
    odd = Skeleton([f"bone{j}" for j in range(4)], sk.parents[:4], sk.offsets[:4], sk.channels[:4], {3: sk.end_sites.get(3, np.ones(3))})
    write_bvh(bvh, BvhMotion(odd, m.frame_time, m.values[:, :odd.num_channels]))
    with pytest.raises(DatasetError, match=r"b\.bvh: its skeleton .* differs from .*2_scott_0_1_1\.npz's and cannot be "
                                           r"retargeted onto it"):
        GestureDataset([two_rigs / "beat2", data], window_s=2.0, use_cache=False)


def test_speakers_take_equal_turns_whatever_their_hours():
    speakers = ["big"] * 90 + ["small"] * 10
    order = BalancedOrder(speakers, seed=3)
    order.set_epoch(0)
    first = list(order)
    assert len(first) == 100 and all(0 <= i < 100 for i in first)
    counts = Counter(speakers[i] for i in first)
    assert counts == {"big": 50, "small": 50}
    assert set(first[k] for k in range(100) if speakers[first[k]] == "small") == set(range(90, 100))  # each repeated
    # any stretch of a batch's length holds both speakers about equally (rounds of one window each)
    assert all(abs(sum(speakers[i] == "small" for i in first[k:k + 8]) - 4) <= 1 for k in range(0, 92, 8))
    again = BalancedOrder(speakers, seed=3)
    again.set_epoch(0)
    assert list(again) == first  # seeded: a resumed run draws the same
    order.set_epoch(1)
    assert list(order) != first


def test_two_rigs_train_one_model_with_a_speaker_condition_that_generate_plays(two_rigs, tmp_path, wav, capsys):
    run = tmp_path / "run"
    data = ["--data", str(two_rigs / "zeggs"), "--data", str(two_rigs / "beat2")]
    onnx_ready = ["--set", "lookahead_ms=100", "--set", "down_kernel=15"]  # (a lookahead of whole calls)
    assert main(["train", *data, "--out", str(run), "--speaker-condition", "--max-steps", "3", *TRAIN[:2], *TRAIN[4:],
                 "--cache-dir", str(tmp_path / "cache"), *onnx_ready]) == 0
    out = capsys.readouterr().out
    assert "2 clips retargeted onto the training skeleton, 2 speakers" in out
    assert "speakers in equal turns" in out and "speaker condition (2 speakers)" in out
    bundle = load_checkpoint(run)
    assert bundle.config.speakers == ("scott", "zeggs")
    assert bundle.skeleton == read_bvh(two_rigs / "zeggs" / "001_Neutral_0.bvh").skeleton
    assert bundle.info["data"] == [str(two_rigs / "zeggs"), str(two_rigs / "beat2")]
    # each speaker's vector moved away from the others' in training, and changes the condition
    feats = torch.randn(1, 40, bundle.model.frontend.dim)
    conds = []
    for name in (None, "scott", "zeggs"):
        bundle.model.use_speaker(name)
        conds.append(bundle.model.condition(feats)[0])
    assert not torch.equal(conds[0], conds[1]) and not torch.equal(conds[1], conds[2])
    outs = {}
    for name in ("scott", "zeggs"):
        path = tmp_path / f"{name}.bvh"
        assert main(["generate", "--checkpoint", str(run), "--audio", str(wav), "--out", str(path),
                     "--speaker", name]) == 0
        outs[name] = read_bvh(path).values
    assert outs["scott"].shape == outs["zeggs"].shape and not np.array_equal(outs["scott"], outs["zeggs"])
    capsys.readouterr()
    assert main(["generate", "--checkpoint", str(run), "--audio", str(wav), "--out", str(tmp_path / "x.bvh"),
                 "--speaker", "nobody"]) == 2
    assert "speaker 'nobody': this model knows scott, zeggs" in capsys.readouterr().err
    serve = ["serve", "--checkpoint", str(run), "--source", str(wav), "--fast", "--no-ws", "--status-every", "0"]
    assert main([*serve, "--speaker", "scott"]) == 0
    assert main([*serve, "--speaker", "nobody"]) == 2
    assert "--speaker: speaker 'nobody': this model knows scott, zeggs" in capsys.readouterr().err
    # ONNX Runtime: an export of that speaker, its vector a constant of the graph; one of another is refused
    pytest.importorskip("onnxruntime")
    from dimgestor.export.onnx_stream import ort_stream
    from helpers.stream import noise_audio

    def frames(stream):
        return np.concatenate([stream.push(audio), stream.finish()])

    from dimgestor.streaming.checkpoint import save_checkpoint

    # (3 steps leave the zero-initialized modulations near zero: every weight shaken, so the speaker shows)
    torch.manual_seed(0)
    with torch.no_grad():
        for p in bundle.model.parameters():
            p.add_(0.2 * torch.randn_like(p))
    run = save_checkpoint(tmp_path / "shaken", bundle.model, bundle.feature_spec, bundle.skeleton, bundle.mean,
                          bundle.std, info=bundle.info)
    bundle = load_checkpoint(run)
    serve[2] = str(run)
    audio = noise_audio(2.0, seed=3)
    got = {}
    for name in (None, "scott"):
        out = tmp_path / f"onnx_{name}"
        assert main(["export-onnx", "--checkpoint", str(run), "--out", str(out), "--no-face",
                     *(["--speaker", name] if name else [])]) == 0
        assert json.loads((out / "manifest.json").read_text())["checkpoint"]["speaker"] == name
        bundle.model.use_speaker(name)
        got[name] = frames(ort_stream(out, seed=5))
        assert np.abs(got[name] - frames(bundle.stream(seed=5))).max() < 1e-4, name
    assert np.abs(got["scott"] - got[None]).max() > 1e-2
    assert main(["export-onnx", "--checkpoint", str(run), "--out", str(tmp_path / "x"), "--speaker", "nobody"]) == 2
    assert "speaker 'nobody': this model knows scott, zeggs" in capsys.readouterr().err
    assert main([*serve, "--speaker", "scott", "--backend", "onnxruntime", "--onnx", str(tmp_path / "onnx_None")]) == 2
    assert "the ONNX export plays no speaker in particular, not speaker 'scott'" in capsys.readouterr().err
    assert main([*serve, "--speaker", "scott", "--backend", "onnxruntime", "--onnx", str(tmp_path / "onnx_scott")]) == 0


def test_a_model_without_the_speaker_condition_refuses_a_speaker(tiny_checkpoint, wav, tmp_path, capsys):
    assert main(["generate", "--checkpoint", str(tiny_checkpoint), "--audio", str(wav), "--out",
                 str(tmp_path / "x.bvh"), "--speaker", "scott"]) == 2
    assert "trained without --speaker-condition" in capsys.readouterr().err


def test_training_balances_speakers_by_default_and_not_when_told(two_rigs, tmp_path, capsys):
    data = ["--data", str(two_rigs / "zeggs"), "--data", str(two_rigs / "beat2")]
    for flag, says in (("--balance-speakers", True), ("--no-balance-speakers", False)):
        assert main(["train", *data, "--out", str(tmp_path / flag), flag, "--max-steps", "1", *TRAIN[:2], *TRAIN[4:],
                     "--cache-dir", str(tmp_path / "cache")]) == 0
        assert ("speakers in equal turns" in capsys.readouterr().out) == says
    assert load_checkpoint(tmp_path / "--balance-speakers").config.speakers == ()


def test_render_draws_a_take(two_rigs, tmp_path, capsys):
    out = tmp_path / "take.png"
    assert main(["render", str(two_rigs / "beat2" / "2_scott_0_1_1.npz"), "--out", str(out), "--panels", "3"]) == 0
    assert "wrote" in capsys.readouterr().out and out.stat().st_size > 5_000


def test_beat2_as_it_ships_smplxflame_beside_wave16k_with_its_split_file(tmp_path):
    """BEAT2's own layout: smplxflame_30/NAME.npz and wave16k/NAME.wav, and train_test_split.csv (id,type) naming
    takes of the whole language, some of them not downloaded."""
    lang = tmp_path / "beat_english_v2.0.0"
    (lang / "smplxflame_30").mkdir(parents=True)
    (lang / "wave16k").mkdir()
    names = ["2_scott_0_1_1", "2_scott_0_2_2", "4_lawrence_0_3_3"]
    for i, name in enumerate(names):
        save(lang / "smplxflame_30" / f"{name}.npz", calm_take(30 + i, 3.0))
        save_wav(lang / "wave16k" / f"{name}.wav", synthetic_speech(3.0, seed=i), 16000)
    (lang / "train_test_split.csv").write_text("id,type\n2_scott_0_1_1,train\n2_scott_0_2_2,test\n"
                                                "4_lawrence_0_3_3,additional\n30_katya_0_1_1,val\n")
    train = GestureDataset(lang, window_s=2.0, use_cache=False)
    valid = GestureDataset(lang, window_s=2.0, use_cache=False, split="valid")
    assert [p.name for p in train.pairs] == [f"smplxflame_30/{n}" for n in names]
    assert all(p.wav == lang / "wave16k" / f"{p.bvh.stem}.wav" for p in train.pairs)
    assert sorted({train.clips[c].name for c, _, _ in train.segments}) == [f"smplxflame_30/{n}" for n in names[::2]]
    assert {valid.clips[c].name for c, _, _ in valid.segments} == {"smplxflame_30/2_scott_0_2_2"}
    assert train.speakers == ["lawrence", "scott"] and smplx.is_smplx(train.skeleton)


def test_our_bvh_through_a_take_and_back_keeps_every_limb_joints_rotation_and_the_root(tmp_path):
    """BVH -> SMPL-X take -> BVH through the retargeting (issue 51's round trip): every arm, leg, hand and finger
    joint SMPL-X also has comes back within 1e-6 rad, the head's world rotation too, and the root within 1e-5 m.
    (ZEGGS' four spine and two neck joints become SMPL-X's three and one: their turns are shared out differently.)"""
    from test_smplx import our_motion

    from dimgestor import rotations as R
    from dimgestor.retarget.export import write_motion

    ours = our_motion(60)
    write_motion(tmp_path / "t.npz", ours)
    take_motion, _ = smplx.read_smplx(tmp_path / "t.npz")
    back = retarget_onto(take_motion, ours.skeleton, tmp_path / "t.npz", "ours")
    sk = ours.skeleton

    def angle(qa, qb):
        return 2 * np.arccos(np.clip(np.abs(np.sum(qa * qb, axis=-1)), 0, 1))

    limbs = [j for j, n in enumerate(sk.names) if n == "Hips" or (
        any(k in n for k in ("Arm", "Hand", "Shoulder", "Leg", "Foot", "ToeBase")) and "End" not in n
        and not n.endswith("4"))]
    assert len(limbs) >= 45
    assert angle(ours.rotations()[:, limbs], back.rotations()[:, limbs]).max() < 1e-6
    head = sk.index("Head")

    def world_head(m):
        q = m.rotations()
        out = q.copy()
        for j, p in enumerate(sk.parents):  # (parents come before their children)
            if p >= 0:
                out[:, j] = R.quat_mul(out[:, p], q[:, j])
        return out[:, head]

    world = [world_head(ours), world_head(back)]
    assert angle(*world).max() < 1e-6
    assert np.abs(ours.translations()[:, 0] - back.translations()[:, 0]).max() / smplx.CM < 1e-5


def test_clips_with_other_bone_lengths_warn_once_for_all(tmp_path):
    from dataclasses import replace

    from dimgestor.bvh import BvhMotion, write_bvh

    data = tmp_path / "d"
    for i in range(3):
        bvh, _ = make_synthetic_pair(data, f"c{i}", seconds=3.0, seed=i)
        if i:
            m = read_bvh(bvh)
            write_bvh(bvh, BvhMotion(replace(m.skeleton, offsets=m.skeleton.offsets * 1.1), m.frame_time, m.values))
    with pytest.warns(UserWarning) as caught:
        GestureDataset(data, window_s=2.0, use_cache=False)
    says = [str(w.message) for w in caught if "bone offsets differ" in str(w.message)]
    assert len(says) == 1 and "c1.bvh and 1 more clips: bone offsets differ from" in says[0] and "c0.bvh" in says[0]


def test_a_training_skeleton_that_is_not_a_motion_file_is_refused_by_name(two_rigs, tmp_path, capsys):
    data = ["--data", str(two_rigs / "zeggs"), "--data", str(two_rigs / "beat2")]
    for given, says in ((tmp_path / "rig.glb", "rig.glb: the training skeleton is read from a BVH or a BEAT2"),
                        (tmp_path / "nope.bvh", "nope.bvh: training skeleton file not found")):
        assert main(["train", *data, "--out", str(tmp_path / "run"), "--skeleton", str(given), *TRAIN]) == 2
        assert says in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
