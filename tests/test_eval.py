"""`dimgestor eval` on a synthetic data folder with a small untrained model."""

import argparse
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from dimgestor.config import get_preset
from dimgestor.evaluation import eval as ev
from dimgestor.evaluation import metrics
from dimgestor.model.network import DiMGestor
from dimgestor.training.dataset import GestureDataset, compute_stats
from dimgestor.training.synthetic import make_synthetic_pair


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaldata")
    make_synthetic_pair(root, "a", seconds=16.0, seed=1)
    make_synthetic_pair(root, "b", seconds=16.0, seed=2)
    cache = tmp_path_factory.mktemp("cache")
    common = dict(window_s=2.0, valid_fraction=0.25, cache_dir=cache)
    return root, GestureDataset(root, split="valid", **common), GestureDataset(root, split="train", **common)


def _bundle(train):
    """What `load_checkpoint` returns, for an untrained tiny model sized to the data."""
    torch.manual_seed(0)
    model = DiMGestor(get_preset("tiny", motion_dim=train.motion_dim)).eval()
    with torch.no_grad():  # adaLN-Zero starts at output 0; give it something to say
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    mean, std = compute_stats(train)
    return SimpleNamespace(model=model, mean=mean, std=std, skeleton=train.skeleton, feature_spec=train.spec,
                           denormalize=lambda f: f * std + mean)


def test_joint_positions_are_root_relative(data):
    _, valid, _ = data
    pos = ev.joint_positions(valid[0]["motion"], valid.skeleton, valid.spec)
    assert pos.shape == (len(valid[0]["motion"]), valid.skeleton.num_joints, 3)
    np.testing.assert_allclose(pos[:, 0], 0.0, atol=1e-9)
    assert np.abs(pos).max() > 10  # the arms are tens of cm from the hips


def test_systems_and_scores(data, tmp_path):
    root, valid, train = data
    bundle = _bundle(train)
    gen = ev.generate_systems(bundle, valid, train, steps=2, seed=0, max_windows=3, log=lambda *_: None)
    assert set(gen["windows"]) == set(ev.SYSTEMS)
    assert all(len(w) == len(gen["audio"]) for w in gen["windows"].values())
    for name, wins in gen["windows"].items():
        assert all(w.shape == (valid.window, valid.motion_dim) for w in wins), name

    ae = ev.fgd_autoencoder(train, tmp_path / "ae", steps=30, log=lambda *_: None)
    assert (tmp_path / "ae" / "fgd_autoencoder.json").is_file()
    res = ev.score(gen["windows"], gen["audio"], valid.skeleton, valid.spec, ae)
    gt, still = res["ground_truth"], res["mean_pose"]
    assert gt["fgd_raw"] == pytest.approx(0.0, abs=1e-6) and gt["fgd_feature"] == pytest.approx(0.0, abs=1e-6)
    assert still["jerk"] == pytest.approx(0.0, abs=1e-6) and still["mean_speed"] == pytest.approx(0.0, abs=1e-6)
    assert still["beat_align"] == 0.0  # a body that never moves has no beats
    assert still["fgd_raw"] > 0 and res["model"]["fgd_raw"] > 0
    for name in ev.SYSTEMS:
        assert all(np.isfinite(res[name][m]) for m in ev.METRICS), name
    assert 0 < gt["beat_align"] <= 1

    # the saved autoencoder is found again and gives the same numbers
    again = ev.fgd_autoencoder(train, tmp_path / "ae", steps=30, log=lambda *_: None)
    chunks = metrics.motion_chunks(valid[0]["motion"], 34, 8)
    np.testing.assert_allclose(again.embed(chunks), ae.embed(chunks), atol=1e-6)

    result = {"checkpoint": "tiny", "data": str(root), "split": "valid", "n_windows": 3, "steps": 2,
              "systems": res}
    ev.plot(result, tmp_path / "r.png")
    assert (tmp_path / "r.png").stat().st_size > 1000
    json.dumps(result)  # JSON-safe


def test_register_adds_the_eval_subcommand():
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    ev.register(sub)
    args = parser.parse_args(["eval", "--checkpoint", "ck", "--data", "d", "--steps", "4", "--out", "x.json",
                              "--plot", "x.png"])
    assert (args.command, args.checkpoint, args.data, args.ks, args.out, args.plot) == ("eval", "ck", "d", "4", "x.json", "x.png")
    assert args.func is ev.main_from_args


def test_eval_command_end_to_end(data, tmp_path, capsys):
    from dimgestor.streaming.checkpoint import save_checkpoint

    root, _, train = data
    b = _bundle(train)
    save_checkpoint(tmp_path / "ck", b.model, b.feature_spec, b.skeleton, b.mean, b.std)
    parser = argparse.ArgumentParser()
    ev.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "ck"), "--data", str(root), "--steps", "1",
                              "--window-s", "2", "--valid-fraction", "0.25", "--max-windows", "2",
                              "--fgd-model", str(tmp_path / "ae"), "--fgd-steps", "20",
                              "--out", str(tmp_path / "res.json"), "--plot", str(tmp_path / "res.png")])
    assert args.func(args) == 0
    result = json.loads((tmp_path / "res.json").read_text())
    assert result["n_windows"] == 2 and result["steps"] == 1 and set(result["systems"]) == set(ev.SYSTEMS)
    assert result["systems"]["ground_truth"]["fgd_raw"] == pytest.approx(0.0, abs=1e-6)
    assert (tmp_path / "res.png").is_file()
    assert "model_other_audio" in capsys.readouterr().out  # the table is printed


def test_eval_refuses_data_of_another_skeleton(data, tmp_path):
    from dimgestor.streaming.checkpoint import save_checkpoint

    root, _, train = data
    b = _bundle(train)
    small = DiMGestor(get_preset("tiny", motion_dim=12))
    save_checkpoint(tmp_path / "ck", small, b.feature_spec, b.skeleton, b.mean[:12], b.std[:12])
    parser = argparse.ArgumentParser()
    ev.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "ck"), "--data", str(root)])
    with pytest.raises(ValueError, match="feature columns"):
        ev.run(args)


def test_per_k_report_has_every_metric_and_real_motion_scores_as_real(data, tmp_path):
    _, valid, train = data
    bundle = _bundle(train)
    ae = ev.fgd_autoencoder(train, tmp_path / "ae", steps=30, log=lambda *_: None)
    clips = ev.valid_clips(valid)
    assert len(clips) == 2 and all(len(a) == len(r) * 800 for a, r in clips)
    train_upper = [ev.upper_positions(raw, train.skeleton, train.spec) for _, raw in ev.valid_clips(train)]
    rep = ev.k_report(bundle, clips, [1, 2], seeds=2, seed=0, ae=ae, log=lambda *_: None, train_upper=train_upper)
    assert list(rep["per_k"]) == ["1", "2"] and set(rep["per_k"]["2"]) == set(ev.KMETRICS)
    for row in rep["per_k"].values():
        assert all(np.isfinite(row[m]) for m in ev.KMETRICS if m != "contrast")
        assert row["jerk_ratio"] > 0 and row["diversity"] >= 0
        assert row["variety"] == pytest.approx(row["nearest"] / rep["reference"]["nearest"])
    # the reference's own numbers: a real clip's jerk ratio would be 1, its contrast follows the synthetic rule
    ref = rep["reference"]
    assert ref["hand_jerk"] > 0 and ref["net_yaw_deg"] >= 0 and 0 < ref["beat_align"] <= 1
    assert ref["nearest"] > 0  # held-out real motion is not a copy of the training motion
    # a training stretch scored against itself replays it exactly
    assert ev.variety_distance(train_upper[0], train_upper, float(train.spec.fps)) == pytest.approx(0.0, abs=1e-9)

    stats = ev.clip_stats(clips[0][1], clips[0][0], valid.skeleton, valid.spec)
    turned = clips[0][1].copy()
    turned[:, valid.spec.columns.index("root_dyaw")] += np.radians(90) / len(turned)  # a quarter turn in total
    n = len(turned)  # the turn of frames 1..n-1 counts (the heading is measured from frame 0)
    assert ev.clip_stats(turned, clips[0][0], valid.skeleton, valid.spec)["net_yaw_deg"] == pytest.approx(
        stats["net_yaw_deg"] + 90 * (n - 1) / n, abs=1e-6)


def test_every_seeds_motion_counts_in_a_ks_numbers(data, tmp_path):
    """--seeds N: jerk, contrast and the rest pool every seed's clips (equal lengths: the mean of each seed's
    own), and FGD is the mean of each seed's FGD, not the first seed's alone."""
    _, valid, train = data
    bundle = _bundle(train)
    ae = ev.fgd_autoencoder(train, tmp_path / "ae", steps=30, log=lambda *_: None)
    clips = ev.valid_clips(valid)
    one = [ev.k_report(bundle, clips, [2], seeds=1, seed=s, ae=ae, log=lambda *_: None)["per_k"]["2"]
           for s in (0, 1)]
    both = ev.k_report(bundle, clips, [2], seeds=2, seed=0, ae=ae, log=lambda *_: None)["per_k"]["2"]
    for m in ("hand_jerk", "jerk_ratio", "auj_ratio", "fgd_feature", "net_yaw_deg"):
        assert both[m] == pytest.approx((one[0][m] + one[1][m]) / 2, rel=1e-6), m
    assert abs(one[0]["fgd_feature"] - one[1]["fgd_feature"]) > 1e-6  # (the seeds differ)


def test_speech_mask_and_contrast():
    sr, fps = 16000, 20
    t = np.arange(10 * sr) / sr
    audio = (np.sin(2 * np.pi * 200 * t) * 0.3 * ((t > 2) & (t < 5))).astype(np.float32)
    mask = metrics.speech_mask(audio, sr, fps, 200)
    assert (mask[45:95] == 1).all() and (mask[:23] == -1).all() and (mask[117:] == -1).all()
    assert (mask[30:38] == 0).all()  # preparation before speech is neither
    speed = np.where(mask == 1, 3.0, 1.0)
    assert metrics.speech_contrast(speed, mask) == pytest.approx(3.0)
    assert np.isnan(metrics.speech_contrast(speed, np.ones(200, int)))  # no silence: undefined


def test_eval_on_speech_without_motion_and_per_k(data, tmp_path, capsys):
    from dimgestor.audio import save_wav
    from dimgestor.streaming.checkpoint import save_checkpoint

    root, _, train = data
    b = _bundle(train)
    save_checkpoint(tmp_path / "ck", b.model, b.feature_spec, b.skeleton, b.mean, b.std)
    wavs = tmp_path / "wavs"
    wavs.mkdir()
    rng = np.random.default_rng(0)
    save_wav(wavs / "one.wav", (0.1 * rng.standard_normal(3 * 16000)).astype(np.float32), 16000)
    save_wav(wavs / "two.wav", (0.1 * rng.standard_normal(2 * 44100)).astype(np.float32), 44100)  # resampled
    parser = argparse.ArgumentParser()
    ev.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "ck"), "--wavs", str(wavs), "--steps", "1,3,2000",
                              "--seeds", "2", "--out", str(tmp_path / "w.json"), "--plot", str(tmp_path / "w.png")])
    assert args.func(args) == 0
    res = json.loads((tmp_path / "w.json").read_text())
    assert res["files"] == ["one.wav", "two.wav"] and res["ks"] == [1, 3]  # 2000 > the chain's 1000 steps: dropped
    assert res["reference"] is None and "systems" not in res
    assert np.isnan(res["per_k"]["3"]["jerk_ratio"]) and res["per_k"]["3"]["hand_jerk"] > 0
    # speech-drivenness beside its chance levels, per K and per file (the per-voice table)
    for row in res["per_k"].values():
        for key in ("coupling", "coupling_shifted", "coupling_shifted_sd", "onset_align", "onset_shuffled",
                    "silence_ratio"):
            assert np.isfinite(row[key]), key
        assert -1 <= row["coupling"] <= 1 and row["coupling_shifted_sd"] > 0 and 0 <= row["coupling_above"] <= 1
        assert 0 <= row["onset_align"] <= 1 and 0 <= row["onset_shuffled"] <= 1 and row["silence_ratio"] > 0
    assert list(res["per_file"]) == ["1", "3"] and list(res["per_file"]["1"]) == ["one.wav", "two.wav"]
    for name, row in res["per_file"]["1"].items():
        assert set(row) == set(ev.VOICE_METRICS), name
        assert row["n_onsets"] > 0 and row["speed_speech"] > 0 and row["speed_silence"] > 0 and row["seconds"] > 1
        assert row["silence_ratio"] == pytest.approx(row["speed_speech"] / row["speed_silence"])
        assert row["coupling_above"] == (row["coupling"] > row["coupling_shifted"] + 2 * row["coupling_shifted_sd"])
    out = capsys.readouterr().out
    assert "per file, K=1" in out and "one.wav" in out and "silence_ratio" in out
    assert (tmp_path / "w.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="--data .* or --wavs"):
        ev.run(parser.parse_args(["eval", "--checkpoint", str(tmp_path / "ck")]))
    with pytest.raises(ValueError, match="--ks"):
        ev.parse_ks("1,x", 8, 4)
    with pytest.raises(ValueError, match="--steps 2000: the model has only 1000"):
        ev.run(parser.parse_args(["eval", "--checkpoint", str(tmp_path / "ck"), "--wavs", str(wavs), "--steps", "2000"]))


def test_voice_row_pools_seeds_and_judges_chance(data):
    _, valid, train = data
    bundle = _bundle(train)
    audio, _ = ev.valid_clips(valid)[0]
    one = ev.seed_stats(bundle, audio, 1, seed=0)[1]
    assert set(ev.voice_row([one])) == set(ev.VOICE_METRICS)
    # the inserted silence is in the middle third of the clip, and the model ran on the longer clip
    assert len(audio) / 16000 / 3 <= one["silence_at_s"] <= 2 * len(audio) / 16000 / 3
    a, b = dict(one, coupling=0.9, coupling_shifted=0.0, coupling_shifted_sd=0.1), dict(one, coupling=0.5)
    row = ev.voice_row([a, b])
    assert row["coupling"] == pytest.approx(0.7) and row["coupling_seed_sd"] == pytest.approx(np.std([0.9, 0.5], ddof=1))
    assert row["coupling_shifted"] == pytest.approx((0.0 + one["coupling_shifted"]) / 2)
    low = ev.voice_row([dict(one, coupling=0.1, coupling_shifted=0.0, coupling_shifted_sd=0.1)])
    assert ev.voice_row([a])["coupling_above"] and not low["coupling_above"]  # 0.9 > 0 + 0.2; 0.1 is not
    pooled = ev.pool_drive([dict(ev.voice_row([a]), seconds=1.0), dict(low, seconds=3.0)])
    assert pooled["coupling"] == pytest.approx(0.9 * 0.25 + 0.1 * 0.75) and pooled["coupling_above"] == 0.5


def test_the_synthetic_rule_follows_its_speech_and_mismatched_audio_does_not(tmp_path):
    """Known answer: the synthetic world's motion (a stroke on each stressed syllable, rest in pauses) scored
    against its own audio clears both chance levels; against its audio rolled by half a clip it does not."""
    from dimgestor.training.synthetic import make_gesture_corpus

    make_gesture_corpus(tmp_path / "world", 2.0, seed=999)
    ds = GestureDataset(tmp_path / "world", split="train", valid_fraction=0.0, window_s=4.0, cache_dir=tmp_path / "c")
    clips = ev.valid_clips(ds)
    own = [ev.voice_row([ev.clip_stats(raw, audio, ds.skeleton, ds.spec)]) for audio, raw in clips]
    rolled = [ev.voice_row([ev.clip_stats(raw, np.roll(audio, len(audio) // 2), ds.skeleton, ds.spec)])
              for audio, raw in clips]
    truth, chance = ev.pool_drive(own), ev.pool_drive(rolled)
    assert truth["coupling_above"] == 1.0 and truth["coupling"] > 0.2
    assert truth["onset_align"] - truth["onset_shuffled"] > 0.15
    assert chance["onset_align"] - chance["onset_shuffled"] < 0.1 and chance["coupling"] < truth["coupling"] - 0.1
    # every syllable's onset dilutes the stressed ones: the rule scores at chance on all onsets
    every = np.mean([r["onset_align_all"] - r["onset_shuffled_all"] for r in own])
    assert every < truth["onset_align"] - truth["onset_shuffled"] - 0.1
