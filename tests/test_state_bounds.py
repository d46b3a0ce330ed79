"""A restored state's values are bounded by what the model's own states hold (issue 52, item 3): the bounds are learnt
from the model itself on probe signals (`dimgestor.streaming.state_bounds`), and real voices the model never heard
stay well inside them, so no real session's state is ever refused for its values."""
from pathlib import Path

import pytest

from dimgestor.audio import load_wav
from dimgestor.streaming import state_bounds
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.streaming.savestate_checks import floats
from dimgestor.streaming.stream import GestureStream

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
VOICES = [SHARED / "zeggs_sample" / "067_Speech_2_x_1_0.wav",  # the studio actor the default model learnt from
          SHARED / "phone_aligned_speech" / "clip000028_tCAkv4ggPgI.wav",  # real-world speakers it never heard
          SHARED / "phone_aligned_speech" / "clip000070_lskPN47Lo8o.wav"]
SECONDS = 45.0  # the denoiser's Mamba-2 state keeps growing for ~40 s of speech, then levels


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_real_voices_keep_the_default_models_state_within_half_its_learnt_bounds():
    voices = [p for p in VOICES if p.exists()]
    if not voices:
        pytest.skip(f"{SHARED} not found: the real voices are only present beside the dev checkout (../shared)")
    bundle = load_checkpoint(None)
    probe = GestureStream(bundle.model)
    limits = state_bounds.bounds(probe)
    worst: dict[str, float] = {}
    for wav in voices:
        audio = load_wav(wav)[: int(SECONDS * 16000)]
        s = GestureStream(bundle.model)
        for at in range(0, len(audio), 3200):
            s.push(audio[at:at + 3200])
            state_bounds.check_bounds(probe, s.state)  # (raises on any leaf beyond its bound)
            for path, v in state_bounds.leaves(s.state):
                a = floats(v)
                if path in limits and a is not None:
                    worst[path] = max(worst.get(path, 0.0), state_bounds._peak(a) / limits[path])
    assert max(worst.values()) < 0.5, {p: round(r, 3) for p, r in sorted(worst.items(), key=lambda x: -x[1])}
