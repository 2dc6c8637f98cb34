"""Ranges and names a type cannot say, refused where the value is consumed, naming the full key and the value:
the simulator's distances, the suite's training towns and weathers, the epochs to train and to keep, the
agent's speed range (the data reader's), runs of different suites in one report, and every job of a multirun
before the first one trains."""
from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cicfw.core.errors import CicfwError, ConfigError

DISTANCES = ("success_radius", "command_distance", "max_deviation", "route_before", "route_after")


@pytest.mark.parametrize("key", DISTANCES)
@pytest.mark.parametrize("value", [-1.0, 0.0, math.nan])
def test_the_embedded_simulators_distances_are_positive(key, value):
    from cicfw.benchmark.suite import make_backend

    with pytest.raises(ConfigError) as err:
        make_backend({"name": "embedded", key: value})
    assert err.value.key == f"sim.{key}"
    assert err.value.value is value or (math.isnan(value) and math.isnan(err.value.value))


@pytest.mark.parametrize("key", DISTANCES)
def test_the_carla_backends_distances_are_positive(key):
    pytest.importorskip("carla", reason="the CARLA client is not installed")
    from cicfw.carla_client.backend import CarlaBackend

    with pytest.raises(ConfigError) as err:
        CarlaBackend(client=object(), **{key: -1.0})
    assert (err.value.key, err.value.value) == (f"sim.{key}", -1.0)


SUITE = dict(towns=["town_a", "town_b"], weathers=["ClearNoon", "ClearSunset", "MidRainyNoon", "WetCloudySunset"],
             limit=1)


@pytest.mark.parametrize("key, value", [("training_towns", "town_c"), ("training_weathers", "HardRainNoon"),
                                        ("training_weathers", "ClearNon")])
def test_training_towns_and_weathers_are_among_the_suites(key, value):
    from cicfw.benchmark.suite import build_suite, make_backend

    with pytest.raises(ConfigError) as err:
        build_suite(make_backend(None), **SUITE, **{key: [value]})
    assert (err.value.key, err.value.value) == (f"suite.{key}", value)


def test_a_subset_of_the_suite_keeps_its_training_sets():
    """``suite.weathers=[MidRainyNoon]`` (a subset) leaves the training weathers the suite defines, undriven."""
    from cicfw.benchmark.suite import build_suite, make_backend

    eps = build_suite(make_backend(None), towns=["town_b"], weathers=["MidRainyNoon"], limit=1,
                      training_towns=["town_a"], training_weathers=["ClearNoon", "ClearSunset"])
    assert {(e.town_set, e.weather_set) for e in eps} == {("new", "new")}
