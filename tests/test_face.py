"""The face as a stream: the same frames whatever the chunking, a resting mouth in silence, and its place in every
session frame (within the body's lookahead, no frame later)."""

import numpy as np
import pytest

from dimgestor.audio import SAMPLE_RATE, load_wav
from dimgestor.face import FACE_LABELS, FaceOptions, FaceStream
from dimgestor.face.listener import unavailable
from dimgestor.face.stream import LISTENERS
from dimgestor.face.visemes import V
from helpers.clients import SPEECH_WAV

SPEECH = load_wav(SPEECH_WAV)[: 6 * SAMPLE_RATE]  # espeak-ng English, 6 s


def stream_face(audio, sizes, lookahead_s=0.3, **options):
    face, rows, at, k = FaceStream(20, lookahead_s, FaceOptions(**options)), [], 0, 0
    while at < len(audio):
        n = sizes[k % len(sizes)]
        face.push(audio[at:at + n])
        rows.append(face.take(face.frames_ready))
        at, k = at + n, k + 1
    face.finish()
    rows.append(face.take(face.frames_ready))
    return np.concatenate(rows)


@pytest.mark.parametrize("listener", LISTENERS)
def test_streamed_face_equals_the_whole_recording_for_awkward_chunk_sizes(listener):
    if "pocketsphinx" in listener and (why := unavailable()) is not None:
        pytest.skip(why)
    whole = stream_face(SPEECH, [len(SPEECH)], listener=listener)
    assert whole.shape[1] == len(FACE_LABELS) and len(whole) >= 6 * 20
    for sizes in ([1, 159, 161, 3333], [7], [160 * 5 + 1, 17], [777], [1600]):
        pieces = stream_face(SPEECH, sizes, listener=listener)
        np.testing.assert_array_equal(pieces, whole, err_msg=f"chunk sizes {sizes}")


def test_speech_opens_the_mouth_and_silence_rests_it():
    audio = np.concatenate([np.zeros(SAMPLE_RATE, np.float32), SPEECH[: 3 * SAMPLE_RATE],
                            np.zeros(2 * SAMPLE_RATE, np.float32)])
    face = stream_face(audio, [3200])
    jaw = face[:, V["jawOpen"]]
    speaking, after = jaw[25:75], jaw[int(4.3 * 20):int(6 * 20)]
    assert speaking.max() > 0.6 and np.mean(speaking > 0.2) > 0.4, np.round(speaking, 2)
    assert np.all(jaw[:15] == 0) and np.all(after == 0), (np.round(jaw[:15], 2), np.round(after, 2))
    assert np.all(face[int(4.3 * 20):int(6 * 20), V["sil"]] == 1)  # the rest viseme in the pause after speech
    vowels = face[25:75][:, [V[v] for v in ("aa", "I", "U", "E", "O")]]
    assert len({int(np.argmax(r)) for r in vowels if r.max() > 0.2}) >= 3, "the vowels take several shapes"


def test_a_silent_stream_blinks_and_never_opens_its_mouth():
    face = stream_face(np.zeros(30 * SAMPLE_RATE, np.float32), [16000])
    assert np.all(face[:, V["PP"]: V["jawOpen"] + 1] == 0) and np.all(face[:, V["sil"]] == 1)  # the rest viseme
    onsets = np.flatnonzero(np.diff((face[:, V["blinkLeft"]] > 0.5).astype(int)) == 1)
    assert 4 <= len(onsets) <= 14, f"{len(onsets)} blinks in 30 s"


def test_the_face_is_ready_within_its_lookahead_and_a_longer_one_is_capped():
    face = FaceStream(20, 0.35)
    assert face.lookahead_s == 0.3
    face.push(SPEECH[: int(1.0 * SAMPLE_RATE)])
    assert face.frames_ready == int(round((1.0 - 0.3) * 20)) + 1  # frames 0..14: each up to its time + 0.3 s
    with pytest.raises(RuntimeError, match="lookahead"):
        face.take(face.frames_ready + 1)


def test_a_float_frame_rate_makes_the_same_face():
    """A checkpoint's fps is a float (20.0), as a Session passes it: the same frames as 20, however long the
    speech (the brows keep 5 s of pitch, a count of frames)."""
    audio = np.concatenate([SPEECH, SPEECH])
    np.testing.assert_array_equal(stream_face_at(20.0, audio), stream_face_at(20, audio))


def stream_face_at(fps, audio):
    face = FaceStream(fps, 0.3)
    face.push(audio)
    face.finish()
    return face.take(face.frames_ready)


def test_a_decoder_back_from_an_ended_stream_hears_as_a_new_one():
    """Decoders are pooled across streams (a server's short sessions would each pay for a new one): one that has
    listened to other speech makes exactly the frames a new one makes."""
    from dimgestor.face.listener import DECODERS

    DECODERS.idle.clear()
    noisy = SPEECH[::-1] * 0.3 + np.random.default_rng(0).normal(0, 0.02, len(SPEECH)).astype(np.float32)
    first = stream_face(SPEECH, [3200], listener="pocketsphinx")  # a new decoder, given back at the end
    other = stream_face(noisy, [3200], listener="pocketsphinx")   # the pooled one, after other sounds (its
    again = stream_face(SPEECH, [3200], listener="pocketsphinx")  # cepstral mean and noise move); pooled again
    assert sum(len(v) for v in DECODERS.idle.values()) == 1 and len(other)
    np.testing.assert_array_equal(again, first)


def test_a_sessions_frames_carry_the_same_face_whatever_the_chunks_and_none_without_one(bundle):
    """Through `Session` (what the server, pipecat and the recorder run): the face in each frame's channel is the
    same for awkward chunkings as for the whole recording, ends with the body's last frame, and a session made
    without a face carries none."""
    from streamer.sessions import Session

    audio = SPEECH[: 3 * SAMPLE_RATE]

    def faces(sizes, face=FaceOptions()):
        s, frames, at, k = Session.from_bundle(bundle, face=face), [], 0, 0
        while at < len(audio):
            frames += s.infer(audio[at:at + sizes[k % len(sizes)]])
            at, k = at + sizes[k % len(sizes)], k + 1
        frames += s.infer_finish()
        return frames

    whole = faces([len(audio)])
    table = np.array([f.channels["face"] for f in whole])
    assert table.shape == (len(whole), len(FACE_LABELS)) and table[:, V["jawOpen"]].max() > 0.5
    for sizes in ([1, 1599, 3333], [800 * 3 + 7]):
        pieces = faces(sizes)
        assert [f.index for f in pieces] == [f.index for f in whole]
        np.testing.assert_array_equal(np.array([f.channels["face"] for f in pieces]), table, err_msg=str(sizes))
    assert all("face" not in f.channels for f in faces([4000], face=None))


def test_faces_pushed_as_one_batch_equal_each_face_alone():
    """`FaceStream.push_many` (a server batch's faces, their listeners stepped together): each face equals the face
    pushed alone, for streams at other points of their speech, other seeds and smiles, and the pocketsphinx
    listener beside the network where it is installed."""
    from dimgestor.face.listener import unavailable

    specs = [dict(offset=0), dict(offset=1234, seed=3), dict(offset=400, smile=0.5)]
    if unavailable() is None:  # (pocketsphinx installed)
        specs.append(dict(offset=0, listener="pocketsphinx"))
    faces = [FaceStream(20, 0.3, FaceOptions(**{k: v for k, v in s.items() if k != "offset"})) for s in specs]
    rows = [[] for _ in specs]
    for at in range(0, len(SPEECH), 1600):
        chunks = [SPEECH[max(0, at - s["offset"]):max(0, at + 1600 - s["offset"])] for s in specs]
        FaceStream.push_many(faces, chunks)
        for r, f in zip(rows, faces):
            r.append(f.take(f.frames_ready))
    for r, f, s in zip(rows, faces, specs):
        f.finish()
        r.append(f.take(f.frames_ready))
        got = np.concatenate(r)
        alone = stream_face(SPEECH[:len(SPEECH) - s["offset"]], [1600],
                            **{k: v for k, v in s.items() if k != "offset"})
        assert got.shape == alone.shape and got[:, V["jawOpen"]].max() > 0.5, s
        np.testing.assert_allclose(got, alone, atol=1e-6, rtol=0, err_msg=str(s))


def test_sessions_batched_by_the_server_make_the_faces_they_make_alone_and_fail_alone(bundle):
    """Through `StreamBatcher` (what `serve` runs): windows of three face sessions taken as one batch (their
    faces made together: `Session.frames_many`) carry the face each makes alone; a session whose frames fail
    fails alone, the others' faces go on."""
    from helpers.batches import one_batch
    from streamer.scheduling import StreamBatcher
    from streamer.sessions import Session

    audio = SPEECH[: 3 * SAMPLE_RATE]
    seeds = (0, 1, 2)

    def alone(seed):
        s = Session.from_bundle(bundle, seed=seed, face=FaceOptions(seed=seed))
        frames = [f for at in range(0, len(audio), 1600) for f in s.infer(audio[at:at + 1600])]
        return np.array([f.channels["face"] for f in frames + s.infer_finish()])

    def batched(broken=None):
        batcher = StreamBatcher()
        sessions = [Session.from_bundle(bundle, seed=k, face=FaceOptions(seed=k), scheduler=batcher) for k in seeds]
        if broken is not None:  # its frames fail after the batch's faces were made
            sessions[broken].channels = {"bad": lambda feats: np.zeros((len(feats) + 1, 1))}
        frames, errors = [[] for _ in seeds], [None] * len(seeds)
        try:
            for at in range(0, len(audio), 1600):
                for k, made in one_batch(batcher, sessions, audio[at:at + 1600], errors).items():
                    frames[k] += made
            assert batcher.stats.peak == sum(e is None for e in errors) or broken is not None
            for k, s in enumerate(sessions):
                if errors[k] is None:
                    frames[k] += s.infer_finish()
        finally:
            batcher.shutdown()
        return [np.array([f.channels["face"] for f in fs]) if e is None else e for fs, e in zip(frames, errors)]

    want = [alone(k) for k in seeds]
    for got, w in zip(batched(), want):
        assert got.shape == w.shape
        np.testing.assert_allclose(got, w, atol=1e-6, rtol=0)
    got = batched(broken=1)
    assert isinstance(got[1], ValueError) and "channel maker" in str(got[1])
    for k in (0, 2):
        np.testing.assert_allclose(got[k], want[k], atol=1e-6, rtol=0)


def test_pitch_is_the_voices_period_and_none_where_unvoiced():
    """`pitch_semitones` on 40 ms of a harmonic voice at 90-310 Hz: a period of it (the fundamental's, or, as plain
    autocorrelation may pick, a multiple within the 70 Hz floor) to the lag's rounding, in semitones above 100 Hz;
    the fundamental itself where no multiple fits (below 140 Hz); noise, silence and a stretch too short for the
    lowest pitch: None."""
    from dimgestor.face.life import pitch_semitones

    t = np.arange(640) / SAMPLE_RATE
    for f0 in (90.0, 123.0, 180.0, 247.0, 310.0):
        voice = sum(np.sin(2 * np.pi * f0 * h * t + h) / h for h in range(1, 6)).astype(np.float32) * 0.3
        got = pitch_semitones(voice)
        assert got is not None, f0
        periods = [m for m in (1, 2, 3) if f0 / m >= 70.0]
        m = min(periods, key=lambda m: abs(got - 12 * np.log2(f0 / m / 100)))
        lag = m * SAMPLE_RATE / f0
        assert abs(got - 12 * np.log2(f0 / m / 100)) <= 12 * np.log2((lag + 1) / lag), (f0, got)
        assert m == 1 or f0 >= 140
    rng = np.random.default_rng(0)
    assert pitch_semitones(rng.standard_normal(640).astype(np.float32) * 0.3) is None
    assert pitch_semitones(np.zeros(640, np.float32)) is None
    assert pitch_semitones(np.sin(2 * np.pi * 150 * t[:400]).astype(np.float32)) is None


def test_brows_rise_on_a_vowel_at_the_voices_peak_more_with_a_pitch_rise_and_settle():
    from dimgestor.face.life import Brows

    b = Brows(fps=20)
    for _ in range(40):  # two seconds of voice at 0 semitones, quiet vowels: no raise
        assert b.step(0.0, -8.0, True) == 0.0
    plain = b.step(0.0, 0.0, True)  # a vowel at the peak, pitch as before
    assert 0.3 < plain < 0.4
    assert b.step(None, 0.0, False) < plain  # settling (a consonant raises nothing)
    rise = Brows(fps=20, recent=[0.0] * 40).step(4.0, 0.0, True)  # the same vowel, 4 semitones up
    assert rise > plain and rise <= 0.6
    settle = [b.step(None, -20.0, False) for _ in range(30)]
    assert all(x > y for x, y in zip(settle, settle[1:])) and settle[-1] < 0.01


def test_without_pocketsphinx_a_server_still_has_its_face_and_asked_for_it_says_why(monkeypatch, tiny_checkpoint,
                                                                                  capsys):
    """Where pocketsphinx has no wheel (Python 3.14; Linux aarch64 on 3.10 and 3.12) the engine installs without it:
    the face's own listener needs none, so `serve` makes the face as anywhere; `--face-listener pocketsphinx` there
    serves bones only and says so once, with what to do; a pocketsphinx listener asked for directly fails saying
    the same."""
    import sys

    from dimgestor.face.listener import PhoneListener, unavailable
    from streamer.options import ServeOptions
    from streamer.server import build

    assert unavailable() is None
    monkeypatch.setitem(sys.modules, "pocketsphinx", None)  # as if not installed
    assert "pip install pocketsphinx" in unavailable()
    options = dict(source="ws", checkpoint=str(tiny_checkpoint), ws=("127.0.0.1", 0), steps=2, status_every=0)
    p = build(ServeOptions(**options))
    assert p.options.face == "vrm0" and p.face is not None and "face" in p.ws.hello
    assert capsys.readouterr().err == ""
    p = build(ServeOptions(**options, face_listener="pocketsphinx"))
    assert p.options.face == "none" and p.face is None and p.ws.seats.terms.face is None and "face" not in p.ws.hello
    assert "no face, bones only: --face-listener pocketsphinx: the face's listener needs pocketsphinx" in \
        capsys.readouterr().err
    with pytest.raises(ImportError, match="pip install pocketsphinx"):
        PhoneListener(30, 0.3, beam=1e-7)  # (a decoder key no other test pooled: a new decoder is made)


def test_both_listeners_together_give_the_mean_of_their_mouths_and_the_networks_blinks_and_brows():
    """--face-listener net+pocketsphinx: each frame's mouth (visemes and jaw) is the mean of the two listeners'
    mouths, each made as it is alone; the eyes and brows follow the network's listener, as with it alone."""
    if (why := unavailable()) is not None:
        pytest.skip(why)
    mouth = slice(0, V["jawOpen"] + 1)  # the visemes and the jaw
    net, ps, both = (stream_face(SPEECH, [1600], listener=lis) for lis in ("net", "pocketsphinx", "net+pocketsphinx"))
    assert len(net) == len(ps) == len(both)
    np.testing.assert_allclose(both[:, mouth], (net[:, mouth] + ps[:, mouth]) / 2, atol=1e-12)
    assert np.abs(net[:, mouth] - ps[:, mouth]).max() > 0.3  # (they do differ)
    rest = [V[n] for n in ("blinkLeft", "blinkRight", "browUp")]
    np.testing.assert_array_equal(both[:, rest], net[:, rest])
