"""`dimgestor serve` flags for VMC receivers and --version, as a user types them."""

import sys
from pathlib import Path

import pytest

from helpers import warm

REPO = Path(__file__).resolve().parents[1]


def dimgestor(*args):
    return warm.run([sys.executable, "-m", "dimgestor_app.cli", *args], cwd=REPO, capture_output=True, text=True,
                    timeout=60)


def test_version():
    r = dimgestor("--version")
    assert r.returncode == 0 and r.stdout.startswith("dimgestor ") and r.stdout.split()[-1][0].isdigit()


@pytest.mark.parametrize("args, message", [
    (["--vmc-max-bytes", "100"], "max bytes must be 0"),
    (["--vmc-hips-height", "0"], "hips height must be in"),
    (["--vmc-root", "1,2"], "expected X,Y,Z or X,Y,Z,YAW_DEG"),
    (["--vmc-bones", "legs"], "invalid choice"),
    (["--vmc-jitter-ms", "-5"], "--vmc-jitter-ms must be in"),
])
def test_bad_vmc_options_exit_2_with_a_message(args, message):
    r = dimgestor("serve", "--no-ws", "--vmc", "127.0.0.1:9", *args)
    assert r.returncode == 2 and message in r.stderr, r.stderr


def test_max_sessions_is_checked_before_anything_starts():
    r = dimgestor("serve", "--source", "ws", "--ws", "127.0.0.1:0", "--max-sessions", "0")
    assert r.returncode == 2 and "--max-sessions must be in 1..4096" in r.stderr, r.stderr
