"""BVH motion capture files: hierarchy, reading, writing and forward kinematics.

Conventions (shared with features.py): BVH space is right-handed, Y up, in file units. A joint's
rotation channels are intrinsic Euler angles in degrees applied in channel order (see
rotations.py). Position channels, where a joint has them, replace the matching component of its
OFFSET as the joint's local translation (so a root's Xposition/Yposition/Zposition are absolute,
the convention of ZEGGS, BEAT and most exporters); joints without them use the OFFSET.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dimgestor import rotations as R

ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")


class BvhError(ValueError):
    """A malformed BVH file; the message names the file and line."""


@dataclass(eq=False)
class Skeleton:
    names: list[str]
    parents: list[int]  # -1 for the root; parents come before their children
    offsets: np.ndarray  # (J, 3) float64, file units
    channels: list[list[str]]  # per joint, in file order
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)  # joint -> End Site offset

    def __post_init__(self):
        self.offsets = np.asarray(self.offsets, dtype=np.float64).reshape(len(self.names), 3)
        self.end_sites = {int(j): np.asarray(o, dtype=np.float64).reshape(3) for j, o in self.end_sites.items()}
        for j, chans in enumerate(self.channels):
            for c in chans:
                if c not in ROTATION_CHANNELS + POSITION_CHANNELS:
                    raise ValueError(f"joint {self.names[j]!r}: unknown channel {c!r}")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def num_channels(self) -> int:
        return sum(len(c) for c in self.channels)

    @property
    def channel_starts(self) -> list[int]:
        """Index of each joint's first channel in a frame's values."""
        return [int(s) for s in np.cumsum([0] + [len(c) for c in self.channels])[:-1]]

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"joint {name!r} not in skeleton ({len(self.names)} joints)") from None

    def children(self, j: int) -> list[int]:
        return [k for k, p in enumerate(self.parents) if p == j]

    def rotation_order(self, j: int) -> str:
        """Rotation axes in channel order, e.g. "ZXY" ("" for a joint without rotation channels)."""
        return "".join(c[0] for c in self.channels[j] if c in ROTATION_CHANNELS)

    def has_position(self, j: int) -> bool:
        return any(c in POSITION_CHANNELS for c in self.channels[j])

    def same_topology(self, other: "Skeleton") -> bool:
        return self.names == other.names and self.parents == other.parents and self.channels == other.channels

    def __eq__(self, other: object) -> bool:
        """Same topology, channels, offsets and End Sites (to 1e-6 file units)."""
        if not isinstance(other, Skeleton):
            return NotImplemented
        return (self.same_topology(other) and np.allclose(self.offsets, other.offsets, rtol=0, atol=1e-6)
                and self.end_sites.keys() == other.end_sites.keys()
                and all(np.allclose(o, other.end_sites[j], rtol=0, atol=1e-6) for j, o in self.end_sites.items()))

    def to_dict(self) -> dict:
        return {
            "names": list(self.names),
            "parents": [int(p) for p in self.parents],
            "offsets": self.offsets.tolist(),
            "channels": [list(c) for c in self.channels],
            "end_sites": {str(j): o.tolist() for j, o in self.end_sites.items()},
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Skeleton":
        return cls(
            names=list(d["names"]),
            parents=[int(p) for p in d["parents"]],
            offsets=np.asarray(d["offsets"], dtype=np.float64),
            channels=[list(c) for c in d["channels"]],
            end_sites={int(j): np.asarray(o) for j, o in d.get("end_sites", {}).items()},
        )


@dataclass(eq=False)
class BvhMotion:
    skeleton: Skeleton
    frame_time: float  # seconds per frame
    values: np.ndarray  # (T, num_channels) in file order: degrees, file units

    def __post_init__(self):
        self.values = np.asarray(self.values, dtype=np.float64)
        if self.values.ndim != 2 or self.values.shape[1] != self.skeleton.num_channels:
            raise ValueError(f"values must be (T, {self.skeleton.num_channels}), got {self.values.shape}")

    @property
    def num_frames(self) -> int:
        return self.values.shape[0]

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def duration(self) -> float:
        return self.num_frames * self.frame_time

    def rotations(self) -> np.ndarray:
        """Local joint rotations (T, J, 4) wxyz; identity for joints without rotation channels."""
        sk = self.skeleton
        q = R.quat_identity((self.num_frames, sk.num_joints))
        for j, start in enumerate(sk.channel_starts):
            cols = [start + k for k, c in enumerate(sk.channels[j]) if c in ROTATION_CHANNELS]
            if cols:
                q[:, j] = R.euler_to_quat(np.radians(self.values[:, cols]), sk.rotation_order(j))
        return q

    def translations(self) -> np.ndarray:
        """Local joint translations (T, J, 3): OFFSET, with position channels replacing components."""
        sk = self.skeleton
        t = np.broadcast_to(sk.offsets, (self.num_frames, sk.num_joints, 3)).copy()
        for j, start in enumerate(sk.channel_starts):
            for k, c in enumerate(sk.channels[j]):
                if c in POSITION_CHANNELS:
                    t[:, j, POSITION_CHANNELS.index(c)] = self.values[:, start + k]
        return t

    @classmethod
    def from_pose(cls, skeleton: Skeleton, frame_time: float, rotations: np.ndarray, translations: np.ndarray) -> "BvhMotion":
        """Inverse of rotations()/translations(): local quaternions (T, J, 4) and translations (T, J, 3)."""
        values, _ = pose_values(skeleton, rotations, translations)
        return cls(skeleton, float(frame_time), values)


def pose_values(skeleton: Skeleton, rotations: np.ndarray, translations: np.ndarray,
                before: dict[int, np.ndarray] | None = None) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Channel values (T, channels) of local quaternions (T, J, 4) and translations (T, J, 3), and each rotating
    joint's last Euler angles (radians, unwrapped); `before`: those of the frame before these (a motion written
    in pieces unwraps across them: the same values as all of it at once)."""
    T = rotations.shape[0]
    values = np.zeros((T, skeleton.num_channels))
    last: dict[int, np.ndarray] = {}
    for j, start in enumerate(skeleton.channel_starts):
        order = skeleton.rotation_order(j)
        if order:
            if len(order) != 3:
                raise ValueError(f"joint {skeleton.names[j]!r}: cannot write rotations to {len(order)} rotation channels")
            # +360 on one angle is the same rotation, so unwrapping per channel only removes jumps.
            euler = R.quat_to_euler(rotations[:, j], order)
            if before is not None and j in before:
                euler = np.unwrap(np.concatenate([before[j][None], euler]), axis=0)[1:]
            else:
                euler = np.unwrap(euler, axis=0)
            if T:
                last[j] = euler[-1]
            rot_cols = iter(np.degrees(euler).T)
        for k, c in enumerate(skeleton.channels[j]):
            if c in ROTATION_CHANNELS:
                values[:, start + k] = next(rot_cols)
            else:
                values[:, start + k] = translations[:, j, POSITION_CHANNELS.index(c)]
    return values, last


def forward_kinematics(motion: BvhMotion | Skeleton, rotations: np.ndarray | None = None,
                       translations: np.ndarray | None = None) -> np.ndarray:
    """World positions of all joints (T, J, 3), from a motion or a skeleton plus local pose."""
    if isinstance(motion, BvhMotion):
        skeleton, rotations, translations = motion.skeleton, motion.rotations(), motion.translations()
    else:
        skeleton = motion
        if rotations is None:
            raise ValueError("forward_kinematics(skeleton, ...) needs local rotations (T, J, 4)")
        if translations is None:
            translations = np.broadcast_to(skeleton.offsets, rotations.shape[:-1] + (3,))
    world_q = np.empty_like(rotations, dtype=np.float64)
    world_p = np.empty(rotations.shape[:-1] + (3,))
    for j, p in enumerate(skeleton.parents):  # parents precede children, so one pass suffices
        if p < 0:
            world_q[:, j] = rotations[:, j]
            world_p[:, j] = translations[:, j]
        else:
            world_q[:, j] = R.quat_mul(world_q[:, p], rotations[:, j])
            world_p[:, j] = world_p[:, p] + R.quat_rotate(world_q[:, p], translations[:, j])
    return world_p


# ---- reading -------------------------------------------------------------------------------------


class _Tokens:
    """Whitespace tokens of the HIERARCHY section with their 1-based line numbers."""

    def __init__(self, path: str, lines: list[str]):
        self.path = path
        self.items = [(tok, n + 1) for n, line in enumerate(lines) for tok in line.split()]
        self.pos = 0
        self.last_line = len(lines)

    def error(self, msg: str, line: int | None = None) -> BvhError:
        return BvhError(f"{self.path}:{line or self.last_line}: {msg}")

    def next(self, what: str) -> tuple[str, int]:
        if self.pos >= len(self.items):
            raise self.error(f"unexpected end of file, expected {what}")
        self.pos += 1
        return self.items[self.pos - 1]

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok != word:
            raise self.error(f"expected {word!r}, found {tok!r}", line)
        return line

    def floats(self, n: int, what: str) -> np.ndarray:
        out = []
        for _ in range(n):
            tok, line = self.next(what)
            try:
                out.append(float(tok))
            except ValueError:
                raise self.error(f"expected a number for {what}, found {tok!r}", line) from None
        return np.array(out)


def _parse_hierarchy(toks: _Tokens, root_name: str, sk: dict) -> None:
    """The joints from ROOT's name to its closing brace, into `sk`, in file order. A loop over the open joints, not
    a recursion: a chain of any depth parses (Python's recursion limit stopped a 1,000-deep one)."""
    open_joints: list[tuple[int, str]] = []  # (index, name) of each joint whose '}' is still to come

    def begin(name: str, parent: int) -> tuple[str, int]:
        """A joint's '{', OFFSET and CHANNELS; returns the token after them."""
        j = len(sk["names"])
        sk["names"].append(name)
        sk["parents"].append(parent)
        toks.expect("{")
        toks.expect("OFFSET")
        sk["offsets"].append(toks.floats(3, f"the OFFSET of {name!r}"))
        tok, line = toks.next("CHANNELS")
        chans: list[str] = []
        if tok == "CHANNELS":
            count_tok, line = toks.next("the channel count")
            if not count_tok.isdigit():
                raise toks.error(f"expected a channel count for {name!r}, found {count_tok!r}", line)
            for _ in range(int(count_tok)):
                c, line = toks.next(f"a channel of {name!r}")
                if c not in ROTATION_CHANNELS + POSITION_CHANNELS:
                    raise toks.error(f"unknown channel {c!r} for joint {name!r}", line)
                chans.append(c)
            tok, line = toks.next("'}'")
        sk["channels"].append(chans)
        open_joints.append((j, name))
        return tok, line

    tok, line = begin(root_name, -1)
    while open_joints:
        j, name = open_joints[-1]
        if tok == "}":
            open_joints.pop()
            if not open_joints:
                return
            tok, line = toks.next(f"'}}' closing {open_joints[-1][1]!r}")
        elif tok == "JOINT":
            child, _ = toks.next("a joint name")
            tok, line = begin(child, j)
        elif tok == "End":
            toks.expect("Site")
            toks.expect("{")
            toks.expect("OFFSET")
            sk["end_sites"][j] = toks.floats(3, f"the End Site OFFSET of {name!r}")
            toks.expect("}")
            tok, line = toks.next(f"'}}' closing {name!r}")
        else:
            raise toks.error(f"expected JOINT, End Site or '}}' inside {name!r}, found {tok!r}", line)


def read_bvh(path: str | Path) -> BvhMotion:
    path = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise BvhError(f"{path}: cannot read: {e.strerror or e}") from None
    lines = text.splitlines()  # handles CRLF and CR
    motion_at = next((n for n, line in enumerate(lines) if line.split()[:1] == ["MOTION"]), None)
    toks = _Tokens(path, lines[:motion_at] if motion_at is not None else lines)
    if not toks.items or toks.items[0][0] != "HIERARCHY":
        raise toks.error("not a BVH file: it does not start with HIERARCHY", toks.items[0][1] if toks.items else 1)
    toks.pos = 1
    toks.expect("ROOT")
    root_name, _ = toks.next("the root name")
    sk = {"names": [], "parents": [], "offsets": [], "channels": [], "end_sites": {}}
    _parse_hierarchy(toks, root_name, sk)
    if toks.pos < len(toks.items):
        tok, line = toks.items[toks.pos]
        raise toks.error(f"unexpected {tok!r} after the hierarchy (only one ROOT is supported)", line)
    if motion_at is None:
        raise BvhError(f"{path}:{len(lines)}: no MOTION section (file truncated?)")
    skeleton = Skeleton(sk["names"], sk["parents"], np.array(sk["offsets"]), sk["channels"], sk["end_sites"])
    n_frames, frame_time, data_at = _parse_motion_header(path, lines, motion_at)
    values = _parse_frames(path, lines, data_at, n_frames, skeleton.num_channels)
    return BvhMotion(skeleton, frame_time, values)


def _parse_motion_header(path: str, lines: list[str], at: int) -> tuple[int, float, int]:
    """Parse 'Frames: N' and 'Frame Time: t' after MOTION; returns them and the first data line index."""
    found: dict[str, str] = {}
    n = at + 1
    while n < len(lines) and len(found) < 2:
        line = lines[n].strip()
        if line:
            key, sep, val = line.partition(":")
            key = " ".join(key.split()).lower()
            if not sep or key not in ("frames", "frame time"):
                raise BvhError(f"{path}:{n + 1}: expected 'Frames:' and 'Frame Time:', found {line[:40]!r}")
            found[key] = val.strip()
        n += 1
    if len(found) < 2:
        raise BvhError(f"{path}:{len(lines)}: file ends inside the MOTION header")
    try:
        n_frames = int(found["frames"])
        frame_time = float(found["frame time"])
    except ValueError:
        raise BvhError(f"{path}:{n}: bad Frames / Frame Time values {found}") from None
    if n_frames < 0 or not frame_time > 0:
        raise BvhError(f"{path}:{n}: need Frames >= 0 and Frame Time > 0, got {n_frames}, {frame_time}")
    return n_frames, frame_time, n


def _parse_frames(path: str, lines: list[str], start: int, n_frames: int, n_channels: int) -> np.ndarray:
    rows = [(n, line.split()) for n, line in enumerate(lines[start:], start) if line.strip()]
    if len(rows) < n_frames:
        last = rows[-1][0] + 1 if rows else start
        raise BvhError(f"{path}:{last}: file ends after {len(rows)} of {n_frames} frames (truncated?)")
    if len(rows) > n_frames:
        raise BvhError(f"{path}:{rows[n_frames][0] + 1}: more frame lines than 'Frames: {n_frames}'")
    for n, toks in rows:
        if len(toks) != n_channels:
            raise BvhError(f"{path}:{n + 1}: frame has {len(toks)} values, the hierarchy has {n_channels} channels")
    try:
        return np.array([t for _, toks in rows for t in toks], dtype=np.float64).reshape(n_frames, n_channels)
    except ValueError:
        for n, toks in rows:
            for t in toks:
                try:
                    float(t)
                except ValueError:
                    raise BvhError(f"{path}:{n + 1}: not a number: {t!r}") from None
        raise


# ---- writing -------------------------------------------------------------------------------------


def _fmt(v: np.ndarray) -> str:
    return " ".join(f"{x:.6f}" for x in v)


def format_hierarchy(sk: Skeleton) -> str:
    """The HIERARCHY section of a BVH file for `sk` (joints must be in depth-first file order)."""
    out = io.StringIO()
    out.write("HIERARCHY\n")

    roots = [j for j, p in enumerate(sk.parents) if p < 0]
    if len(roots) != 1:
        raise ValueError(f"a BVH skeleton needs exactly one root, got {len(roots)}")
    visited: list[int] = []
    children: list[list[int]] = [[] for _ in sk.parents]
    for k, p in enumerate(sk.parents):
        if p >= 0:
            children[p].append(k)
    # (joint, depth, opening?): a joint's head and children, then its end site and '}' (a loop: any depth)
    todo: list[tuple[int, int, bool]] = [(roots[0], 0, True)]
    while todo:
        j, depth, opening = todo.pop()
        pad = "\t" * depth
        if not opening:
            if j in sk.end_sites:
                out.write(f"{pad}\tEnd Site\n{pad}\t{{\n{pad}\t\tOFFSET {_fmt(sk.end_sites[j])}\n{pad}\t}}\n")
            out.write(f"{pad}}}\n")
            continue
        visited.append(j)
        out.write(f"{pad}{'ROOT' if sk.parents[j] < 0 else 'JOINT'} {sk.names[j]}\n{pad}{{\n")
        out.write(f"{pad}\tOFFSET {_fmt(sk.offsets[j])}\n")
        if sk.channels[j]:
            out.write(f"{pad}\tCHANNELS {len(sk.channels[j])} {' '.join(sk.channels[j])}\n")
        todo.append((j, depth, False))
        todo.extend((c, depth + 1, True) for c in reversed(children[j]))
    if visited != list(range(sk.num_joints)):
        raise ValueError("skeleton joints must be in depth-first file order to be written as BVH")
    return out.getvalue()


def format_frames(values: np.ndarray) -> str:
    """Frame lines of a BVH MOTION section (6 decimals), one per row of `values`."""
    out = io.StringIO()
    np.savetxt(out, values, fmt="%.6f", delimiter=" ")
    return out.getvalue()


class BvhWriter:
    """A BVH file written a few frames at a time (a recording of any length in the memory of one piece): the same
    text as `write_bvh` of all of them. `frames`: how many will come (the header says it first)."""

    def __init__(self, path: str | Path, skeleton: Skeleton, frame_time: float, frames: int):
        self.path, self.skeleton, self.frames, self.written = Path(path), skeleton, int(frames), 0
        self._last: dict[int, np.ndarray] | None = None
        self._file = open(self.path, "w", encoding="utf-8")
        self._file.write(format_hierarchy(skeleton) + f"MOTION\nFrames: {self.frames}\nFrame Time: {float(frame_time)!r}\n")

    def write(self, rotations: np.ndarray, translations: np.ndarray) -> None:
        """The next frames: local quaternions (n, J, 4) and translations (n, J, 3) on the skeleton."""
        if self.written + len(rotations) > self.frames:
            raise ValueError(f"{self.path}: {self.written + len(rotations)} frames written, the header says {self.frames}")
        values, last = pose_values(self.skeleton, rotations, translations, self._last)
        self._last = last or self._last
        self._file.write(format_frames(values))
        self.written += len(values)

    def close(self) -> None:
        self._file.close()
        if self.written != self.frames:
            raise ValueError(f"{self.path}: {self.written} frames written, the header says {self.frames}")

    def __enter__(self) -> "BvhWriter":
        return self

    def __exit__(self, kind, *_) -> None:
        if kind is None:
            self.close()
        else:
            self._file.close()


def write_bvh(path: str | Path, motion: BvhMotion) -> None:
    """Write a BVH file (6 decimals: 1e-6 degrees, well inside the 1e-4 round-trip promise)."""
    text = (format_hierarchy(motion.skeleton) + f"MOTION\nFrames: {motion.num_frames}\nFrame Time: {motion.frame_time!r}\n"
            + format_frames(motion.values))
    Path(path).write_text(text, encoding="utf-8")
