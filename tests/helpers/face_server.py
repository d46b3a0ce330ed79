"""A server that speaks the face of protocol revision 7 as docs/protocol.md writes it (hello.face; a client hello's
`face`; JSON frames' `face` object; after the ask, a `channels` message and the face's float32 values after a
binary frame's rotations), encoded here from that text with `struct` and `json`, and serving the web viewer's files
on its port as `dimgestor serve` does. The frames hold the synthetic skeleton at rest and carry a real face: the
`FaceStream` of a speech clip followed by silence, looped, paced in real time in bursts of one window.

For the viewer's face tests: they check the page against a known face track without a model or the server's own
face code in the way (tests/test_clients_web_face.py; the end-to-end test there uses `dimgestor serve`)."""

from __future__ import annotations

import asyncio
import json
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np

FPS = 20
WINDOW = 4  # frames a burst (200 ms)
SETS = ("vrm0", "vrm1", "arkit", "oculus")


def speech_then_silence(speech_s: float, silence_s: float):
    """The demo clip's first `speech_s` seconds then `silence_s` of silence, 16 kHz float32."""
    from dimgestor.audio import load_wav

    from helpers.clients import SPEECH_WAV

    x = load_wav(SPEECH_WAV).astype(np.float32)[: int(speech_s * 16000)]
    return np.concatenate([x, np.zeros(int(silence_s * 16000), np.float32)])


def face_track(audio: np.ndarray, lookahead_s: float = 0.35) -> np.ndarray:
    """The canonical face (T, 20) a `FaceStream` makes of `audio` at FPS, one frame per 1/FPS s of it: of the first
    blink seed whose track has a full blink on both lids in a frame (blinks come every 3.6 s on average, irregularly:
    a few seconds of track may hold none, and the tests look for one on screen)."""
    from dimgestor.face import FaceOptions, FaceStream
    from dimgestor.face.visemes import V

    for seed in range(50):
        fs = FaceStream(FPS, lookahead_s, FaceOptions(seed=seed))
        fs.push(audio)
        fs.push(np.zeros(int(lookahead_s * 16000) + 1600, np.float32))  # what follows: the last frames' lookahead
        track = fs.take(len(audio) * FPS // 16000)
        if np.any(np.minimum(track[:, V["blinkLeft"]], track[:, V["blinkRight"]]) > 0.9):
            return track
    raise AssertionError("no blink seed of 50 blinks in this track")


@dataclass
class FaceServer:
    """`track`: canonical face frames, looped; `default_set`: the names a client that did not ask gets in JSON."""

    track: np.ndarray
    default_set: str = "vrm0"
    port: int = 0
    hellos: list = field(default_factory=list)  # the client hellos received, in order

    def __post_init__(self):
        from dimgestor.training.synthetic import synthetic_skeleton
        from streamer import protocol as P
        from streamer.pose import HumanoidRig, load_humanoid_map

        sk = synthetic_skeleton()
        rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
        self.joints = len(sk.names)
        self.root = np.asarray(sk.offsets[0], np.float64)
        self.hello = P.hello(P.SkeletonInfo.from_skeleton(sk), rig.mapping(sk.names), FPS, 0.35, False,
                             window_ms=1000 * WINDOW // FPS, source="file")
        self.hello["revision"] = 7
        self.hello["face"] = {"names": self.default_set, "sets": list(SETS), "labels": self.labels(self.default_set)}

    @staticmethod
    def labels(name_set: str) -> list[str]:
        from dimgestor.face import names_of

        return list(names_of(name_set))

    def weights(self, index: int, name_set: str) -> np.ndarray:
        from dimgestor.face import convert

        return convert(self.track[index % len(self.track)], name_set)

    # ---- the wire, from docs/protocol.md
    def frame_json(self, index: int, name_set: str | None) -> str:
        msg = {"type": "frame", "index": index, "pts": index / FPS, "root": self.root.tolist(),
               "rotations": [[1.0, 0.0, 0.0, 0.0]] * self.joints}
        if name_set:
            msg["face"] = {n: round(float(w), 4) for n, w in zip(self.labels(name_set), self.weights(index, name_set))}
        return json.dumps(msg)

    def frame_binary(self, index: int, name_set: str | None) -> bytes:
        head = struct.pack("<4sId3f", b"DGF1", index, index / FPS, *self.root)
        rot = np.tile(np.array([1, 0, 0, 0], "<f4"), self.joints).tobytes()
        face = self.weights(index, name_set).astype("<f4").tobytes() if name_set else b""
        return head + rot + face

    def layout(self, name_set: str) -> list[dict]:
        labels = self.labels(name_set)
        return [{"name": "face", "size": len(labels), "offset": 28 + 16 * self.joints, "labels": labels}]

    # ---- one client
    async def _client(self, ws) -> None:
        await ws.send(json.dumps(self.hello))
        hello = json.loads(await asyncio.wait_for(ws.recv(), 10))
        self.hellos.append(hello)
        binary = hello.get("encoding") == "binary"
        asked = hello.get("face")
        if asked not in (None, "none", *SETS):
            await ws.send(json.dumps({"type": "error", "code": "bad_message",
                                      "message": f"unknown face name set {asked!r}: known sets are {', '.join(SETS)}"}))
            asked = None
        name_set = None if asked == "none" else asked or (None if binary else self.default_set)
        if asked is not None:
            await ws.send(json.dumps({"type": "channels", "channels": self.layout(asked) if asked != "none" else []}))
        start, index = time.monotonic(), 0
        while True:  # bursts of WINDOW frames, each when its window's audio would have been heard
            for _ in range(WINDOW):
                await ws.send(self.frame_binary(index, name_set) if binary else self.frame_json(index, name_set))
                index += 1
            await asyncio.sleep(max(0.0, start + index / FPS - time.monotonic()))

    async def _handle(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            await self._client(ws)
        except ConnectionClosed:
            pass

    def __enter__(self) -> FaceServer:
        from websockets.asyncio.server import serve

        from streamer.viewer import ViewerFiles, is_upgrade

        files = ViewerFiles()

        def process_request(connection, request):
            if not is_upgrade(request.headers.get_all("Upgrade")):
                return files.answer("GET", request.path).response()
            return None

        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="face-server", daemon=True)
        self.thread.start()

        async def start():
            return await serve(self._handle, "127.0.0.1", self.port, process_request=process_request,
                               max_size=2**20)

        self.server = asyncio.run_coroutine_threadsafe(start(), self.loop).result(10)
        self.port = self.server.sockets[0].getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}/"
        return self

    def __exit__(self, *exc) -> None:
        async def stop():
            self.server.close()
            await self.server.wait_closed()

        asyncio.run_coroutine_threadsafe(stop(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()
