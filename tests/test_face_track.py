"""The face track file: `dimgestor generate --face-csv OUT.csv` and the `OUT.face.csv` that `serve --record OUT.bvh`
writes beside its BVH share one format (`dimgestor.face.track`): a header `time,` + the VRM 0 names + ARKit's 52,
then one row per BVH frame; the recording's holds whole rows, as many as the BVH's frames, at every flush."""

import asyncio
import csv
import re

import numpy as np
import pytest

from dimgestor.audio import SAMPLE_RATE, load_wav, save_wav
from dimgestor.bvh import read_bvh
from dimgestor.face import FACE_LABELS, FaceOptions, convert, names_of
from dimgestor.face.names import ARKIT
from dimgestor.face.track import TRACK_NAMES, track_header, track_rows
from dimgestor.face.visemes import V
from dimgestor.training.synthetic import synthetic_speech
from dimgestor_app.cli import main
from streamer.face import FACE
from streamer.frames import Frame
from streamer.record import BvhRecorder, RecordError, channels_path, face_path
from streamer.sessions import Session
from streamer.sources import WavSource
from helpers.clients import SPEECH_WAV

pytestmark = pytest.mark.timeout(180)
MOUTH = ["A", "I", "U", "E", "O"]


def read_track(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array(rows[1:], dtype=float).reshape(len(rows) - 1, len(rows[0]))


def column(header, table, name):
    return table[:, header.index(name)]


def test_the_header_is_time_then_vrm0_then_arkit_and_each_cell_has_4_decimals():
    assert track_header() == ",".join(["time", *names_of("vrm0"), *ARKIT]) + "\n"
    assert track_header().startswith("time,A,I,U,E,O,Blink,Blink_L,Blink_R,Joy,eyeBlinkLeft,")
    assert len(TRACK_NAMES) == 9 + 52
    face = np.zeros((3, len(FACE_LABELS)))
    face[1, V["aa"]] = face[1, V["jawOpen"]] = 0.123456
    cells = [r.rstrip("\n").split(",") for r in track_rows(face, 20, first=199)]
    assert [c[0] for c in cells] == ["9.9500", "10.0000", "10.0500"]  # time = index / fps
    assert all(len(c) == 1 + len(TRACK_NAMES) and all(re.fullmatch(r"\d+\.\d{4}", x) for x in c) for c in cells)
    by_name = dict(zip(TRACK_NAMES, cells[1][1:]))
    assert by_name["A"] == by_name["jawOpen"] == "0.1235" and by_name["I"] == "0.0000"
    assert set(cells[0][1:]) == {"0.0000"}  # the resting face: no -0.0000 either
    assert track_rows(np.zeros((0, len(FACE_LABELS))), 20) == []


def test_the_recording_writes_the_face_beside_the_bvh_a_row_per_frame_at_every_flush(bundle, tmp_path):
    """A session with a face, recorded with a flush after every window: at each, the CSV has whole rows, as many
    as the BVH has frames; row i is frame i's face at time i / 20 in both name sets."""
    save_wav(tmp_path / "a.wav", synthetic_speech(2.37, seed=5), SAMPLE_RATE)
    out = tmp_path / "out.bvh"
    session = Session.from_bundle(bundle, steps=2, seed=3, window_ms=130, face=FaceOptions(seed=3))
    rec = BvhRecorder(out, bundle.skeleton, bundle.feature_spec, flush_every_s=0.0, face=True)
    frames, counts = [], []

    def emit(fs):
        frames.extend(fs)
        rec.on_frames(fs)
        counts.append((read_bvh(out).num_frames, len(read_track(face_path(out))[1])))

    n = asyncio.run(session.run(WavSource(tmp_path / "a.wav", realtime=False, chunk_ms=7), emit))
    assert rec.close() == out
    assert len(counts) > 3 and all(b == f for b, f in counts) and counts[-1] == (n, n) and n == 47
    assert face_path(out) == tmp_path / "out.face.csv" and not channels_path(out).exists()
    header, table = read_track(face_path(out))
    assert header == ["time", *TRACK_NAMES]
    np.testing.assert_array_equal(table[:, 0], np.round(np.arange(n) / 20, 4))
    face = np.stack([f.channels[FACE] for f in frames])
    want = np.concatenate([convert(face, "vrm0"), convert(face, "arkit")], axis=1)
    np.testing.assert_allclose(table[:, 1:], want, rtol=0, atol=5e-5 + 1e-9)


def test_a_frame_without_a_face_is_recorded_at_rest_and_no_face_no_csv(bundle, tmp_path):
    feats = bundle.denormalize(np.zeros((4, bundle.feature_spec.dim)))
    frames = [Frame(i, i / 20, np.zeros(3), np.zeros((1, 4)), feats[i]) for i in range(4)]
    rec = BvhRecorder(tmp_path / "rest.bvh", bundle.skeleton, bundle.feature_spec, face=True)
    rec.on_frames(frames)
    rec.close()
    header, table = read_track(tmp_path / "rest.face.csv")
    assert table.shape == (4, 1 + len(TRACK_NAMES)) and not table[:, 1:].any()
    rec = BvhRecorder(tmp_path / "bare.bvh", bundle.skeleton, bundle.feature_spec)
    rec.on_frames(frames)
    rec.close()
    assert not (tmp_path / "bare.face.csv").exists()
    (tmp_path / "taken.face.csv").mkdir()
    with pytest.raises(RecordError, match="taken.face.csv"):
        BvhRecorder(tmp_path / "taken.bvh", bundle.skeleton, bundle.feature_spec, face=True)


def generate(tiny_checkpoint, tmp_path, audio, name):
    save_wav(tmp_path / f"{name}.wav", audio, SAMPLE_RATE)
    bvh, face = tmp_path / f"{name}.bvh", tmp_path / f"{name}.csv"
    assert main(["generate", "--checkpoint", str(tiny_checkpoint), "--audio", str(tmp_path / f"{name}.wav"),
                 "--out", str(bvh), "--face-csv", str(face), "--steps", "2"]) == 0
    return read_bvh(bvh), *read_track(face)


def test_generate_writes_a_face_row_per_frame_and_silence_rests_the_mouth(tiny_checkpoint, tmp_path):
    motion, header, table = generate(tiny_checkpoint, tmp_path, np.zeros(2 * SAMPLE_RATE + 123, np.float32), "quiet")
    assert header == ["time", *TRACK_NAMES] and len(table) == motion.num_frames == 40
    np.testing.assert_array_equal(table[:, 0], np.round(np.arange(40) / 20, 4))
    for name in [*MOUTH, "jawOpen", "mouthFunnel", "mouthPucker", "mouthClose"]:
        assert not column(header, table, name).any(), name

    speech = load_wav(SPEECH_WAV)[: 3 * SAMPLE_RATE]
    motion, header, table = generate(tiny_checkpoint, tmp_path, speech, "speech")
    assert len(table) == motion.num_frames == 60
    mouth = np.stack([column(header, table, v) for v in MOUTH], axis=1)
    assert mouth.max() > 0.3 and np.mean(mouth.max(axis=1) > 0.1) > 0.3, "speech opens the mouth"


def test_generate_face_into_a_missing_folder_is_one_error_line(tiny_checkpoint, tmp_path, capsys):
    save_wav(tmp_path / "a.wav", synthetic_speech(0.5, seed=1), SAMPLE_RATE)
    args = ["generate", "--checkpoint", str(tiny_checkpoint), "--audio", str(tmp_path / "a.wav"),
            "--out", str(tmp_path / "a.bvh")]
    assert main([*args, "--face-csv", str(tmp_path / "nowhere" / "a.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --face-csv ") and str(tmp_path / "nowhere") in err and "does not exist" in err
    assert not (tmp_path / "a.bvh").exists()  # refused before anything is written
    assert main([*args, "--face-csv", str(tmp_path / "a.bvh")]) == 2
    assert "the same path as --out" in capsys.readouterr().err


def test_generate_without_pocketsphinx_refuses_its_listener_in_one_line_before_any_work(tiny_checkpoint, tmp_path, capsys,
                                                                                   monkeypatch):
    """Where pocketsphinx has no wheel (pyproject.toml) its listener cannot run: --face-listener pocketsphinx with
    --face-csv or a .vrma says why at once (the face's own listener needs no pocketsphinx: tested beside)."""
    import sys

    save_wav(tmp_path / "a.wav", synthetic_speech(0.5, seed=1), SAMPLE_RATE)
    monkeypatch.setitem(sys.modules, "pocketsphinx", None)  # as if not installed
    args = ["generate", "--checkpoint", str(tiny_checkpoint), "--audio", str(tmp_path / "a.wav"),
            "--face-listener", "pocketsphinx"]
    assert main([*args, "--out", str(tmp_path / "a.bvh"), "--face-csv", str(tmp_path / "a.csv")]) == 2
    assert "error: --face-csv: the face's listener needs pocketsphinx" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "a.vrma")]) == 2
    assert "a.vrma: the face's listener needs pocketsphinx" in capsys.readouterr().err
    both = [*args[:-1], "net+pocketsphinx"]  # (both listeners: pocketsphinx's is needed all the same)
    assert main([*both, "--out", str(tmp_path / "a.bvh"), "--face-csv", str(tmp_path / "a.csv")]) == 2
    assert "error: --face-csv: the face's listener needs pocketsphinx" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["a.wav"]  # nothing written
    assert main([*args[:-2], "--out", str(tmp_path / "a.bvh"), "--face-csv", str(tmp_path / "a.csv")]) == 0
    assert (tmp_path / "a.csv").is_file()  # the face's own listener: no pocketsphinx needed
