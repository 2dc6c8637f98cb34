"""The tests cicfw's docs/plugins.md asks a plugin author to run (plus this mixer's own behaviour).

Run after `pip install .` (the entry point and the Hydra search path exist only once installed):
    pytest plugins/cicfw-attention-mixer/tests
"""
from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_module

from cicfw.registry import MIXERS
from cicfw.testing import check_mixer, fast_dev_run
from cicfw_attention_mixer import AttentionMixer


def test_registered_by_entry_point():
    assert MIXERS.get("attention") is AttentionMixer
    assert MIXERS.origin("attention") == "cicfw-attention-mixer"


def test_mixer_contract():
    check_mixer("attention", hidden=32, heads=4)
    check_mixer("attention", hidden=32, heads=2, gate_init=1.0)


def test_config_found_through_search_path():
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("train", overrides=["mixer=attention", "mixer.heads=8"])
    assert cfg.mixer.name == "attention" and cfg.mixer.heads == 8 and cfg.mixer.hidden == 256


@pytest.mark.parametrize("kwargs, word", [
    ({"hidden": 30, "heads": 4}, "divisor"),
    ({"hidden": 0}, "positive"),
    ({"dropout": 1.0}, "probability"),
    ({"attn_dropout": -0.1}, "probability"),
    ({"gate_init": "zero"}, "number"),
    ({"gate_init": float("nan")}, "finite number"),  # a NaN gate steers NaN from the first step
])
def test_bad_kwargs_say_what_is_accepted(kwargs, word):
    with pytest.raises(ValueError, match=word):
        AttentionMixer(in_dim=16, out_dim=1, **kwargs)


def _branch_outputs_after_editing_branch0(mixer: AttentionMixer, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    mixer.eval()
    with torch.no_grad():
        before = mixer(h)
        mixer.branches[0][0].weight.add_(1.0)
        return before, mixer(h)


def test_gate_zero_is_independent_branches_and_gate_open_shares():
    torch.manual_seed(0)
    h = torch.randn(3, 16)
    before, after = _branch_outputs_after_editing_branch0(AttentionMixer(16, 1, hidden=8, heads=2), h)
    assert not torch.allclose(before[:, 0], after[:, 0])  # branch 0 changed ...
    assert torch.allclose(before[:, 1:], after[:, 1:])  # ... and, gate shut, the others did not notice
    before, after = _branch_outputs_after_editing_branch0(AttentionMixer(16, 1, hidden=8, heads=2, gate_init=1.0), h)
    assert not torch.allclose(before[:, 1:], after[:, 1:])  # gate open: the others read branch 0


def test_attention_weights_are_inspectable():
    mixer = AttentionMixer(16, 9, hidden=8, heads=2)
    mixer(torch.randn(5, 16))
    seen = mixer.inspect()
    assert seen["attention"].shape == (5, 4, 4)
    assert torch.allclose(seen["attention"].sum(-1), torch.ones(5, 4))  # each branch's read sums to 1
    assert seen["gate"].shape == (4, 1)


def test_trains_by_name(tmp_path):
    assert fast_dev_run(tmp_path, "mixer=attention", "mixer.hidden=64") >= 0.0
