"""Faces made in a child process beside the batcher (`serve --face-process`, `streamer.face_process`)."""

import os
import signal

import numpy as np
import pytest
from helpers.batches import one_batch
from helpers.clients import SPEECH_WAV

from dimgestor.audio import SAMPLE_RATE, load_wav
from dimgestor.face import FACE_LABELS, FaceOptions
from dimgestor.face.visemes import V

SPEECH = load_wav(SPEECH_WAV)[: 3 * SAMPLE_RATE]


@pytest.fixture(scope="module")
def face_process():
    from streamer.face_process import FaceProcess

    process = FaceProcess()
    process.ready()
    yield process
    process.close()


def _batched(bundle, face_process, options, smile_at=None, kill_at=None, bodies_only=()):
    """Sessions taken as one batch per window by a `StreamBatcher` (what `serve` runs) -> each one's face rows (or
    its exception) and its frame count. smile_at: the window at which session 0's smile is set to 0.8; kill_at:
    the window before which the face process is killed; bodies_only: sessions without a face."""
    from streamer.scheduling import StreamBatcher
    from streamer.sessions import Session

    batcher = StreamBatcher()
    sessions = [Session.from_bundle(bundle, seed=k, face=None if k in bodies_only else o, scheduler=batcher,
                                    face_process=face_process) for k, o in enumerate(options)]
    rows, counts, errors = [[] for _ in options], [0] * len(options), [None] * len(options)
    try:
        for w, at in enumerate(range(0, len(SPEECH), 1600)):
            if w == smile_at:
                sessions[0].set_smile(0.8)
            if w == kill_at:
                os.kill(face_process.pid, signal.SIGKILL)
                face_process._process.join(10)
            for k, frames in one_batch(batcher, sessions, SPEECH[at:at + 1600], errors).items():
                counts[k] += len(frames)
                rows[k] += [fr.channels["face"] for fr in frames if "face" in fr.channels]
        for k, s in enumerate(sessions):
            if errors[k] is None:
                last = s.infer_finish()
                counts[k] += len(last)
                rows[k] += [fr.channels["face"] for fr in last if "face" in fr.channels]
    finally:
        batcher.shutdown()
        for s in sessions:
            s._close_face()
    return [np.array(r) if e is None else e for r, e in zip(rows, errors)], counts


def test_faces_made_in_the_face_process_are_the_faces_made_in_the_batch(bundle, face_process):
    """The same sessions, windows and batches with their faces in the child and in the batcher's thread: the same
    face bit for bit, a smile set midway included, up to the frames after the audio ends."""
    options = [FaceOptions(seed=0), FaceOptions(seed=1, smile=0.3), FaceOptions(seed=2)]
    there, n_there = _batched(bundle, face_process, options, smile_at=12)
    here, n_here = _batched(bundle, None, options, smile_at=12)
    assert n_there == n_here and all(n > 50 for n in n_here)
    for a, b in zip(there, here):
        assert a.shape == b.shape == (len(a), b.shape[1]) and a[:, 0].std() > 0
        np.testing.assert_array_equal(a, b)
    assert there[0][:20, V["smile"]].max() == 0 and there[0][30:, V["smile"]].min() > 0.3  # (set midway)


def test_a_face_that_fails_in_the_child_fails_its_own_session_and_a_killed_child_fails_only_the_faces(bundle):
    """A face the child cannot make (an unknown listener) fails its session's window, the others' faces go on;
    once the child is killed, each face session's next window fails with one line naming the face process, a
    session without a face keeps making frames, and sessions started after make their faces in the batch's thread."""
    from streamer.face_process import FaceProcess, FaceProcessEnded

    process = FaceProcess()
    process.ready()
    try:
        got, counts = _batched(bundle, process, [FaceOptions(), FaceOptions(listener="nothing"), FaceOptions()])
        assert isinstance(got[1], ValueError) and "face listener 'nothing'" in str(got[1])
        assert got[0].shape[0] == counts[0] > 50 and got[2].shape[0] == counts[2]
        got, counts = _batched(bundle, process, [FaceOptions(), FaceOptions(), FaceOptions()], kill_at=5,
                               bodies_only=(2,))
        for k in (0, 1):
            assert isinstance(got[k], FaceProcessEnded), got[k]
            assert "face process" in str(got[k]) and "\n" not in str(got[k])
        assert counts[2] > 50 and len(got[2]) == 0  # (the session without a face: every frame, no face)
        got, counts = _batched(bundle, process, [FaceOptions(), FaceOptions()])  # (sessions after: faces made here)
        here, _ = _batched(bundle, None, [FaceOptions(), FaceOptions()])
        for a, b in zip(got, here):
            np.testing.assert_array_equal(a, b)
    finally:
        process.close()


def parse(*flags: str):
    from dimgestor_app.cli import build_parser
    from streamer.options import ServeOptions

    args = build_parser().parse_args(["serve", *flags])
    return ServeOptions.parse(**{k: v for k, v in vars(args).items() if k in ServeOptions.model_fields})


def test_serve_face_process_flag_starts_the_child_and_its_sessions_use_it(tiny_checkpoint):
    """`serve --face-process` (parsed as the CLI does) builds a pipeline whose sessions make their faces in the
    child; without a face there is no child."""
    from streamer.face_process import RemoteFace
    from streamer.server import build

    common = ("--source", "ws", "--checkpoint", str(tiny_checkpoint), "--ws", "127.0.0.1:0", "--status-every", "0")
    pipeline = build(parse(*common, "--face-process"))
    try:
        assert pipeline.face_process is not None and pipeline.face_process.pid
        session = pipeline.make_session()
        assert isinstance(session._face_stream(), RemoteFace)
        frames = [f for at in range(0, 8000, 1600) for f in session.infer(SPEECH[at:at + 1600])]
        assert len(frames) > 5 and all(f.channels["face"].shape == (len(FACE_LABELS),) for f in frames)
    finally:
        pipeline.scheduler.shutdown()
        pipeline.face_process.close()
    none = build(parse(*common, "--face-process", "--face", "none"))
    none.scheduler.shutdown()
    assert none.face_process is None


def test_answers_reach_their_own_waiters_in_any_order_and_a_stopped_child_is_ended(monkeypatch):
    """Two exchanges waited for in the other order each get their own answer (the rows of their own face); a child
    that stops answering is ended after `ANSWER_TIMEOUT_S`, its faces failing with one line that says so."""
    import streamer.face_process as fp

    process = fp.FaceProcess()
    process.ready()
    try:
        a, b = process.face(20, 0.3, FaceOptions()), process.face(20, 0.3, FaceOptions(seed=5))
        first = process.begin([a], [SPEECH[:16000]])
        second = process.begin([b], [SPEECH[:8000]])
        got_b, _ = process.wait(second)
        got_a, _ = process.wait(first)
        assert set(got_a) == {a.id} and set(got_b) == {b.id}
        assert len(got_a[a.id]) > len(got_b[b.id]) > 0  # (1 s of audio against 0.5 s)
        monkeypatch.setattr(fp, "ANSWER_TIMEOUT_S", 1.0)
        os.kill(process.pid, signal.SIGSTOP)
        with pytest.raises(fp.FaceProcessEnded, match="did not answer in 1 s and was ended"):
            a.push(SPEECH[16000:17600])
        assert process.ended
    finally:
        process.close()


def test_a_program_that_only_makes_faces_imports_no_torch():
    """The face (its listener's mel filters included: `dimgestor.audio.mel_weights`) is numpy only, so the face
    process's child stays small and starts at once."""
    import subprocess
    import sys

    code = ("import sys, numpy as np\nfrom dimgestor.face import FaceStream\nf = FaceStream(20, 0.3)\n"
            "f.push(np.random.default_rng(0).standard_normal(16000).astype(np.float32) * 0.1)\n"
            "print(f.frames_ready, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert int(out[0]) > 0 and out[1] == "False"
