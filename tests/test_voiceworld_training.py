"""A small model trained in CI time on the voice world follows voices it never heard (issue 20).

Trained on 3 minutes of the train voices (without mirroring or speed perturbation: with them the same budget
measured contrast 1.8 and coupling margin -0.18, the model not yet following the audio), scored on held-out voices (unseen variants and an unseen language):
its wrist speed must follow the speech's loudness (coupling above the circularly shifted baseline by
COUPLING_MARGIN; the rule's own is ~0.34) and its hands must rest in pauses (speech/silence wrist speed at
least CONTRAST; the rule's own is ~20).

The recipe is RECIPE (override with DIMGESTOR_TEST_RECIPE): by default the embedded default model's own (its
front end, lookahead and condition dropout from its recorded training options, sampled at its guidance scale),
so the recipe that ships is the one held to the rule. Recipes measured not to learn the rule at this scale are
listed in KNOWN_TO_FAIL with what they scored, and the tests are then marked as expected failures and not run
(the training would only confirm it); do not lower the bars to make one pass.
"""

import os
import shutil

import pytest
import torch

from dimgestor.evaluation.eval import generate_raw, valid_clips
from dimgestor.evaluation.voiceworld import make_voice_world, margins, score_motion
from dimgestor.streaming.checkpoint import load_checkpoint
from dimgestor.training.dataset import GestureDataset
from dimgestor.training.train import TrainConfig, train

RECIPE = os.environ.get("DIMGESTOR_TEST_RECIPE", "default")
TRAIN_MINUTES, HELDOUT_MINUTES, STEPS = 3.0, 1.5, 300
WINDOW_S = 2.5  # training windows (the shipped model trains on 5 s): half the compute per step, scores alike (below)
COUPLING_MARGIN = 0.1  # coupling - mean coupling against shifted audio
CONTRAST = 3.0  # wrist speed in speech / in silence (natural pauses)
# Measured with this file's settings on held-out voices (the rule itself: contrast ~20, coupling margin ~0.3-0.4),
# ~1.5 min on one thread of the shared 2-core machine (the other recipes were measured on 5 s windows):
#   default (speech front end, 300 ms lookahead, dropout 0.15, guidance 1.25): contrast 4.5, coupling margin
#     0.19 (training seed 1: 8.2, 0.33); on 5 s windows 5.6, 0.21 (seed 1: 4.5, 0.20), unguided 3.2 / 0.11
#     (seed 1: 3.3 / 0.13)
#   logmel: contrast 3.9, coupling margin 0.13 (seed 1: 4.3, 0.13)
# Stroke margins stay small for every recipe (0.01-0.09; the rule's 0.27): strokes are not asserted here
# (benchmarks/voice_world.py follows them).
KNOWN_TO_FAIL = {
    "speech": "speech front end, 150 ms lookahead, no dropout (main 7deaad2), these settings: measured contrast 2.9, "
              "coupling margin 0.06 (stroke margin 0.05); at 30 min x 500 steps it beats log-mel "
              "(benchmarks/results/voice_world_speech.json)",
}
EXPECTED_FAILURE = pytest.mark.xfail(RECIPE in KNOWN_TO_FAIL, run=False,
                                     reason=f"{RECIPE} recipe at CI scale: {KNOWN_TO_FAIL.get(RECIPE)}")


def recipe(name: str) -> tuple[dict, float, float]:
    """(model overrides, condition dropout, guidance scale) of a named recipe."""
    if name == "default":  # the embedded model's own, as recorded in its config
        shipped = load_checkpoint(None)
        opts = shipped.info["options"]
        return dict(opts["overrides"]), float(opts["cond_drop"] or 0.0), shipped.config.guidance
    if name in ("logmel", "speech"):
        return {"frontend": name}, 0.0, 1.0
    raise ValueError(f"DIMGESTOR_TEST_RECIPE: unknown recipe {name!r} (default, logmel, speech)")


pytestmark = [pytest.mark.slow, pytest.mark.timeout(1200),
              pytest.mark.skipif(shutil.which("espeak-ng") is None,
                                 reason="espeak-ng is not installed (Debian: apt-get install espeak-ng)")]


@pytest.fixture(scope="module")
def held_out_scores(tmp_path_factory):
    root = tmp_path_factory.mktemp("voiceworld")
    make_voice_world(root / "world", TRAIN_MINUTES, HELDOUT_MINUTES, seed=11, clip_s=30.0)
    torch.set_num_threads(1)
    overrides, cond_drop, guidance = recipe(RECIPE)
    run = train(TrainConfig(data=str(root / "world"), out=str(root / "run"), preset="realtime",
                             overrides=overrides, cond_drop=cond_drop, max_steps=STEPS, batch_size=8, window_s=WINDOW_S,
                             ckpt_every=STEPS, valid_every=0, seed=0, cache_dir=str(root / "cache"),
                             progress=False, mirror=False, speeds=()))
    bundle = load_checkpoint(run)
    bundle.model.eval()
    bundle.config = bundle.model.config = bundle.config.model_copy(update={"guidance": guidance})
    valid = GestureDataset(root / "world", split="valid", spec=bundle.feature_spec, window_s=5.0,
                           cache_dir=root / "cache")
    audios = [a for a, _ in valid_clips(valid)]
    raws = [generate_raw(bundle, a, bundle.config.sample_steps, seed=i) for i, a in enumerate(audios)]
    row = score_motion(raws, audios, bundle.skeleton, bundle.feature_spec)
    row.update(margins(row))
    return row


@EXPECTED_FAILURE
def test_hand_speed_follows_the_loudness_of_held_out_voices(held_out_scores):
    assert held_out_scores["coupling_margin"] >= COUPLING_MARGIN, held_out_scores


@EXPECTED_FAILURE
def test_hands_rest_in_the_pauses_of_held_out_voices(held_out_scores):
    assert held_out_scores["contrast"] >= CONTRAST, held_out_scores
