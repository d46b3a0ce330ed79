"""`dimgestor eval` on a synthetic data folder with a small untrained model."""

import argparse
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from dimgestor import eval as ev
from dimgestor import metrics
from dimgestor.config import get_preset
from dimgestor.dataset import GestureDataset, compute_stats
from dimgestor.model import DiMGestor
from dimgestor.synthetic import make_synthetic_pair


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
    assert (args.command, args.checkpoint, args.data, args.steps, args.out, args.plot) == ("eval", "ck", "d", 4, "x.json", "x.png")
    assert args.func is ev.main_from_args


def test_eval_command_end_to_end(data, tmp_path, capsys):
    from dimgestor.checkpoint import save_checkpoint

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
    from dimgestor.checkpoint import save_checkpoint

    root, _, train = data
    b = _bundle(train)
    small = DiMGestor(get_preset("tiny", motion_dim=12))
    save_checkpoint(tmp_path / "ck", small, b.feature_spec, b.skeleton, b.mean[:12], b.std[:12])
    parser = argparse.ArgumentParser()
    ev.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "ck"), "--data", str(root)])
    with pytest.raises(ValueError, match="feature columns"):
        ev.run(args)
