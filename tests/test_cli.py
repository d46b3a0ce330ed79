"""The `dimgestor` command: info, train -> generate -> a BVH as long as the audio, clear errors (exit 2)."""
import json
import sys

import bvh as pypi_bvh
import numpy as np
import pytest

from dimgestor.audio import save_wav
from dimgestor.bvh import read_bvh
from dimgestor.training.synthetic import make_synthetic_pair
from dimgestor_app.cli import main

from helpers import warm


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny model trained for a few steps through the CLI (--no-augment: the augmented bank was 2/3 of this
    fixture's time; augmented training is tests/test_train.py's and tests/test_train_ddp.py's, the CLI's
    small-data defaults tests/test_train.py's)."""
    root = tmp_path_factory.mktemp("cli")
    make_synthetic_pair(root / "data", "a", seconds=12.0, seed=0)
    rc = main(["train", "--data", str(root / "data"), "--preset", "tiny", "--out", str(root / "run"),
               "--max-steps", "6", "--batch-size", "2", "--window-s", "2", "--ckpt-every", "3", "--valid-every", "3",
               "--cache-dir", str(root / "cache"), "--no-progress", "--no-augment", "--set", "hidden=48",
               "--set", "schedule=sqrt_linear"])
    assert rc == 0
    return root


def test_info_json(capsys):
    assert main(["info", "--preset", "tiny", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    p = info["parameters"]
    assert p["total"] == sum(v for k, v in p.items() if k != "total") and p["denoiser_blocks"] > 0
    assert info["stream_state_bytes"]["total"] > 0 and info["lookahead_s"] == pytest.approx(0.08)
    assert main(["info", "--preset", "paper"]) == 0
    assert "denoiser_blocks" in capsys.readouterr().out


def test_train_then_generate_writes_a_bvh_as_long_as_the_audio(run, tmp_path, capsys):
    ckpt = run / "run" / "ckpt_0000006"
    assert (ckpt / "model.safetensors").is_file() and (run / "run" / "ckpt_0000003" / "train_state.pt").is_file()
    cfg = json.loads((ckpt / "config.json").read_text())["model"]
    assert cfg["hidden"] == 48 and cfg["schedule"] == "sqrt_linear"
    audio = np.random.default_rng(0).standard_normal(44100 * 2 + 1234) * 0.1  # 2.03 s at 44.1 kHz, resampled
    save_wav(tmp_path / "speech.wav", audio.astype(np.float32), 44100)
    out = tmp_path / "out.bvh"
    assert main(["generate", "--checkpoint", str(run / "run"), "--audio", str(tmp_path / "speech.wav"),
                 "--out", str(out), "--steps", "3", "--seed", "1"]) == 0
    motion = read_bvh(out)
    n16 = len(audio) * 16000 // 44100
    assert motion.values.shape[0] == n16 * 20 // 16000 == 40
    assert motion.frame_time == pytest.approx(0.05)
    with open(out) as f:  # an independent parser agrees
        other = pypi_bvh.Bvh(f.read())
    assert other.nframes == 40 and other.get_joints_names()[0] == motion.skeleton.names[0]
    assert main(["info", "--checkpoint", str(run / "run")]) == 0

    exported = tmp_path / "default_model"
    assert main(["export", "--checkpoint", str(run / "run"), "--out", str(exported)]) == 0
    assert sorted(p.name for p in exported.iterdir()) == ["config.json", "model.safetensors", "norm.safetensors"]
    again = tmp_path / "again.bvh"
    assert main(["generate", "--checkpoint", str(exported), "--audio", str(tmp_path / "speech.wav"),
                 "--out", str(again), "--steps", "3", "--seed", "1"]) == 0
    assert again.read_text() == out.read_text()  # same weights, same seed: the same motion

    # export can set the sampling defaults that generate then uses when not told
    tuned = tmp_path / "tuned"
    assert main(["export", "--checkpoint", str(run / "run"), "--out", str(tuned), "--steps", "3",
                 "--smooth", "4"]) == 0
    config = json.loads((tuned / "config.json").read_text())["model"]
    assert config["sample_steps"] == 3 and config["smooth_hz"] == 4.0
    assert main(["generate", "--checkpoint", str(tuned), "--audio", str(tmp_path / "speech.wav"),
                 "--out", str(again), "--seed", "1", "--smooth", "0"]) == 0
    assert again.read_text() == out.read_text()  # K = 3 from the checkpoint, filter turned off
    assert main(["generate", "--checkpoint", str(tuned), "--audio", str(tmp_path / "speech.wav"),
                 "--out", str(again), "--seed", "1"]) == 0
    assert again.read_text() != out.read_text()  # the checkpoint's 4 Hz filter


@pytest.mark.parametrize("args, message", [
    (["generate", "--checkpoint", "/no/such/ckpt", "--audio", "x.wav", "--out", "o.bvh"], "checkpoint not found"),
    (["generate", "--checkpoint", "{run}/run", "--audio", "{tmp}/not_audio.wav", "--out", "{tmp}/o.bvh"], "not_audio.wav"),
    (["generate", "--checkpoint", "{run}/run", "--audio", "{tmp}/missing.wav", "--out", "{tmp}/o.bvh"], "missing.wav"),
    (["generate", "--checkpoint", "{run}/run", "--audio", "{tmp}/not_audio.wav", "--out", "{tmp}/o.txt"], "expected a .bvh"),
    (["generate", "--checkpoint", "{run}/run", "--audio", "x.wav", "--out", "o.bvh", "--steps", "0"], "--steps"),
    (["generate", "--checkpoint", "{run}/run", "--audio", "x.wav", "--out", "o.bvh", "--smooth", "-1"], "--smooth"),
    (["export", "--checkpoint", "{run}/run", "--out", "{tmp}/e", "--steps", "0"], "--steps must be >= 1"),
    (["train", "--data", "{tmp}/empty", "--out", "{tmp}/r"], "no NAME.bvh (or NAME.npz) + NAME.wav pairs"),
    (["train", "--data", "{tmp}/broken", "--out", "{tmp}/r", "--cache-dir", "{tmp}/c"], "broken.bvh:"),
    (["train", "--data", "{run}/data", "--out", "{tmp}/r", "--preset", "tiny", "--set", "headdim=5"], "headdim"),
    (["train", "--data", "{run}/data", "--out", "{run}/run", "--preset", "tiny", "--cache-dir", "{run}/cache"],
     "already holds checkpoints"),
])
def test_bad_inputs_print_one_error_line_and_exit_2(run, tmp_path, capsys, args, message):
    (tmp_path / "empty").mkdir()
    (tmp_path / "not_audio.wav").write_text("this is not a RIFF file")
    bvh_path, _ = make_synthetic_pair(tmp_path / "broken", "broken", seconds=3.0, seed=0)
    text = bvh_path.read_text()
    bvh_path.write_text(text[: len(text) // 2])  # truncated mid-frames
    args = [a.format(run=run, tmp=tmp_path) for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and "Traceback" not in err, err


def test_console_script_exit_code(tmp_path):
    r = warm.run([sys.executable, "-m", "dimgestor_app.cli", "generate", "--checkpoint", str(tmp_path),
                  "--audio", "a.wav", "--out", "o.bvh"], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr


def test_generate_makes_a_long_recording_in_the_memory_of_one_block(tiny_checkpoint, tmp_path, monkeypatch):
    """Issue 52, item 5: a .bvh (and its face CSV) is made and written a block of audio at a time, so the memory
    generate holds does not grow with the recording (a 3-hour WAV once took 16 GB and rising): its peak of traced
    allocations (numpy's among them) over 6 blocks is within 1.5x its peak over one, and the file is the one the
    whole recording at once makes."""
    import tracemalloc

    import dimgestor_app.generate as G
    from dimgestor.audio import load_wav
    from dimgestor.bvh import write_bvh
    from dimgestor.streaming.checkpoint import load_checkpoint

    monkeypatch.setattr(G, "BLOCK_S", 2.0)
    rng = np.random.default_rng(3)
    peaks = {}
    for seconds in (2.0, 12.0):
        wav = tmp_path / f"speech{seconds:g}.wav"
        save_wav(wav, (0.1 * rng.standard_normal(int(48000 * seconds))).astype(np.float32), 48000)
        tracemalloc.start()
        assert main(["generate", "--checkpoint", str(tiny_checkpoint), "--audio", str(wav), "--steps", "2",
                     "--out", str(tmp_path / f"{seconds:g}.bvh")]) == 0
        peaks[seconds] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peaks[12.0] < 1.5 * peaks[2.0], peaks
    bundle = load_checkpoint(tiny_checkpoint)
    whole = G.generate_motion(bundle, load_wav(tmp_path / "speech12.wav"), steps=2)
    write_bvh(tmp_path / "whole.bvh", whole)
    streamed, offline = read_bvh(tmp_path / "12.bvh"), read_bvh(tmp_path / "whole.bvh")
    assert streamed.values.shape == offline.values.shape == (240, offline.skeleton.num_channels)
    assert np.abs(streamed.values - offline.values).max() < 0.05  # degrees and cm: streaming = offline (1e-4)


def test_generate_refuses_a_glb_of_a_recording_over_its_limit_in_one_line(tiny_checkpoint, tmp_path, monkeypatch,
                                                                          capsys):
    import dimgestor_app.generate as G

    monkeypatch.setattr(G, "WHOLE_MAX_S", 1.0)
    save_wav(tmp_path / "speech.wav", np.zeros(16000 * 2, np.float32), 16000)
    assert main(["generate", "--checkpoint", str(tiny_checkpoint), "--audio", str(tmp_path / "speech.wav"),
                 "--out", str(tmp_path / "o.glb")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "0:00:02 long (at most 0:00:01): write a .bvh" in err, err
    assert not (tmp_path / "o.glb").exists()
