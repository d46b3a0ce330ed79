"""Training on the synthetic fixture: the validation loss falls, --resume continues exactly, checkpoints load."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from dimgestor.streaming.checkpoint import CheckpointError, latest_checkpoint, load_checkpoint, resolve_checkpoint
from dimgestor.training.synthetic import make_synthetic_pair
from dimgestor.training.train import TrainConfig, train


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("traindata")
    make_synthetic_pair(root, "a", seconds=24.0, seed=0)
    return root


def _opts(data, out, cache, **kw):
    base = dict(data=str(data), out=str(out), preset="tiny", max_steps=40, batch_size=4, lr=3e-3, warmup=20,
                window_s=2.0, ckpt_every=20, valid_every=20, ema=0.99, seed=0, device="cpu",
                cache_dir=str(cache), progress=False, valid_fraction=0.2)
    return TrainConfig(**{**base, **kw})


def _log(run):
    return [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]


def test_training_lowers_the_validation_loss(data, tmp_path):
    last = train(_opts(data, tmp_path / "run", tmp_path / "cache", max_steps=100, valid_every=50, ckpt_every=100))
    log = _log(tmp_path / "run")
    assert [r["step"] for r in log] == [0, 50, 100]
    # the held-out tail of the synthetic clip moves more than the training part, so the floor is well above 0
    # (seeds 0, 1, 2 reach 0.55-0.57 of the start at step 100, 0.43-0.44 at step 300)
    assert log[-1]["valid_loss"] < 0.85 * log[0]["valid_loss"], log
    assert last == tmp_path / "run" / "ckpt_0000100" == latest_checkpoint(tmp_path / "run")

    bundle = load_checkpoint(tmp_path / "run")  # a run folder resolves to its latest checkpoint
    assert bundle.path == last and bundle.config.motion_dim == bundle.feature_spec.dim == len(bundle.mean)
    assert bundle.skeleton.names[0] and bundle.info["step"] == 100
    audio = np.random.default_rng(0).standard_normal(16000).astype(np.float32) * 0.1
    feats = bundle.generate(audio, steps=4)
    assert feats.shape == (20, bundle.config.motion_dim) and np.isfinite(feats).all()
    f = np.random.default_rng(1).standard_normal((3, len(bundle.mean))).astype(np.float32)
    assert np.allclose(bundle.denormalize(bundle.normalize(f)), f, atol=1e-5)


@pytest.fixture(scope="module")
def interrupted(data, tmp_path_factory):
    """(a run of 40 steps, the same run stopped at step 20): trained once for the resume tests, each of which
    resumes its own copy of the stopped run."""
    root = tmp_path_factory.mktemp("interrupted")
    whole = train(_opts(data, root / "whole", root / "cache", max_steps=40))
    part = train(_opts(data, root / "part", root / "cache", max_steps=20))
    return whole, part


def test_training_without_validation_takes_the_same_steps_and_logs_its_last(data, interrupted, tmp_path):
    """--valid-every 0: no held-out loss (and no held-out windows featurized), the same weights as a run that
    validates (validation draws nothing from the training's generators), and the last step's train loss logged."""
    whole, _ = interrupted
    last = train(_opts(data, tmp_path / "run", tmp_path / "cache", valid_every=0))
    assert [r["step"] for r in _log(tmp_path / "run")] == [40]
    assert "valid_loss" not in _log(tmp_path / "run")[0] and _log(tmp_path / "run")[0]["train_loss"] > 0
    a = torch.load(last / "train_state.pt", map_location="cpu", weights_only=False)
    b = torch.load(whole / "train_state.pt", map_location="cpu", weights_only=False)
    assert all(torch.equal(a["ema"][k], b["ema"][k]) for k in b["ema"])
    assert a["history"][-1]["train_loss"] == b["history"][-1]["train_loss"]


def _copy_run(part: Path, out: Path) -> Path:
    import shutil

    shutil.copytree(part.parent, out)
    return out


def test_resume_continues_from_the_step_it_stopped_at(data, interrupted, tmp_path):
    cache = tmp_path / "cache"
    whole, part = interrupted
    assert part.name == "ckpt_0000020"
    _copy_run(part, tmp_path / "part")
    resumed = train(_opts(data, tmp_path / "part", cache, max_steps=40, resume=True))
    assert resumed.name == "ckpt_0000040"
    assert [r["step"] for r in _log(tmp_path / "part")] == [0, 20, 40]
    a, b = load_checkpoint(whole).model.state_dict(), load_checkpoint(resumed).model.state_dict()
    for k in a:  # the interrupted run ends with the same EMA weights as the uninterrupted one
        assert torch.allclose(a[k], b[k], atol=1e-6), k


def test_clear_errors(data, tmp_path):
    cache = tmp_path / "cache"
    with pytest.raises(ValueError, match="no checkpoint found"):
        train(_opts(data, tmp_path / "none", cache, resume=True))
    train(_opts(data, tmp_path / "r", cache, max_steps=1, ckpt_every=1, valid_every=1))
    with pytest.raises(ValueError, match="already holds checkpoints"):
        train(_opts(data, tmp_path / "r", cache, max_steps=1))
    with pytest.raises(CheckpointError, match="neither a checkpoint folder"):
        resolve_checkpoint(tmp_path)
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "missing")
    ck = latest_checkpoint(tmp_path / "r")
    (ck / "config.json").write_text("{ not json")
    with pytest.raises(CheckpointError, match=r"config.json:1: not valid JSON"):
        load_checkpoint(ck)


def test_no_embedded_default_model_is_a_clear_error(tmp_path, monkeypatch):
    import dimgestor.streaming.checkpoint as ckpt
    monkeypatch.setattr(ckpt, "DEFAULT_MODEL_DIR", tmp_path / "default_model")
    with pytest.raises(CheckpointError, match="no embedded default model"):
        load_checkpoint(None)


def test_recipes_set_the_diffusion_and_the_losses():
    from dimgestor.training.train import RECIPES, resolve_recipe

    cfg, w = resolve_recipe(TrainConfig(data="", out="", recipe="paper"))
    assert (cfg["n_steps"], cfg["schedule"], cfg["prediction"]) == (1000, "linear", "eps")
    assert w == {"vel_weight": 0.0, "acc_weight": 0.0, "root_weight": 0.0}  # the paper's plain noise MSE
    cfg, w = resolve_recipe(TrainConfig(data="", out=""))  # the default recipe
    assert cfg == RECIPES["streaming"].config and cfg["prediction"] == "x0" and cfg["n_steps"] <= 16
    assert w["vel_weight"] > 0 and w["acc_weight"] > 0 and w["root_weight"] > 0
    cfg, w = resolve_recipe(TrainConfig(data="", out="", overrides={"noise_taps": 3}, vel_weight=0.0))
    assert cfg["noise_taps"] == 3 and w["vel_weight"] == 0.0  # explicit settings win over the recipe
    with pytest.raises(ValueError, match="unknown recipe"):
        resolve_recipe(TrainConfig(data="", out="", recipe="nope"))


def test_cli_turns_augmentation_on_for_small_data(data, tmp_path, monkeypatch, capsys):
    import dimgestor.training.train as train_module
    from dimgestor_app.cli import main

    seen = {}
    monkeypatch.setattr(train_module, "train", lambda opts: seen.setdefault("opts", opts) and tmp_path)
    common = ["train", "--data", str(data), "--out", str(tmp_path / "r"), "--cache-dir", str(tmp_path / "c")]
    assert main(common) == 0
    assert seen["opts"].mirror is True and seen["opts"].speeds == (0.9, 1.1) and seen["opts"].recipe == "streaming"
    assert seen["opts"].augment is True and seen["opts"].aug_copies == 4
    assert seen["opts"].arm_mix is False  # body-part mixing only when asked for
    seen.clear()
    assert main(common + ["--arm-mix"]) == 0 and seen["opts"].arm_mix is True
    seen.clear()
    assert main(common + ["--no-mirror", "--speeds", "", "--recipe", "paper", "--no-augment"]) == 0
    assert seen["opts"].mirror is False and seen["opts"].speeds == () and seen["opts"].recipe == "paper"
    assert seen["opts"].augment is False
    seen.clear()
    assert main(common + ["--aug-copies", "2"]) == 0 and seen["opts"].aug_copies == 2 and seen["opts"].augment
    assert main(common + ["--aug-copies", "0"]) == 2
    assert "--aug-copies must be positive" in capsys.readouterr().err
    assert main(common + ["--speeds", "fast"]) == 2
    assert "--speeds expects" in capsys.readouterr().err


def test_augmented_bank_holds_front_end_features_of_seeded_augmented_audio(data, tmp_path):
    from dimgestor.config import get_preset
    from dimgestor.features import FeatureSpec
    from dimgestor.model.network import DiMGestor
    from dimgestor.training.augment import AugmentConfig, augment
    from dimgestor.training.dataset import GestureDataset, compute_stats
    from dimgestor.training.train import WindowBank

    ds = GestureDataset(data, FeatureSpec(), window_s=2.0, hop_s=0.5, mirror=True, cache_dir=tmp_path, valid_fraction=0.2)
    model = DiMGestor(get_preset("tiny", motion_dim=ds.motion_dim))
    mean, std = compute_stats(ds)
    bank = WindowBank(ds, model, mean, std, "cpu", copies=2, seed=5)
    again = WindowBank(ds, model, mean, std, "cpu", copies=2, seed=5)
    clean = WindowBank(ds, model, mean, std, "cpu")
    assert clean.versions == [] and clean.draw_versions(4, torch.Generator()) is None
    assert ds.windows[0][3] is False and ds.windows[1][3] is True  # a window and its mirror hear the same audio
    assert bank.versions[0] is bank.versions[1] and len(bank.versions[0]) == 2
    babble = [ds.clips[c].audio[a * ds.spf: b * ds.spf] for c, a, b in ds.segments]
    u = 1  # the second distinct audio window (windows 2 and 3)
    with_context, warm = WindowBank._with_context(ds, 2, ds[2]["audio"],
                                                  model.samples_needed(len(ds[2]["motion"])) - len(ds[2]["audio"]))
    assert warm == min(ds.windows[2][1] * ds.spf, int(WindowBank.WARM_S * ds.fps) * ds.spf) and warm > 0
    audio = augment(with_context, 16000, (5, u, 1), AugmentConfig(), babble)  # the warm-up heard augmented too
    expected = WindowBank._features(model, audio, warm, len(ds[2]["motion"]), "cpu")
    assert torch.equal(bank.versions[2][1], expected) and torch.equal(bank.versions[2][1], again.versions[2][1])
    idx = [0, 2, 4]
    x0, f_clean = bank.batch(idx, 15, 5)
    x0b, f_aug = bank.batch(idx, 15, 5, versions=[0, 2, 1])
    assert torch.equal(x0, x0b) and torch.equal(f_clean, clean.batch(idx, 15, 5)[1])  # motion never changes
    assert torch.equal(f_aug[0], f_clean[0]) and not torch.allclose(f_aug[1], f_clean[1])
    assert not torch.allclose(f_aug[2], f_clean[2]) and f_aug.shape == f_clean.shape
    draws = bank.draw_versions(4000, torch.Generator().manual_seed(0))
    assert set(draws) == {0, 1, 2} and abs(draws.count(0) / 4000 - 1 / 3) < 0.03


def test_bank_features_are_those_a_stream_computes_mid_clip(data, tmp_path):
    """A window's features come from a front end that heard the clip before it (as a live stream has), not a
    cold one: equal to the whole clip's features at the window's place when the clip starts within WARM_S."""
    from dimgestor.config import get_preset
    from dimgestor.features import FeatureSpec
    from dimgestor.model.network import DiMGestor
    from dimgestor.training.dataset import GestureDataset, compute_stats
    from dimgestor.training.train import WindowBank

    ds = GestureDataset(data, FeatureSpec(), window_s=2.0, hop_s=0.5, cache_dir=tmp_path, valid_fraction=0.2)
    model = DiMGestor(get_preset("tiny", frontend="speech", motion_dim=ds.motion_dim))
    bank = WindowBank(ds, model, *compute_stats(ds), "cpu")
    fe, c = model.frontend, model.config
    i = next(k for k, w in enumerate(ds.windows) if 0 < w[1] <= WindowBank.WARM_S * ds.fps)
    clip, start = ds.clips[ds.windows[i][0]], ds.windows[i][1]
    whole, _ = fe(torch.from_numpy(np.asarray(clip.audio, np.float32))[None], fe.init_state(1))
    a = start * c.feats_per_frame
    n = min(len(bank.feats[i]), whole.shape[1] - a)  # the lookahead too: the clip's real audio after the window
    assert torch.allclose(bank.feats[i][:n], whole[0, a:a + n], atol=1e-5)
    cold = WindowBank._features(model, ds[i]["audio"], 0, len(ds[i]["motion"]), "cpu")
    assert not torch.allclose(cold[:n], bank.feats[i][:n], atol=1e-3)  # a cold start reads differently


def test_resume_with_augmentation_continues_exactly(data, tmp_path):
    cache = tmp_path / "cache"
    aug = dict(augment=True, aug_copies=2)
    whole = train(_opts(data, tmp_path / "whole", cache, max_steps=30, ckpt_every=15, valid_every=15, **aug))
    train(_opts(data, tmp_path / "part", cache, max_steps=15, ckpt_every=15, valid_every=15, **aug))
    resumed = train(_opts(data, tmp_path / "part", cache, max_steps=30, ckpt_every=15, valid_every=15, resume=True,
                          **aug))
    plain = train(_opts(data, tmp_path / "plain", cache, max_steps=30, ckpt_every=15, valid_every=15))
    a, b = load_checkpoint(whole).model.state_dict(), load_checkpoint(resumed).model.state_dict()
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-6), k
    c = load_checkpoint(plain).model.state_dict()
    assert any(not torch.allclose(a[k], c[k], atol=1e-4) for k in a)  # the augmented features were trained on
    assert load_checkpoint(whole).info["options"]["augment"] is True
    # validation stays clean: step 0 is the same untrained EMA model on the same held-out windows
    assert _log(tmp_path / "whole")[0]["valid_loss"] == _log(tmp_path / "plain")[0]["valid_loss"]


def test_train_config_is_validated_once_and_frozen():
    from pydantic import ValidationError

    from dimgestor.training.train import TrainConfig

    c = TrainConfig(data=Path("d"), out="o", speeds=[0.9, 1.1])
    assert c.speeds == (0.9, 1.1) and c.data == "d" and c.warmup == 200 and c.grad_clip == 1.0
    with pytest.raises(ValidationError):
        c.max_steps = 5  # frozen: a run's options are what was validated
    for bad in (dict(max_steps=0), dict(lr=0.0), dict(ema=1.0), dict(warmup=-1), dict(weight_decay=-0.1),
                dict(grad_clip=-1.0), dict(speeds=(0.9, 0.0)), dict(heading="sideways"), dict(cond_drop=1.5),
                dict(aug_config={"p_pitch": 2.0}), dict(nonsense=1)):
        with pytest.raises(ValidationError):
            TrainConfig(data="d", out="o", **bad)


# The training options the previous embedded default model recorded (commit cdc995f), saved by the options
# dataclass TrainConfig replaced: no augment, aug_*, cond_drop fields.
OPTIONS_BEFORE_TRAIN_CONFIG = {
    "data": "/work/shared/data/zeggs_sample", "out": "/work/runs/G", "preset": "realtime", "overrides": {},
    "recipe": "streaming", "max_steps": 800, "batch_size": 8, "lr": 0.0005, "warmup": 200, "weight_decay": 0.0,
    "grad_clip": 1.0, "vel_weight": None, "acc_weight": None, "root_weight": None, "heading": None,
    "speeds": [0.9, 1.1], "ema": 0.999, "window_s": 5.0, "hop_s": None, "mirror": True, "valid_fraction": 0.15,
    "valid_seconds": 15.0, "ckpt_every": 200, "valid_every": 200, "keep": 0, "seed": 0, "device": "auto"}


def test_saved_options_read_back_including_a_checkpoint_from_before_train_config():
    from dimgestor.streaming.checkpoint import DEFAULT_MODEL_DIR
    from dimgestor.training.train import TrainConfig

    shipped = json.loads((DEFAULT_MODEL_DIR / "config.json").read_text())["info"]["options"]
    c = TrainConfig.from_saved(shipped)  # saved by TrainConfig itself
    assert c.cond_drop == shipped["cond_drop"] and c.overrides == shipped["overrides"]
    saved = OPTIONS_BEFORE_TRAIN_CONFIG
    c = TrainConfig.from_saved(saved)
    assert c.speeds == tuple(saved["speeds"]) and c.max_steps == saved["max_steps"] and c.augment is False
    with pytest.raises(ValueError, match="does not have: \\['retired'\\]"):
        TrainConfig.from_saved({**saved, "retired": 1})


def test_a_run_saved_by_the_previous_code_resumes_exactly(data, interrupted, tmp_path):
    """Resuming reads weights, optimizer, generators and history from train_state.pt, never the saved options:
    a run whose options were saved in the old layout (the TrainConfig dataclass's vars, fewer fields) resumes."""
    cache = tmp_path / "cache"
    whole = interrupted[0]
    part = _copy_run(interrupted[1], tmp_path / "part") / interrupted[1].name
    ts = torch.load(part / "train_state.pt", weights_only=False)
    old = {k: v for k, v in ts["options"].items() if k not in ("augment", "aug_copies", "aug_config", "cond_drop")}
    torch.save({**ts, "options": {**old, "speeds": list(old["speeds"])}}, part / "train_state.pt")
    resumed = train(_opts(data, tmp_path / "part", cache, max_steps=40, resume=True))
    a, b = load_checkpoint(whole).model.state_dict(), load_checkpoint(resumed).model.state_dict()
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-6), k
    saved = load_checkpoint(resumed).info["options"]  # written anew, in the current layout
    assert saved["max_steps"] == 40 and saved["cond_drop"] is None and "resume" not in saved


def test_cli_sets_warmup_weight_decay_and_grad_clip(data, tmp_path, monkeypatch, capsys):
    import dimgestor.training.train as train_module
    from dimgestor_app.cli import main

    seen = {}
    monkeypatch.setattr(train_module, "train", lambda opts: seen.setdefault("opts", opts) and tmp_path)
    common = ["train", "--data", str(data), "--out", str(tmp_path / "r"), "--cache-dir", str(tmp_path / "c")]
    assert main(common + ["--warmup", "7", "--weight-decay", "0.01", "--grad-clip", "0", "--set", "noise_taps=3"]) == 0
    o = seen["opts"]
    assert (o.warmup, o.weight_decay, o.grad_clip, o.overrides, o.progress) == (7, 0.01, 0.0, {"noise_taps": 3}, True)
    assert main(common + ["--grad-clip", "-1"]) == 2
    assert "--grad-clip" in capsys.readouterr().err
