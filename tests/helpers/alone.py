"""The `alone` mark: a test that runs with no other test beside it when pytest-xdist runs several test processes
(`make test` runs two on two cores). Such a test measures how a cluster of several processes keeps real time, which
needs the machine's cores: beside another cluster test on CI's 2 cores, a rolling restart's clients that stayed
saw 0.68-0.79 s frame gaps against 0.25-0.35 s alone (the other test's processes, not the restart).

Every test holds a lock shared by the run's test processes from its setup to its teardown (its module's fixtures
included): an `alone` test the exclusive lock, every other test a shared one. An alone test waits for the tests
running beside it to end, and no other test starts meanwhile. One test process, or a system
without flock (Windows), runs as usual.
"""

import tempfile
import uuid
from pathlib import Path

import pytest

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None


def pytest_configure(config):
    config.addinivalue_line("markers", "alone: runs with no other test beside it (tests/helpers/alone.py)")
    # The main process names the run (xdist's --testrunuid, which it hands to every test process) so that it can
    # remove the run's two lock files at the end: a run used to leave them in the temporary folder.
    if not hasattr(config, "workerinput") and getattr(config.option, "testrunuid", "absent") is None:
        config.option.testrunuid = uuid.uuid4().hex


def _files(run: str) -> list[Path]:
    folder = Path(tempfile.gettempdir())
    return [folder / f"dimgestor-tests-{run}.gate", folder / f"dimgestor-tests-{run}.lock"]


def pytest_unconfigure(config):
    run = getattr(config.option, "testrunuid", None)
    if run is not None and not hasattr(config, "workerinput"):  # the main process, after every test process ended
        for f in _files(run):
            f.unlink(missing_ok=True)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    run = getattr(item.config, "workerinput", {}).get("testrunuid")
    if run is None or fcntl is None:  # one process (no other test beside it), or no flock (Windows)
        yield
        return
    alone = item.get_closest_marker("alone") is not None
    gate_file, lock_file = _files(run)
    # The gate first: an alone test waiting for the lock holds it, so the other processes' next tests wait behind it
    # (flock would go on granting them the shared lock, and the alone test could wait for test after test).
    with open(gate_file, "a") as gate, open(lock_file, "a") as lock:
        fcntl.flock(gate, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        fcntl.flock(lock, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        if not alone:
            fcntl.flock(gate, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
            fcntl.flock(gate, fcntl.LOCK_UN)
