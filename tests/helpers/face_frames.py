"""Folders of server messages that carry the face (protocol revision 7), made with the server's own encoder
(`streamer.protocol`, the face channel of `streamer.face.face_channel`), for the compiled clients' tests: what a
client that asked for a name set receives, and what each frame carries."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dimgestor.face.names import NAME_SETS, names_of
from dimgestor.face.visemes import FACE_LABELS
from dimgestor.training.synthetic import synthetic_skeleton
from streamer import protocol as P
from streamer.face import FACE, face_channel
from streamer.frames import Channel, Frame, channel_values

PAIR = Channel("pair", 2, "test only")  # a channel laid out before the face: offsets come from the layout
TRAILING = b"\x7f" * 12  # a later revision's bytes after the layout: ignored


def face_messages(folder: Path, encoding: str, name_set: str, frames: int = 6, seed: int = 5) -> list[dict]:
    """Write NNNNNN.json / NNNNNN.bin as clients/python/client.py --save does, for a client that sent
    `{"face": name_set}` in its hello: the server's hello (its face in the default set, no binary channels yet),
    for binary a `channels` message (PAIR, then the face), then `frames` frames with a face (one binary frame with
    bytes past the layout), then for binary a `channels` message with [] and one frame without a face.

    Returns per frame {index, pts, root, rotations, face: {name: weight as the client must read it}, pair}."""
    folder.mkdir(parents=True, exist_ok=True)
    sk = synthetic_skeleton()
    J = len(sk.names)
    face = face_channel(name_set)
    hello = P.hello(P.SkeletonInfo.from_skeleton(sk), {}, 20, 0.25, True,
                    face={"names": "vrm0", "sets": list(NAME_SETS), "labels": list(names_of("vrm0"))})
    files = [P.dumps(hello)]
    layout = {PAIR.name: PAIR, FACE: face} if encoding == "binary" else {}
    if encoding == "binary":
        files.append(P.dumps({"type": "channels", "channels": P.channel_layout(J, layout)}))
    rng = np.random.default_rng(seed)
    expected = []
    for i in range(frames + (encoding == "binary")):
        q = rng.normal(size=(J, 4))
        f = Frame(i, i / 20, rng.normal(size=3) * 10, (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(np.float32),
                  np.zeros(3), {FACE: rng.uniform(0, 1, len(FACE_LABELS)), PAIR.name: np.array([i, -0.5])})
        weights = channel_values(f, face)
        if i == frames:  # the client asked for "none" meanwhile: no face, no channels
            files.append(P.dumps({"type": "channels", "channels": []}))
            files.append(P.frame_binary(f, {}))
            weights, pair = None, None
        elif encoding == "binary":
            files.append(P.frame_binary(f, layout) + (TRAILING if i == 2 else b""))
            weights, pair = weights.astype(np.float32).astype(np.float64), [float(i), -0.5]
        else:
            msg = json.loads(P.frame_json(f, {}))
            msg["face"] = {n: round(float(w), 4) for n, w in zip(face.labels, weights)}
            files.append(P.dumps(msg))
            weights, pair = np.array(list(msg["face"].values())), None
        expected.append({"index": i, "pts": f.pts, "root": np.asarray(f.root_pos, np.float64),
                         "rotations": f.rotations.astype(np.float64), "pair": pair,
                         "face": None if weights is None else dict(zip(face.labels, weights.tolist()))})
    for k, data in enumerate(files):
        path = folder / f"{k:06d}.{'bin' if isinstance(data, bytes) else 'json'}"
        path.write_bytes(data) if isinstance(data, bytes) else path.write_text(data)
    return expected


def lerp_face(a: dict, b: dict, u: float) -> dict:
    """The face between two frames as the clients' playout interpolates it (linearly, by name)."""
    return {n: w + (b[n] - w) * u if n in b else w for n, w in a.items()}


def interpolated(expected: list[dict], t: float) -> tuple[dict, np.ndarray]:
    """The face and root at pts t as the playout interpolates them (the frame at or before t with the next)."""
    a = max((e for e in expected if e["pts"] <= t + 1e-12), key=lambda e: e["pts"])
    later = [e for e in expected if e["pts"] > t + 1e-12]
    if not later:
        return a["face"], a["root"]
    b = later[0]
    u = (t - a["pts"]) / (b["pts"] - a["pts"])
    return lerp_face(a["face"], b["face"] or {}, u), a["root"] + (b["root"] - a["root"]) * u


def check_face_frames(out: list[dict], expected: list[dict], exact: bool) -> None:
    """A decoder's frames against what the encoder put in: the face by name (binary: the float32 exactly; JSON: the
    4-decimal numbers), the pose, the channel laid out before the face, and no face where none was sent."""
    frames = [d for d in out if d["type"] == "frame"]
    assert [f["index"] for f in frames] == [e["index"] for e in expected]
    for got, want in zip(frames, expected):
        np.testing.assert_allclose(got["rotations"], want["rotations"], atol=1e-6)
        if want["face"] is None:
            assert "face" not in got, got["index"]
            continue
        assert got["face"].keys() == want["face"].keys()
        np.testing.assert_allclose([got["face"][n] for n in want["face"]], list(want["face"].values()), rtol=0,
                                   atol=0 if exact else 1e-12)
        if want["pair"] is not None:
            assert got["channels"]["pair"] == want["pair"]


def check_recorded_face(records: list[Path], decoded: list[dict]) -> None:
    """A compiled decoder's frames of a live server's recording carry the face exactly as it was sent: a JSON
    frame's `face` (the server's default set: the recording client did not ask), none in binary frames (not asked)."""
    by_file = {d["file"]: d for d in decoded}
    for path in records:
        if path.suffix == ".bin":
            assert "face" not in by_file[path.name], path.name
        elif (ref := json.loads(path.read_text()))["type"] == "frame":
            assert by_file[path.name].get("face") == ref.get("face"), path.name
