"""The `alone` mark (tests/helpers/alone.py): with two test processes, a test marked alone never overlaps another,
and the others still run side by side."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def spans(root: Path, alone: str) -> dict[str, list[float]]:
    """Three modules a, b, c of three 0.5 s tests each, run by `pytest -n 2 --dist loadfile` with the plugin;
    the modules in `alone` marked alone -> each test's (start, end)."""
    out, tmp = root / "spans", root / "tmp"
    out.mkdir(parents=True)
    tmp.mkdir()
    for name in "abc":
        mark = "@pytest.mark.alone" if name in alone else ""
        (root / f"test_{name}.py").write_text(textwrap.dedent(f"""
            import json, os, time
            import pytest

            @pytest.mark.parametrize("i", range(3))
            {mark}
            def test_{name}(i):
                t0 = time.monotonic()
                time.sleep(0.5)
                with open(os.path.join({str(out)!r}, "{name}%d" % i), "w") as f:
                    json.dump([t0, time.monotonic()], f)
        """))
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "helpers.alone", "-n", "2", "--dist", "loadfile",
                          "-p", "no:cacheprovider", "--rootdir", str(root), str(root)],
                         cwd=root, env={"PYTHONPATH": str(TESTS), "PATH": "/usr/bin:/bin", "TMPDIR": str(tmp)},
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert not list(tmp.glob("dimgestor-tests-*")), list(tmp.iterdir())  # the run's lock files are gone with it
    return {p.name: json.loads(p.read_text()) for p in out.iterdir()}


def overlap(x, y):
    return x[0] < y[1] and y[0] < x[1]


def test_an_alone_test_runs_with_no_other_test_beside_it(tmp_path):
    span = spans(tmp_path / "alone", alone="a")
    assert len(span) == 9
    assert not any(overlap(span[a], span[o]) for a in span if a[0] == "a" for o in span if o != a), span
    span = spans(tmp_path / "none", alone="")  # without the mark, the same modules share the two processes
    assert any(overlap(span[x], span[y]) for x in span for y in span if x[0] != y[0]), span
