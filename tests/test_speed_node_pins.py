"""Folders pinned, and cells recorded, while the speed switches were keys of the trainer node
(``trainer.compile=true``) are the plan of the budget that spells them ``speed.compile=true``
(``speed_node_spelling`` in cicfw/reproduction/catalogue.py); a real difference of a switch is still refused."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
from hydra import initialize_config_module

from cicfw.reproduction import app as reproduce

REPO = Path(__file__).resolve().parents[1]
KEYS = ("budget", "train", "suite")


def published_pin(folder: str = "converged6_xeon") -> dict:
    return json.loads((REPO / "docs" / "results" / folder / "reproduce.json").read_text())["pinned"]


def test_the_legacy_spelling_becomes_the_speed_nodes():
    assert reproduce.speed_node_spelling(["trainer.compile=true", "trainer.max_epochs=6", "trainer.adam=fused",
                                          "speed.channels_last=true", "trainer.keep_memory_x=1"]) == [
        "speed.compile=true", "trainer.max_epochs=6", "speed.adam=fused", "speed.channels_last=true",
        "trainer.keep_memory_x=1"]


@pytest.fixture(scope="module")
def converged6():
    """The plan of converged6_xeon's budget, composed once for the module (a test that changes it, a copy)."""
    return reproduce.compose_plan(["budget=converged6", "weather_family=harsh"])


def test_a_legacy_pin_matches_the_budget_that_spells_the_speed_node(converged6):
    pinned = published_pin()
    assert "trainer.compile=true" in pinned["train"]  # as published
    cfg = converged6
    ours = reproduce.fingerprint(cfg, None)
    assert "speed.compile=true" in ours["train"] and not any(o.startswith("trainer.compile") for o in ours["train"])
    assert reproduce.pinned_differences(pinned, ours, cfg, KEYS) == []
    reproduce.refuse_other_pin("continue_from", "fix", pinned, ours, cfg, KEYS)  # not refused


@pytest.mark.parametrize("legacy", [True, False])
def test_a_real_difference_of_a_speed_switch_is_still_refused(legacy, converged6):
    pinned = published_pin()
    if not legacy:
        pinned = {**pinned, "train": reproduce.speed_node_spelling(pinned["train"])}
    cfg = copy.deepcopy(converged6)
    cfg.budget.train = [("speed.compile=false" if o == "speed.compile=true" else o) for o in cfg.budget.train]
    ours = reproduce.fingerprint(cfg, None)
    assert reproduce.pinned_differences(pinned, ours, cfg, KEYS) == ["train"]
    with pytest.raises(reproduce.ReproduceError, match="another train"):
        reproduce.refuse_other_pin("continue_from", "fix", pinned, ours, cfg, KEYS)


def test_a_cell_recorded_with_the_legacy_spelling_composes_again():
    """A cell's .hydra/config.yaml keeps the budget it ran with; its training config is composed from it again
    (cicfw.diagnose)."""
    cfg = reproduce.compose_plan(["budget=converged6"])
    cfg.budget.train = published_pin()["train"]
    overrides = reproduce.row_overrides(cfg, "cil", 0)
    assert "speed.compile=true" in overrides and not any(o.startswith("trainer.compile") for o in overrides)
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        tcfg = reproduce.compose_train(cfg, "cil", 0)
    assert tcfg.speed.compile is True and tcfg.speed.channels_last is True
