"""Protocol v1 messages (docs/protocol.md) as pure functions: build, encode, parse and validate; no sockets."""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from dimgestor import __version__
from dimgestor.audio import SAMPLE_RATE
from dimgestor.face.names import NAME_SETS, check_name_set, names_of
from streamer.face import FACE
from streamer.frames import Channel, Frame, channel_values

PROTOCOL = 1
SERVER = f"dimgestor/{__version__}"
AUDIO_FORMATS = ("pcm16", "float32")
AUDIO_RATE = SAMPLE_RATE  # the model's input rate; server source audio is sent at this rate
MAX_TEXT_BYTES = 64 * 1024
MAX_JSON_DEPTH = 16  # nesting of objects/arrays in a client message
MAX_NUMBER_CHARS = 32  # digits of one JSON number (Python would parse 4300-digit integers)
MIN_RATE, MAX_RATE = 8000, 192000  # accepted client audio sample rates, Hz
MAX_AUDIO_ABS = 4.0  # float32 samples beyond this are not -1..1 audio (wrong format or scale): refused
MAX_BINARY_BYTES = 1024 * 1024
HARD_MAX_BYTES = 4 * 1024 * 1024  # above this the WebSocket layer closes the connection (1009)
FRAME_MAGIC = b"DGF1"
FRAME_HEADER = struct.Struct("<4sId3f")  # magic, index, pts, root xyz: 28 bytes, then float32[J * 4], channels
REVISION = 9  # protocol 1 revisions add optional fields and messages only (docs/protocol.md, "Revisions")
MAX_SPEAKER_CHARS = 128  # a speaker's name in a client hello (revision 9), at most
MAX_RIG_JOINTS = 512  # a client's rig (revision 8): joints at most (its hello must also fit MAX_TEXT_BYTES)
PARSE_ASIDE_BYTES = 2048  # a text message longer than this (a rig) is parsed on the worker thread, as its sender's work
MAX_REFUSED_RIGS = 8  # rigs refused on one connection before it is closed (1008): each also costs REFUSED_RIG_TOKENS
REFUSED_RIG_TOKENS = 125  # ...messages of the sender's budget (its next messages are read 0.5 s later)
MAX_RIG_OFFSET_M = 1000.0  # a client rig's offsets at most this far a side (a kilometre: finite poses on any chain)
FACE_DECIMALS = 4  # a JSON frame's face weights (0..1): 1e-4 is below what any rig shows
AUDIO_MAGIC = b"DGA1"
AUDIO_HEADER = struct.Struct("<4sId")  # magic, sample rate, pts of the first sample: 16 bytes, then int16[n]


# The WebSocket sink's channel map: the channels every frame sent to a client carries, in this order (after the
# rotations of a binary frame, under "channels" in a JSON frame), and what `hello.channels` announces. Empty: the
# frames are exactly those of revision 5. A new channel is one entry here (name -> its `Channel`), made before the
# server's hello is built (the hello announces the layout every frame then has). The face is not one of them: it
# is each client's own (its name set, asked in its hello: `streamer.client_session.ClientSession.channels`).
WS_CHANNELS: dict[str, Channel] = {}


class ProtocolError(ValueError):
    """A client message the server rejects; `code` is the error code sent back."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class SkeletonInfo:
    names: list[str]
    parents: list[int]
    offsets: np.ndarray  # (J, 3)
    units: str = "cm"
    rest_rotations: np.ndarray | None = None  # (J, 4) wxyz; None: identity (BVH skeletons)

    @classmethod
    def from_skeleton(cls, skeleton, units: str = "cm") -> "SkeletonInfo":
        return cls(list(skeleton.names), [int(p) for p in skeleton.parents],
                   np.asarray(skeleton.offsets, dtype=np.float64), units)


@dataclass(frozen=True)
class AudioFormat:
    rate: int = AUDIO_RATE
    format: str = "pcm16"
    channels: int = 1


def hello(skeleton: SkeletonInfo, humanoid: dict[str, str], fps: int, lookahead_s: float,
          accepts_audio: bool, **optional) -> dict:
    """The server's hello; `optional` adds the optional fields (window_ms, source, ...)."""
    j = len(skeleton.names)
    channels = channel_layout(j)
    return {
        "type": "hello", "protocol": PROTOCOL, "revision": REVISION, "server": SERVER, "fps": fps, "encoding": "json",
        "skeleton": {
            "joints": skeleton.names, "parents": skeleton.parents,
            "offsets": np.round(skeleton.offsets, 6).tolist(),
            "rest_rotations": ([[1.0, 0.0, 0.0, 0.0]] * j if skeleton.rest_rotations is None
                               else np.round(skeleton.rest_rotations, 6).tolist()),
            "units": skeleton.units, "handedness": "right", "up": "y",
        },
        "humanoid": humanoid,
        "audio": {"accepts": accepts_audio, "rate": AUDIO_RATE, "formats": list(AUDIO_FORMATS)},
        "lookahead_s": round(float(lookahead_s), 6),
        "max_message_bytes": MAX_BINARY_BYTES,
        "binary_frame_bytes": FRAME_HEADER.size + 16 * j + sum(4 * c["size"] for c in channels),
        "channels": channels,
        **optional,
    }


def speakers_hello(names, default: str | None, fixed: bool) -> dict:
    """`hello.speakers` (revision 9) of a server whose model has a speaker condition: the speakers a client may
    ask (`names`), the one its sessions play unless it asks (`default`, None: no speaker in particular); `fixed`:
    the server plays `default` only (its ONNX Runtime graph holds that speaker's vector)."""
    offered = ([] if default is None else [default]) if fixed else list(names)
    return {"names": offered, "default": default, "choice": not fixed}


def face_hello(name_set: str) -> dict:
    """`hello.face` (revision 7) of a server whose frames carry the face in `name_set`'s names by default."""
    return {"names": check_name_set(name_set), "sets": list(NAME_SETS), "labels": list(names_of(name_set))}


def channels_message(layout: list[dict]) -> str:
    """Revision 7: the binary layout (`channel_layout`) of this client's frames from the next one on."""
    return json.dumps({"type": "channels", "channels": layout}, separators=(",", ":"))


def channel_layout(joints: int, channels: Mapping[str, Channel] | None = None) -> list[dict]:
    """`hello.channels` (revision 6): each sent channel's name, size, byte offset in a binary frame of `joints`
    joints, and its labels and description where it has them."""
    at, out = FRAME_HEADER.size + 16 * joints, []
    for c in (WS_CHANNELS if channels is None else channels).values():
        out.append({"name": c.name, "size": c.size, "offset": at,
                    **({"labels": list(c.labels)} if c.labels else {}),
                    **({"description": c.description} if c.description else {})})
        at += 4 * c.size
    return out


def frame_json(frame: Frame, channels: Mapping[str, Channel] | None = None) -> str:
    msg = {
        "type": "frame", "index": frame.index, "pts": round(frame.pts, 6),
        "root": np.round(np.nan_to_num(frame.root_pos), 5).tolist(),
        "rotations": np.round(np.nan_to_num(frame.rotations), 6).tolist(),
    }  # nan_to_num: a model failure must not make unparseable JSON
    channels = WS_CHANNELS if channels is None else channels
    for c in channels.values():
        values = np.nan_to_num(channel_values(frame, c))
        if c.name == FACE and c.labels:  # revision 7: the face as weight by name, not under "channels"
            msg[FACE] = dict(zip(c.labels, np.round(values, FACE_DECIMALS).tolist()))
        else:
            msg.setdefault("channels", {})[c.name] = np.round(values, 6).tolist()
    return json.dumps(msg, separators=(",", ":"))


def frame_binary(frame: Frame, channels: Mapping[str, Channel] | None = None) -> bytes:
    head = FRAME_HEADER.pack(FRAME_MAGIC, frame.index, frame.pts, *map(float, frame.root_pos))
    parts = [head, np.ascontiguousarray(frame.rotations, dtype="<f4").tobytes()]
    for c in (WS_CHANNELS if channels is None else channels).values():
        parts.append(channel_values(frame, c).astype("<f4").tobytes())
    return b"".join(parts)


def encode_frames(frames: Sequence[Frame], encoding: str,
                  channels: Mapping[str, Channel] | None = None) -> list[str | bytes]:
    """A client's frame messages in its encoding ("json" or "binary") with its channels (None: `WS_CHANNELS`);
    a JSON frame carries the face channel as `"face": {name: weight}`."""
    channels = dict(WS_CHANNELS if channels is None else channels)  # one layout for the whole call
    if encoding == "binary":
        return [frame_binary(f, channels) for f in frames]
    return [frame_json(f, channels) for f in frames]


def parse_frame_binary(buf: bytes, joints: int | None = None, channels: Sequence[dict] = ()) -> dict:
    """Inverse of frame_binary (for clients and tests): {index, pts, root, rotations (J, 4), channels}.

    Without `joints` every byte after the header is a rotation (a revision 5 frame, or no channel sent); with
    `joints` and the hello's `channels` each channel is read at its offset, and bytes no channel names (a later
    revision's) are ignored."""
    if len(buf) < FRAME_HEADER.size:
        raise ValueError(f"not a DGF1 frame ({len(buf)} bytes)")
    magic, index, pts, *root = FRAME_HEADER.unpack_from(buf)
    rotation_bytes = len(buf) - FRAME_HEADER.size if joints is None else 16 * joints
    end = max([FRAME_HEADER.size + rotation_bytes] + [c["offset"] + 4 * c["size"] for c in channels])
    if magic != FRAME_MAGIC or rotation_bytes % 16 or len(buf) < end:
        raise ValueError(f"not a DGF1 frame of this layout ({len(buf)} bytes, magic {magic!r})")
    rot = np.frombuffer(buf, "<f4", count=rotation_bytes // 4, offset=FRAME_HEADER.size).reshape(-1, 4)
    values = {c["name"]: np.frombuffer(buf, "<f4", count=c["size"], offset=c["offset"]) for c in channels}
    return {"index": index, "pts": pts, "root": np.array(root), "rotations": rot, "channels": values}


def dumps(msg: dict) -> str:
    """JSON for the wire: finite numbers only (browsers cannot parse NaN or Infinity)."""
    return json.dumps(msg, allow_nan=False, separators=(",", ":"))


def source_audio_binary(pts: float, samples: np.ndarray, rate: int = AUDIO_RATE) -> bytes:
    """A DGA1 message: the server source's audio from `pts` on, PCM16 mono at `rate`."""
    pcm = np.clip(np.round(np.asarray(samples, np.float32) * 32767.0), -32768, 32767).astype("<i2")
    return AUDIO_HEADER.pack(AUDIO_MAGIC, rate, pts) + pcm.tobytes()


def parse_source_audio_binary(buf: bytes) -> dict:
    """Inverse of source_audio_binary (for clients and tests): {rate, pts, samples float32}."""
    magic, rate, pts = AUDIO_HEADER.unpack_from(buf)
    if magic != AUDIO_MAGIC or (len(buf) - AUDIO_HEADER.size) % 2:
        raise ValueError(f"not a DGA1 audio message ({len(buf)} bytes, magic {magic!r})")
    pcm = np.frombuffer(buf, "<i2", offset=AUDIO_HEADER.size)
    return {"rate": rate, "pts": pts, "samples": pcm.astype(np.float32) / 32767.0}


def status(latency_ms: float, rtf: float, frames_sent: int, dropped: int, clients: int, **optional) -> str:
    finite = lambda v, nd: round(v, nd) if np.isfinite(v) else 0.0  # noqa: E731
    return json.dumps({"type": "status", "latency_ms": finite(latency_ms, 2), "rtf": finite(rtf, 4),
                       "frames_sent": frames_sent, "dropped": dropped, "clients": clients, **optional})


def timing(first: int, frames: int, window, sent_s: float) -> str:
    """Revision 5: when one window's audio arrived, was dispatched and its `frames` frames from index `first`
    were sent, on the server's monotonic clock (s); `window` is a `streamer.sessions.WindowTiming`."""
    return json.dumps({"type": "timing", "first": first, "frames": frames,
                       "audio_until_s": round(window.audio_until_s, 6), "arrived_s": round(window.arrived_s, 6),
                       "dispatched_s": round(window.dispatched_s, 6), "sent_s": round(sent_s, 6)})


def error(code: str, message: str, retry_after_s: float | None = None) -> str:
    """An error reply; `retry_after_s`: when to try again (a `busy` at capacity)."""
    extra = {} if retry_after_s is None else {"retry_after_s": round(float(retry_after_s), 3)}
    return json.dumps({"type": "error", "code": code, **extra, "message": message})


def session_live(retry_after_s: float) -> str:
    """resume_session refused: the token's session is still live on a connection (a periodic-save token is for a
    lost connection only); try again after `retry_after_s`, once the server sees that connection gone."""
    return json.dumps({"type": "error", "code": "session_live", "retry_after_s": round(float(retry_after_s), 3),
                       "message": "this session is live on another connection: its token resumes it only once "
                                  "that connection is gone (try again after retry_after_s)"})


def end(frames: int) -> str:
    return json.dumps({"type": "end", "frames": frames})


def rig_reply(joints: int, humanoid: dict[str, str] | None, channels: list[dict]) -> str:
    """Revision 8: the client's rig is taken (`humanoid`: {HumanBodyBones name: its joint} recognised) and its
    frames from the next one on carry `joints` rotations (binary: `channels`' offsets); humanoid None: back on the
    server's skeleton."""
    msg = {"type": "rig", "joints": joints, "channels": channels}
    if humanoid is not None:
        msg["humanoid"] = humanoid
    return json.dumps(msg, separators=(",", ":"))


def resume(backlog_s: float) -> str:
    """After a `slow_down`: the client's backlog is down to `backlog_s` (at most half the cap); send again."""
    return json.dumps({"type": "resume", "backlog_s": round(float(backlog_s), 3)})


def goaway(token: str, samples: int, frames: int, rate: int) -> str:
    """The worker is stopping: the session's state is saved under `token`; reconnect, send resume_session and
    re-send the audio from sample `samples` (at the client's `rate`), the frames going on from `frames`."""
    return json.dumps({"type": "goaway", "reason": "restart", "resume_token": token, "samples": int(samples),
                       "rate": int(rate), "frames": int(frames)})


def goaway_unsaved(frames: int, why: str) -> str:
    """The worker is stopping and could not save the session (`why`): no token; reconnect and start a fresh
    stream with the audio of the first frame not received (the frames go on from 0 in the new session)."""
    return json.dumps({"type": "goaway", "reason": "restart", "resume_token": None, "frames": int(frames),
                       "message": f"the worker is stopping and {why}: connect again and start a fresh stream"})


def session_saved(token: str, samples: int, frames: int, rate: int) -> str:
    """A periodic save (--save-state-every): after a lost connection, resume_session with `token` goes on from
    sample `samples` (at `rate`) and frame `frames` of this session."""
    return json.dumps({"type": "session_saved", "resume_token": token, "samples": int(samples), "rate": int(rate),
                       "frames": int(frames)})


def session_resumed(samples: int, frames: int, rate: int) -> str:
    return json.dumps({"type": "session_resumed", "samples": int(samples), "rate": int(rate), "frames": int(frames)})


def _number(kind):
    def parse(text: str):
        if len(text) > MAX_NUMBER_CHARS:
            raise ProtocolError("bad_message", f"a number with {len(text)} characters (at most {MAX_NUMBER_CHARS})")
        value = kind(text)
        if kind is float and not np.isfinite(value):
            raise ProtocolError("bad_message", f"number {text[:20]} is out of range")
        return value
    return parse


def _constant(name: str):
    raise ProtocolError("bad_message", f"{name} is not a JSON number")


def _too_deep(value, limit: int) -> bool:
    """Whether a parsed JSON value nests containers more than `limit` levels deep (no recursion)."""
    level = [value]
    for _ in range(limit):
        level = [v for x in level if isinstance(x, (dict, list)) for v in (x.values() if isinstance(x, dict) else x)]
        if not any(isinstance(x, (dict, list)) for x in level):
            return False
    return True


def parse_text_or_error(text: str) -> dict | ProtocolError:
    """`parse_text`, its ProtocolError returned rather than raised (for a parse done on another thread)."""
    try:
        return parse_text(text)
    except ProtocolError as e:
        return e


def parse_text(text: str) -> dict:
    """A client text message -> a validated dict; raises ProtocolError("bad_message"/...)."""
    if len(text.encode("utf-8", "surrogatepass")) > MAX_TEXT_BYTES:
        raise ProtocolError("too_large", f"text messages are limited to {MAX_TEXT_BYTES} bytes")
    try:
        msg = json.loads(text, parse_int=_number(int), parse_float=_number(float), parse_constant=_constant)
    except json.JSONDecodeError as e:
        raise ProtocolError("bad_message", f"not JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    except RecursionError:  # the C parser's own guard (about 1000 levels)
        raise ProtocolError("bad_message", f"JSON nested more than {MAX_JSON_DEPTH} levels deep") from None
    if _too_deep(msg, MAX_JSON_DEPTH):
        raise ProtocolError("bad_message", f"JSON nested more than {MAX_JSON_DEPTH} levels deep")
    if not isinstance(msg, dict) or not isinstance(msg.get("type"), str):
        raise ProtocolError("bad_message", 'expected a JSON object with a "type" field')
    kind = msg["type"]
    if kind == "hello":
        return {"type": "hello", **_parse_hello(msg)}
    if kind in ("ping", "audio_end"):
        return msg
    if kind == "resume_session":
        token = msg.get("token")
        if not isinstance(token, str) or not 0 < len(token) <= 128:
            raise ProtocolError("bad_message", "resume_session needs the token of a goaway (a string)")
        return {"type": kind, "token": token}
    raise ProtocolError("bad_message", f"unknown message type {kind!r} (expected hello, ping, audio_end or "
                                       "resume_session)")


def _parse_hello(msg: dict) -> dict:
    out = {}
    if "protocol" in msg and msg["protocol"] != PROTOCOL:
        raise ProtocolError("unsupported_protocol", f"this server speaks protocol {PROTOCOL}, not {msg['protocol']!r}")
    if "encoding" in msg:
        if msg["encoding"] not in ("json", "binary"):
            raise ProtocolError("bad_message", f'encoding must be "json" or "binary", got {msg["encoding"]!r}')
        out["encoding"] = msg["encoding"]
    if "source_audio" in msg:
        if not isinstance(msg["source_audio"], bool):
            raise ProtocolError("bad_message", f"source_audio must be true or false, got {msg['source_audio']!r}")
        out["source_audio"] = msg["source_audio"]
    if "timing" in msg:
        if not isinstance(msg["timing"], bool):
            raise ProtocolError("bad_message", f"timing must be true or false, got {msg['timing']!r}")
        out["timing"] = msg["timing"]
    if "face" in msg:
        face = msg["face"]
        if face != "none":
            try:
                check_name_set(face if isinstance(face, str) else repr(face))
            except ValueError as e:
                raise ProtocolError("bad_message", f'face: {e} (or "none")') from None
        out["face"] = face
    if "smile" in msg:
        smile = msg["smile"]
        if not isinstance(smile, (int, float)) or isinstance(smile, bool) or not 0 <= smile <= 1:
            raise ProtocolError("bad_message", f"smile must be a number from 0 to 1, got {smile!r}")
        out["smile"] = float(smile)
    if "rig" in msg:
        out["rig"] = None if msg["rig"] is None else _parse_rig(msg["rig"])
    if "speaker" in msg:
        speaker = msg["speaker"]
        if speaker is not None and not (isinstance(speaker, str) and 0 < len(speaker) <= MAX_SPEAKER_CHARS):
            raise ProtocolError("bad_message", f"speaker must be a speaker's name (a string of 1 to "
                                               f"{MAX_SPEAKER_CHARS} characters) or null, got {speaker!r:.80}")
        out["speaker"] = speaker
    if "audio" in msg:
        a = msg["audio"]
        if not isinstance(a, dict):
            raise ProtocolError("bad_message", "audio must be an object {rate, format, channels}")
        rate, fmt, ch = a.get("rate", AUDIO_RATE), a.get("format", "pcm16"), a.get("channels", 1)
        if not isinstance(rate, int) or isinstance(rate, bool) or not MIN_RATE <= rate <= MAX_RATE:
            raise ProtocolError("bad_audio", f"audio.rate must be an integer in {MIN_RATE}..{MAX_RATE} Hz, got {rate!r}")
        if fmt not in AUDIO_FORMATS:
            raise ProtocolError("bad_audio", f"audio.format must be one of {list(AUDIO_FORMATS)}, got {fmt!r}")
        if ch not in (1, 2) or isinstance(ch, bool):
            raise ProtocolError("bad_audio", f"audio.channels must be 1 or 2, got {ch!r}")
        out["audio"] = AudioFormat(rate, fmt, ch)
    return out


def _parse_rig(rig) -> dict:
    """`hello.rig` (revision 8): the client's own skeleton, in the schema of the server's `hello.skeleton`
    (joints, parents, offsets, optional rest_rotations and units) plus an optional bone `map`."""
    def bad(text: str) -> ProtocolError:
        return ProtocolError("bad_rig", f"rig: {text}")

    if not isinstance(rig, dict):
        raise bad("expected an object {joints, parents, offsets, rest_rotations, units, map}")
    names, parents, offsets = rig.get("joints"), rig.get("parents"), rig.get("offsets")
    if not isinstance(names, list) or not 1 <= len(names) <= MAX_RIG_JOINTS:
        raise bad(f"joints must be a list of 1..{MAX_RIG_JOINTS} names")
    J = len(names)
    if not all(isinstance(n, str) and 0 < len(n) <= 128 for n in names) or len(set(names)) != J:
        raise bad("joints must be distinct non-empty names (at most 128 characters)")
    if not isinstance(parents, list) or len(parents) != J or not all(
            isinstance(p, int) and not isinstance(p, bool) for p in parents):
        raise bad(f"parents must be {J} integers")
    if parents[0] != -1 or any(not 0 <= p < j for j, p in enumerate(parents) if j > 0):
        raise bad("parents: the first joint is the root (-1), every other joint's parent comes before it")
    out = {"joints": list(names), "parents": list(parents), "offsets": _vectors(offsets, J, 3, "offsets", bad)}
    units = rig.get("units", "m")
    if units not in ("m", "cm", "mm"):
        raise bad(f'units must be "m", "cm" or "mm", got {units!r}')
    largest = float(np.abs(out["offsets"]).max()) * {"m": 1.0, "cm": 0.01, "mm": 0.001}[units]
    if largest > MAX_RIG_OFFSET_M:
        raise bad(f"offsets: one of {largest:.3g} m; each at most {MAX_RIG_OFFSET_M:g} m a side (in units {units!r})")
    if "rest_rotations" in rig:
        q = np.asarray(_vectors(rig["rest_rotations"], J, 4, "rest_rotations", bad))
        if np.abs(q).max() > 2 or np.any(np.abs(np.linalg.norm(q, axis=1) - 1) > 1e-2):  # (no overflow: |q| <= 2)
            raise bad("rest_rotations must be unit quaternions [w, x, y, z]")
        out["rest_rotations"] = (q / np.linalg.norm(q, axis=1, keepdims=True)).tolist()
    out["units"] = units
    if "map" in rig:
        if not isinstance(rig["map"], dict) or not all(isinstance(v, str) or v is None for v in rig["map"].values()):
            raise bad("map must be an object {humanoid bone: joint name or null}")
        out["map"] = dict(rig["map"])
    return out


def _vectors(values, count: int, size: int, what: str, bad) -> list[list[float]]:
    if not isinstance(values, list) or len(values) != count or not all(
            isinstance(v, list) and len(v) == size and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                           and math.isfinite(x) for x in v) for v in values):
        raise bad(f"{what} must be {count} lists of {size} finite numbers")
    return [[float(x) for x in v] for v in values]


def check_audio(data: bytes, fmt: AudioFormat) -> None:
    """The constant-time checks of a binary audio message (size, whole sample frames)."""
    if len(data) > MAX_BINARY_BYTES:
        raise ProtocolError("too_large", f"binary messages are limited to {MAX_BINARY_BYTES} bytes, got {len(data)}")
    width = 2 if fmt.format == "pcm16" else 4
    if len(data) % (width * fmt.channels):
        raise ProtocolError("bad_audio", f"{len(data)} bytes is not a whole number of {fmt.format} "
                                         f"sample frames ({width * fmt.channels} bytes each)")


def decode_audio(data: bytes, fmt: AudioFormat) -> np.ndarray:
    """A binary audio message -> float32 mono at fmt.rate in [-1, 1]; raises ProtocolError("bad_audio"/"too_large").

    float32 samples slightly beyond [-1, 1] are clipped; NaN, infinity or anything beyond
    MAX_AUDIO_ABS (not audio in this format: e.g. integers sent as floats) is refused.
    """
    check_audio(data, fmt)
    if fmt.format == "pcm16":
        x = np.frombuffer(data, "<i2").astype(np.float32) / 32768.0
    else:
        x = np.frombuffer(data, "<f4")
        peak = float(np.max(np.abs(x), initial=0.0))
        if not np.isfinite(peak):
            raise ProtocolError("bad_audio", "float32 audio contains NaN or infinity")
        if peak > MAX_AUDIO_ABS:
            raise ProtocolError("bad_audio", f"float32 audio must be scaled to -1..1, found a sample of {peak:.3g}")
        x = np.clip(x, -1.0, 1.0)
    if fmt.channels == 2:
        x = x.reshape(-1, 2).mean(axis=1, dtype=np.float32)
    return x
