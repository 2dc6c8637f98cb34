"""Towns as data: the shipped towns load, and each mistake in a town file gives one clear error."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from cicfw.sim.roadgraph import LEFT, RIGHT, STRAIGHT, RoadGraph, single_turn_routes
from cicfw.sim.town import TownError, build_town, load_town, town_names

STYLE = {k: [100, 100, 100] for k in ("road", "marking", "centre_line", "sidewalk", "terrain", "roof",
                                        "vegetation", "pole", "sky")}
STYLE["facades"] = [[200, 100, 50], [50, 100, 200]]

# A small hand-made town: a rectangle whose two ends are loops, four T junctions.
#   N1 ---- N2
#   |        |      (plus curved loops west of S1/N1 and east of S2/N2)
#   S1 ---- S2
SMALL = {
    "name": "small",
    "lane_width": 3.5,
    "sidewalk_width": 2.0,
    "style": STYLE,
    "nodes": {"S1": [60, 0], "S2": [160, 0], "N1": [60, 100], "N2": [160, 100]},
    "roads": [
        ["S1", "S2"],
        ["N1", "N2"],
        ["S1", "N1"],
        ["S2", "N2"],
        {"id": "west", "a": "S1", "b": "N1", "via": [[0, 0], [0, 100]], "radius": 20},
        {"id": "east", "a": "S2", "b": "N2", "via": [[220, 0], [220, 100]], "radius": 20},
    ],
    "buildings": {"seed": 1},
    "props": {"seed": 2},
}


def small(**changes) -> dict:
    spec = copy.deepcopy(SMALL)
    spec.update(changes)
    return spec


def test_shipped_towns_load_with_t_and_x_junctions():
    assert {"town_a", "town_b"} <= set(town_names())
    for name in ("town_a", "town_b"):
        t = load_town(name)
        assert t.name == name and len(t.roads) >= 10 and len(t.buildings) > 50
        assert {p.kind for p in t.props} == {"tree", "pole"}
        arms = [len(j.arms) for j in t.junctions]
        assert set(arms) <= {3, 4} and 3 in arms and 4 in arms
        for r in t.roads:  # centrelines start and end on the junction edges, 0.5 m step
            step = np.linalg.norm(np.diff(r.centreline, axis=0), axis=1)
            assert step.max() < 0.51 and step.min() > 0.3
            for end, node in ((r.centreline[0], r.a), (r.centreline[-1], r.b)):
                j = t.junction(node)
                assert np.linalg.norm(end - j.centre) == pytest.approx(j.radius, abs=0.05)
        for j in t.junctions:  # CCW polygons around their centre
            p = j.polygon
            area = 0.5 * np.sum(p[:, 0] * np.roll(p[:, 1], -1) - p[:, 1] * np.roll(p[:, 0], -1))
            assert area > 0
    a, b = load_town("town_a"), load_town("town_b")
    assert len(a.junctions) > len(b.junctions)  # the training town is the larger one
    assert a.style.road != b.style.road and a.style.facades != b.style.facades


def test_load_by_path_and_generation_is_deterministic(tmp_path: Path):
    p = tmp_path / "mine.yaml"
    p.write_text(yaml.safe_dump(SMALL))
    t1, t2 = load_town(str(p)), build_town(copy.deepcopy(SMALL))
    assert t1.name == "small" and len(t1.junctions) == 4
    assert len(t1.buildings) == len(t2.buildings) > 0
    assert all(np.array_equal(x.footprint, y.footprint) for x, y in zip(t1.buildings, t2.buildings))


def test_buildings_and_trees_stay_off_the_roads():
    t = load_town("town_a")
    pts = np.vstack([r.centreline for r in t.roads])
    clear = t.lane_width + t.sidewalk_width
    for b in t.buildings:
        d = np.min(np.linalg.norm(pts[:, None, :] - b.footprint[None], axis=2))
        assert d > clear
    for p in t.props:
        d = np.min(np.linalg.norm(pts - p.position, axis=1))
        assert d > t.lane_width  # poles stand on the sidewalk, trees beyond it


@pytest.mark.parametrize("spec, words", [
    (lambda: small(roads=SMALL["roads"] + [["S1", "Q"]]), ["dangling", "'Q'", "unknown node"]),
    (lambda: small(nodes={**SMALL["nodes"], "S2": [75, 0]}), ["junctions", "overlap"]),
    (lambda: small(nodes={**SMALL["nodes"], "X1": [500, 0], "X2": [600, 0], "X3": [550, 90], "X4": [550, 30]},
                   roads=SMALL["roads"] + [["X1", "X2"], ["X2", "X3"], ["X3", "X1"], ["X4", "X1"],
                                           ["X4", "X2"], ["X4", "X3"]]), ["isolated component"]),
    (lambda: small(lane_widht=3.5), ["unknown field 'lane_widht'"]),
    (lambda: small(lane_width="wide"), ["lane_width must be a number"]),
    (lambda: small(style={**STYLE, "road": [300, 0, 0]}), ["style.road", "0-255"]),
    (lambda: small(nodes={**SMALL["nodes"], "Z": [60, -60]}, roads=SMALL["roads"] + [["S1", "Z"]]),
     ["node 'Z' is a dead end"]),
    (lambda: small(roads=SMALL["roads"][:-1]), ["joins only 2 roads", "via"]),
    (lambda: small(roads=SMALL["roads"] + [["S1", "N2"], ["N1", "S2"]]), ["cross", "S1-N2", "N1-S2"]),
    (lambda: small(roads=SMALL["roads"] + [["S1", "S2"]]), ["defined twice"]),
    (lambda: small(roads=[r for r in SMALL["roads"] if r != ["S1", "N1"]]
                   + [{"a": "S1", "b": "N1", "frontage": "shops"}]), ["frontage", "shops"]),
])
def test_each_mistake_gives_one_clear_error(spec, words):
    with pytest.raises(TownError) as err:
        build_town(spec(), source="bad.yaml")
    msg = str(err.value)
    assert msg.startswith("bad.yaml: ")
    for w in words:
        assert w in msg, msg


def test_unknown_town_name_lists_the_shipped_ones():
    with pytest.raises(TownError) as err:
        load_town("town_z")
    assert all(s in str(err.value) for s in ("'town_z'", "town_a", "town_b")), err.value  # the name, those shipped


def test_bad_yaml_is_a_town_error(tmp_path: Path):
    p = tmp_path / "broken.yaml"
    p.write_text("name: [unclosed\n")
    with pytest.raises(TownError) as err:
        load_town(str(p))
    assert str(p) in str(err.value) and "YAML" in str(err.value)  # the file, and what it is not


def test_single_turn_routes_cover_every_manoeuvre_once_sorted_and_stable():
    for name in ("town_a", "town_b"):
        town = load_town(name)
        routes = single_turn_routes(town)
        expected = sum(len(j.arms) * (len(j.arms) - 1) for j in town.junctions)
        assert len(routes) == expected
        names = [r.name for r in routes]
        assert len(set(names)) == len(names)
        assert names == [r.name for r in single_turn_routes(town)]
        for r in routes:
            assert len(r.turns) == 1 and r.turns[0][1] in (LEFT, RIGHT, STRAIGHT)
            assert set(np.unique(r.commands)) == {2, r.turns[0][1]}
            assert 40 < r.length < 90
        for j in town.junctions:  # every junction has every one of its manoeuvres
            cmds = sorted(r.meta["command"] for r in routes if r.meta["junction"] == j.id)
            assert cmds == ([3] * 4 + [4] * 4 + [5] * 4 if len(j.arms) == 4 else [3, 3, 4, 4, 5, 5])


def test_a_left_turn_gets_command_3_before_the_junction_and_2_after_it():
    town = build_town(copy.deepcopy(SMALL))
    g = RoadGraph(town, command_distance=12.0)
    # southbound on S1-N1 (x ~ 60 - 1.75), turning left (east) at S1 onto S1-S2
    route = g.route((58.25, 70.0, -np.pi / 2), (100.0, -1.75))
    assert [lane.split(":")[0] for lane in route.lanes] == ["S1-N1", "S1-S2"]
    (junction, cmd, entry, exit_), = route.turns
    assert junction == "S1" and cmd == LEFT
    at = lambda s: int(route.commands[np.searchsorted(route.s, s)])  # noqa: E731
    assert at(entry - 20.0) == 2  # follow lane, further than 12 m before the junction
    assert at(entry - 5.0) == 3 and at(entry + 1.0) == 3 and at(exit_ - 0.5) == 3
    assert at(exit_ + 3.0) == 2  # after the exit: follow again
    assert route.in_junction[np.searchsorted(route.s, entry + 1.0)]
    # westbound on S1-S2 (north side of its centreline), turning right (north) at S1 onto S1-N1
    r2 = g.route((100.0, 1.75, np.pi), (61.75, 60.0))
    assert [lane.split(":")[0] for lane in r2.lanes] == ["S1-S2", "S1-N1"]
    assert [t[1] for t in r2.turns] == [RIGHT]


@pytest.mark.parametrize("name, head", [("map.svg", b"<?xml"), ("map.png", b"\x89PNG"), ("map.pdf", b"%PDF")])
def test_a_map_is_written_in_the_format_its_suffix_names(tmp_path: Path, name, head):
    from cicfw.sim.mapplot import save_map

    town = build_town(copy.deepcopy(SMALL))
    assert save_map(town, tmp_path / name, size=2).read_bytes().startswith(head)


def test_a_map_suffix_no_format_matches_is_refused_before_writing(tmp_path: Path):
    from cicfw.core.errors import ConfigError
    from cicfw.sim.mapplot import save_map

    with pytest.raises(ConfigError) as e:
        save_map(build_town(copy.deepcopy(SMALL)), tmp_path / "map.jpgx")
    assert e.value.key == "path" and e.value.value.endswith("map.jpgx")
    assert not list(tmp_path.iterdir())
