"""The `alone` mark: a test that runs with no other test beside it when pytest-xdist runs several test processes
(`make test` runs two on two cores). Such a test measures how a cluster of several processes keeps real time, which
needs the machine's cores: beside another cluster test on CI's 2 cores, a rolling restart's clients that stayed
saw 0.68-0.79 s frame gaps against 0.25-0.35 s alone (the other test's processes, not the restart).

Every test holds a lock shared by the run's test processes from its setup to its teardown (its module's fixtures
included): an `alone` test the exclusive lock, every other test a shared one. One test process, or a system
without flock (Windows), runs as usual.
"""

import tempfile
from pathlib import Path

import pytest

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None


def pytest_configure(config):
    config.addinivalue_line("markers", "alone: runs with no other test beside it (tests/helpers/alone.py)")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    run = getattr(item.config, "workerinput", {}).get("testrunuid")
    if run is None or fcntl is None:  # one process (no other test beside it), or no flock (Windows)
        yield
        return
    with open(Path(tempfile.gettempdir()) / f"dimgestor-tests-{run}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX if item.get_closest_marker("alone") else fcntl.LOCK_SH)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
