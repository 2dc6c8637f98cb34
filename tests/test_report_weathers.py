"""A reproduction report says under which weathers its suite was driven: a folder pinned before the weather
families names none and was driven under the harsh presets."""
from __future__ import annotations

from cicfw.reproduction.report import weathers_said


def test_the_family_a_folder_pinned_is_named():
    pinned = {"pinned": {"suite": ["suite=single_turn", "sim.weather_family=carla"]}}
    assert weathers_said(pinned) == "; weathers: the `carla` family"


def test_a_folder_pinned_before_the_families_was_driven_under_the_harsh_ones():
    assert weathers_said({"pinned": {"suite": ["suite=single_turn"]}}) == "; weathers: the `harsh` family"


def test_another_simulator_or_no_pin_says_nothing():
    assert weathers_said({"pinned": {"suite": ["sim=carla"]}}) == ""
    assert weathers_said({}) == ""
