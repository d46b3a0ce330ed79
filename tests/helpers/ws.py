"""An in-process `WsServer` on a (tiny) model bundle, and a client read that skips status messages."""

import asyncio
import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

from streamer import protocol as P
from streamer.sessions import Session
from streamer.pose import HumanoidRig, load_humanoid_map
from dataclasses import fields

from streamer.ws import Attached, WsConfig, WsServer


def server(hello: dict, make_session, **kw) -> WsServer:
    """A `WsServer` on 127.0.0.1 and a free port; `kw`: fields of `WsConfig` and of `Attached` (a hello's `face`
    is the config's `face`, as `serve` makes it)."""
    config = {f.name for f in fields(WsConfig)}
    if "face" in hello:
        kw.setdefault("face", hello["face"]["names"])
    for key in ("origins", "also"):
        if key in kw:
            kw[key] = tuple(kw[key])
    return WsServer(WsConfig("127.0.0.1", 0, **{k: v for k, v in kw.items() if k in config}), hello, make_session,
                    Attached(**{k: v for k, v in kw.items() if k not in config}))


def make_server(bundle, hello_extra: dict | None = None, make_session="default", **kw) -> WsServer:
    """`server` with the bundle's hello (plus `hello_extra`) and its sessions (make_session None: no client audio)."""
    sk = bundle.skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    hello = {**P.hello(P.SkeletonInfo.from_skeleton(sk), rig.mapping(sk.names), 20, 0.1, True), **(hello_extra or {})}
    if make_session == "default":
        make_session = lambda **kw: Session.from_bundle(bundle, steps=2, seed=3, window_ms=100, **kw)  # noqa: E731
    return server(hello, make_session, **kw)


@contextmanager
def running(ws: WsServer):
    """`ws` open on its own thread and event loop, for tests that talk to it with plain sockets."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="ws-test", daemon=True)
    thread.start()
    asyncio.run_coroutine_threadsafe(ws.open(), loop).result(10)
    try:
        yield ws
    finally:
        asyncio.run_coroutine_threadsafe(ws.close(within_s=0.5), loop).result(10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        loop.close()


async def recv_json(c, timeout=10.0):
    while True:
        m = await asyncio.wait_for(c.recv(), timeout)
        if isinstance(m, str):
            d = json.loads(m)
            if d["type"] != "status":
                return d


class SlowExecutor(ThreadPoolExecutor):
    """Inference that takes at least `delay_s` (50 ms) a call, so a flushing session stays alive for a while."""

    def __init__(self, max_workers=None, delay_s: float = 0.05):
        super().__init__(max_workers)
        self.delay_s = delay_s

    def submit(self, fn, /, *args, **kwargs):
        return super().submit(lambda: (time.sleep(self.delay_s), fn(*args, **kwargs))[1])
