"""Python subprocesses that start without importing torch again: `popen` forks them from a warm interpreter.

Most processes the tests start are `dimgestor serve` and other commands of ours, and most of what each costs at
start is importing torch (~1.5 s of CPU here; the suite starts a few hundred). `popen` takes the arguments of
`subprocess.Popen` for a `[sys.executable, ...]` command and, where it can, asks one warm interpreter per test
process (started on first use, torch and the other heavy third-party modules already imported, none of ours) to
fork a child that runs the command as `python` would: its own argv, sys.path, environment, working directory,
standard streams and `__main__`, and Python's own shutdown and exit status. Ours are imported fresh in every child,
so a child runs the code on disk with its environment as a new interpreter would. What a child cannot share with
the warm interpreter (another thread count, PYTHONPATH or other `PYTHON*`, `LD_*`, a stdin pipe, interpreter flags)
runs as a plain `subprocess.Popen`, as does everything off Linux (forking a process that has loaded torch is not
safe on macOS) and when DIMGESTOR_TEST_COLD=1.

The handle answers what the tests use of `Popen`: pid, args, returncode, stdout, poll, wait, send_signal,
terminate, kill, and `with`.
"""

from __future__ import annotations

import atexit
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading

PRELOAD = ("numpy", "numpy.random", "numpy.ma", "torch", "torch.nn", "pydantic", "websockets.asyncio.server",
           "websockets.asyncio.client", "pythonosc.udp_client", "asyncio", "argparse", "json")
# What a forked child shares with the warm interpreter from its start: these variables must be the same in both
SHARED_ENV = ("OMP_", "MKL_", "OPENBLAS_", "KMP_", "GOTO", "ATEN_", "DNNL_", "ONEDNN_", "TORCH", "PYTORCH", "CUDA",
              "LD_", "PYTHON")
CHILD_ENV = ("PYTHONUNBUFFERED",)  # what a child sets up for itself
# Signals a new python has as its parent had them if ignored, else as default (SIGINT: Python's KeyboardInterrupt)
_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2,
            signal.SIGALRM)


def _shared(env: dict) -> dict:
    return {k: v for k, v in env.items() if k.startswith(SHARED_ENV) and k not in CHILD_ENV}


# --- the test side -------------------------------------------------------------------------------------------

class _Zygote:
    """The warm interpreter of this test process: started on first use, gone when this process exits (it reads
    its stdin until EOF and then kills what it forked)."""

    _lock = threading.Lock()
    _one: _Zygote | None = None

    def __init__(self):
        self.dir = tempfile.mkdtemp(prefix="dimgestor-warm-")
        atexit.register(shutil.rmtree, self.dir, ignore_errors=True)  # (its socket; the run used to leave it)
        self.path = os.path.join(self.dir, "sock")
        self.env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
        self.proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), self.path], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, env=self.env, cwd=self.dir)
        line = self.proc.stdout.readline()
        if line.strip() != b"ready":
            raise RuntimeError(f"the warm interpreter did not start: {line!r}")

    @classmethod
    def get(cls) -> _Zygote:
        with cls._lock:
            if cls._one is None or cls._one.proc.poll() is not None:
                cls._one = cls()
            return cls._one


def _eligible(cmd, env: dict, kwargs: dict) -> bool:
    if (os.environ.get("DIMGESTOR_TEST_COLD") == "1" or sys.platform != "linux" or kwargs or not cmd
            or cmd[0] != sys.executable):
        return False
    if len(cmd) > 1 and cmd[1].startswith("-") and cmd[1] not in ("-c", "-m"):
        return False  # interpreter flags
    want = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    return _shared(env) == _shared(want)


def _fd(spec, default: int, closers: list) -> int:
    if spec is None:
        return default
    if spec == subprocess.DEVNULL:
        f = open(os.devnull, "r+b")
        closers.append(f)
        return f.fileno()
    return spec if isinstance(spec, int) else spec.fileno()


class WarmProcess:
    """A child of the warm interpreter, handled like a `subprocess.Popen`."""

    def __init__(self, cmd, *, cwd=None, env=None, stdin=None, stdout=None, stderr=None, text=False,
                 encoding=None, errors=None):
        self.args = list(cmd)
        self.returncode: int | None = None
        self.stdout = self.stderr = self.stdin = None
        closers: list = []
        ours: list[int] = []  # pipe ends the child gets (closed here once sent)
        textual = bool(text or encoding or errors)

        def pipe() -> tuple[int, io.IOBase]:
            r, w = os.pipe()
            ours.append(w)
            f = open(r, "rb")
            return w, (io.TextIOWrapper(f, encoding=encoding or "utf-8", errors=errors or "strict") if textual else f)

        if stdout == subprocess.PIPE:
            out, self.stdout = pipe()
        else:
            out = _fd(stdout, 1, closers)
        if stderr == subprocess.STDOUT:
            err = out
        elif stderr == subprocess.PIPE:
            err, self.stderr = pipe()
        else:
            err = _fd(stderr, 2, closers)
        fds = [_fd(stdin, 0, closers), out, err]
        ignored = [int(n) for n in _SIGNALS if signal.getsignal(n) == signal.SIG_IGN]  # exec keeps only these
        request = {"argv": self.args[1:], "cwd": os.path.abspath(cwd or os.getcwd()),
                   "env": dict(os.environ if env is None else env), "ignored": ignored}
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self._sock.connect(_Zygote.get().path)
            socket.send_fds(self._sock, [json.dumps(request).encode()], fds)
            self.pid = int(json.loads(self._sock.recv(4096))["pid"])
        finally:
            for fd in ours:
                os.close(fd)
            for f in closers:
                f.close()

    def _read_exit(self, block: bool, timeout: float | None = None) -> None:
        self._sock.settimeout(timeout if block else 0.0)
        try:
            data = self._sock.recv(4096)
        except (BlockingIOError, socket.timeout):
            return
        # an empty read: the warm interpreter went away (it kills its children when it does)
        self.returncode = int(json.loads(data)["exit"]) if data else -signal.SIGKILL
        self._sock.close()

    def poll(self) -> int | None:
        if self.returncode is None:
            self._read_exit(False)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None:
            self._read_exit(True, timeout)
            if self.returncode is None:
                raise subprocess.TimeoutExpired(self.args, timeout)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def communicate(self, input=None, timeout: float | None = None):
        """Read stdout and stderr (where piped) to their ends and wait; no input."""
        if input is not None:
            raise ValueError("WarmProcess has no stdin pipe")
        got: dict = {}
        readers = [threading.Thread(target=lambda n=n, f=f: got.__setitem__(n, f.read()), daemon=True)
                   for n, f in (("out", self.stdout), ("err", self.stderr)) if f is not None]
        for t in readers:
            t.start()
        self.wait(timeout)
        for t in readers:
            t.join(timeout)
        return got.get("out"), got.get("err")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        for f in (self.stdout, self.stderr):
            if f:
                f.close()
        self.wait()


def popen(cmd, *, cwd=None, env=None, stdin=None, stdout=None, stderr=None, text=False, **kwargs):
    """`subprocess.Popen(cmd, ...)`, forked from the warm interpreter where the command allows it."""
    if stdin == subprocess.PIPE or not _eligible(cmd, dict(os.environ if env is None else env), kwargs):
        return subprocess.Popen(cmd, cwd=cwd, env=env, stdin=stdin, stdout=stdout, stderr=stderr, text=text,
                                **kwargs)
    return WarmProcess(cmd, cwd=cwd, env=env, stdin=stdin, stdout=stdout, stderr=stderr, text=text)


def run(cmd, *, capture_output=False, timeout=None, check=False, text=False, cwd=None, env=None, **kwargs):
    """`subprocess.run` through `popen`."""
    out = subprocess.PIPE if capture_output else kwargs.pop("stdout", None)
    err = subprocess.PIPE if capture_output else kwargs.pop("stderr", None)
    with popen(cmd, cwd=cwd, env=env, stdout=out, stderr=err, text=text, **kwargs) as p:
        try:
            stdout, stderr = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
            raise
    r = subprocess.CompletedProcess(cmd, p.returncode, stdout, stderr)
    if check:
        r.check_returncode()
    return r


# --- the warm interpreter --------------------------------------------------------------------------------------

def _child(request: dict, fds: list[int]):
    """In the forked child: become `python ARGV` in CWD with ENV and the given streams, and run."""
    import builtins
    import ctypes
    import runpy
    import types

    for target, fd in enumerate(fds):
        os.dup2(fd, target)
    for fd in set(fds):
        if fd > 2:
            os.close(fd)
    try:  # die with the warm interpreter, as it kills its children when its test process goes
        ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    for n in _SIGNALS:  # as exec would leave them for a child of the test process (not of this interpreter)
        ignored = int(n) in request["ignored"]
        signal.signal(n, signal.SIG_IGN if ignored else signal.default_int_handler if n == signal.SIGINT
                      else signal.SIG_DFL)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    tempfile.tempdir = None
    unbuffered = bool(os.environ.get("PYTHONUNBUFFERED"))

    def stream(fd, mode, **kw):
        raw = io.FileIO(fd, mode, closefd=False)
        buffered = raw if (unbuffered and mode == "w") else (io.BufferedWriter(raw) if mode == "w"
                                                               else io.BufferedReader(raw))
        return io.TextIOWrapper(buffered, encoding="utf-8", write_through=unbuffered and mode == "w", **kw)

    sys.stdin = sys.__stdin__ = stream(0, "r")
    sys.stdout = sys.__stdout__ = stream(1, "w", line_buffering=os.isatty(1))
    sys.stderr = sys.__stderr__ = stream(2, "w", errors="backslashreplace", line_buffering=True)
    argv = request["argv"]
    main = types.ModuleType("__main__")
    main.__builtins__ = builtins
    sys.modules["__main__"] = main
    base = list(sys.path)  # the warm interpreter's, without its own script's folder
    code = 0
    try:
        if argv and argv[0] == "-c":
            sys.argv = ["-c", *argv[2:]]
            sys.path[:] = ["", *base]
            exec(compile(argv[1], "<string>", "exec"), main.__dict__)
        elif argv and argv[0] == "-m":
            sys.argv = ["-m", *argv[2:]]
            sys.path[:] = [os.getcwd(), *base]
            runpy._run_module_as_main(argv[1])
        elif not os.path.exists(argv[0]):
            print(f"{sys.executable}: can't open file {os.path.abspath(argv[0])!r}: [Errno 2] No such file or "
                  "directory", file=sys.stderr)
            code = 2
        else:
            sys.argv = list(argv)
            sys.path[:] = [os.path.dirname(os.path.realpath(argv[0])), *base]
            runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as e:
        code = e.code
    except KeyboardInterrupt:  # as python does: the exit status of SIGINT
        import traceback

        traceback.print_exc()
        sys.stderr.flush()
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
    except BaseException:
        import traceback

        traceback.print_exc()
        code = 1
    sys.exit(code)  # Python's own shutdown: atexit, non-daemon threads, flushing


def _serve(path: str):
    """Fork a child per request on PATH; tell each requester its child's pid and, later, its exit status."""
    import importlib
    import selectors

    for name in PRELOAD:
        importlib.import_module(name)
    sys.path[0:1] = []  # this file's folder: a child puts its own first
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    listener.bind(path)
    listener.listen(64)
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    sel = selectors.DefaultSelector()
    sel.register(listener, selectors.EVENT_READ, "accept")
    sel.register(wake_r, selectors.EVENT_READ, "child")
    sel.register(sys.stdin.fileno(), selectors.EVENT_READ, "stdin")
    children: dict[int, socket.socket] = {}
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    while True:
        for key, _ in sel.select():
            if key.data == "accept":
                conn, _ = listener.accept()
                msg, fds, _, _ = socket.recv_fds(conn, 1 << 20, 3)
                if not msg or len(fds) != 3:
                    conn.close()
                    continue
                request = json.loads(msg)
                pid = os.fork()
                if pid == 0:
                    signal.set_wakeup_fd(-1)
                    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                    sel.close()
                    for c in (listener, conn, *children.values()):
                        c.close()
                    os.close(wake_r)
                    os.close(wake_w)
                    return lambda: _child(request, fds)
                for fd in fds:
                    os.close(fd)
                conn.send(json.dumps({"pid": pid}).encode())
                children[pid] = conn
            elif key.data == "child":
                os.read(wake_r, 4096)
                while children:
                    try:
                        pid, status = os.waitpid(-1, os.WNOHANG)
                    except ChildProcessError:
                        break
                    if pid == 0:
                        break
                    conn = children.pop(pid, None)
                    if conn is not None:
                        try:
                            conn.send(json.dumps({"exit": os.waitstatus_to_exitcode(status)}).encode())
                        except OSError:
                            pass
                        conn.close()
            elif not os.read(sys.stdin.fileno(), 4096):  # the test process is gone
                for pid in children:
                    try:
                        os.kill(pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                return None


if __name__ == "__main__":
    job = _serve(sys.argv[1])
    if job is not None:
        job()
