"""The live default root mode keeps the avatar facing its start heading: the looping demo through the
engine (the same Session and PoseDecoder as `streamer serve`, run faster than real time) for a minute."""

import asyncio

import numpy as np
import pytest

from dimgestor import rotations as R
from dimgestor.audio import load_wav
from dimgestor.audio import SAMPLE_RATE
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor_app.cli import build_parser
from streamer.sessions import Session
from streamer.sources import DEMO_WAV, AudioChunk

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]


def run_session(bundle, audio, **root):
    async def source():
        for i in range(0, len(audio), SAMPLE_RATE // 5):
            yield AudioChunk(audio[i : i + SAMPLE_RATE // 5], i / SAMPLE_RATE, 0.0)

    frames = []
    session = Session.from_bundle(bundle, **root)
    asyncio.run(session.run(source(), frames.extend))
    return frames


def headings_deg(frames):
    return np.degrees(np.unwrap([R.split_heading(f.rotations[0])[0] for f in frames]))


def test_the_looping_demo_faces_its_start_on_average_under_the_live_default():
    args = build_parser().parse_args(["serve"])
    assert args.root == "tether"
    bundle = load_checkpoint(None)
    clip = load_wav(DEMO_WAV)
    audio = np.tile(clip, int(np.ceil(60 * SAMPLE_RATE / len(clip))))[: 60 * SAMPLE_RATE]
    frames = run_session(bundle, audio, root=args.root, tether_s=args.tether_s)
    assert len(frames) == 60 * 20
    heading = headings_deg(frames)
    assert np.abs(heading).mean() < 30, f"mean |heading| {np.abs(heading).mean():.0f} degrees from the start"
    ground = np.linalg.norm([f.root_pos[[0, 2]] for f in frames], axis=1)
    assert ground.max() < 50  # cm: stays on its spot
    assert heading.std() > 1  # but still turns as the model gestures (not locked)
