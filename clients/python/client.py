#!/usr/bin/env python3
"""Example dimgestor client (protocol v1 revision 7, docs/protocol.md): print frames, optionally send a WAV or the mic.

    python clients/python/client.py                                # watch the server's source
    python clients/python/client.py --wav speech.wav --binary      # own session from a WAV file
    python clients/python/client.py --mic                          # own session from the microphone (Ctrl-C ends)
    python clients/python/client.py --save DIR --frames 50         # keep every message verbatim (NNNNNN.json/.bin)
    python clients/python/client.py --wav speech.wav --bvh out.bvh  # the frames received, as a BVH file
    python clients/python/client.py --wav speech.wav --face arkit --face-csv face.csv  # the face, as a CSV file

Needs `websockets` and `numpy`; `--mic` also needs `sounddevice`.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import signal
import struct
import sys
import wave
from collections import deque
from pathlib import Path
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import numpy as np
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosedError, InvalidStatus

BINARY_HEADER = struct.Struct("<4sId3f")  # magic, index, pts, root xyz: 28 bytes, then J*4 float32 wxyz
CHUNK_S = 0.02  # audio message length: small enough for latency, large enough for little overhead
FAST_CHUNK_S = 1.0  # --fast: messages of about a second (docs/protocol.md, Audio), few and small enough to pause
AHEAD_S = 10.0  # a file is sent at most this far ahead of the pts of the last frame back (self-clocked)
RESUME_WITHIN_S = 10.0  # after a goaway: connections tried for this long before the stream starts again
MIC_HOLD_S = 10.0  # microphone audio held while the server has us paused; beyond it the oldest is dropped, counted


def decode_binary_frame(buf: bytes, hello: dict | None = None) -> dict:
    """Decode a DGF1 binary frame into the same dict a JSON frame parses to. With the server's hello the frame has
    its joint count of rotations, then each of `hello["channels"]` (revision 6; after a `channels` message, its
    layout) at its offset; without it every byte after the header is a rotation (a frame without channels). The
    face channel (revision 7) becomes `"face": {name: weight}`, as in a JSON frame."""
    channels = (hello or {}).get("channels") or []
    joints = len(hello["skeleton"]["joints"]) if hello else (len(buf) - BINARY_HEADER.size) // 16
    end = max([BINARY_HEADER.size + 16 * joints] + [c["offset"] + 4 * c["size"] for c in channels])
    if len(buf) < end or (hello is None and (len(buf) - BINARY_HEADER.size) % 16):
        raise ValueError(f"binary frame of {len(buf)} bytes is not 28 + 16*J + the hello's channels")
    magic, index, pts, *root = BINARY_HEADER.unpack_from(buf)
    if magic != b"DGF1":
        raise ValueError(f"binary frame magic {magic!r}, expected b'DGF1'")
    rotations = np.frombuffer(buf, "<f4", count=4 * joints, offset=BINARY_HEADER.size).reshape(-1, 4)
    msg = {"type": "frame", "index": index, "pts": pts, "root": root, "rotations": rotations.tolist()}
    for c in channels:  # bytes past the last channel the layout names (a later revision's) are ignored
        values = np.frombuffer(buf, "<f4", count=c["size"], offset=c["offset"]).tolist()
        if c["name"] == "face" and c.get("labels"):
            msg["face"] = dict(zip(c["labels"], values))
        else:
            msg.setdefault("channels", {})[c["name"]] = values
    return msg


def read_wav(path: str) -> tuple[np.ndarray, int]:
    """Integer-PCM WAV -> (float32 samples (n, channels) in -1..1, rate). Errors name the file."""
    try:
        with wave.open(path, "rb") as w:
            width, channels, rate = w.getsampwidth(), w.getnchannels(), w.getframerate()
            raw = w.readframes(w.getnframes())
    except FileNotFoundError:
        raise SystemExit(f"{path}: no such file")
    except (wave.Error, EOFError) as e:
        raise SystemExit(f"{path}: not a PCM WAV file ({e}); convert it, e.g. `sox {path} -b 16 out.wav`")
    if width == 3:  # 24-bit: widen to int32 by putting the bytes in the top three
        b = np.frombuffer(raw, np.uint8).reshape(-1, 3)
        raw = (np.pad(b, ((0, 0), (1, 0))).view("<i4")).tobytes()
        width = 4
    dtype = {1: np.uint8, 2: "<i2", 4: "<i4"}[width]
    x = np.frombuffer(raw, dtype).astype(np.float32)
    x = (x - 128.0) / 128.0 if width == 1 else x / float(2 ** (8 * width - 1))
    return x.reshape(-1, channels), rate


def with_token(url: str, token: str | None) -> str:
    if not token:
        return url
    parts = urlsplit(url)
    query = dict(parse_qsl(parts.query), token=token)
    return urlunsplit(parts._replace(query=urlencode(query)))


class AudioFlow:
    """When our audio may go out (docs/protocol.md, Audio): not between a `slow_down` and its `resume`, and
    never more than `ahead_s` seconds beyond the pts of the last frame of our own session (self-clocked:
    the server's 30 s backlog is then never reached, so it never has to hold our socket, pings included)."""

    def __init__(self, ahead_s: float = float("inf")):
        self.ahead_s = ahead_s
        self.sent_s = 0.0  # audio sent in this session, seconds
        self.heard_s = 0.0  # pts of the last frame of our own session, plus one frame
        self.frames = 0  # frames of our own session received (after a fresh restart: counted on from before)
        self.offset_s = 0.0  # a fresh stream after a lost worker starts at pts 0 this far into our audio
        self.saved: dict | None = None  # the server's last `session_saved` (--save-state-every): resumable
        self.own = False  # our session's frames have begun (a frame with index 0 after our first audio)
        self.paused = False
        self.pauses = 0
        self.refused: str | None = None  # the server will not take our audio (busy, ...): stop sending
        self.changed = asyncio.Event()

    def on_message(self, msg: dict, fps: float) -> None:
        kind = msg.get("type")
        if kind == "error" and msg.get("code") == "slow_down":
            self.paused, self.pauses = True, self.pauses + 1
        elif kind == "resume":
            self.paused = False
        elif kind == "error" and msg.get("code") in ("busy", "audio_disabled", "internal"):
            self.refused = msg["code"]
        elif kind == "session_saved":
            self.saved = msg
            return
        elif kind == "frame" and self.sent_s > 0:
            # Frames of the broadcast we followed before our audio may still come; ours start at index 0.
            self.own = self.own or msg["index"] == 0
            if self.own:
                self.heard_s = max(self.heard_s, self.offset_s + msg["pts"] + 1.0 / fps)
                self.frames = max(self.frames, round(self.offset_s * fps) + msg["index"] + 1)
        else:
            return
        self.changed.set()

    def on_resumed(self, sent_s: float, heard_s: float) -> None:
        """A new connection after a goaway: our audio goes on from sent_s, the frames from heard_s."""
        self.sent_s, self.heard_s, self.paused, self.refused = sent_s, heard_s, False, None
        self.changed.set()

    def on_restarted(self, at_s: float) -> None:
        """A new connection after the worker was lost: a fresh stream of our audio from at_s, its pts from 0."""
        self.offset_s, self.own, self.saved = at_s, False, None
        self.on_resumed(at_s, at_s)

    def may_send(self) -> bool:
        return self.refused is not None or (not self.paused and self.sent_s - self.heard_s < self.ahead_s)

    async def ready(self) -> None:
        while not self.may_send():
            self.changed.clear()
            await self.changed.wait()


def quat_to_euler_zxy(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) wxyz -> BVH "Zrotation Xrotation Yrotation" angles in degrees (..., 3), z x y:
    the rotation is Rz(z) Rx(x) Ry(y), as a BVH reader composes the channels in the order they are listed."""
    w, x, y, z = np.moveaxis(np.asarray(q, np.float64), -1, 0)
    r01 = 2 * (x * y - w * z)
    r11 = 1 - 2 * (x * x + z * z)
    r20 = 2 * (x * z - w * y)
    r21 = 2 * (y * z + w * x)
    r22 = 1 - 2 * (x * x + y * y)
    ax = np.arcsin(np.clip(r21, -1.0, 1.0))
    ay = np.arctan2(-r20, r22)
    az = np.arctan2(-r01, r11)
    return np.degrees(np.stack([az, ax, ay], axis=-1))


class BvhWriter:
    """--bvh OUT: the frames of our own session, by index (a resumed session goes on at the next index), written
    as a BVH file of the hello's skeleton (its units, 20 fps) when the client stops."""

    def __init__(self, path: str):
        self.path = Path(path)
        self.skeleton: dict | None = None
        self.fps = 20.0
        self.frames: dict[int, tuple[list, list]] = {}

    def add(self, msg: dict, offset: int = 0) -> None:
        self.frames[offset + msg["index"]] = (msg["root"], msg["rotations"])

    def write(self) -> int:
        """Write the file (frames in index order, a gap filled with the frame before it) -> frames written."""
        if not self.frames or self.skeleton is None:
            return 0
        names, parents = self.skeleton["joints"], self.skeleton["parents"]
        offsets = np.asarray(self.skeleton["offsets"], np.float64)
        children = {j: [k for k, p in enumerate(parents) if p == j] for j in range(len(names))}
        lines = ["HIERARCHY"]

        order: list[int] = []

        def joint(j: int, depth: int) -> None:
            order.append(j)
            pad = "\t" * depth
            lines.append(f"{pad}{'ROOT' if parents[j] < 0 else 'JOINT'} {names[j]}")
            lines.append(f"{pad}{{")
            lines.append(f"{pad}\tOFFSET " + " ".join(f"{v:.6f}" for v in offsets[j]))
            lines.append(f"{pad}\tCHANNELS " + ("6 Xposition Yposition Zposition " if parents[j] < 0 else "3 ")
                         + "Zrotation Xrotation Yrotation")
            for k in children[j]:
                joint(k, depth + 1)
            if not children[j]:
                lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET 0.000000 0.000000 0.000000",
                              f"{pad}\t}}"])
            lines.append(f"{pad}}}")

        joint(parents.index(-1), 0)
        if order != list(range(len(names))):  # a BVH lists channels in hierarchy order: it must be the joints'
            raise ValueError("the hello's joints are not in depth-first order: cannot write them as BVH")
        last = max(self.frames)
        roots, rotations, previous = [], [], self.frames[min(self.frames)]
        for i in range(last + 1):
            previous = self.frames.get(i, previous)
            roots.append(previous[0])
            rotations.append(previous[1])
        angles = quat_to_euler_zxy(np.asarray(rotations))  # (T, J, 3)
        angles = np.degrees(np.unwrap(np.radians(angles), axis=0))  # no 360-degree jumps between frames
        # channel order: parents come first in the hello's joint order, which is the file's depth-first order
        values = np.concatenate([np.asarray(roots, np.float64), angles.reshape(len(angles), -1)], axis=1)
        lines += ["MOTION", f"Frames: {len(values)}", f"Frame Time: {1.0 / self.fps!r}"]
        lines += [" ".join(f"{v:.6f}" for v in row) for row in values]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text("\n".join(lines) + "\n")
        return len(values)


class FaceCsv:
    """--face-csv OUT: the face of the frames of our own session (or of the broadcast we follow), by index, written
    when the client stops: a header `time,` + the set's names, then one row per frame (time = index / fps)."""

    def __init__(self, path: str):
        self.path = Path(path)
        self.fps = 20.0
        self.names: list[str] | None = None
        self.rows: dict[int, dict] = {}

    def add(self, msg: dict, offset: int = 0) -> None:
        if "face" in msg:
            self.names = self.names or list(msg["face"])
            self.rows[offset + msg["index"]] = msg["face"]

    def write(self) -> int:
        """Write the file (frames in index order) -> rows written."""
        if not self.rows:
            return 0
        lines = [",".join(["time", *self.names])]
        for i in sorted(self.rows):
            lines.append(",".join([f"{i / self.fps:.4f}", *(f"{self.rows[i].get(n, 0.0):.4f}" for n in self.names)]))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text("\n".join(lines) + "\n")
        return len(self.rows)


class Printer:
    """Prints messages (and saves them verbatim with --save); counts frames."""

    def __init__(self, args):
        self.args, self.frames, self.count, self.skeleton, self.fps = args, 0, 0, None, 20.0
        self.hello: dict | None = None  # the server's: the binary frame layout
        self.save = Path(args.save) if args.save else None
        if self.save:
            self.save.mkdir(parents=True, exist_ok=True)

    def handle(self, message: str | bytes) -> dict:
        if self.save:
            name = f"{self.count:06d}." + ("bin" if isinstance(message, bytes) else "json")
            mode = "wb" if isinstance(message, bytes) else "w"
            with open(self.save / name, mode) as f:
                f.write(message)
        self.count += 1
        msg = decode_binary_frame(message, self.hello) if isinstance(message, bytes) else json.loads(message)
        kind = msg.get("type")
        if kind == "frame":
            self.frames += 1
            if not self.args.quiet:
                root = ", ".join(f"{v:7.2f}" for v in msg["root"])
                name = self.skeleton[1] if self.skeleton and len(self.skeleton) > 1 else "joint 1"
                q = ", ".join(f"{v:+.3f}" for v in msg["rotations"][min(1, len(msg["rotations"]) - 1)])
                extra = "".join(f"  {k} [{', '.join(f'{v:+.3f}' for v in vals[:3])}{', ...' if len(vals) > 3 else ''}]"
                                for k, vals in msg.get("channels", {}).items())
                if msg.get("face"):
                    face = [f"{k} {v:.2f}" for k, v in msg["face"].items()]
                    extra += f"  face {', '.join(face[:5])}" + (", ..." if len(face) > 5 else "")
                print(f"frame {msg['index']:5d}  pts {msg['pts']:7.3f}  root [{root}]  {name} [{q}]{extra}")
        elif kind == "hello":
            self.hello = msg
            self.skeleton, self.fps = msg["skeleton"]["joints"], float(msg.get("fps", self.fps))
            print(f"hello: {msg.get('server')} protocol {msg.get('protocol')}, {len(self.skeleton)} joints "
                  f"({msg['skeleton'].get('units')}), {msg.get('fps')} fps, lookahead {msg.get('lookahead_s')} s, "
                  f"audio {msg.get('audio')}"
                  + "".join(f", channel {c['name']} ({c['size']} values)" for c in msg.get("channels") or [])
                  + (f", face in {msg['face']['names']} names (sets {', '.join(msg['face']['sets'])})"
                     if msg.get("face") else "")
                  + (f", speakers {', '.join(msg['speakers']['names']) or 'none'} (default "
                     f"{msg['speakers']['default'] or 'none in particular'})" if msg.get("speakers") else ""))
        elif kind == "channels":  # (revision 7) the binary frames' layout from the next frame on
            self.hello = {**(self.hello or {}), "channels": msg["channels"]}
            if not self.args.quiet:
                print("channels: " + (", ".join(f"{c['name']} ({c['size']} values at byte {c['offset']})"
                                                for c in msg["channels"]) or "none"))
        elif kind == "status" and not self.args.quiet:
            print(f"status: latency {msg.get('latency_ms')} ms, rtf {msg.get('rtf')}, sent {msg.get('frames_sent')}, "
                  f"dropped {msg.get('dropped')}, clients {msg.get('clients')}")
        elif kind == "error" and msg.get("code") == "face_withheld":  # a notice: admitted, without a face
            print(f"face_withheld: this session's frames carry no face ({msg.get('message')})")
        elif kind == "error" and msg.get("code") == "slow_down":  # a notice: nothing was lost
            print(f"slow_down: pausing our audio until resume ({msg.get('message')})")
        elif kind == "resume":
            print(f"resume: the server's backlog of our audio is down to {msg.get('backlog_s')} s; sending again")
        elif kind in ("error", "end"):
            print(f"{kind}: {json.dumps({k: v for k, v in msg.items() if k != 'type'})}")
        return msg


def client_hello(binary: bool, audio: dict | None = None, asks: dict | None = None) -> str:
    """Our hello; every hello states the encoding, since a later hello replaces the earlier one. `asks`: what else
    we ask (`hello_asks`)."""
    hello = {"type": "hello", "protocol": 1, "encoding": "binary" if binary else "json"}
    if audio:
        hello["audio"] = audio
    return json.dumps({**hello, **(asks or {})})


def hello_asks(args) -> dict:
    """The hello fields of our options: `face`, the name set our frames' face is in (revision 7; binary frames carry
    it only once asked) or "none"; `speaker`, the speaker our sessions play (revision 9), or null for none."""
    asks = {"face": args.face} if args.face else {}
    if args.speaker is not None:
        asks["speaker"] = None if args.speaker == "" else args.speaker
    return asks


async def send_wav(ws, audio: np.ndarray, rate: int, pace: bool, binary: bool, flow: AudioFlow, start: int = 0,
                   hello: bool = True, asks: dict | None = None) -> None:
    """Send audio[start:] (paced like a talker unless not pace), then audio_end."""
    if hello:
        await ws.send(client_hello(binary, wav_format(audio, rate), asks))
    step = max(1, int(rate * (CHUNK_S if pace else FAST_CHUNK_S)))
    for i in range(start, len(audio), step):
        await flow.ready()  # paused by slow_down, or too far ahead of the frames we got back
        if flow.refused:
            break  # (audio_end below: the server answers `end`)
        chunk = audio[i:i + step]
        await ws.send(chunk.astype("<f4").tobytes())
        flow.sent_s += len(chunk) / rate
        if pace:  # like a live talker
            await asyncio.sleep(CHUNK_S)
    await ws.send(json.dumps({"type": "audio_end"}))


def wav_format(audio: np.ndarray, rate: int) -> dict:
    return {"rate": rate, "format": "float32", "channels": audio.shape[1]}


async def resume_session(ws, goaway: dict, binary: bool, audio: np.ndarray, rate: int, asks: dict | None = None) -> int:
    """After a `goaway`: on a new connection, hello and resume_session with its token; returns the audio sample
    to send from (the server's `session_resumed`). Raises ResumeFailed when the server cannot resume it."""
    await ws.send(client_hello(binary, wav_format(audio, rate), asks))
    await ws.send(json.dumps({"type": "resume_session", "token": goaway["resume_token"]}))
    async for message in ws:
        msg = json.loads(message) if isinstance(message, str) else {}
        if msg.get("type") == "session_resumed":
            return int(msg["samples"])
        if msg.get("type") == "error":
            code = msg.get("code")
            # busy: a stopping or full worker; session_live: the server does not yet see our lost connection
            # as gone (a crashed worker's lease runs out within seconds)
            raise ResumeFailed(f"{code}: {msg.get('message')}", retry=code in ("busy", "session_live"),
                               after_s=float(msg.get("retry_after_s", 0.1)) if code == "session_live" else 0.1)
    raise ResumeFailed("the connection closed before session_resumed", retry=True)


class ResumeFailed(Exception):
    def __init__(self, message: str, retry: bool = False, after_s: float = 0.1):
        super().__init__(message)
        self.retry = retry  # the token is still good: another worker (or this one, later) may resume it
        self.after_s = min(max(after_s, 0.1), 5.0)  # ... after this long


def open_mic(device: str | None, rate: int | None) -> tuple[int | str | None, int]:
    """--device (index or name part) and --rate checked before we connect: (device, a rate it captures at)."""
    try:
        import sounddevice as sd  # only needed here
    except (ImportError, OSError) as e:
        raise SystemExit(f"--mic needs the sounddevice package and PortAudio ({e})")
    dev = int(device) if device is not None and device.isdigit() else device
    try:
        info = sd.query_devices(dev, "input")
    except (sd.PortAudioError, ValueError) as e:
        why = " ".join(str(e).split())
        raise SystemExit(f"no input device {device!r}: {why} (list them: python -m sounddevice)" if device is not None
                         else f"no default input device ({why}); pick one with --device")
    rate = int(rate or info["default_samplerate"])
    try:
        sd.check_input_settings(dev, channels=1, samplerate=rate, dtype="float32")
    except (sd.PortAudioError, ValueError) as e:
        raise SystemExit(f"input device {info['name']!r} cannot capture at {rate} Hz ({e}); "
                         f"its default rate is {info['default_samplerate']:.0f} Hz (--rate)")
    return dev, rate


class MicHold:
    """Microphone chunks not sent yet (paused by `slow_down`, or a stalled socket): at most `hold_s` seconds;
    beyond that the oldest go, and are counted (a live talker wants now, not what it said long ago)."""

    def __init__(self, rate: int, hold_s: float = MIC_HOLD_S):
        self.rate, self.max_samples = rate, int(hold_s * rate)
        self.chunks: deque[bytes] = deque()
        self.samples = 0
        self.dropped_samples = 0

    def add(self, data: bytes) -> None:
        self.chunks.append(data)
        self.samples += len(data) // 4
        while self.samples > self.max_samples:
            old = self.chunks.popleft()
            self.samples -= len(old) // 4
            self.dropped_samples += len(old) // 4

    def take(self) -> bytes:
        data = self.chunks.popleft()
        self.samples -= len(data) // 4
        return data

    @property
    def dropped_s(self) -> float:
        return self.dropped_samples / self.rate


async def send_mic(ws, rate: int, device, binary: bool, flow: AudioFlow, asks: dict | None = None) -> MicHold:
    import sounddevice as sd

    loop = asyncio.get_running_loop()
    hold = MicHold(rate)

    def on_audio(indata, frames, time, status):
        data = indata[:, 0].astype("<f4").tobytes()
        def put():
            dropped = hold.dropped_samples
            hold.add(data)
            if hold.dropped_samples and not dropped:
                print(f"microphone: the server has held us back for {MIC_HOLD_S:.0f} s; dropping the oldest audio "
                      f"(counted, reported at the end)", file=sys.stderr)
            flow.changed.set()
        loop.call_soon_threadsafe(put)

    await ws.send(client_hello(binary, {"rate": rate, "format": "float32", "channels": 1}, asks))
    print(f"microphone: {rate} Hz; Ctrl-C to stop", file=sys.stderr)
    with sd.InputStream(samplerate=rate, channels=1, dtype="float32", blocksize=int(rate * CHUNK_S),
                        device=device, callback=on_audio):
        try:
            while True:
                while not (hold.chunks and not flow.paused) and not flow.refused:  # paused: they wait in `hold`
                    flow.changed.clear()
                    await flow.changed.wait()
                if flow.refused:
                    break
                data = hold.take()
                await ws.send(data)
                flow.sent_s += len(data) / 4 / rate
        except asyncio.CancelledError:
            pass
    # Stopped (Ctrl-C): what is held goes too, after the server's `resume` if it has us paused; then audio_end.
    while flow.paused and not flow.refused:
        flow.changed.clear()
        await flow.changed.wait()
    while hold.chunks and not flow.refused:
        await ws.send(hold.take())
    await ws.send(json.dumps({"type": "audio_end"}))
    return hold


RETRY_STATUS = (502, 503, 504)  # a balancer with no worker free right now, a worker that is stopping


async def first_connection(urls: list[str], token: str | None, within_s: float = 10.0):
    """Our first connection: a refused connection or a 502/503/504 (a rolling restart under way) is tried again,
    the URLs in turn, for up to within_s; any other refusal (401, 403, ...) at once is final."""
    loop = asyncio.get_running_loop()
    deadline, delay, attempt = loop.time() + within_s, 0.05, 0
    while True:
        try:
            return await connect(with_token(urls[attempt % len(urls)], token), max_size=8 * 2**20, open_timeout=5.0)
        except (OSError, InvalidStatus) as e:
            retry = not isinstance(e, InvalidStatus) or e.response.status_code in RETRY_STATUS
            if not retry or loop.time() + delay > deadline:
                raise
        attempt += 1
        await asyncio.sleep(delay)
        delay = min(delay * 2, 0.5)


async def reconnect(urls: list[str], token: str | None, attempt: int, within_s: float = 10.0):
    """A new connection after a goaway: the URLs in turn (a balancer's one URL, or workers named one by one),
    retried with a short back-off for up to within_s."""
    loop = asyncio.get_running_loop()
    deadline, delay, last = loop.time() + within_s, 0.05, None
    while loop.time() < deadline:
        url = urls[attempt % len(urls)]
        attempt += 1
        try:
            return await connect(with_token(url, token), max_size=8 * 2**20, open_timeout=2.0)
        except (OSError, InvalidStatus, asyncio.TimeoutError) as e:
            last = e
            await asyncio.sleep(delay)
            delay = min(delay * 2, 0.5)
    raise OSError(f"could not reconnect within {within_s:g} s: {last!r}")


async def run(args) -> int:
    printer = Printer(args)
    bvh = BvhWriter(args.bvh) if args.bvh else None
    face_csv = FaceCsv(args.face_csv) if args.face_csv else None
    wav = read_wav(args.wav) if args.wav else None  # a bad file or device fails before we connect
    mic = open_mic(args.device, args.rate) if args.mic else None
    flow = AudioFlow(AHEAD_S if args.wav else float("inf"))  # a microphone is clocked by the talker
    urls = args.url if isinstance(args.url, list) else [args.url]
    ws = await first_connection(urls, args.token)
    start, hello, resumes, lost = 0, True, 0, 0
    try:
        while True:  # one connection; a goaway with a resume token (the worker is stopping) goes on on another
            try:
                result = await _connection(ws, args, printer, flow, wav, mic, start, hello, bvh, face_csv)
            except ConnectionClosedError as e:  # no goaway, no close frame: the worker died (or the network)
                if not args.wav:
                    raise
                lost += 1
                why = e.rcvd.code if e.rcvd else "no close frame"
                if flow.saved is None:
                    ws = await reconnect(urls, args.token, resumes + lost)
                    start = flow.frames * wav[1] // round(printer.fps)  # the audio of the first frame we lack
                    print(f"connection lost ({why}): a fresh stream from sample {start} (frame {flow.frames})",
                          file=sys.stderr)
                    flow.on_restarted(start / wav[1])
                    hello = True
                    continue
                # the server saved our session lately (--save-state-every): resume from there, exactly; the
                # frames after the save come again (the same ones: --bvh keeps one per index)
                print(f"connection lost ({why}): resuming from the last saved state (frame "
                      f"{flow.saved['frames']})", file=sys.stderr)
                result = flow.saved
            if not isinstance(result, dict):
                return result
            goaway, flow.saved = result, None
            await ws.close()
            if not goaway.get("resume_token"):  # the worker could not save our session: start afresh elsewhere
                ws = await reconnect(urls, args.token, resumes + lost + 1)
                start = flow.frames * wav[1] // round(printer.fps)  # the audio of the first frame we lack
                print(f"goaway without a token ({goaway.get('message', 'not saved')}): a fresh stream from sample "
                      f"{start} (frame {flow.frames})", file=sys.stderr)
                flow.on_restarted(start / wav[1])
                lost, hello = lost + 1, True
                continue
            loop = asyncio.get_running_loop()
            deadline = loop.time() + RESUME_WITHIN_S
            base = round(flow.offset_s * wav[1])  # where this session's audio began in the file
            while True:  # a worker that is stopping too (or full) answers busy: the token stays good elsewhere
                resumes += 1
                ws = await reconnect(urls, args.token, resumes, max(0.5, deadline - loop.time()))
                try:
                    start = base + await resume_session(ws, goaway, args.binary, *wav, asks=hello_asks(args))
                    print(f"resumed from sample {start} (frame {flow.frames})", file=sys.stderr)
                    flow.on_resumed(start / wav[1], base / wav[1] + goaway.get("frames", 0) / printer.fps)
                    break
                except ResumeFailed as e:
                    if e.retry and loop.time() + e.after_s < deadline:
                        print(f"resume refused ({e}): trying again in {e.after_s:.1f} s", file=sys.stderr)
                        await ws.close()
                        await asyncio.sleep(e.after_s)
                        continue
                    start = flow.frames * wav[1] // round(printer.fps)  # the audio of the first frame we lack
                    print(f"resume failed ({e}): a fresh stream from sample {start} (frame {flow.frames})",
                          file=sys.stderr)
                    flow.on_restarted(start / wav[1])
                    break
            hello = False  # resume_session sent it
    finally:
        await ws.close()
        if bvh is not None:
            written = bvh.write()
            print(f"wrote {written} frames to {bvh.path}" if written else f"no frames came: {bvh.path} not written",
                  file=sys.stderr)
        if face_csv is not None:
            written = face_csv.write()
            print(f"wrote the face of {written} frames to {face_csv.path}" if written else
                  f"no face came: {face_csv.path} not written (the server runs --face none, or before revision 7)",
                  file=sys.stderr)


async def _connection(ws, args, printer, flow, wav, mic, start: int = 0, hello: bool = True, bvh=None, face_csv=None):
    """One connection: send our audio (a WAV from sample `start`), print what comes. Returns the exit status,
    or the `goaway` message when the server hands our session over (only with --wav, which can re-send)."""
    sender = None
    if args.wav:
        sender = asyncio.create_task(send_wav(ws, *wav, not args.fast, args.binary, flow, start, hello,
                                                hello_asks(args)))
    elif args.mic:
        sender = asyncio.create_task(send_mic(ws, mic[1], mic[0], args.binary, flow, hello_asks(args)))
        loop = asyncio.get_running_loop()

        def stop_talking():  # first Ctrl-C: (held audio and) audio_end, wait for the last frames; second: quit
            loop.remove_signal_handler(signal.SIGINT)
            sender.cancel()
        loop.add_signal_handler(signal.SIGINT, stop_talking)
    elif args.binary or hello_asks(args):
        await ws.send(client_hello(args.binary, asks=hello_asks(args)))
    goaway = None

    async def receive():
        nonlocal goaway
        fps = 20.0
        async for message in ws:
            msg = printer.handle(message)
            fps = msg.get("fps", fps) if msg.get("type") == "hello" else fps
            flow.on_message(msg, fps)
            if bvh is not None:
                if msg.get("type") == "hello":
                    bvh.skeleton, bvh.fps = msg["skeleton"], float(msg.get("fps", bvh.fps))
                elif msg.get("type") == "frame" and (flow.own or not (args.wav or args.mic)):
                    bvh.add(msg, round(flow.offset_s * fps))  # our own session's (or the broadcast we follow)
            if face_csv is not None:
                if msg.get("type") == "hello":
                    face_csv.fps = float(msg.get("fps", face_csv.fps))
                elif msg.get("type") == "frame" and (flow.own or not (args.wav or args.mic)):
                    face_csv.add(msg, round(flow.offset_s * fps))
            if msg.get("type") == "goaway" and args.wav:  # (the worker stops; no token: it could not save us)
                goaway = msg
                return
            if msg.get("type") == "end" and args.wav and not sender.done():
                continue  # before our audio_end: the stray `end` earlier servers sent after a resume_failed
            if msg.get("type") == "end" or (args.frames and printer.frames >= args.frames):
                return
    try:
        await asyncio.wait_for(receive(), args.seconds or None)
    except asyncio.TimeoutError:
        pass  # --seconds elapsed
    finally:
        if sender and not sender.done():
            sender.cancel()
            await asyncio.gather(sender, return_exceptions=True)
    if goaway is not None:
        return goaway
    if sender and sender.done() and not sender.cancelled() and sender.exception():
        print(f"sending audio failed: {sender.exception()!r}", file=sys.stderr)
        return 1
    notes = [f"paused {flow.pauses} times at slow_down"] if flow.pauses else []
    hold = sender.result() if args.mic and sender and sender.done() and not sender.cancelled() else None
    if hold is not None and hold.dropped_samples:
        notes.append(f"dropped {hold.dropped_s:.2f} s of microphone audio held back beyond {MIC_HOLD_S:.0f} s")
    print(f"received {printer.frames} frames" + "".join(f"; {n}" for n in notes), file=sys.stderr)
    return 0


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--url", action="append", help="server WebSocket URL (default ws://127.0.0.1:8765/); repeat it "
                   "to name workers without a balancer: after a goaway the next one is tried")
    p.add_argument("--token", help="access token, when the server was started with --token")
    p.add_argument("--binary", action="store_true", help="ask for DGF1 binary frames instead of JSON")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--wav", help="send this WAV as our own audio session, then audio_end")
    src.add_argument("--mic", action="store_true", help="send the microphone (sounddevice) until Ctrl-C")
    p.add_argument("--fast", action="store_true", help="with --wav: send as fast as the server reads")
    p.add_argument("--rate", type=int, help="with --mic: capture rate (default: the device's)")
    p.add_argument("--device", default=None, help="with --mic: input device index or name part (python -m sounddevice)")
    p.add_argument("--frames", type=int, default=0, help="stop after this many frames (0: until end)")
    p.add_argument("--seconds", type=float, default=0, help="stop after this many seconds (0: no limit)")
    p.add_argument("--save", help="write every received message verbatim into this folder")
    p.add_argument("--bvh", metavar="OUT", help="write the frames received as a BVH file (the hello's skeleton; "
                   "a resumed session's frames go on in the same file)")
    p.add_argument("--face", choices=("vrm0", "vrm1", "arkit", "oculus", "none"),
                   help="ask for the face in these blendshape names (revision 7; binary frames carry it only when "
                   "asked), or none for no face (default: the server's set, JSON frames only)")
    p.add_argument("--speaker", metavar="NAME", help="our sessions play this speaker's style, of a server whose "
                   "model has several (revision 9: its hello lists them); \"\" for none in particular (default: "
                   "the server's)")
    p.add_argument("--face-csv", metavar="OUT", help="write the face of the frames received as a CSV file: time, then "
                   "one column per name (asks for --face, vrm0 when not given)")
    p.add_argument("--quiet", action="store_true", help="print only hello, errors and the end")
    args = p.parse_args(argv)
    args.url = args.url or ["ws://127.0.0.1:8765/"]
    if args.face_csv and args.face == "none":
        p.error("--face-csv needs a face: not --face none")
    if args.face_csv and not args.face:
        args.face = "vrm0"
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        return asyncio.run(run(args))
    except KeyboardInterrupt:
        return 0
    except InvalidStatus as e:
        code = e.response.status_code
        hint = " (wrong or missing --token)" if code == 401 else ""
        print(f"{args.url[0]} refused the connection: HTTP {code}{hint}", file=sys.stderr)
        return 1
    except OSError as e:
        print(f"cannot connect to {args.url[0]}: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
