"""VMC protocol sink: the server as a Performer sending OSC over UDP to a Marionette (default :39539).

Per frame, one bundle (types as in the VMC Marionette spec):
  /VMC/Ext/Root/Pos (s)"root" (f)p.x p.y p.z (f)q.x q.y q.z q.w
  /VMC/Ext/Bone/Pos (s)HumanBodyBones name (f)p.x p.y p.z (f)q.x q.y q.z q.w   per mapped bone, local
  /VMC/Ext/Blend/Apply
  /VMC/Ext/OK (i)1
  /VMC/Ext/T (f)seconds since start
in Unity's left-handed frame and metres (streamer.pose). Receivers apply each bundle on arrival, so
frames are released by a clock at their presentation time (plus a small jitter buffer), not in the
bursts inference produces them in.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque

import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder
from pythonosc.udp_client import UDPClient

from streamer.engine import Frame
from streamer.pose import HumanoidRig, to_unity_position, to_unity_quat

DEFAULT_PORT = 39539


def _message(address: str, *args) -> object:
    m = OscMessageBuilder(address)
    for a in args:
        m.add_arg(a, "s" if isinstance(a, str) else "i" if isinstance(a, int) else "f")
    return m.build()


def _xyzw(q: np.ndarray) -> list[float]:
    return [float(q[1]), float(q[2]), float(q[3]), float(q[0])]


class VmcSink:
    """Sends frames as VMC bundles; `pace=False` sends them as soon as they are made (--fast)."""

    def __init__(self, host: str, port: int, rig: HumanoidRig, scale: float = 0.01, pace: bool = True,
                 jitter_s: float = 0.25, max_queue: int = 200):
        self.client = UDPClient(host, port)
        self.host, self.port = host, port
        self.rig, self.scale, self.pace, self.jitter_s = rig, scale, pace, jitter_s
        self.t0 = time.monotonic()
        self.queue: deque[Frame] = deque()
        self.max_queue = max_queue
        self.dropped = 0
        self.sent = 0
        self.anchor: float | None = None  # monotonic time at which pts 0 is shown
        self.ready = asyncio.Event()
        self.task: asyncio.Task | None = None
        self.closing = False

    def bundle(self, frame: Frame) -> bytes:
        """The OSC bundle of one frame (bytes ready to send)."""
        pos, rot = self.rig.local_pose(frame.root_pos[None], frame.rotations[None])
        pos, rot = to_unity_position(pos[0], self.scale), to_unity_quat(rot[0])
        b = OscBundleBuilder(IMMEDIATELY)
        b.add_content(_message("/VMC/Ext/Root/Pos", "root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0))
        for name, p, q in zip(self.rig.bones, pos, rot):
            b.add_content(_message("/VMC/Ext/Bone/Pos", name, *map(float, p), *_xyzw(q)))
        b.add_content(_message("/VMC/Ext/Blend/Apply"))
        b.add_content(_message("/VMC/Ext/OK", 1))
        b.add_content(_message("/VMC/Ext/T", float(time.monotonic() - self.t0)))
        return b.build()

    def heartbeat(self) -> None:
        """No frames flowing: tell the Marionette the link is up but no model pose is loaded."""
        self.client.send(_message("/VMC/Ext/OK", 0))
        self.client.send(_message("/VMC/Ext/T", float(time.monotonic() - self.t0)))

    def on_frames(self, frames: list[Frame]) -> None:
        for f in frames:
            if len(self.queue) >= self.max_queue:
                self.queue.popleft()
                self.dropped += 1
            self.queue.append(f)
        self.ready.set()

    def restart_clock(self) -> None:
        """A new stream starts (pts back to 0): re-anchor the playout clock."""
        self.anchor = None

    async def run(self) -> None:
        """The playout loop: send each queued frame at anchor + pts, or a heartbeat each second when idle."""
        loop = asyncio.get_running_loop()
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
            f = self.queue[0]
            if self.pace and not self.closing:
                late = self.anchor is not None and self.anchor + f.pts < time.monotonic() - self.jitter_s
                if self.anchor is None or f.index == 0 or late:  # (re)start the clock a jitter buffer ahead
                    self.anchor = time.monotonic() + self.jitter_s - f.pts
                delay = self.anchor + f.pts - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
            self.queue.popleft()
            self.client.send(self.bundle(f))
            self.sent += 1
            await asyncio.sleep(0)

    def start(self) -> None:
        self.task = asyncio.get_running_loop().create_task(self.run(), name="vmc")

    async def close(self, timeout: float = 5.0) -> None:
        """Send what is queued (without pacing), then the idle heartbeat."""
        self.closing = True
        self.ready.set()
        if self.task is not None:
            try:
                await asyncio.wait_for(self.task, timeout)
            except asyncio.TimeoutError:
                self.task.cancel()
        self.heartbeat()
