"""VMC protocol sink: the server as a Performer sending OSC over UDP to a Marionette (default :39539).

Per frame, one bundle (types as in the VMC Marionette spec; EVMC4U checks each of them):
  /VMC/Ext/Root/Pos (s)"root" (f)p.x p.y p.z (f)q.x q.y q.z q.w      the fixed root pose (`VmcOptions.root`)
  /VMC/Ext/Bone/Pos (s)HumanBodyBones name (f)p.x p.y p.z (f)q.x q.y q.z q.w   per sent bone, local
  /VMC/Ext/Blend/Val (s)name (f)value   per value of each channel of the sink's map (`face_channels`: the face,
                                        every name of the server's --face set; a frame without one: zeros)
  /VMC/Ext/Blend/Apply
  /VMC/Ext/OK (i)1
  /VMC/Ext/T (f)the frame's presentation time, seconds on the stream's audio clock
in Unity's left-handed frame and metres (streamer.pose). With `max_bytes` a frame is split into several
bundles of at most that size (the root in the first; Apply, OK and T in the last, after every Blend/Val), for
receivers on a LAN that drop fragmented UDP datagrams. Receivers apply each bundle on arrival, so frames are released by
a `Pacer` at their presentation time plus a jitter buffer, not in the bursts inference makes them in.

Bundles are packed with `struct` from per-bone headers built once (`VmcEncoder.packets`);
`VmcEncoder.messages` + `reference_bundle` (python-osc's builders) is the reference they must equal.
"""

from __future__ import annotations

import asyncio
import logging
import math
import socket
import struct
import time
from collections import deque
from dataclasses import dataclass
from typing import Mapping, Protocol

import numpy as np

from streamer.frames import Channel, Frame, channel_values
from streamer.pacing import Pacer
from streamer.pose import HumanoidRig, to_unity_position, to_unity_quat

log = logging.getLogger("streamer.vmc")
DEFAULT_PORT = 39539
POSITION_MODES = ("hips", "all")
BONE_SETS = ("all", "upper")
# Upper body without neck and head, for mixing with face tracking (which drives the head).
UPPER_BODY = frozenset(
    ["Spine", "Chest", "UpperChest", "LeftShoulder", "RightShoulder", "LeftUpperArm", "RightUpperArm",
     "LeftLowerArm", "RightLowerArm", "LeftHand", "RightHand"]
    + [f"{side}{finger}{part}" for side in ("Left", "Right") for finger in ("Thumb", "Index", "Middle", "Ring", "Little")
       for part in ("Proximal", "Intermediate", "Distal")])
MIN_SPLIT_BYTES = 256  # a bundle must hold at least one bone message (~80 B) besides its header


@dataclass(frozen=True)
class VmcOptions:
    """What the VMC stream carries; the defaults suit a receiver driving the user's own avatar."""

    positions: str = "hips"       # "hips": only Hips moves by position, other bones carry their rest offset; "all": every bone's posed position
    hips_height_m: float | None = None  # scale positions so the rest Hips stand this high (the avatar's); None: the skeleton's own size
    root: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # /VMC/Ext/Root/Pos: x, y, z metres (Unity), yaw degrees
    bones: str = "all"            # "all" mapped bones, or "upper" (spine, arms, hands, fingers: no hips, legs, neck, head)
    max_bytes: int = 0            # split a frame's bundle into bundles of at most this many bytes; 0: one bundle per frame

    def __post_init__(self):
        if self.positions not in POSITION_MODES:
            raise ValueError(f"positions must be one of {POSITION_MODES}, got {self.positions!r}")
        if self.bones not in BONE_SETS:
            raise ValueError(f"bones must be one of {BONE_SETS}, got {self.bones!r}")
        if self.hips_height_m is not None and not 0.1 <= self.hips_height_m <= 10:
            raise ValueError(f"hips height must be in 0.1..10 m, got {self.hips_height_m}")
        if len(self.root) != 4 or not all(math.isfinite(v) for v in self.root):
            raise ValueError(f"root must be 4 finite numbers x, y, z, yaw_deg; got {self.root}")
        if self.max_bytes and self.max_bytes < MIN_SPLIT_BYTES:
            raise ValueError(f"max bytes must be 0 (no split) or >= {MIN_SPLIT_BYTES}, got {self.max_bytes}")


class VmcChannel(Protocol):
    """How one frame channel is sent over VMC: its spec and the OSC messages of its values."""

    channel: Channel

    def messages(self, values: np.ndarray) -> list[tuple[str, list]]:
        """(address, args) messages of one frame's values (size,), sent before /VMC/Ext/Blend/Apply."""


@dataclass(frozen=True)
class BlendValues:
    """A channel sent as blendshape values: /VMC/Ext/Blend/Val (s)label (f)value, one message per value."""

    channel: Channel

    def messages(self, values: np.ndarray) -> list[tuple[str, list]]:
        labels = self.channel.labels or [f"{self.channel.name}_{i}" for i in range(self.channel.size)]
        return [("/VMC/Ext/Blend/Val", [name, float(v)]) for name, v in zip(labels, values)]


# The VMC sink's default channel map: frame channel name -> how it is sent. Empty: the bundles are those of the
# pose alone. A sink given its own map (`channels=`, e.g. `face_channels`) sends that instead.
VMC_CHANNELS: dict[str, VmcChannel] = {}


def face_channels(name_set: str) -> dict[str, VmcChannel]:
    """A VMC sink's channel map for the face in `name_set`'s names ("none": no face; ValueError for an unknown set,
    listing the known ones)."""
    if name_set == "none":
        return {}
    from streamer.face import FACE, face_channel

    return {FACE: BlendValues(face_channel(name_set))}


# ---- OSC packing ---------------------------------------------------------------------------------


def _osc_string(s: str) -> bytes:
    b = s.encode("utf-8") + b"\0"
    return b + b"\0" * (-len(b) % 4)


def _osc_message(address: str, *args) -> bytes:
    tags, data = ",", b""
    for a in args:
        if isinstance(a, str):
            tags, data = tags + "s", data + _osc_string(a)
        elif isinstance(a, int):
            tags, data = tags + "i", data + struct.pack(">i", a)
        else:
            tags, data = tags + "f", data + struct.pack(">f", a)
    return _osc_string(address) + _osc_string(tags) + data


_BUNDLE_HEAD = b"#bundle\0" + struct.pack(">Q", 1)  # time tag 1: immediately


def _bundle(messages: list[bytes]) -> bytes:
    return _BUNDLE_HEAD + b"".join(struct.pack(">i", len(m)) + m for m in messages)


def reference_bundle(messages: list[tuple[str, list]]) -> bytes:
    """python-osc's builders on (address, args) messages: the reference `VmcEncoder.packets` must equal."""
    from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
    from pythonosc.osc_message_builder import OscMessageBuilder

    b = OscBundleBuilder(IMMEDIATELY)
    for address, args in messages:
        m = OscMessageBuilder(address)
        for a in args:
            m.add_arg(a, "s" if isinstance(a, str) else "i" if isinstance(a, int) else "f")
        b.add_content(m.build())
    return b.build().dgram


# ---- frames -> bundles ---------------------------------------------------------------------------


class VmcEncoder:
    """Frames -> VMC datagrams for one rig and one set of options (no I/O)."""

    def __init__(self, rig: HumanoidRig, options: VmcOptions = VmcOptions(), scale: float = 0.01,
                 channels: Mapping[str, VmcChannel] | None = None):
        self.rig, self.options = rig, options
        self.channels = list((VMC_CHANNELS if channels is None else channels).values())
        if options.hips_height_m is not None:
            scale = options.hips_height_m / rig.rest_hips_height()
        self.scale = scale
        self.sent_bones = [i for i, b in enumerate(rig.bones) if options.bones == "all" or b in UPPER_BODY]
        self.names = [rig.bones[i] for i in self.sent_bones]
        self.hips = rig.bones.index("Hips") if "Hips" in rig.bones else 0
        # Rest local positions (Unity, metres): what "hips" sends for every bone but the hips.
        rest, _ = rig.local_pose(rig.offsets[rig.root_joint][None], rig.rest_pose()[None])
        self.rest = to_unity_position(rest[0], scale)
        x, y, z, yaw = options.root
        half = math.radians(yaw) / 2
        self.root_args = ["root", float(x), float(y), float(z), 0.0, math.sin(half), 0.0, math.cos(half)]
        self.headers = [_bone_header(n) for n in self.names]
        self.root_msg = _osc_message("/VMC/Ext/Root/Pos", *self.root_args)
        self.apply_msg = _osc_message("/VMC/Ext/Blend/Apply")
        self.ok_msg = _osc_message("/VMC/Ext/OK", 1)

    def bone_values(self, frame: Frame) -> np.ndarray:
        """(sent bones, 7) position xyz + rotation xyzw in Unity's frame, float64."""
        pos, rot = self.rig.local_pose(frame.root_pos[None], frame.rotations[None])
        pos, rot = to_unity_position(pos[0], self.scale), to_unity_quat(rot[0])
        if self.options.positions == "hips":
            keep = pos[self.hips].copy()
            pos = self.rest.copy()
            pos[self.hips] = keep
        out = np.concatenate([pos, rot[:, 1:], rot[:, :1]], axis=1)  # wxyz -> xyzw
        return out[self.sent_bones]

    def messages(self, frame: Frame) -> list[list[tuple[str, list]]]:
        """The reference: each datagram's (address, args) messages, built one float at a time."""
        values = self.bone_values(frame)
        bones = [("/VMC/Ext/Bone/Pos", [n, *map(float, v)]) for n, v in zip(self.names, values)]
        head = [("/VMC/Ext/Root/Pos", list(self.root_args))]
        tail = [("/VMC/Ext/Blend/Apply", []), ("/VMC/Ext/OK", [1]), ("/VMC/Ext/T", [float(frame.pts)])]
        items = [head] + [[b] for b in bones] + [[m] for m in self.channel_messages(frame)] + [tail]
        sizes = [sum(len(_osc_message(a, *args)) + 4 for a, args in it) for it in items]
        groups = _split(sizes, self.options.max_bytes)
        return [sum((items[i] for i in g), []) for g in groups]

    def packets(self, frame: Frame) -> list[bytes]:
        """The datagrams of one frame, packed directly (equal to `reference_bundle` of `messages`)."""
        floats = self.bone_values(frame).astype(">f4").tobytes()
        bones = [h + floats[28 * i : 28 * i + 28] for i, h in enumerate(self.headers)]
        t = _osc_message("/VMC/Ext/T", float(frame.pts))
        extra = [[_osc_message(a, *args)] for a, args in self.channel_messages(frame)]
        items = [[self.root_msg]] + [[b] for b in bones] + extra + [[self.apply_msg, self.ok_msg, t]]
        if not self.options.max_bytes:
            return [_bundle([m for it in items for m in it])]
        sizes = [sum(len(m) + 4 for m in it) for it in items]
        return [_bundle([m for i in g for m in items[i]]) for g in _split(sizes, self.options.max_bytes)]

    def channel_messages(self, frame: Frame) -> list[tuple[str, list]]:
        """The (address, args) messages of the frame's mapped channels (zeros for a channel it lacks)."""
        return [m for c in self.channels for m in c.messages(channel_values(frame, c.channel))]

    def heartbeat(self, t: float) -> list[bytes]:
        """No frames flowing: the link is up but no pose is loaded."""
        return [_osc_message("/VMC/Ext/OK", 0), _osc_message("/VMC/Ext/T", float(t))]


def _bone_header(name: str) -> bytes:
    """Address + type tags + name of one bone message; the 7 floats follow."""
    return _osc_string("/VMC/Ext/Bone/Pos") + _osc_string(",sfffffff") + _osc_string(name)


def _split(sizes: list[int], max_bytes: int) -> list[list[int]]:
    """Group consecutive items (sizes in bytes, with their size prefix) into bundles of at most max_bytes."""
    if not max_bytes:
        return [list(range(len(sizes)))]
    room = max_bytes - len(_BUNDLE_HEAD)
    groups, cur, used = [], [], 0
    for i, s in enumerate(sizes):
        if cur and used + s > room:
            groups.append(cur)
            cur, used = [], 0
        cur.append(i)
        used += s
    groups.append(cur)
    return groups


# ---- the sink ------------------------------------------------------------------------------------


class VmcSink:
    """Sends frames as VMC bundles, paced (`Pacer`); `pace=False` sends them as soon as they are made (--fast).
    A `Sink` (streamer/sink.py); drain_s: how long `close` plays out what is queued when the source ended."""

    def __init__(self, host: str, port: int, rig: HumanoidRig, scale: float = 0.01, pace: bool = True,
                 jitter_s: float = 0.25, max_queue: int = 200, options: VmcOptions = VmcOptions(),
                 drain_s: float = 2.0, channels: Mapping[str, VmcChannel] | None = None, pose=None):
        self.sock: socket.socket | None = None
        self.pose = pose  # frames -> frames on `rig`'s skeleton (a `streamer.pose.TargetPose`), None: as made
        self.host, self.port = host, port
        self.drain_s = drain_s
        self.reported_dropped = 0  # drops already told in a status line
        self.encoder = VmcEncoder(rig, options, scale, channels)
        self.pace, self.jitter_s = pace, jitter_s
        self.pacer = Pacer(buffer_s=jitter_s)
        self.queue: deque[Frame] = deque()
        self.max_queue = max_queue
        self.dropped_full = 0  # frames pushed out of a full queue, or still queued at a Ctrl-C
        self.send_errors = 0
        self.sent = 0
        self.last_t = 0.0
        self.ready = asyncio.Event()
        self.task: asyncio.Task | None = None
        self.closing = False

    @property
    def dropped(self) -> int:
        """Frames never sent: late at their turn (after a stall) or pushed out of a full queue."""
        return self.pacer.stats.dropped_late + self.dropped_full

    def _send(self, datagrams: list[bytes]) -> None:
        for d in datagrams:
            try:
                self.sock.send(d)
            except OSError:  # no receiver (ICMP refused) or a full socket buffer: UDP loses it, we count it
                self.send_errors += 1

    def heartbeat(self) -> None:
        self._send(self.encoder.heartbeat(self.last_t))

    def send(self, frames: list[Frame]) -> None:
        if self.pose is not None:
            frames = self.pose(frames)
        now = time.monotonic()
        if frames and self.pace and self.pacer.anchor is not None:
            log.debug("frames %d..%d in, due in %.3f..%.3f s", frames[0].index, frames[-1].index,
                      self.pacer.due(frames[0].pts) - now, self.pacer.due(frames[-1].pts) - now)
        for f in frames:
            if f.index == 0:
                self.pacer.reset()  # a new stream: pts start again at 0
            if self.pace:
                self.pacer.arrived(f.pts, now)
            if len(self.queue) >= self.max_queue:  # drop the oldest; the clock does not move
                self.queue.popleft()
                self.dropped_full += 1
            self.queue.append(f)
        self.ready.set()

    def restart_clock(self) -> None:
        """A new stream starts (pts back to 0): re-anchor the playout clock."""
        self.pacer.reset()

    async def run(self) -> None:
        """The playout loop: send each queued frame at its due time (late ones are dropped), heartbeat when idle."""
        while True:
            if not self.queue:
                if self.closing:
                    return
                self.ready.clear()
                try:
                    await asyncio.wait_for(self.ready.wait(), 1.0)
                except asyncio.TimeoutError:
                    self.heartbeat()
                continue
            f = self.queue.popleft()  # the frame sent is the frame paced, whatever arrives meanwhile
            if self.pace:
                now = time.monotonic()
                delay = self.pacer.wait(f.pts, now)
                if delay is None:
                    log.debug("frame %d dropped: %.3f s late", f.index, now - self.pacer.due(f.pts))
                    continue
                if delay > 0:
                    try:
                        await asyncio.sleep(delay)
                    except asyncio.CancelledError:  # closing: the frame in hand is not sent either
                        self.dropped_full += 1
                        raise
            self._send(self.encoder.packets(f))
            self.last_t = f.pts
            self.sent += 1
            await asyncio.sleep(0)

    async def open(self) -> None:
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            self.sock.connect((self.host, self.port))  # fails early on a bad address
        except OSError as e:
            self.sock.close()
            self.sock = None
            raise OSError(f"--vmc {self.host}:{self.port}: {e.strerror or e}") from None
        self.task = asyncio.get_running_loop().create_task(self.run(), name="vmc")

    def describe(self) -> str:
        return f"VMC/OSC -> {self.host}:{self.port}"

    def status(self) -> str:
        line = f"vmc sent {self.sent} dropped {self.dropped}"
        if self.dropped > self.reported_dropped:  # a stall (CPU busy, process paused): say so
            line += (f" | WARNING: VMC dropped {self.dropped - self.reported_dropped} late frames (a stall: CPU busy "
                     f"or process paused)")
            self.reported_dropped = self.dropped
        return line

    async def close(self, drain: bool = True) -> None:
        """Stop: play out what is queued for at most drain_s (drain=False: drop it, as on Ctrl-C), then the idle
        heartbeat."""
        drain_s = self.drain_s if drain else 0.0
        self.closing = True
        self.ready.set()
        if self.task is not None:
            try:
                await asyncio.wait_for(asyncio.shield(self.task), drain_s) if drain_s > 0 else None
            except asyncio.TimeoutError:
                pass
            if not self.task.done():
                self.task.cancel()
                await asyncio.gather(self.task, return_exceptions=True)
        self.dropped_full += len(self.queue)
        self.queue.clear()
        self.reported_dropped = self.dropped  # (what a stop drops is the queue, not a stall to warn about)
        if self.sock is not None:
            self.heartbeat()
            self.sock.close()
