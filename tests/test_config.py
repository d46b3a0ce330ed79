import json

import pytest

from dimgestor.config import PRESETS, ConfigError, ModelConfig, exact_div, get_preset


def test_presets_build_and_have_the_paper_sizes():
    for name in PRESETS:
        get_preset(name)
    paper = get_preset("paper")
    assert (paper.hidden, paper.n_blocks, paper.d_state, paper.d_conv, paper.expand, paper.down_kernel) == \
        (1280, 6, 256, 4, 2, 201)
    assert (paper.n_steps, paper.beta_start, paper.beta_end) == (1000, 1e-4, 8e-2)


def test_rates_are_derived_exactly():
    c = get_preset("tiny")
    assert (c.hop_length, c.feats_per_frame, c.samples_per_frame) == (160, 5, 800)
    assert c.lookahead_feats == 3  # 30 ms at 100 Hz
    # centred kernel: 201 taps around the middle of a 5-feature frame -> 98 features after its last one
    assert get_preset("paper").lookahead_feats == 98


def test_exact_div_fails_loudly():
    assert exact_div(16000, 160) == 100
    with pytest.raises(ValueError, match="not a multiple"):
        exact_div(16000, 300, "sample_rate / feature_rate")


@pytest.mark.parametrize("overrides, message", [
    ({"fps": 30}, "feature_rate / fps"),
    ({"headdim": 24}, "headdim"),
    ({"lookahead_ms": 100}, "down_kernel 11 cannot see"),
    ({"lookahead_ms": 15}, "lookahead_ms"),
    ({"beta_end": 2.0}, "beta_start < beta_end"),
    ({"frontend": "pretrained"}, "pretrained_path"),
    ({"hidden": 0}, "hidden must be positive"),
    ({"no_such_field": 1}, "no_such_field"),
])
def test_bad_values_give_clear_errors(overrides, message):
    with pytest.raises(ConfigError, match=message):
        get_preset("tiny", **overrides)


def test_unknown_preset_lists_the_known_ones():
    with pytest.raises(ConfigError, match="paper, realtime, tiny"):
        get_preset("huge")


def test_config_is_frozen_and_round_trips_through_json():
    c = get_preset("realtime", motion_dim=99)
    with pytest.raises(Exception):
        c.hidden = 3
    again = ModelConfig(**json.loads(json.dumps(c.model_dump())))
    assert again == c and again.motion_dim == 99
