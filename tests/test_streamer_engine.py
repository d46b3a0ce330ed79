"""Session (windowed streaming inference) equals offline generation; the recording equals `generate`."""

import asyncio

import numpy as np
import pytest

from dimgestor.audio import save_wav
from dimgestor.bvh import read_bvh, write_bvh
from dimgestor.features import features_to_motion
from dimgestor.streaming.stream import generate_offline
from dimgestor.training.synthetic import synthetic_speech
from streamer.record import BvhRecorder
from streamer.scheduling import StreamBatcher
from streamer.sessions import Session
from streamer.sources import WavSource
from helpers.ws import SlowExecutor

pytestmark = pytest.mark.timeout(120)


@pytest.mark.parametrize("window_ms", [10, 130, 1000])
def test_windowed_session_equals_offline_generation(bundle, tmp_path, window_ms):
    audio = synthetic_speech(2.37, seed=5)  # not a whole number of frames or windows
    wav = tmp_path / "a.wav"
    save_wav(wav, audio, 16000)
    src = WavSource(wav, realtime=False, chunk_ms=7)
    session = Session.from_bundle(bundle, steps=3, seed=11, window_ms=window_ms)
    recorder = BvhRecorder(tmp_path / "stream.bvh", bundle.skeleton, bundle.feature_spec)
    frames = []

    def emit(fs):
        frames.extend(fs)
        recorder.on_frames(fs)

    n = asyncio.run(session.run(src, emit))
    recorder.close()

    offline = bundle.denormalize(generate_offline(bundle.model, src.audio, steps=3, seed=11))
    assert n == len(frames) == len(offline) == len(src.audio) * 20 // 16000
    assert [f.index for f in frames] == list(range(n))
    assert np.allclose([f.pts for f in frames], np.arange(n) / 20)
    assert np.allclose(np.stack([f.features for f in frames]), offline, atol=1e-4)
    rot = np.stack([f.rotations for f in frames])
    assert np.allclose(np.linalg.norm(rot, axis=-1), 1.0, atol=1e-6)

    write_bvh(tmp_path / "offline.bvh", features_to_motion(offline, bundle.skeleton, bundle.feature_spec))
    a, b = read_bvh(tmp_path / "stream.bvh"), read_bvh(tmp_path / "offline.bvh")
    assert a.values.shape == b.values.shape and np.abs(a.values - b.values).max() < 1e-3

    st = session.stats
    assert st.ended and st.frames == n and st.audio_s == pytest.approx(len(src.audio) / 16000)
    assert st.rtf > 0 and st.latency_ms > 0


@pytest.mark.parametrize("batched", [True, False])
def test_a_session_that_falls_behind_on_a_batcher_takes_whole_windows_and_still_equals_offline(bundle, tmp_path,
                                                                                            batched):
    """On a batching scheduler, audio that queued while inference ran is taken as whole windows, a chunk cut where
    the last one ends (its rest opens the next window): the calls of a session that fell behind are a window's
    multiple, as everyone's, and share the others' batches. Only the call after the source ended is shorter.
    Elsewhere a window takes everything queued (a source in bursts gets its last frames at once). The frames are
    offline's either way."""
    audio = synthetic_speech(2.37, seed=5)
    wav = tmp_path / "a.wav"
    save_wav(wav, audio, 16000)
    src = WavSource(wav, realtime=False, chunk_ms=7)  # 112-sample chunks: no 130 ms window ends on a chunk's end
    scheduler = StreamBatcher() if batched else SlowExecutor(1, delay_s=0.03)
    session = Session.from_bundle(bundle, steps=2, seed=3, window_ms=130, scheduler=scheduler)
    calls, push = [], session.scheduler.submit_push
    session.scheduler.submit_push = lambda source, samples, rank: (calls.append(len(samples)), push(source, samples,
                                                                                                      rank))[1]
    frames = []
    try:
        asyncio.run(session.run(src, frames.extend))
    finally:
        scheduler.shutdown()
    window = session.windows.window
    assert window == 2080 and sum(calls) == len(src.audio) and max(calls) > window  # it fell behind (a fast source)
    assert all(n % window == 0 for n in calls[:-1]) == batched and calls[-1] <= session.windows.call
    offline = bundle.denormalize(generate_offline(bundle.model, src.audio, steps=2, seed=3))
    assert np.allclose(np.stack([f.features for f in frames]), offline, atol=1e-4)


def test_a_failing_source_surfaces_its_error(bundle):
    async def broken():
        from streamer.sources import AudioChunk

        yield AudioChunk(np.zeros(3200, np.float32), 0.0, 0.0)
        raise OSError("device unplugged")

    session = Session.from_bundle(bundle, steps=2, window_ms=100)
    with pytest.raises(OSError, match="unplugged"):
        asyncio.run(session.run(broken(), lambda fs: None))


@pytest.mark.parametrize("why, said", [("PortAudio library not found", ""),
                                       ("libportaudio.so.2: bad ELF", " (libportaudio.so.2: bad ELF)")])
def test_a_missing_portaudio_is_said_once_with_the_package_to_install(monkeypatch, why, said):
    import builtins

    from streamer.sources import SourceError, list_input_devices

    real_import = builtins.__import__

    def no_portaudio(name, *args, **kw):
        if name == "sounddevice":
            raise OSError(why)
        return real_import(name, *args, **kw)

    monkeypatch.setattr(builtins, "__import__", no_portaudio)
    with pytest.raises(SourceError) as e:
        list_input_devices()
    assert str(e.value) == f"PortAudio library not found{said}; install it, e.g. `apt install libportaudio2`"
