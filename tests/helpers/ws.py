"""An in-process `WsServer` on a (tiny) model bundle, and a client read that skips status messages."""

import asyncio
import json
import time
from concurrent.futures import ThreadPoolExecutor

from streamer import protocol as P
from streamer.engine import Session
from streamer.pose import HumanoidRig, load_humanoid_map
from streamer.ws import WsServer


def make_server(bundle, **kw) -> WsServer:
    sk = bundle.skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    hello = P.hello(P.SkeletonInfo.from_skeleton(sk), rig.mapping(sk.names), 20, 0.1, True)
    return WsServer("127.0.0.1", 0, hello, lambda: Session.from_bundle(bundle, steps=2, seed=3, window_ms=100), **kw)


async def recv_json(c, timeout=10.0):
    while True:
        m = await asyncio.wait_for(c.recv(), timeout)
        if isinstance(m, str):
            d = json.loads(m)
            if d["type"] != "status":
                return d


class SlowExecutor(ThreadPoolExecutor):
    """Inference that takes at least 50 ms a call, so a flushing session stays alive for a while."""

    def submit(self, fn, /, *args, **kwargs):
        return super().submit(lambda: (time.sleep(0.05), fn(*args, **kwargs))[1])
