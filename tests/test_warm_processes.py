"""The tests' warm processes (tests/helpers/warm.py) behave as `python ...` started by `subprocess` would."""

import os
import signal
import subprocess
import sys
import textwrap

import pytest

from helpers import warm

pytestmark = pytest.mark.skipif(sys.platform != "linux" or os.environ.get("DIMGESTOR_TEST_COLD") == "1",
                                reason="warm processes are forked on Linux only")
PY = sys.executable


def both(cmd, **kw):
    """The same command started warm and cold: (warm result, cold result)."""
    w = warm.run(cmd, capture_output=True, text=True, timeout=60, **kw)
    c = subprocess.run(cmd, capture_output=True, text=True, timeout=60, **kw)
    return w, c


def test_a_child_is_forked_and_sees_its_own_argv_cwd_environment_path_and_main(tmp_path):
    code = textwrap.dedent("""
        import os, sys
        print(sys.argv, os.getcwd(), os.environ.get("WARM_TEST"), sys.path[0], __name__, "torch" in sys.modules)
        print("to stderr", file=sys.stderr)
        sys.exit(3)
    """)
    env = {**os.environ, "WARM_TEST": "yes"}
    p = warm.popen([PY, "-c", code, "a", "b"], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                   stderr=subprocess.PIPE, text=True)
    assert isinstance(p, warm.WarmProcess)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 3 and err == "to stderr\n"
    argv, rest = out.split("] ", 1)
    assert argv == "['-c', 'a', 'b'" and rest.split() == [str(tmp_path), "yes", "__main__", "True"], out
    cold = subprocess.run([PY, "-c", code, "a", "b"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert (cold.returncode, cold.stderr) == (3, "to stderr\n")
    assert cold.stdout.replace("True", "False") == out.replace("True", "False")  # only torch is already there


def test_modules_and_scripts_run_as_main_with_pythons_path_and_exit_statuses(tmp_path):
    script = tmp_path / "prog.py"
    script.write_text(textwrap.dedent("""
        import atexit, sys, threading, time
        atexit.register(lambda: print("atexit ran", flush=True))
        threading.Thread(target=lambda: (time.sleep(0.2), print("thread joined", flush=True))).start()
        print(__name__, sys.argv[1:], sys.path[0])
        raise SystemExit(sys.argv[1])
    """))
    w, c = both([PY, str(script), "7"])
    assert (w.returncode, w.stdout, w.stderr) == (c.returncode, c.stdout, c.stderr)
    assert w.stdout.splitlines() == ["__main__ ['7'] " + str(tmp_path), "thread joined", "atexit ran"]
    assert w.stderr == "7\n" and w.returncode == 1  # SystemExit with a string: printed, status 1
    w, c = both([PY, "-m", "json.tool", "--help"])
    assert (w.returncode, w.stdout) == (c.returncode, c.stdout) == (0, c.stdout) and "json.tool" in w.stdout
    w, c = both([PY, "-c", "raise ValueError('bad')"])
    assert w.returncode == c.returncode == 1 and w.stderr.endswith("ValueError: bad\n")
    w, c = both([PY, str(tmp_path / "missing.py")])
    assert w.returncode == c.returncode == 2 and "can't open file" in w.stderr


def test_signals_end_a_child_as_they_end_python_and_wait_times_out():
    # the signals as a new python started by the test process has them: ignored where the test process ignores
    # them (a test run started in the background ignores SIGINT), else their defaults
    show = "import signal; print([signal.getsignal(n) for n in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)])"
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        w, c = both([PY, "-c", show])
    finally:
        signal.signal(signal.SIGHUP, previous)
    assert w.stdout == c.stdout and "Handlers.SIG_IGN: 1>]" in w.stdout, (w.stdout, c.stdout)
    w, c = both([PY, "-c", show])
    # SIGTERM and SIGHUP as this process has them: their defaults, or ignored (a run under nohup ignores SIGHUP)
    inherited = [signal.SIG_IGN if signal.getsignal(n) == signal.SIG_IGN else signal.SIG_DFL
                 for n in (signal.SIGTERM, signal.SIGHUP)]
    assert w.stdout == c.stdout and w.stdout.endswith(f"{inherited[0]!r}, {inherited[1]!r}]\n"), (w.stdout, c.stdout)
    code = "import signal, time; signal.signal(signal.SIGINT, signal.default_int_handler); print('up', flush=True); " \
           "time.sleep(60)"
    p = warm.popen([PY, "-c", code], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline() == "up\n"
    with pytest.raises(subprocess.TimeoutExpired):
        p.wait(0.2)
    p.send_signal(signal.SIGINT)
    assert p.wait(30) == -signal.SIGINT  # KeyboardInterrupt unhandled: python ends by SIGINT
    p.stdout.close()
    p = warm.popen([PY, "-c", "import time; time.sleep(60)"])
    p.terminate()
    assert p.wait(30) == -signal.SIGTERM and p.poll() == -signal.SIGTERM
    p.kill()  # after it ended: nothing to signal, as Popen


def test_what_a_child_cannot_share_with_the_warm_interpreter_starts_cold():
    threads = {**os.environ, "OMP_NUM_THREADS": "2"}
    assert isinstance(warm.popen([PY, "-c", "pass"], env=threads), subprocess.Popen)
    assert isinstance(warm.popen([PY, "-u", "-c", "pass"]), subprocess.Popen)
    assert isinstance(warm.popen(["true"]), subprocess.Popen)
    p = warm.popen([PY, "-c", "import os; print(os.environ['OMP_NUM_THREADS'])"], env=threads,
                   stdout=subprocess.PIPE, text=True)
    assert p.communicate(timeout=60)[0] == "2\n"


def test_a_test_process_leaves_no_warm_folder_behind(tmp_path):
    """A process that used a warm interpreter removes its socket's folder when it exits (a run used to leave one
    per test process in the temporary folder)."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(warm.__file__.rsplit('/helpers/', 1)[0])!r})
        from helpers import warm
        assert isinstance(warm.popen([sys.executable, "-c", "pass"]), warm.WarmProcess)
        assert warm.run([sys.executable, "-c", "pass"], timeout=60).returncode == 0
        import os
        print(sorted(os.listdir({str(tmp)!r})))
    """)
    out = subprocess.run([PY, "-c", code], env={**os.environ, "TMPDIR": str(tmp)}, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.startswith("['dimgestor-warm-"), out.stdout  # (it was there while the process ran)
    assert list(tmp.iterdir()) == []
