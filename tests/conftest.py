import os
from pathlib import Path

import pytest

# Two cores on CI and tiny tensors in tests: one torch thread per process avoids oversubscription
# (the servers that tests spawn run their own inference thread beside the test process).
os.environ.setdefault("OMP_NUM_THREADS", "1")

REPO = Path(__file__).resolve().parents[1]
ZEGGS_DIR = REPO.parent / "shared" / "data" / "zeggs_sample"


@pytest.fixture
def zeggs_dir():
    """The licensed ZEGGS sample beside the checkout; skipped on a fresh clone without it."""
    if not ZEGGS_DIR.is_dir():
        pytest.skip(f"real ZEGGS sample not found at {ZEGGS_DIR} (only present beside the dev checkout)")
    return ZEGGS_DIR
