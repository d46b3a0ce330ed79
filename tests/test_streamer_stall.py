"""A live server that is paused (SIGSTOP/SIGCONT, 6 x 2.5 s) recovers: VMC and WebSocket back to full rate
within 2 s of the last pause, and no more lag than a jitter buffer over what it had before."""

import asyncio
import json
import os
import signal
import threading
import time

import numpy as np
import pytest
from websockets.asyncio.client import connect

from helpers.serve import serve
from helpers.stalls import runnable_waiting_s, wait_counting_cpu_waits
from helpers.udp_capture import UdpCapture

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow,
              pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="needs SIGSTOP/SIGCONT (POSIX)")]
JITTER_S = 0.25
PAUSES, PAUSE_S, RUN_S = 6, 2.5, 1.0


class VmcTimes(UdpCapture):
    """Receives VMC bundles; keeps (arrival, /VMC/Ext/T) per bundle (T is the frame's pts)."""

    def __init__(self):
        super().__init__()
        self.times: list[tuple[float, float]] = []

    def on_datagram(self, d: bytes, at: float) -> None:
        if d.startswith(b"#bundle") and (i := d.rfind(b"/VMC/Ext/T\0\0,f\0\0")) >= 0:
            self.times.append((at, float(np.frombuffer(d[i + 16 : i + 20], ">f4")[0])))


class WsTimes(threading.Thread):
    """Follows the broadcast; keeps (arrival, pts) per frame."""

    def __init__(self, url):
        super().__init__(daemon=True)
        self.url, self.times, self.stop = url, [], False

    def run(self):
        async def go():
            async with connect(self.url) as c:
                while not self.stop:
                    try:
                        m = await asyncio.wait_for(c.recv(), 0.2)
                    except asyncio.TimeoutError:
                        continue
                    m = json.loads(m)
                    if m["type"] == "frame":
                        self.times.append((time.monotonic(), m["pts"]))

        asyncio.run(go())


def check_recovery(times, name, last_resume, baseline_window, fps=20):
    t = np.array(times)
    assert len(t), f"{name}: nothing received"
    lag = t[:, 0] - t[:, 1]
    base = np.median(lag[(t[:, 0] >= baseline_window[0]) & (t[:, 0] < baseline_window[1])])
    after = (t[:, 0] >= last_resume + 2.0) & (t[:, 0] < last_resume + 4.0)
    rate = after.sum() / 2.0
    assert rate >= 18, f"{name}: {rate:.1f} frames/s in the 2 s from 2 s after the last pause"
    extra = lag[after] - base
    assert extra.max() <= JITTER_S + 0.1, f"{name}: {extra.max():.2f} s more lag than before the pauses"
    print(f"{name}: {rate:.1f} frames/s after the pauses, extra lag max {extra.max() * 1000:.0f} ms, median {np.median(extra) * 1000:.0f} ms")
    return rate, float(extra.max())


def test_vmc_and_websocket_recover_from_sigstop_pauses(tiny_checkpoint, wav):  # noqa: F811
    vmc = VmcTimes()
    vmc.start()
    s = serve(tiny_checkpoint, "--source", str(wav), "--loop", "--vmc", f"127.0.0.1:{vmc.port}")
    try:
        url = s.wait_for(r"WebSocket\s+(ws://\S+)").group(1)
        ws = WsTimes(url)
        ws.start()
        t_start = time.monotonic()
        time.sleep(3.0)
        for _ in range(PAUSES):
            os.kill(s.proc.pid, signal.SIGSTOP)
            time.sleep(PAUSE_S)
            os.kill(s.proc.pid, signal.SIGCONT)
            last_resume = time.monotonic()
            time.sleep(RUN_S)
        time.sleep(4.0 - RUN_S)
        vmc.stop = ws.stop = True
        waiting0 = runnable_waiting_s(s.proc.pid)
        t_ctrl_c = time.monotonic()
        s.proc.send_signal(signal.SIGINT)
        waited = wait_counting_cpu_waits(s.proc, waiting0, timeout=30)  # (the machine's other work, not the server's)
        took = time.monotonic() - t_ctrl_c
        assert s.finish(timeout=30) == 0, s.output
        assert took - waited < 5.0, f"Ctrl-C took too long: {took:.1f} s, of which {waited:.2f} s waiting for a CPU"
    finally:
        if s.proc.poll() is None:
            os.kill(s.proc.pid, signal.SIGCONT)
            s.proc.kill()
    ws.join(5)
    vmc.join(5)
    baseline = (t_start + 1.0, t_start + 3.0)
    check_recovery(vmc.times, "VMC", last_resume, baseline)
    check_recovery(ws.times, "WebSocket", last_resume, baseline)
    assert "WARNING: VMC dropped" in s.output  # the user is told about the stall
