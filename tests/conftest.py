import os
from pathlib import Path

import pytest

# Two cores on CI and tiny tensors in tests: one torch thread per process avoids oversubscription
# (the servers that tests spawn run their own inference thread beside the test process).
os.environ.setdefault("OMP_NUM_THREADS", "1")

REPO = Path(__file__).resolve().parents[1]
pytest_plugins = ["helpers.alone"]  # the `alone` mark

# The modules that take longest (seconds on the 2-core CI machine, one worker's span), handed out first (`make test`:
# --dist loadfile --no-loadscope-reorder gives modules to the workers in collection order): a worker that starts one
# of them near the end of the run would keep the others waiting for it. The rest follow in file order.
LONGEST_MODULES = ("test_benchmarks.py", "test_clients_web.py", "test_streamer_handover.py", "test_onnx.py",
                   "test_clients_web_local.py", "test_recipe_quality.py", "test_voiceworld_training.py",
                   "test_streamer_store_faults.py", "test_clients_python.py", "test_streamer_cli.py",
                   "test_train_ddp.py", "test_clients_web_face.py", "test_streamer_sessions.py",
                   "test_clients_unity.py", "test_streamer_mic.py", "test_streamer_abuse.py", "test_deploy.py",
                   "test_voices_benchmark.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_MODULES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order within and after
ZEGGS_DIR = REPO.parent / "shared" / "data" / "zeggs_sample"


@pytest.fixture
def zeggs_dir():
    """The licensed ZEGGS sample beside the checkout; skipped on a fresh clone without it."""
    if not ZEGGS_DIR.is_dir():
        pytest.skip(f"real ZEGGS sample not found at {ZEGGS_DIR} (only present beside the dev checkout)")
    return ZEGGS_DIR


# Fixtures shared by several test modules (a test module never imports another one).

@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory):
    """A random-init `tiny` model on the synthetic skeleton, saved like a trained one (fast, exact)."""
    from helpers.checkpoint import make_tiny_checkpoint

    return make_tiny_checkpoint(tmp_path_factory.mktemp("ckpt"))


@pytest.fixture(scope="module")
def bundle(tiny_checkpoint):
    """`tiny_checkpoint` loaded (modules that need another model define their own `bundle`)."""
    from dimgestor.streaming.checkpoint import load_checkpoint

    return load_checkpoint(tiny_checkpoint)


@pytest.fixture(scope="module")
def wav(tmp_path_factory):
    """WAV_SECONDS of synthetic speech at the model's rate, for `streamer serve --source`."""
    from dimgestor.audio import SAMPLE_RATE, save_wav
    from dimgestor.training.synthetic import synthetic_speech
    from helpers.serve import WAV_SECONDS

    path = tmp_path_factory.mktemp("audio") / "speech.wav"
    save_wav(path, synthetic_speech(WAV_SECONDS, seed=4), SAMPLE_RATE)
    return path


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """The client tests' tiny checkpoint (its own seed, so their recorded numbers stay as they were)."""
    from helpers.checkpoint import make_tiny_checkpoint

    return make_tiny_checkpoint(tmp_path_factory.mktemp("ckpt"), seed=1)
