"""A loopback UDP receiver thread for the VMC tests: a large socket buffer (VMC bundles come in bursts),
a free port, and a hook per datagram."""

import socket
import threading
import time


class UdpCapture(threading.Thread):
    """Every datagram that reaches a free loopback UDP port, raw, with its arrival time (monotonic)."""

    def __init__(self):
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.datagrams: list[bytes] = []
        self.stop = False

    def on_datagram(self, data: bytes, at: float) -> None:
        self.datagrams.append(data)

    def run(self):
        while not self.stop:
            try:
                data = self.sock.recv(65536)
            except socket.timeout:
                continue
            self.on_datagram(data, time.monotonic())
