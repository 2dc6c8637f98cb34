"""The paper's single-turn suite: turns only, every turn of every junction, keys shared with the
junctions suite; the report says which suite ran and breaks success down by manoeuvre."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cicfw.benchmark.evaluation_report import Run, markdown_table, summary
from cicfw.benchmark.suite import build_suite, make_backend
from cicfw.sim.town import load_town

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
WEATHERS = ["ClearNoon"]


def heading_change_deg(route) -> float:
    """The route's turn through its junction, positive to the left (CCW), in degrees, computed from its
    points alone (the segment entering the junction vs the one leaving it), independent of its labels."""
    inside = np.flatnonzero(route.in_junction)
    i, j = max(inside[0], 1), min(inside[-1], len(route.points) - 2)
    a = route.points[i] - route.points[i - 1]
    b = route.points[j + 1] - route.points[j]
    d = np.arctan2(b[1], b[0]) - np.arctan2(a[1], a[0])
    return float(np.degrees((d + np.pi) % (2 * np.pi) - np.pi))


def geometric_manoeuvre(route) -> str:
    d = heading_change_deg(route)
    return "straight" if abs(d) < 30 else ("left" if d > 0 else "right")


@pytest.fixture(scope="module")
def backend():
    return make_backend({"name": "embedded"})


@pytest.mark.parametrize("town", ["town_a", "town_b", TOWN])
def test_single_turn_has_no_straight_and_covers_every_turn_of_every_junction(backend, town):
    routes = backend.single_turn_routes(town)
    eps = build_suite(backend, [town], WEATHERS, name="single_turn")
    # the turns, classified from geometry: every (junction, in road, out road) that turns
    turns = {(r.meta["junction"], r.meta["from_road"], r.meta["to_road"]): geometric_manoeuvre(r)
             for r in routes if geometric_manoeuvre(r) != "straight"}
    got = {(routes[e.pair].meta["junction"], routes[e.pair].meta["from_road"], routes[e.pair].meta["to_road"]): e.command
           for e in eps}
    assert len(got) == len(eps)  # each turn once per weather
    assert got == turns  # exactly the geometric turns, with their geometric labels
    assert "straight" not in {e.command for e in eps}
    junctions = {r.meta["junction"] for r in routes}
    assert {j for j, _, _ in got} == junctions  # every junction is covered
    assert {e.command for e in eps} == {"left", "right"}


def test_shipped_towns_single_turn_counts(backend):
    """48 turns in the training town (24 left, 24 right) and 32 in the new town: 320 episodes."""
    counts = {}
    for town in ("town_a", "town_b"):
        eps = build_suite(backend, [town], WEATHERS, name="single_turn")
        counts[town] = (sum(e.command == "left" for e in eps), sum(e.command == "right" for e in eps))
    assert counts == {"town_a": (24, 24), "town_b": (16, 16)}


def test_junctions_suite_keeps_straights_and_shares_keys(backend):
    full = build_suite(backend, [TOWN], WEATHERS, name="junctions")
    turns = build_suite(backend, [TOWN], WEATHERS, name="single_turn")
    assert "straight" in {e.command for e in full}
    assert {e.key for e in turns} == {e.key for e in full if e.command != "straight"}
    assert build_suite(backend, [TOWN], WEATHERS) == full  # junctions stays the library default


def test_unknown_suite_and_empty_selection_are_one_clear_line(backend):
    with pytest.raises(ValueError, match=r"unknown suite 'turns'; known suites: single_turn \(left/right\), "
                                         r"junctions \(left/right/straight\)"):
        build_suite(backend, [TOWN], WEATHERS, name="turns")
    routes = backend.single_turn_routes(TOWN)
    straight = [i for i, r in enumerate(routes) if r.meta["command"] == 5]
    with pytest.raises(ValueError, match="keeps none of the chosen pairs"):
        build_suite(backend, [TOWN], WEATHERS, name="single_turn", pairs=straight[:1])


def test_report_names_the_suite_and_breaks_success_down_by_manoeuvre():
    def row(cmd, ok):
        return {"town_set": "training", "weather_set": "training", "command": cmd, "success": ok,
                "reason": "goal" if ok else "off_road"}

    rows = [row("left", True), row("left", False), row("right", True), row("right", True), row("left", True)]
    run = Run("m", rows, meta={"suite": {"name": "single_turn"}})
    s = summary(run)
    assert s["suite"] == "single_turn"
    assert s["manoeuvres"] == {"left": {"success": 2, "episodes": 3, "rate": 66.67},
                               "right": {"success": 2, "episodes": 2, "rate": 100.0}}
    md = markdown_table([run])
    assert "Suite: single_turn (the paper's single-turn task: turns only)." in md
    assert "| m | 66.67 (2/3) | 100.00 (2/2) |" in md
    assert "Straight" not in md
