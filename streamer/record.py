"""BVH recording sink: frames are decoded and written to disk as they come, so a crash loses at most ~1 s.

The file is opened when the server starts (an unwritable path fails then, before anything streams)
and always holds a valid BVH: frame lines are appended, then the header's `Frames:` count (a fixed-width
field) is rewritten in place, at least every `flush_every_s`. After a SIGKILL the file parses with the
frames of the last flush. The root is integrated across chunks exactly as `features_to_motion` does on
the whole recording, so the file equals `dimgestor generate` on the same audio, seed and steps. A full
disk (or any write error) stops the recording with one message and keeps what was written.

With `face=True` (the server makes a face) the face track goes beside it, `OUT.face.csv`, in the format of
`dimgestor generate --face-csv` (`dimgestor.face.track`: `time,` then the VRM 0 and ARKit names, one row per BVH
frame). Other frame channels named in the recording's map (`RECORD_CHANNELS` by default) go to `OUT.channels.csv`
(one line per frame, `index,pts`, then one column per value); with the map empty there is no such CSV. Both are
written at the BVH's flushes, so each holds whole rows at all times.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Mapping

import numpy as np

from streamer.face import FACE
from streamer.frames import Channel, Frame, channel_values

COUNT_WIDTH = 12  # room for the frame count in the header (space-padded, so any reader takes it)
# The recording's channel map: frame channel name -> its spec (the CSV's columns are `name.label`, or
# `name.i` for unlabelled values). A new channel is one entry here.
RECORD_CHANNELS: dict[str, Channel] = {}


class RecordError(OSError):
    """The recording cannot be opened (the message says why)."""


def channels_path(path: str | Path) -> Path:
    """Where a recording's channels go: OUT.bvh -> OUT.channels.csv."""
    path = Path(path)
    return path.with_name(path.stem + ".channels.csv")


def face_path(path: str | Path) -> Path:
    """Where a recording's face track goes: OUT.bvh -> OUT.face.csv."""
    path = Path(path)
    return path.with_name(path.stem + ".face.csv")


class CsvLog:
    """Whole lines appended to a CSV file at each flush (after its header); a write error stops it with one
    message and keeps the lines written before it."""

    def __init__(self, path: Path, header: str, what: str):
        self.path, self.what = path, what
        self.pending: list[str] = [header]
        self.size, self.failed = 0, ""
        try:
            if path.is_dir():
                raise IsADirectoryError(21, "is a folder")
            self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as e:
            raise RecordError(f"cannot record to {path}: {e.strerror or e}") from None
        self.flush()

    def add(self, lines: list[str]) -> None:
        self.pending += lines

    def flush(self) -> None:
        if self.failed or not self.pending:
            return
        view = memoryview("".join(self.pending).encode())
        self.pending = []
        at = self.size
        try:
            while view:
                k = os.pwrite(self.fd, view, at)
                view, at = view[k:], at + k
        except OSError as e:
            self.failed = f"{e.strerror or e}"
            try:
                os.ftruncate(self.fd, self.size)  # no partial line
            except OSError:
                pass
            print(f"dimgestor: {self.what} recording stopped: cannot write {self.path}: {self.failed}",
                  file=sys.stderr, flush=True)
            return
        self.size = at

    def close(self) -> None:
        self.flush()
        os.close(self.fd)


class ChannelTable(CsvLog):
    """The mapped channels of each frame: `index,pts`, then one column per value."""

    def __init__(self, path: Path, channels: list[Channel]):
        self.channels = channels
        names = [f"{c.name}.{label}" for c in channels for label in (c.labels or range(c.size))]
        super().__init__(path, ",".join(["index", "pts", *names]) + "\n", "channel")

    def add_frames(self, frames: list[Frame]) -> None:
        for f in frames:
            values = np.concatenate([channel_values(f, c) for c in self.channels])
            self.add([f"{f.index},{f.pts!r}," + ",".join(f"{v:.6g}" for v in values) + "\n"])


class FaceTable(CsvLog):
    """The face track (`dimgestor.face.track`: the format of `dimgestor generate --face-csv`), row i beside the BVH's
    frame i (its time i / fps); a frame without a face (none made for it) is the resting face, all zeros."""

    def __init__(self, path: Path, fps: float):
        from dimgestor.face import FACE_LABELS
        from dimgestor.face.track import track_header

        self.fps, self.rows = fps, 0
        self.canonical = Channel(FACE, len(FACE_LABELS))  # the frame channel as the session makes it
        super().__init__(path, track_header(), "face")

    def add_frames(self, frames: list[Frame]) -> None:
        from dimgestor.face.track import track_rows

        if frames:
            face = np.stack([channel_values(f, self.canonical) for f in frames])
            self.add(track_rows(face, self.fps, self.rows))
            self.rows += len(frames)


class BvhRecorder:
    def __init__(self, path: str | Path, skeleton, feature_spec, root: str = "free", tether_s: float = 5.0,
                 flush_every_s: float = 0.5, channels: Mapping[str, Channel] | None = None, face: bool = False):
        from dimgestor.bvh import format_hierarchy
        from dimgestor.features import PoseDecoder

        self.path = Path(path)
        self.skeleton = skeleton
        self.decoder = PoseDecoder(skeleton, feature_spec, root=root, tether_s=tether_s)
        self.frame_time = 1.0 / feature_spec.fps
        from dimgestor.bvh import ROTATION_CHANNELS

        self.rot_cols = np.array([c in ROTATION_CHANNELS for chans in skeleton.channels for c in chans])
        self.last: np.ndarray | None = None  # the previous frame's rotation channels, degrees
        self.flush_every_s = flush_every_s
        head = format_hierarchy(skeleton) + "MOTION\nFrames: "
        self.count_at = len(head.encode())
        head += " " * COUNT_WIDTH + f"\nFrame Time: {self.frame_time!r}\n"
        try:
            if self.path.is_dir():
                raise IsADirectoryError(21, "is a folder")
            self.fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as e:
            raise RecordError(f"cannot record to {self.path}: {e.strerror or e}") from None
        self.size = 0  # bytes safely on disk
        self.frames = 0  # frames safely on disk (the header's count)
        self.pending: list[str] = []
        self.pending_frames = 0
        self.last_flush = time.monotonic()
        self.failed = self.closed = False
        if not self._append(head.encode()) or not self._set_count(0):
            os.close(self.fd)
            raise RecordError(f"cannot record to {self.path}: {self.failed}")
        channels = [c for c in (RECORD_CHANNELS if channels is None else channels).values() if c.name != FACE]
        self.tables: list[CsvLog] = []  # the CSVs beside the BVH, flushed with it
        try:
            if face:
                self.tables.append(FaceTable(face_path(self.path), feature_spec.fps))
            if channels:
                self.tables.append(ChannelTable(channels_path(self.path), channels))
        except RecordError:
            for t in self.tables:
                t.close()
            os.close(self.fd)
            raise

    def on_frames(self, frames: list[Frame]) -> None:
        if not frames or self.failed or self.closed:
            return
        from dimgestor.bvh import BvhMotion, format_frames

        pose = self.decoder.decode(np.stack([f.features for f in frames]))
        n, sk = len(frames), self.skeleton
        translations = np.broadcast_to(sk.offsets, (n, sk.num_joints, 3)).copy()
        translations[:, 0] = pose.root_pos
        values = BvhMotion.from_pose(sk, self.frame_time, pose.rotations, translations).values
        if self.last is not None:  # continue the angle unwrapping of the previous chunk (whole turns only)
            values[:, self.rot_cols] += 360.0 * np.round((self.last - values[0, self.rot_cols]) / 360.0)
        self.last = values[-1, self.rot_cols]
        self.pending.append(format_frames(values))
        self.pending_frames += n
        for t in self.tables:
            t.add_frames(frames)
        if time.monotonic() - self.last_flush >= self.flush_every_s:
            self.flush()

    def flush(self) -> None:
        """Append the pending frame lines, then rewrite the header's frame count."""
        self.last_flush = time.monotonic()
        if not self.pending or self.failed:
            return
        data, n = "".join(self.pending).encode(), self.pending_frames
        self.pending, self.pending_frames = [], 0
        if self._append(data):
            self._set_count(self.frames + n)
        for t in self.tables:
            t.flush()

    def _append(self, data: bytes) -> bool:
        at = self.size
        try:
            view = memoryview(data)
            while view:
                k = os.pwrite(self.fd, view, at)
                view, at = view[k:], at + k
        except OSError as e:
            self._fail(e)
            return False
        self.size = at
        return True

    def _set_count(self, frames: int) -> bool:
        try:
            os.pwrite(self.fd, str(frames).ljust(COUNT_WIDTH).encode(), self.count_at)
        except OSError as e:
            self._fail(e)
            return False
        self.frames = frames
        return True

    def _fail(self, e: OSError) -> None:
        """Stop recording: cut a partly written frame line, keep the frames the header counts."""
        self.failed = f"{e.strerror or e}"
        try:
            os.ftruncate(self.fd, self.size)
        except OSError:
            pass
        if self.size:  # the header is there: say what was kept
            print(f"dimgestor: recording stopped: cannot write {self.path}: {self.failed}; kept the first "
                  f"{self.frames} frames ({self.frames * self.frame_time:.1f} s)", file=sys.stderr, flush=True)

    def close(self) -> Path | None:
        """Write what is pending and close; the path, or None if the recording failed."""
        if self.closed:
            return None
        self.flush()
        self.closed = True
        os.close(self.fd)
        for t in self.tables:
            t.close()
        return None if self.failed else self.path


def bvh_path(path: str | Path) -> Path:
    """Where a recording's BVH goes: OUT.bvh itself; beside OUT.glb, OUT.vrma or OUT.npz (a BEAT2 / SMPL-X take),
    OUT.bvh (written as it comes, so a crash keeps it; the other file is made from it when the recording ends)."""
    path = Path(path)
    return path.with_suffix(".bvh") if path.suffix.lower() in (".glb", ".vrma", ".npz") else path


class RecordingSink:
    """`BvhRecorder` as a `Sink` (streamer/sink.py): the file is created by `open`, last of all the sinks, so
    that a failure to start anything else leaves an old recording alone. A .glb, .vrma or .npz path (optionally on
    a `target` rig: a `dimgestor.retarget.Target` as read at start, or a rig's path and `target_map`) is written at
    the end from the BVH beside it (and the face, for .vrma; a .npz is retargeted onto SMPL-X)."""

    def __init__(self, path: str | Path, skeleton, feature_spec, root: str = "free", tether_s: float = 5.0,
                 channels: Mapping[str, Channel] | None = None, face: bool = False, target=None,
                 target_map: str | None = None):
        self.path = Path(path)
        self.args = (skeleton, feature_spec, root, tether_s)
        self.channels, self.face = channels, face
        self.target, self.target_map = target, target_map
        self.recorder: BvhRecorder | None = None
        self.faces: list[np.ndarray] = []  # for a .vrma: the canonical face of each frame

    async def open(self) -> None:
        # (RecordError says why not)
        self.recorder = BvhRecorder(bvh_path(self.path), *self.args, channels=self.channels, face=self.face)

    def send(self, frames: list[Frame]) -> None:
        self.recorder.on_frames(frames)
        if self.path.suffix.lower() == ".vrma" and self.face:
            from dimgestor.face import FACE_LABELS

            canonical = Channel(FACE, len(FACE_LABELS))
            self.faces += [channel_values(f, canonical) for f in frames]

    async def close(self, drain: bool = True) -> None:
        path = self.recorder.close() if self.recorder is not None else None
        if path:
            print(f"dimgestor: wrote {self.recorder.frames} frames to {path}", file=sys.stderr)
        if path and (path != self.path or self.target is not None):
            self._convert(path)

    def _convert(self, bvh: Path) -> None:
        """The finished BVH as the file asked for (on the target rig); an error says so and keeps the BVH."""
        from dimgestor.bvh import read_bvh
        from dimgestor.retarget.export import write_motion

        try:
            motion = read_bvh(bvh)
            face = None
            if self.faces:
                from dimgestor.face.names import convert, names_of

                weights = convert(np.stack(self.faces[:motion.num_frames]), "vrm1")
                face = dict(zip(names_of("vrm1"), weights.T))
            what = write_motion(self.path, motion, self.target, self.target_map, face)
            print(f"dimgestor: wrote {self.path} ({what})", file=sys.stderr)
        except (OSError, ValueError) as e:
            print(f"dimgestor: could not write {self.path} ({e}); the recording is in {bvh}", file=sys.stderr)

    def describe(self) -> str:
        channels = RECORD_CHANNELS if self.channels is None else self.channels
        bvh = bvh_path(self.path)
        beside = ([f"face: {face_path(bvh)}"] if self.face else []) + (
            [f"channels: {channels_path(bvh)}"] if any(c != FACE for c in channels) else [])
        also = f" and {self.path} at the end" if bvh != self.path else ""
        return f"recording  {bvh}{also}" + (f" ({', '.join(beside)})" if beside else "")

    def status(self) -> str:
        return ""
