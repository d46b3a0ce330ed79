"""GestureProcessor (streamer/pipecat.py) in real pipecat pipelines: a TTS-like stage bursting audio faster than
real time -> the processor -> an output transport that plays it in real time and records when each chunk is
heard. Gestures go out when their audio is heard, continuously across bursts and between utterances; an
interruption sends nothing of the audio that is never heard and eases the avatar to rest without a jump.

Timing bounds are the target (50 ms) plus how long this test process's own event loop stalled (the processor, the
transport and the clock all run on it), measured while it ran (helpers/stalls.py): the stalls from LOOKBACK_S
before a frame to its audio (the processor learns that a stall delayed the transport from its next reports)."""

import asyncio
import json
import sys
import time
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("pipecat", reason="pipecat-ai is not installed (pip install 'dimgestor[pipecat]')")

from pipecat.frames.frames import EndFrame, InterruptionFrame, TTSSpeakFrame  # noqa: E402
from pipecat.pipeline.pipeline import Pipeline  # noqa: E402
from pipecat.pipeline.worker import PipelineParams, PipelineWorker  # noqa: E402
from pipecat.workers.runner import WorkerRunner  # noqa: E402

from helpers.clients import REPO, SPEECH_WAV  # noqa: E402
from helpers.serve import Serve  # noqa: E402
from helpers.stalls import LoopStalls  # noqa: E402

sys.path.insert(0, str(REPO / "examples"))
from pipecat_avatar import PacedAudioOutput, WavTTS, load_speech  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]
RATE = 24000     # a TTS's usual output rate (the model's is 16 kHz)
SYNC_S = 0.05    # the target: a gesture within 50 ms of its audio being heard
LOOKBACK_S = 1.0
FPS = 20


class KeptFrames:
    """A sink that keeps what it is sent (GestureProcessor's sinks: `send(frames)`)."""

    def __init__(self):
        self.frames = []

    def send(self, frames):
        self.frames += frames


@pytest.fixture(scope="module")
def bundle():
    from dimgestor.streaming.checkpoint import load_checkpoint

    return load_checkpoint(None)  # the embedded default model (350 ms lookahead)


@pytest.fixture(scope="module")
def speech():
    return load_speech(SPEECH_WAV, RATE)[: 6 * RATE]  # 6 s of espeak-ng speech, int16 at 24 kHz


@dataclass
class Run:
    gestures: object         # the GestureProcessor
    output: PacedAudioOutput
    tts: WavTTS
    released: list           # streamer.pipecat.Released, in order
    marks: dict              # what the script noted (monotonic times)
    stalls: LoopStalls       # this process's loop stalls meanwhile

    @property
    def stall_s(self) -> float:
        return self.stalls.worst

    def slack(self, *times: float) -> float:
        """This loop's stalls (every late wake of the watcher) from LOOKBACK_S before the earliest of `times` to
        the latest, and one watcher period (a stall no longer than that may end before the watcher is due)."""
        return self.stalls.within(min(times) - LOOKBACK_S, max(times)) + self.stalls.period_s


def run_pipeline(bundle, speech, script, speed=5.0, burst_s=1.0, observe=True, **kw) -> Run:
    """TTS -> GestureProcessor -> PacedAudioOutput as a real pipecat pipeline; `script(worker, marks)` drives it
    (TTSSpeakFrame: say `speech`) and ends it with an EndFrame."""
    from streamer.pipecat import GestureProcessor

    async def main() -> Run:
        released, marks, stalls = [], {}, LoopStalls(period_s=0.005)
        gestures = GestureProcessor([], bundle=bundle, on_release=released.append, **kw)
        tts, output = WavTTS(speech, RATE, speed=speed, burst_s=burst_s), PacedAudioOutput(RATE)
        worker = PipelineWorker(Pipeline([tts, gestures, output]), idle_timeout_secs=None, enable_rtvi=False,
                                params=PipelineParams(audio_out_sample_rate=RATE),
                                observers=[gestures.playout_observer] if observe else [])
        watch = asyncio.create_task(stalls.watch())
        runner = WorkerRunner(handle_sigint=False)
        await runner.add_workers(worker)
        driver = asyncio.create_task(script(worker, marks))
        await asyncio.wait_for(runner.run(), 120)
        await driver
        watch.cancel()
        return Run(gestures, output, tts, released, marks, stalls)

    return asyncio.run(main())


def playout(output: PacedAudioOutput, since: float, sample: float) -> float:
    """When the transport played sample `sample` (at RATE) of the audio it began after `since` (monotonic)."""
    chunks = [p for p in output.played if p.start >= since]
    first = np.cumsum([0] + [p.samples for p in chunks])
    i = int(np.searchsorted(first, sample, side="right")) - 1
    assert i < len(chunks), f"sample {sample} was never played"
    return chunks[i].start + (sample - first[i]) / RATE


def dry_s(output: PacedAudioOutput, t0: float, t1: float) -> float:
    """How long within [t0, t1] the transport had nothing to play between two chunks (its device ran dry)."""
    ends = [(a.start + a.samples / RATE, b.start) for a, b in zip(output.played, output.played[1:])]
    return sum(max(0.0, min(t1, s) - max(t0, e)) for e, s in ends)


def check_continuous(run: Run, until: float) -> None:
    """Frames went out at 20 fps until `until`: no longer apart than a frame and this process's worst stall,
    within an utterance also any time its audio paused (the transport ran dry: the picture waits with it)."""
    pairs = [(a, b) for a, b in zip(run.released, run.released[1:]) if b.wall <= until]
    for a, b in pairs:
        paused = dry_s(run.output, a.wall, b.wall) if a.utterance == b.utterance >= 0 else 0.0
        gap = b.wall - a.wall
        assert gap <= 1 / FPS + run.slack(a.wall, b.wall) + paused, f"a gap of {gap:.3f} s before {b}"


def max_angle(a: np.ndarray, b: np.ndarray) -> float:
    """The largest joint rotation between two poses (J, 4), radians."""
    return float(2 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0, 1)).max())


def test_burst_tts_gestures_are_released_when_their_audio_is_heard(bundle, speech):
    """A TTS 5x faster than real time, 1 s bursts at 24 kHz: every gesture frame reaches the sinks within 50 ms
    of its audio's playout as the transport records it; frames run on at 20 fps across burst edges with none
    missing; past the blend-in they equal `dimgestor generate` on the same audio, seed and K."""
    from dimgestor.audio import resample

    async def script(worker, marks):
        await asyncio.sleep(0.5)  # rest frames first
        marks["speak"] = time.monotonic()
        await worker.queue_frames([TTSSpeakFrame("hello")])
        await asyncio.sleep(len(speech) / RATE + 1.5)
        marks["end"] = time.monotonic()
        await worker.queue_frames([EndFrame()])

    run = run_pipeline(bundle, speech, script, seed=3)
    g, stats = run.gestures, run.gestures.stats
    speech_frames = [r for r in run.released if r.utterance == 0]
    expected = bundle.generate(resample(speech.astype(np.float32) / 32768, RATE, 16000), seed=3)
    assert [r.k for r in speech_frames] == list(range(len(expected))), "a frame went missing or out of order"

    # (1) each frame when its audio is heard (the transport's own record of when each chunk started)
    assert np.allclose([r.audio_s for r in speech_frames], [r.k / FPS for r in speech_frames])  # (no gap in it)
    errors = np.array([r.wall - playout(run.output, run.marks["speak"], r.audio_s * RATE) for r in speech_frames])
    print(f"sync error {1000 * errors.min():+.1f}..{1000 * errors.max():+.1f} ms over {len(errors)} frames, "
          f"loop stall {1000 * run.stall_s:.0f} ms, audio held {1000 * stats.held_s:.0f} ms at the start")
    for r, e in zip(speech_frames, errors):
        assert abs(e) <= SYNC_S + run.slack(r.wall, r.wall - e), f"frame {r.k} {1000 * e:.0f} ms off its audio"
    # The burst edges: the TTS pushed a burst every 0.2 s; the frames' audio clock never skips or stalls there.
    pts = np.array([r.frame.pts for r in speech_frames])
    assert np.allclose(np.diff(pts), 1 / FPS, atol=1e-9)
    check_continuous(run, run.marks["end"])
    assert [r.frame.index for r in run.released] == list(range(len(run.released)))
    assert len(run.tts.bursts) == int(np.ceil(len(speech) / RATE))

    # (2) the model's own frames: exactly generate's once the blend-in from rest is over
    blend = g.blend_in
    got = np.stack([r.frame.features for r in speech_frames[blend:]])
    np.testing.assert_allclose(got, expected[blend:], atol=1e-4, rtol=1e-4)
    from dimgestor.features import PoseDecoder

    rotations = PoseDecoder(bundle.skeleton, bundle.feature_spec).decode(expected).rotations
    np.testing.assert_allclose(np.stack([r.frame.rotations for r in speech_frames[blend:]]), rotations[blend:],
                               atol=1e-4)
    # rest frames before it, at the same 20 fps (after it: the interruption test)
    assert [r.utterance for r in run.released[:9]] == [-1] * 9

    # (3) the face travels with its frame, released when its audio is heard: the utterance's session made it from
    # the same audio (the face of the audio alone, seeded as the body); the mouth opens on speech, rests before it
    from dimgestor.face import FaceOptions, FaceStream
    from dimgestor.face.visemes import V

    alone = FaceStream(FPS, 0.3, FaceOptions(seed=3))
    alone.push(resample(speech.astype(np.float32) / 32768, RATE, 16000))
    alone.finish()
    expected_face = alone.take(alone.frames_ready)[: len(speech_frames)]
    face = np.stack([r.frame.channels["face"] for r in speech_frames])
    jaw = face[:, V["jawOpen"]]
    assert jaw.max() > 0.6 and np.mean(jaw > 0.2) > 0.3, np.round(jaw, 2)
    assert np.corrcoef(jaw, expected_face[:, V["jawOpen"]])[0, 1] > 0.95
    np.testing.assert_array_equal(face[:, V["blinkLeft"]] > 0.5, expected_face[:, V["blinkLeft"]] > 0.5)
    rest = np.stack([r.frame.channels["face"] for r in run.released[:9]])
    assert np.all(rest[:, V["jawOpen"]] == 0) and np.all(rest[:, V["sil"]] == 1)


def test_interruption_sends_nothing_unheard_and_eases_to_rest(bundle, speech):
    """The user barges in 2 s into a 6 s answer (all of it already sent by the TTS): no frame of the audio that
    is never heard goes out, the avatar is back at rest within REST_S without a step larger than the model's
    own largest frame-to-frame step, and the next answer gestures again, in sync."""
    rest_s = 1.0  # the spring (rest_hz 1.3, critically damped) is within 1 % of rest by then

    async def script(worker, marks):
        await asyncio.sleep(0.3)
        marks["speak"] = time.monotonic()
        await worker.queue_frames([TTSSpeakFrame("a long answer")])
        await asyncio.sleep(2.0)
        marks["interrupt"] = time.monotonic()
        await worker.queue_frames([InterruptionFrame()])
        await asyncio.sleep(2.0)
        marks["again"] = time.monotonic()
        await worker.queue_frames([TTSSpeakFrame("the next answer")])
        await asyncio.sleep(3.0)
        marks["end"] = time.monotonic()
        await worker.queue_frames([EndFrame()])

    given = []  # the agent's audio as the processor hands it on (to a viewer): (when, 16 kHz samples)
    run = run_pipeline(bundle, speech, script, seed=1, on_audio=lambda pts, y: given.append((time.monotonic(), len(y))))
    g, stats = run.gestures, run.gestures.stats
    first = [r for r in run.released if r.utterance == 0]
    heard = sum(p.samples for p in run.output.played if run.marks["speak"] <= p.start < run.marks["again"])
    assert heard < len(speech) * 0.6, "the interruption did not stop the audio"
    assert stats.interruptions == 1 and stats.dropped_unplayed > 0
    # (1) nothing of the audio never heard: each frame's own audio was played before the interruption
    assert all(r.audio_s * RATE < heard for r in first)
    assert max(r.wall for r in first) <= run.marks["interrupt"] + run.slack(run.marks["interrupt"]) + 1 / FPS
    handed = sum(n for t, n in given if t < run.marks["again"])  # a viewer plays no more than was heard either
    assert 0 < handed <= heard / RATE * 16000 + 16000 / FPS

    # (2) back to rest smoothly
    own = first[g.blend_in:]  # the model's own frames
    normal = max(max_angle(a.frame.rotations, b.frame.rotations) for a, b in zip(own, own[1:]))
    cut = first[-1].wall  # its last frame: the interruption reached the processor by the next
    after = [r for r in run.released if cut < r.wall < run.marks["again"]]
    assert after and all(r.utterance == -1 for r in after)
    last = first[-1].frame.rotations
    steps = [max_angle(a.frame.rotations, b.frame.rotations) for a, b in zip([first[-1]] + after, after)]
    start = max_angle(last, g.rest.rotations)
    settled = [max_angle(r.frame.rotations, g.rest.rotations)
               for r in after if r.wall >= cut + rest_s]
    print(f"return to rest: from {np.degrees(start):.1f} deg, largest step {np.degrees(max(steps)):.1f} deg "
          f"(model's own largest {np.degrees(normal):.1f}), {np.degrees(settled[0]):.2f} deg off after {rest_s} s")
    assert max(steps) <= normal, "a jump on the way to rest"
    assert max(settled) <= 0.01 * start + 1e-6
    check_continuous(run, run.output.played[-1].start)  # never frozen (then the pipeline shuts down)

    # (3) the next answer gestures again, in sync with its audio
    second = [r for r in run.released if r.utterance == 1]
    assert [r.k for r in second[:40]] == list(range(40))
    for r in second:
        e = r.wall - playout(run.output, run.marks["again"], r.audio_s * RATE)
        assert abs(e) <= SYNC_S + run.slack(r.wall, r.wall - e), f"frame {r.k} {1000 * e:.0f} ms off its audio"
    spread = np.std(np.stack([r.frame.rotations for r in second[g.blend_in:]]), axis=0).max()
    assert spread > 0.05, "the avatar does not gesture after the interruption"


def test_a_tts_slower_than_real_time_gestures_late_never_early_and_drops_nothing(bundle, speech):
    """A TTS at 0.8x real time: the transport runs dry between bursts (silence the model hears too). Frames
    whose audio came too late go out as soon as they are made (counted), none before its audio is heard, none
    lost, and the playout clock still matches the transport's, gaps included."""
    clip = speech[: 3 * RATE]

    async def script(worker, marks):
        await asyncio.sleep(0.3)
        marks["speak"] = time.monotonic()
        await worker.queue_frames([TTSSpeakFrame("slowly")])
        await asyncio.sleep(3 / 0.8 + 1.5)
        await worker.queue_frames([EndFrame()])

    # (with 0.4 s bursts the transport's 40 ms chunks line up with them: no audio waits for the next burst)
    run = run_pipeline(bundle, clip, script, speed=0.8, burst_s=0.4)
    stats = run.gestures.stats
    frames = [r for r in run.released if r.utterance == 0]
    assert [r.k for r in frames] == list(range(len(frames))) and len(frames) >= 3 * FPS
    played = [p for p in run.output.played if p.start >= run.marks["speak"]]
    ends = [p.start + p.samples / RATE for p in played]
    gaps = np.array([0.0] + [b.start - e for b, e in zip(played[1:], ends)])  # silence before each chunk
    assert (gaps > 0.02).sum() >= 5, "the transport never ran dry: not a slow TTS"
    assert stats.late == sum(1 for r in frames if r.wall - r.due > 1 / FPS) and stats.late > 0
    # Each frame shows a moment of the TTS's audio (or silence, where the transport ran dry). Its due time is
    # when the transport plays that moment; it goes out then, or, not made in time, as soon as it is made.
    shown = [r for r in frames if r.audio_s is not None]
    assert len(shown) >= len(clip) / RATE * FPS - 1, "frames of the audio are missing"
    for r in shown:
        heard = playout(run.output, run.marks["speak"], r.audio_s * RATE)
        slack = run.slack(r.due, heard, r.wall)
        assert abs(r.due - heard) <= SYNC_S + slack, f"frame {r.k} due {1000 * (r.due - heard):.0f} ms off"
        assert r.wall >= heard - SYNC_S - slack, f"frame {r.k} went out before its audio"
    # and a frame that shows silence was due while the transport had nothing to play
    dry = [(e, b.start) for b, e in zip(played[1:], ends) if b.start - e > 1e-3] + [(ends[-1], np.inf)]
    for r in frames:
        if r.audio_s is None:
            off = min(max(0.0, e - r.due, r.due - s) for e, s in dry)
            assert off <= SYNC_S + run.slack(r.due), f"frame {r.k} shows silence {1000 * off:.0f} ms off a pause"
    print(f"slow TTS: {stats.late} of {len(frames)} frames late, up to {1000 * stats.max_late_s:.0f} ms")


def test_the_old_name_executor_still_works_and_warns(bundle):
    """GestureProcessor(executor=) is the deprecated spelling of scheduler=: the same scheduler, with a warning."""
    from concurrent.futures import ThreadPoolExecutor

    from streamer import pipecat as sp

    with ThreadPoolExecutor(1) as pool:
        with pytest.warns(DeprecationWarning, match="use scheduler="):
            g = sp.GestureProcessor([], bundle=bundle, executor=pool)
        assert g.scheduler is pool
        with pytest.raises(TypeError, match="scheduler= only"):
            sp.GestureProcessor([], bundle=bundle, scheduler=pool, executor=pool)


def test_without_pocketsphinx_its_listener_is_refused_at_construction_and_the_face_works(bundle, monkeypatch):
    """Where pocketsphinx has no wheel (Python 3.14; Linux aarch64 on 3.10 and 3.12) its listener cannot run: the
    processor asked for it says so when built, not in the middle of a call; the face's own listener and face=None
    work there."""
    from dimgestor.face import FaceOptions
    from streamer import pipecat as sp

    monkeypatch.setitem(sys.modules, "pocketsphinx", None)  # as if not installed
    with pytest.raises(ImportError, match="needs pocketsphinx.*or face=None"):
        sp.GestureProcessor([], bundle=bundle, face=FaceOptions(listener="pocketsphinx"))
    assert sp.GestureProcessor([], bundle=bundle).face is not None
    assert sp.GestureProcessor([], bundle=bundle, face=None).face is None


def test_a_frame_at_the_instant_a_pause_begins_shows_the_pause():
    """A slow TTS sends twenty 20 ms chunks, then nothing until 0.525 s: the transport is silent from 0.4 s. Frame 8
    (pts 0.4) shows that silence, not the audio after it (which is heard only at 0.525 s): the pause begins where
    the audio counted in samples ends, exactly (a sum of 20 ms as seconds is 0.4000000000000001). On a fake clock."""
    from streamer.playout import Playout, Utterance

    playout, u = Playout(), Utterance(0, None, None, None, RATE)
    for _ in range(20):
        assert playout.schedule(u, RATE // 50, now=0.0) == 0.0
    assert playout.schedule(u, RATE // 50, now=0.525) == pytest.approx(0.125)
    shown = [u.audio_at(k / FPS) for k in range(13)]
    assert shown[:8] == [k / FPS for k in range(8)]
    assert shown[8:11] == [None, None, None]
    assert shown[11:] == pytest.approx([0.425, 0.475])


def test_a_tts_ahead_of_real_time_leaves_no_gap_however_long_the_machine_has_been_up():
    """Chunks pushed ahead of their playout play back to back: no transport gap, so every frame shows audio. The
    clock's sums round differently from the audio's (picoseconds, more the longer the machine has been up: the
    monotonic clock counts from boot); a frame at a chunk's edge must not fall into such a "gap". Fake clock."""
    from streamer.playout import Playout, Utterance

    for up in (0.0, 9_876.54321, 15_000.0, 1_234_567.891):
        playout, u = Playout(), Utterance(0, None, None, None, RATE)
        for _ in range(100):  # 2 s of 20 ms chunks, all pushed at once
            assert playout.schedule(u, RATE // 50, now=up) == 0.0
        assert u.gaps == []
        assert [u.audio_at(k / FPS) for k in range(40)] == [k / FPS for k in range(40)]


def test_an_utterance_that_starts_while_a_rest_frame_goes_out_continues_its_clock(bundle, monkeypatch):
    """Its audio is pushed at 48.7 ms; the transport has not confirmed it when the rest frame due at 50 ms goes out
    (pts 0.05). Its first frame and its audio come after that on the frames' clock, never before (a receiver's
    clock must not step back: seen once in CI as a VMC time going from 0.05 to 0.0487). On a fake clock."""
    from streamer import pipecat as sp
    from streamer.frames import Frame
    from streamer.playout import Utterance

    clock = SimpleNamespace(monotonic=lambda: 0.0)
    monkeypatch.setattr(sp, "time", clock)
    heard = []
    sink = KeptFrames()
    g = sp.GestureProcessor([sink], bundle=bundle, on_audio=lambda pts, y: heard.append((pts, len(y))))
    g.origin, g.playout.observed = 0.0, True
    g._release_rest(0.0)
    clock.monotonic = lambda: 0.0487
    u = Utterance(0, None, None, None, RATE)
    g._schedule(u, RATE // 50)
    u.audio.append((0.0, np.zeros(320, np.float32)))
    clock.monotonic = lambda: 0.05
    g._release_rest(0.05)
    f = g.resting.pose_frame()
    g._release_speech(u, Frame(0, 0.0, f.root_pos, f.rotations, f.features), u.start, 0.05)
    pts = [f.pts for f in sink.frames]
    assert pts[:2] == [0.0, 0.05] and pts[2] > pts[1]
    assert heard == [(pts[2], 320)]  # its audio on the same clock as its frames
    g._release_rest(0.1)
    assert sink.frames[3].pts > pts[2]


def test_a_change_after_the_clocks_wait_timed_out_makes_it_look_again(bundle, monkeypatch):
    """An interruption that lands after the clock's wait timed out and before the clock task runs again (a loaded
    event loop widens that gap): the wait says something changed, so the clock looks again instead of releasing
    from the utterance the interruption emptied (seen in CI: the clock task died on an empty deque, `deque index
    out of range`, and no frame went out after the interruption)."""
    from streamer import pipecat as sp

    g = sp.GestureProcessor([KeptFrames()], bundle=bundle)

    async def timed_out_and_meanwhile_changed(waiting, timeout):
        waiting.close()
        g._changed.set()  # the interruption, run before this task resumes
        raise asyncio.TimeoutError

    async def main():
        quiet = await g._wait(0.01)
        monkeypatch.setattr(sp.asyncio, "wait_for", timed_out_and_meanwhile_changed)
        return quiet, await g._wait(0.01)

    assert asyncio.run(main()) == (False, True)


def test_between_utterances_the_face_rests_and_blinks(bundle, monkeypatch):
    """Rest frames (the spring's, between utterances) carry a face too: the mouth at rest, the eyes blinking as a
    stream's do in silence (irregularly, 4-14 times in 30 s), the smile held; face=None: frames without a face.
    On a fake clock."""
    from dimgestor.face import FaceOptions
    from dimgestor.face.visemes import V
    from streamer import pipecat as sp

    clock = SimpleNamespace(monotonic=lambda: 0.0)
    monkeypatch.setattr(sp, "time", clock)
    sink = KeptFrames()
    g = sp.GestureProcessor([sink], bundle=bundle, face=FaceOptions(smile=0.4))
    g.origin = 0.0
    for k in range(30 * FPS):
        g._release_rest(k / FPS)
    face = np.stack([f.channels["face"] for f in sink.frames])
    assert np.all(face[:, V["PP"]: V["jawOpen"] + 1] == 0) and np.all(face[:, V["sil"]] == 1)
    assert np.allclose(face[:, V["smile"]], 0.4)
    onsets = np.flatnonzero(np.diff((face[:, V["blinkLeft"]] > 0.5).astype(int)) == 1) / FPS
    assert 4 <= len(onsets) <= 14, f"{len(onsets)} blinks in 30 s"
    assert len(set(np.round(np.diff(onsets), 2))) > len(onsets) // 2, "metronomic blinks"

    bare = sp.GestureProcessor([KeptFrames()], bundle=bundle, face=None)
    bare.origin = 0.0
    bare._release_rest(0.0)
    assert bare.sinks[0].frames[0].channels == {}


def test_example_speaks_to_a_websocket_client_and_a_vmc_receiver(tmp_path):
    """examples/pipecat_avatar.py end to end: it waits for a WebSocket client, speaks the file in bursts and
    serves continuous frames with the agent's audio (DGA1) to the viewer's protocol, and VMC to a receiver."""
    from websockets.sync.client import connect

    from dimgestor.audio import load_wav, save_wav
    from streamer import protocol as P
    from helpers.vmc import bundles, check_vmc_bundle
    from helpers.udp_capture import UdpCapture

    wav = tmp_path / "say.wav"
    save_wav(wav, load_wav(SPEECH_WAV)[: 3 * 16000], 16000)
    vmc = UdpCapture()
    vmc.start()
    proc = Serve("--wav", str(wav), "--ws", "127.0.0.1:0", "--vmc", f"127.0.0.1:{vmc.port}", "--burst", "5",
                 command=("examples/pipecat_avatar.py",))
    try:
        url = proc.wait_for(r"WebSocket\s+(ws://\S+)", timeout=60).group(1)
        proc.wait_for("waiting for a WebSocket client", timeout=30)
        frames, audio, statuses = [], [], []
        with connect(url, max_size=2**24) as c:
            hello = json.loads(c.recv(timeout=30))
            assert hello["type"] == "hello" and hello["source_audio"]["rate"] == 16000
            c.send(json.dumps({"type": "hello", "protocol": 1, "source_audio": True}))
            for m in c:
                if isinstance(m, bytes):
                    audio.append(P.parse_source_audio_binary(m))
                    continue
                d = json.loads(m)
                if d["type"] == "frame":
                    frames.append(d)
                elif d["type"] == "status":
                    statuses.append(d)
                elif d["type"] == "end":
                    break
        assert proc.finish(60) == 0, proc.output
    finally:
        if proc.proc.poll() is None:
            proc.proc.kill()
        vmc.stop = True
        vmc.join(5)
    print(proc.output[-600:])
    assert [f["index"] for f in frames] == list(range(frames[0]["index"], frames[0]["index"] + len(frames)))
    assert len(frames) >= 3 * FPS
    rot = np.array([f["rotations"] for f in frames])
    assert np.std(rot, axis=0).max() > 0.05, "no gestures"
    # the agent's audio, on the frames' clock: all of it, starting where the gestures for it start
    assert sum(len(a["samples"]) for a in audio) >= int(2.95 * 16000), "the agent's audio did not reach the client"
    assert all(a["rate"] == 16000 for a in audio)
    assert frames[0]["pts"] <= audio[0]["pts"] <= frames[-1]["pts"]
    frames_vmc, msgs = [], []  # each frame's messages (its bundles: the last ends with its time)
    for b in bundles(vmc.datagrams):
        msgs += b
        if b[-1][0] == "/VMC/Ext/T":
            frames_vmc, msgs = frames_vmc + [msgs], []
    assert len(frames_vmc) >= 3 * FPS
    for msgs in frames_vmc:
        check_vmc_bundle([m for m in msgs if m[0] != "/VMC/Ext/Blend/Val"])  # (the face's: below)
    # the face with every frame, in VRM 0 names (the example's default --face): the mouth speaks
    from dimgestor.face import names_of

    faces = [[(p[0], p[1]) for a, tags, p in msgs if a == "/VMC/Ext/Blend/Val" and tags == "sf"] for msgs in frames_vmc]
    assert all([name for name, _ in f] == list(names_of("vrm0")) for f in faces), faces[0]
    mouth = np.array([[v for name, v in f if name in ("A", "I", "U", "E", "O")] for f in faces])
    assert mouth.max() > 0.5 and np.sum(mouth.max(axis=1) > 0.2) >= 10, np.round(mouth.max(axis=1), 2)
    times = [m[-1][2][0] for m in frames_vmc]  # the frames' pts, in order: the receiver got the same clock
    assert np.all(np.diff(times) > 0)
    assert "1 utterances" in proc.output
    # `status` as `streamer serve` sends it (docs/protocol.md): the viewer's HUD shows the model's latency and RTF
    speaking = [s for s in statuses if s["latency_ms"] > 0]
    assert speaking and all(s["rtf"] > 0 and s["session"] == "broadcast" for s in speaking), statuses
    assert statuses[-1]["frames_sent"] > 0 and statuses[-1]["clients"] == 1
