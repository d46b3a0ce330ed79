"""The sessions' faces made in a child process beside the batcher (`serve --face-process`).

A server's batcher thread steps every stream's body and then every stream's face, one after the other: the face
is about a third of that thread's work, and the process's other core waits (the GIL keeps a second thread from
helping: the face is many small numpy steps). Here a child process holds the faces (`dimgestor.face.FaceStream`,
the same code, so the same numbers): a batch sends its windows' audio to the child before the bodies are
stepped (`begin`), and takes the faces' new rows after (`wait`), so body and face run at once on two cores.

Each face lives in the child under a number (`RemoteFace`); what a session asks of it (its first audio, a smile,
the end of its audio, closing it) travels with the next exchange. The child answers every exchange in order; a
face that fails there fails its own session's window, and a child that ended fails every face's next window
with one line saying so (the sessions without a face go on, and faces begun after it are made in the batch's
thread: `Session`).
"""

from __future__ import annotations

import itertools
import multiprocessing
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from dimgestor.face import FACE_LABELS

__all__ = ["FaceProcess", "RemoteFace", "FaceProcessEnded", "ANSWER_TIMEOUT_S"]


ANSWER_TIMEOUT_S = 30.0  # an exchange is a batch's faces (milliseconds); a child this late is stuck


class FaceProcessEnded(RuntimeError):
    """The child process that makes the faces is gone (killed, or out of memory)."""


@dataclass
class _Ops:
    """What one exchange asks of the child, in this order: new faces, smiles, audio (one batch), ends, closes."""

    new: list = field(default_factory=list)  # (face id, fps, lookahead_s, options, start_sample, start_frame)
    smile: list = field(default_factory=list)  # (face id, smile)
    push: list = field(default_factory=list)  # (face id, samples)
    finish: list = field(default_factory=list)  # face ids
    close: list = field(default_factory=list)  # face ids


def _child(conn) -> None:
    """The child's loop: an exchange's ops in order -> {face id: its new rows (n, F) or the exception}, and the
    seconds of this process's CPU the exchange took. (The face needs numpy only: no torch is imported here.)"""
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1, "blas")  # (small products: one thread each, as `serve` sets its own)
    except ImportError:  # pragma: no cover - installed with the engine
        pass
    from dimgestor.face import FaceStream

    faces: dict[int, FaceStream] = {}
    broken: dict[int, BaseException] = {}  # a failed face's failure, its answer to whatever is asked of it after
    while True:
        try:
            token, ops = conn.recv()
        except (EOFError, OSError):
            return
        t = time.thread_time()
        out: dict[int, object] = {}

        def fail(fid: int, e: BaseException, out=out) -> None:
            out[fid] = broken[fid] = e if _picklable(e) else RuntimeError(f"{type(e).__name__}: {e}")
            faces.pop(fid, None)

        for fid, fps, lookahead_s, options, sample, frame in ops.new:
            try:
                faces[fid] = FaceStream(fps, lookahead_s, options, start_sample=sample, start_frame=frame)
            except Exception as e:  # noqa: BLE001 - that face's session's failure
                fail(fid, e)
        for fid, smile in ops.smile:
            if fid in faces:
                faces[fid].smile = smile
        pushed = [(fid, x) for fid, x in ops.push if fid in faces]
        if pushed:
            try:
                FaceStream.push_many([faces[fid] for fid, _ in pushed], [x for _, x in pushed])
            except Exception as e:  # noqa: BLE001 - the batch's shared step: each of its faces' failure
                for fid, _ in pushed:
                    fail(fid, e)
        for fid in ops.finish:
            if fid in faces:
                try:
                    faces[fid].finish()
                except Exception as e:  # noqa: BLE001
                    fail(fid, e)
        for fid in [fid for fid, _ in ops.push] + list(ops.finish):
            if fid in faces and fid not in out:
                out[fid] = faces[fid].take(faces[fid].frames_ready)
            elif fid in broken:
                out[fid] = broken[fid]
        for fid in ops.close:
            broken.pop(fid, None)
            face = faces.pop(fid, None)
            if face is not None:
                face.close()
        if token is not None:
            conn.send((token, out, time.thread_time() - t))


def _picklable(e: BaseException) -> bool:
    import pickle

    try:
        pickle.loads(pickle.dumps(e))
    except Exception:  # noqa: BLE001
        return False
    return True


class FaceProcess:
    """One child process making faces for any number of sessions and threads. `begin` sends an exchange (the
    faces' queued asks and a batch's audio) and returns its token; `wait(token)` gives its answer. Exchanges from
    several threads interleave safely: answers come back in order and each goes to its own waiter.

    The child is started by multiprocessing's spawn, which imports the starting program's main module again
    there: a script that makes one keeps its work under `if __name__ == "__main__":` (`dimgestor serve` does), and
    the child's start costs that module's imports (`dimgestor serve`'s: about 0.2 s, 30 MB)."""

    def __init__(self, start_method: str = "spawn"):
        ctx = multiprocessing.get_context(start_method)
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_child, args=(child,), name="dimgestor-faces", daemon=True)
        self._process.start()
        child.close()
        self._ids = itertools.count()
        self._tokens = itertools.count()
        self._send_lock = threading.Lock()
        self._cond = threading.Condition()
        self._answers: dict[int, tuple] = {}
        self._reading = False
        self._ended: FaceProcessEnded | None = None

    def ready(self, timeout: float = 120.0) -> None:
        """Wait until the child has started and answers (its imports take a few seconds); FaceProcessEnded where
        it ended or did not answer within `timeout`."""
        token = self._send(_Ops(), answer=True)
        if not self._conn.poll(timeout):
            self.close(timeout=1.0)
            raise FaceProcessEnded(f"the face process did not start within {timeout:g} s")
        self.wait(token)

    @property
    def ended(self) -> bool:
        """Whether the child is known to be gone (its pipe broke)."""
        return self._ended is not None

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def face(self, fps: int, lookahead_s: float, options, start_sample: int = 0, start_frame: int = 0) -> "RemoteFace":
        """A new face in the child (made there with the next exchange that carries it)."""
        return RemoteFace(self, next(self._ids), (fps, lookahead_s, options, int(start_sample), int(start_frame)))

    def push_many(self, faces: Sequence["RemoteFace"], audio: Sequence[np.ndarray]) -> tuple[dict[int, object], float]:
        """`FaceStream.push_many` of these faces in the child, waited for (`wait`'s answer)."""
        return self.wait(self.begin(faces, audio))

    def begin(self, faces: Sequence["RemoteFace"], audio: Sequence[np.ndarray], finish: Sequence["RemoteFace"] = ()
              ) -> int:
        """Send the faces' queued asks, their audio (one batch in the child) and the ends of `finish`'s audio."""
        ops = _Ops()
        for f in {id(f): f for f in (*faces, *finish)}.values():
            f._queued_into(ops)
        ops.push = [(f.id, np.asarray(x, np.float32).reshape(-1)) for f, x in zip(faces, audio)]
        ops.finish = [f.id for f in finish]
        return self._send(ops, answer=True)

    def wait(self, token: int) -> tuple[dict[int, object], float]:
        """The answer of exchange `token`: ({face id: its new rows or the exception that failed it}, the seconds of
        the child's CPU it took); `RemoteFace.receive` queues a face's rows on it."""
        with self._cond:
            while token not in self._answers:
                if self._ended is not None:
                    raise self._ended
                if self._reading:  # another thread reads the pipe: it hands this answer over
                    self._cond.wait()
                    continue
                self._reading = True
                self._cond.release()
                try:
                    got = self._recv()
                finally:
                    self._cond.acquire()
                    self._reading = False
                if got is not None:
                    self._answers[got[0]] = got
                self._cond.notify_all()
            _, out, cpu_s = self._answers.pop(token)
        return out, cpu_s

    def _recv(self):
        try:
            if not self._conn.poll(ANSWER_TIMEOUT_S):  # (a child that hangs would hold every batch: it is ended)
                self._process.kill()
                self._process.join(timeout=5.0)
                self._ended = FaceProcessEnded(
                    f"the face process (pid {self._process.pid}) did not answer in {ANSWER_TIMEOUT_S:g} s and was "
                    "ended: this session's face cannot go on")
                return None
            return self._conn.recv()
        except (EOFError, OSError):
            self._process.join(timeout=1.0)
            self._ended = FaceProcessEnded(f"the face process (pid {self._process.pid}) ended (exit code "
                                           f"{self._process.exitcode}): this session's face cannot go on")
            return None

    def _send(self, ops: _Ops, answer: bool) -> int | None:
        if self._ended is not None:
            raise self._ended
        token = next(self._tokens) if answer else None
        with self._send_lock:
            try:
                self._conn.send((token, ops))
            except (BrokenPipeError, OSError):
                with self._cond:
                    if self._ended is None:
                        self._process.join(timeout=1.0)
                        self._ended = FaceProcessEnded(
                            f"the face process (pid {self._process.pid}) ended (exit code {self._process.exitcode}): "
                            "this session's face cannot go on")
                raise self._ended from None
        return token

    def close_face(self, face: "RemoteFace") -> None:
        """Forget a face in the child (no answer is waited for)."""
        if self._ended is not None or not face._made:
            return
        ops = _Ops(close=[face.id])
        try:
            self._send(ops, answer=False)
        except FaceProcessEnded:
            pass

    def close(self, timeout: float = 5.0) -> None:
        """End the child."""
        try:
            self._conn.close()
        finally:
            self._process.join(timeout)
            if self._process.is_alive():
                self._process.kill()
                self._process.join(timeout)


class RemoteFace:
    """A `FaceStream` living in a `FaceProcess`: the same calls a session makes of one (`push`, `take`,
    `frames_ready`, `finish`, `smile`, `close`); its rows come back with each exchange that pushes its audio."""

    def __init__(self, process: FaceProcess, face_id: int, spec: tuple):
        self.process, self.id = process, face_id
        self._spec, self._made = spec, False
        self._smile, self._smile_queued = float(spec[2].smile), False
        self._rows: deque[np.ndarray] = deque()
        self._held = 0

    def _queued_into(self, ops: _Ops) -> None:
        if not self._made:
            ops.new.append((self.id, *self._spec))
            self._made = True
        if self._smile_queued:
            ops.smile.append((self.id, self._smile))
            self._smile_queued = False

    def receive(self, answer: dict[int, object]) -> None:
        """This face's part of an answer's faces: its rows queued, or its failure raised."""
        got = answer.get(self.id)
        if isinstance(got, BaseException):
            raise got
        if got is not None and len(got):
            self._rows.append(got)
            self._held += len(got)

    @property
    def smile(self) -> float:
        return self._smile

    @smile.setter
    def smile(self, value: float) -> None:
        self._smile, self._smile_queued = float(value), True

    @property
    def frames_ready(self) -> int:
        return self._held

    def push(self, samples: np.ndarray) -> None:
        self.receive(self.process.push_many([self], [samples])[0])

    def finish(self) -> None:
        self.receive(self.process.wait(self.process.begin([], [], finish=[self]))[0])

    def take(self, n: int) -> np.ndarray:
        if n > self._held:
            raise RuntimeError(f"{n} face frames asked, {self._held} made: the face's lookahead exceeds the caller's")
        parts, need = [], n
        while need:
            rows = self._rows[0]
            if len(rows) <= need:
                parts.append(self._rows.popleft())
                need -= len(rows)
            else:
                parts.append(rows[:need])
                self._rows[0] = rows[need:]
                need = 0
        self._held -= n
        return np.concatenate(parts) if parts else np.zeros((0, len(FACE_LABELS)))

    def close(self) -> None:
        self.process.close_face(self)
