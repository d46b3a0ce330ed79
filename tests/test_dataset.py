"""BVH + WAV folders -> aligned, cached, split windows; normalization statistics; synthetic fixtures."""

import json
import warnings

import numpy as np
import pytest

import dimgestor.training.dataset as dataset_module
from dimgestor.audio import load_wav, save_wav
from dimgestor.bvh import BvhError, BvhMotion, Skeleton, read_bvh, write_bvh
from dimgestor.features import FeatureSpec, mirror_features, mix_arms, motion_to_features
from dimgestor.training.dataset import DatasetError, GestureDataset, collate_windows, compute_stats, find_pairs
from dimgestor.training.synthetic import loudness_envelope, make_synthetic_pair, synthetic_speech


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    make_synthetic_pair(root, "a", seconds=12.0, seed=0, fps=30)
    make_synthetic_pair(root / "session2", "b", seconds=8.0, seed=1, fps=60)
    return root


def make(data_dir, tmp_path, **kw):
    return GestureDataset(data_dir, window_s=kw.pop("window_s", 4.0), cache_dir=tmp_path / "cache", **kw)


def test_synthetic_pair_is_deterministic_and_gestures_follow_loudness(tmp_path):
    bvh1, wav1 = make_synthetic_pair(tmp_path / "x", seconds=6.0, seed=3)
    bvh2, wav2 = make_synthetic_pair(tmp_path / "y", seconds=6.0, seed=3)
    assert bvh1.read_bytes() == bvh2.read_bytes() and wav1.read_bytes() == wav2.read_bytes()
    motion, audio = read_bvh(bvh1), load_wav(wav1)
    assert motion.num_frames == 180 and len(audio) == 96000
    assert len({motion.skeleton.rotation_order(j) for j in range(motion.skeleton.num_joints)}) >= 3
    # Forearm flexion tracks the speech loudness: strongly correlated, and silence means rest.
    sk = motion.skeleton
    elbow = motion.values[:, sk.channel_starts[sk.index("LeftForeArm")] + 1]  # ZYX: Y is the middle channel
    env = loudness_envelope(audio, 16000, 30, motion.num_frames)
    assert np.corrcoef(elbow, env)[0, 1] < -0.99  # more flexion (more negative Y) when louder
    silent = synthetic_speech(6.0, seed=3)[:3200]
    assert np.abs(silent).max() == 0.0  # it starts with a pause of at least 0.2 s


def test_find_pairs_walks_sub_folders_and_names_what_is_wrong(data_dir, tmp_path):
    assert [p.name for p in find_pairs(data_dir)] == ["a", "session2/b"]
    (tmp_path / "only.bvh").write_text("x")
    with pytest.raises(DatasetError, match=rf"{tmp_path}: no NAME.bvh \(or NAME.npz\) \+ NAME.wav pairs found \(1 motion and 0 .wav"):
        find_pairs(tmp_path)
    with pytest.raises(DatasetError, match="data folder not found"):
        find_pairs(tmp_path / "nowhere")
    save_wav(tmp_path / "only.wav", np.zeros(100), 16000)
    (tmp_path / "extra.wav").write_bytes(b"")
    with pytest.warns(UserWarning, match="extra.wav"):
        assert [p.name for p in find_pairs(tmp_path)] == ["only"]


def test_windows_are_aligned_motion_and_audio(data_dir, tmp_path):
    ds = make(data_dir, tmp_path, hop_s=1.5)
    assert ds.spec.fps == 20 and ds.motion_dim == ds.spec.dim == 42
    for i in (0, 3, len(ds) - 1):
        item = ds[i]
        n = len(item["motion"])
        assert item["motion"].dtype == np.float32 and item["audio"].shape == (n * 800,)
        pair = next(p for p in ds.pairs if p.name == item["name"])
        s = item["start_frame"]
        np.testing.assert_array_equal(item["motion"], motion_to_features(read_bvh(pair.bvh), ds.spec)[s:s + n])
        np.testing.assert_array_equal(item["audio"], load_wav(pair.wav)[s * 800:(s + n) * 800])
    full = [w for w in ds.windows if w[2] == 80]
    assert len(full) == len(ds)  # 4 s windows fit in both training stretches
    starts_a = [w[1] for w in ds.windows if w[0] == 0]
    assert starts_a[:3] == [0, 30, 60] and starts_a[-1] + 80 == 204  # hop 1.5 s, and the tail is covered


def test_default_split_holds_out_the_last_15_percent(data_dir, tmp_path):
    train, valid = make(data_dir, tmp_path), make(data_dir, tmp_path, split="valid")
    assert train.segments == [(0, 0, 204), (1, 0, 136)]  # 240 and 160 frames at 20 fps
    assert valid.segments == [(0, 204, 240), (1, 136, 160)]
    assert all(len(valid[i]["motion"]) == 36 for i in range(len(valid)) if valid[i]["name"] == "a")  # shorter than a window
    by_seconds = make(data_dir, tmp_path, split="valid", valid_seconds=3.0)
    assert by_seconds.segments == [(0, 180, 240), (1, 100, 160)]


@pytest.mark.parametrize("name, text", [("split.txt", "# held out\nsession2/b valid\n"),
                                        ("split.csv", "name,split\nb,valid\na,train\n"),
                                        ("split.json", json.dumps({"train": ["a"], "valid": ["b"]}))])
def test_split_file_assigns_whole_clips(data_dir, tmp_path, name, text):
    split = tmp_path / name
    split.write_text(text)
    train = make(data_dir, tmp_path, split_file=split)
    valid = make(data_dir, tmp_path, split="valid", split_file=split)
    assert train.segments == [(0, 0, 240)] and valid.segments == [(1, 0, 160)]


def test_bad_split_file_names_the_line(data_dir, tmp_path):
    split = tmp_path / "split.txt"
    split.write_text("a train\nzzz valid\n")
    with pytest.raises(DatasetError, match=r"split\.txt:2: 'zzz' is not one of the pairs"):
        make(data_dir, tmp_path, split_file=split)


def test_second_run_uses_the_cache_and_a_changed_file_invalidates_it(tmp_path, monkeypatch):
    data = tmp_path / "d"
    bvh_path, _ = make_synthetic_pair(data, "c", seconds=5.0, seed=2)
    first = make(data, tmp_path)

    def no_parsing(path):
        raise AssertionError(f"parsed {path} although it was cached")

    monkeypatch.setattr(dataset_module, "read_bvh", no_parsing)
    second = make(data, tmp_path)
    np.testing.assert_array_equal(second[0]["motion"], first[0]["motion"])
    np.testing.assert_array_equal(second[0]["audio"], first[0]["audio"])
    assert second.skeleton.same_topology(first.skeleton)
    motion = read_bvh(bvh_path)
    motion.values[:, 1] += 1.0  # raise the hips by 1 cm: a new file must not reuse the old entry
    write_bvh(bvh_path, motion)
    with pytest.raises(AssertionError, match="although it was cached"):
        make(data, tmp_path)


def test_mirroring_adds_mirrored_copies(data_dir, tmp_path):
    plain, mirrored = make(data_dir, tmp_path), make(data_dir, tmp_path, mirror=True)
    assert len(mirrored) == 2 * len(plain)
    item, twin = mirrored[0], mirrored[1]
    assert not item["mirrored"] and twin["mirrored"] and item["start_frame"] == twin["start_frame"]
    np.testing.assert_allclose(twin["motion"], mirror_features(item["motion"], mirrored.spec))
    np.testing.assert_array_equal(twin["audio"], item["audio"])


def test_arm_mixing_adds_one_copy_per_training_window_with_the_sides_taking_turns(data_dir, tmp_path):
    plain, mixed = make(data_dir, tmp_path, mirror=True), make(data_dir, tmp_path, mirror=True, arm_mix=True)
    assert len(mixed) == 3 * len(plain) // 2 and "arm-mixed" in mixed.summary()
    items = [mixed[i] for i in range(6)]
    assert [(it["mirrored"], it["arms"]) for it in items] == [(False, None), (True, None), (False, "left"),
                                                             (False, None), (True, None), (False, "right")]
    for it in (items[2], items[5]):
        base = items[0] if it is items[2] else items[3]
        assert it["start_frame"] == base["start_frame"]
        np.testing.assert_allclose(it["motion"], mix_arms(base["motion"], mixed.spec, mixed.skeleton, it["arms"]),
                                   atol=1e-6)
        np.testing.assert_array_equal(it["audio"], base["audio"])  # the same speech
    np.testing.assert_array_equal(mixed.frames(), plain.frames())  # statistics as before
    assert len(make(data_dir, tmp_path, split="valid", arm_mix=True)) == len(make(data_dir, tmp_path, split="valid"))
    with pytest.raises(DatasetError, match="arm mixing needs left and right arm joints"):
        make(data_dir, tmp_path, spec=FeatureSpec(joints=("Spine", "Head")), arm_mix=True)  # no arms kept


def test_stats_cover_each_training_frame_once_and_floor_constant_columns(tmp_path):
    data = tmp_path / "d"
    bvh_path, _ = make_synthetic_pair(data, "c", seconds=5.0, seed=4)
    motion = read_bvh(bvh_path)
    sk = motion.skeleton
    head = sk.channel_starts[sk.index("Head")]
    motion.values[:, head:head + 3] = 7.0  # a head that never moves
    write_bvh(bvh_path, motion)
    ds = make(data, tmp_path, hop_s=0.5)  # heavily overlapping windows must not change the stats
    mean, std = compute_stats(ds)
    frames = motion_to_features(motion, ds.spec)[:85]  # 100 frames, the last 15 held out
    np.testing.assert_allclose(mean, frames.mean(0), rtol=1e-5, atol=1e-6)
    head_cols = [ds.spec.columns.index(f"Head_r{a}") for a in "xyz"]
    np.testing.assert_array_equal(std[head_cols], np.float32(1e-4))
    normalized = (frames - mean) / std
    assert np.isfinite(normalized).all() and np.abs(normalized[:, head_cols]).max() < 0.1


def test_mismatched_lengths_warn_and_trim(tmp_path):
    data = tmp_path / "d"
    _, wav_path = make_synthetic_pair(data, "c", seconds=6.0, seed=5)
    save_wav(wav_path, load_wav(wav_path)[:16000 * 4], 16000)  # audio now 2 s shorter than motion
    with pytest.warns(UserWarning, match=r"c: motion is 6\.00 s but audio is 4\.00 s"):
        ds = make(data, tmp_path, use_cache=False, valid_fraction=0.0)
    assert ds.clips[0].features.shape[0] == 80 and ds.clips[0].audio.shape == (64000,)


def test_inconsistent_skeletons_and_broken_files_are_named(tmp_path):
    data = tmp_path / "d"
    make_synthetic_pair(data, "a", seconds=3.0, seed=0)
    bvh_path, wav_path = make_synthetic_pair(data, "b", seconds=3.0, seed=1)
    m = read_bvh(bvh_path)
    sk = m.skeleton
    small = Skeleton(sk.names[:5], sk.parents[:5], sk.offsets[:5], sk.channels[:5], {4: sk.end_sites[4]})
    write_bvh(bvh_path, BvhMotion(small, m.frame_time, m.values[:, :small.num_channels]))
    with pytest.raises(DatasetError, match=r"b\.bvh: its skeleton .* differs from .*a\.bvh"):
        make(data, tmp_path, use_cache=False)
    bvh_path.write_text(bvh_path.read_text()[:-3000])  # truncated mid-frame
    with pytest.raises(BvhError, match=r"b\.bvh:\d+: "):
        make(data, tmp_path, use_cache=False)


def test_collate_crops_to_the_shortest_window(data_dir, tmp_path):
    valid = make(data_dir, tmp_path, split="valid")
    batch = collate_windows([valid[i] for i in range(len(valid))])
    assert batch["motion"].shape == (2, 24, 42) and batch["audio"].shape == (2, 24 * 800)


def test_zeggs_sample_windows(zeggs_dir, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # motion and audio lengths agree; the sample is one clean pair
        train = GestureDataset(zeggs_dir, FeatureSpec(), cache_dir=tmp_path / "cache")
    valid = GestureDataset(zeggs_dir, FeatureSpec(), split="valid", cache_dir=tmp_path / "cache")
    assert train.motion_dim == 228 and len(train.skeleton.names) == 75
    assert train.segments == [(0, 0, 1170)] and valid.segments == [(0, 1170, 1376)]  # last ~10 s held out
    item = train[0]
    assert item["motion"].shape == (400, 228) and item["audio"].shape == (320000,)
    assert [w[1] for w in train.windows] == [0, 200, 400, 600, 770]


def test_speed_perturbation_adds_faster_and_slower_copies_of_the_training_part_only(tmp_path):
    from dimgestor.training.dataset import speed_perturb

    data = tmp_path / "d"
    make_synthetic_pair(data, "a", seconds=10.0, seed=2)
    plain = GestureDataset(data, window_s=2.0, cache_dir=tmp_path / "cache", valid_seconds=2.0)
    fast = GestureDataset(data, window_s=2.0, cache_dir=tmp_path / "cache", valid_seconds=2.0, speeds=(0.9, 1.1))
    valid = GestureDataset(data, window_s=2.0, cache_dir=tmp_path / "cache", valid_seconds=2.0, split="valid",
                           speeds=(0.9, 1.1))
    assert len(valid.clips) == 1 and len(valid.segments) == 1  # nothing added to the held-out split
    assert [c.name for c in fast.clips] == ["a", "a@0.9x", "a@1.1x"]
    train_frames = plain.segments[0][2]  # 8 s at 20 fps
    assert [len(fast.clips[i].features) for i in (1, 2)] == [int(train_frames / 0.9), int(train_frames / 1.1)]
    for clip in fast.clips[1:]:
        assert len(clip.audio) == len(clip.features) * fast.spf  # audio and motion stay aligned
    assert fast.seconds() == pytest.approx(plain.seconds() * (1 + 1 / 0.9 + 1 / 1.1), rel=0.02)

    # the copies are the same motion at another tempo: per-frame root steps scale, poses are resampled
    clip = plain.clips[0]
    twice = speed_perturb(clip, 2.0, 20.0, 800)
    f, g = np.asarray(clip.features), twice.features
    assert len(g) == len(f) // 2
    np.testing.assert_allclose(g[:, 6:], f[: 2 * len(g):2, 6:], atol=1e-5)  # every other frame's joint angles
    np.testing.assert_allclose(g[:, :3], 2 * f[: 2 * len(g):2, :3], atol=1e-5)  # root velocities per frame double
    assert np.sum(g[:, 2]) == pytest.approx(np.sum(f[: 2 * len(g), 2]), abs=0.05)  # about the same total turn
    with pytest.raises(ValueError, match="positive"):
        GestureDataset(data, window_s=2.0, cache_dir=tmp_path / "cache", speeds=(0.0,))
