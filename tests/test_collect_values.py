"""Collect values the expert cannot drive with, and a seed the episodes cannot derive from, are one line
naming the key before any work."""
from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_module

import cicfw.collect.app as collect_mod
import cicfw.collect.dataset as dataset_mod
from cicfw.sim.expert import ExpertParams


@pytest.mark.parametrize("override, key, accepted", [
    ("expert.cruise_kmh=-5", "collect.expert.cruise_kmh", "> 0 km/h"),
    ("expert.cruise_kmh=0", "collect.expert.cruise_kmh", "> 0 km/h"),
    ("expert.cruise_kmh=500", "collect.expert.cruise_kmh", "the car's top speed, got 500"),
    ("expert.lookahead_max=0", "collect.expert.lookahead_max", "> 0 m"),
    ("expert.lookahead_max=2", "collect.expert.lookahead_max", "below expert.lookahead_min"),
    ("expert.decel=-1", "collect.expert.decel", "> 0 m/s^2"),
    ("expert.lateral_accel=0", "collect.expert.lateral_accel", "> 0 m/s^2"),
    ("expert.min_kmh=40", "collect.expert.min_kmh", "at most the cruise speed"),
    ("expert.lookahead_gain=-0.5", "collect.expert.lookahead_gain", ">= 0 s"),
    ("seed=-1", "collect.seed", "integer >= 0"),
    ("sim.command_distance=30", "sim.command_distance", "command_distance=30.0"),  # the suite's, not read here
])
def test_a_value_the_collection_cannot_use_is_one_line_naming_the_key(tmp_path: Path, capsys, monkeypatch,
                                                                      override: str, key: str, accepted: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("collect", overrides=[f"out_dir={tmp_path / 'out'}", "workers=0", override])
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("simulated despite a bad value"))
    with pytest.raises(SystemExit) as exc:
        collect_mod.run(cfg)
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"cicfw: error: {key}"), lines
    assert accepted in lines[0]
    assert not (tmp_path / "out").exists()


def test_the_expert_refuses_such_values_wherever_it_is_built():
    with pytest.raises(ValueError, match=r"^expert\.lookahead_max"):
        ExpertParams(lookahead_max=0)
    ExpertParams(cruise_kmh=30, min_kmh=30)  # the bounds themselves are accepted


def test_the_collection_s_own_command_distance_is_the_one_to_set():
    """``command_distance`` places the collected commands; ``sim.command_distance`` may equal it or stay the
    backend's default (the sim group always sets it), and is refused otherwise (it would be ignored)."""
    from cicfw.collect.config import resolve_config

    for sim_cd in (12.0, 30.0):
        cfg = resolve_config({"command_distance": 30.0, "sim": {"name": "embedded", "command_distance": sim_cd}})
        assert cfg["command_distance"] == 30.0
