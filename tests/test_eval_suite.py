"""The single-turn suite: stable, covers every junction manoeuvre, clear errors for unknown names;
the runner's lockstep batching, its failure reasons, determinism and worker processes."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cicfw.benchmark.builtin_policies import ConstantPolicy, ExpertPolicy
from cicfw.benchmark.policy import Observations, Policy
from cicfw.benchmark.runner import RunnerConfig, run
from cicfw.benchmark.suite import build_suite, make_backend
from cicfw.sim.town import load_town

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
FAST = RunnerConfig(progress_bar=False)


class Backend:
    """The embedded backend with the paper's weathers, whether or not the renderer is installed
    (these tests never render: their policies read no camera)."""

    def __init__(self) -> None:
        self._b = make_backend({"name": "embedded"})

    def towns(self):
        return self._b.towns()

    def weathers(self):
        return ["ClearNoon", "ClearSunset", "MidRainyNoon", "WetCloudySunset"]

    def __getattr__(self, name):
        return getattr(self._b, name)


@pytest.fixture(scope="module")
def backend():
    return Backend()


def test_suite_covers_every_junction_turn_of_the_test_town_and_is_stable(backend):
    town = load_town(TOWN)
    eps = build_suite(backend, [TOWN], ["ClearNoon", "MidRainyNoon"], training_towns=["bench_town"])
    assert eps == build_suite(backend, [TOWN], ["ClearNoon", "MidRainyNoon"], training_towns=["bench_town"])
    one_weather = [e for e in eps if e.weather == "ClearNoon"]
    # every ordered pair of distinct arms at every junction, exactly once (X: 12, T: 6)
    expected = {(j.id, a, b) for j in town.junctions for a in j.arms for b in j.arms if a != b}
    got = [(e.route.split("/")[1], *e.route.split("/")[2].split(">")) for e in one_weather]
    assert len(got) == len(set(got)) == len(expected) == 12 + 4 * 6
    assert set(got) == expected
    assert sorted({e.command for e in one_weather}) == ["left", "right", "straight"]
    # each pair under each weather; ids in order; keys unique; table groups from the config
    assert len(eps) == 2 * len(expected) and [e.index for e in eps] == list(range(len(eps)))
    assert len({e.key for e in eps}) == len(eps)
    assert {(e.weather, e.weather_set) for e in eps} == {("ClearNoon", "training"), ("MidRainyNoon", "new")}
    assert {e.town_set for e in eps} == {"training"}


def test_subsets_by_town_weather_and_pair(backend):
    eps = build_suite(backend, ["town_a", "town_b"], ["ClearSunset"], training_towns=["town_a"], pairs=[0, 3])
    assert [(e.town, e.pair) for e in eps] == [("town_a", 0), ("town_a", 3), ("town_b", 0), ("town_b", 3)]
    assert [e.town_set for e in eps] == ["training", "training", "new", "new"]
    assert len(build_suite(backend, ["town_b"], ["ClearNoon"], limit=5)) == 5
    assert build_suite(backend, "town_b", "ClearNoon", limit=5) == build_suite(backend, ["town_b"], ["ClearNoon"], limit=5)
    with pytest.raises(ValueError) as err:
        build_suite(backend, ["town_b"], ["ClearNoon"], pairs=[999])
    assert (err.value.key, err.value.value) == ("suite.pairs", 999) and "'town_b'" in str(err.value)


@pytest.mark.parametrize("kind, kwargs, known", [
    ("town", dict(towns=["Town07"], weathers=["ClearNoon"]), "town_a, town_b"),
    ("weather", dict(towns=["town_a"], weathers=["ClearNoon", "Foggy"]), "ClearNoon, ClearSunset, MidRainyNoon"),
])
def test_unknown_town_or_weather_lists_the_known_ones(backend, kind, kwargs, known):
    with pytest.raises(ValueError) as err:
        build_suite(backend, **kwargs)
    assert err.value.value == kwargs[f"{kind}s"][-1] and known in str(err.value)  # the name, and those known


def test_always_hard_left_fails_off_road_before_the_timeout(backend):
    eps = build_suite(backend, [TOWN], ["ClearNoon"], pairs=[0, 7, 20])
    res = run(eps, ConstantPolicy(steer=-1.0), backend, FAST)
    for row in res.rows:
        assert not row["success"] and row["reason"] == "off_road", row
        assert row["time_s"] < row["timeout_s"]
        assert row["offroad_fraction"] > 0.1  # the car circles across the road edge
        off = res.trajectories[row["key"]]["off_road"]
        assert (off >= 0.5).sum() * 0.1 > FAST.off_road_s  # more than 3 s with its centre off the road


def test_expert_reaches_the_goal_and_straight_ahead_fails_turns_off_route(backend):
    eps = build_suite(backend, [TOWN], ["ClearNoon"])
    res = run(eps, ExpertPolicy(), backend, FAST)
    assert all(r["success"] and r["reason"] == "success" for r in res.rows)
    assert all(r["goal_distance_m"] <= 2.0 and r["offroad_fraction"] == 0.0 for r in res.rows)
    assert all(0 < r["time_s"] < r["timeout_s"] for r in res.rows)
    # steering straight ahead only completes the straight pairs; turns end far off the route
    res = run(eps, ConstantPolicy(steer=0.0), backend, FAST)
    turns = [r for r in res.rows if r["command"] != "straight"]
    assert turns and all(r["reason"] == "off_route" for r in turns)


class Recording(Policy):
    """Steers like the expert and records the size of every call."""

    def __init__(self) -> None:
        self.expert = ExpertPolicy()
        self.calls: list[int] = []
        self.label = "recording"

    def reset(self, episodes):
        self.expert.reset(episodes)

    def act(self, obs: Observations) -> np.ndarray:
        assert obs.images == {} and obs.command.dtype == np.int64 and set(obs.command) <= {2, 3, 4, 5}
        self.calls.append(len(obs))
        return self.expert.act(obs)


def test_lockstep_one_call_per_chunk_per_step_and_deterministic(backend):
    eps = build_suite(backend, [TOWN], ["ClearNoon"], limit=7)
    pol = Recording()
    res = run(eps, pol, backend, RunnerConfig(batch_size=3, progress_bar=False))
    steps = [r["steps"] for r in res.rows]
    # step k serves every episode still running, in ceil(active / 3) calls of at most 3
    expected = []
    for k in range(max(steps)):
        active = sum(s > k for s in steps)
        expected += [3] * (active // 3) + ([active % 3] if active % 3 else [])
    assert pol.calls == expected and res.steps == sum(steps)
    again = run(eps, ExpertPolicy(), backend, RunnerConfig(batch_size=64, progress_bar=False))
    assert again.rows == res.rows  # the expert is batch-independent: same rows, same bytes
    for k in res.trajectories:
        assert all(np.array_equal(res.trajectories[k][c], again.trajectories[k][c]) for c in res.trajectories[k])


def test_worker_processes_give_the_same_rows():
    sim = {"name": "embedded"}
    eps = build_suite(Backend(), ["town_b"], ["ClearNoon"], limit=6)
    one = run(eps, {"name": "expert"}, sim, FAST)
    two = run(eps, {"name": "expert"}, sim, RunnerConfig(workers=2, progress_bar=False))
    assert two.rows == one.rows and set(two.trajectories) == set(one.trajectories)
    with pytest.raises(ValueError, match="config specs"):
        run(eps, ExpertPolicy(), sim, RunnerConfig(workers=2, progress_bar=False))


def test_a_policy_returning_garbage_is_named():
    class Bad(Policy):
        label = "bad"

        def act(self, obs):
            return np.full(len(obs) + 1, 0.0)

    eps = build_suite(Backend(), [TOWN], ["ClearNoon"], limit=2)
    with pytest.raises(ValueError, match="policy 'bad': act\\(\\) returned 3 values for a batch of 2"):
        run(eps, Bad(), Backend(), FAST)


def test_workers_get_whole_cells_balanced_and_videos_are_chosen_by_id(backend):
    from cicfw.benchmark.runner import shard
    from cicfw.benchmark.video import select_episodes

    eps = build_suite(backend, ["town_a", "town_b"], ["ClearNoon", "ClearSunset", "MidRainyNoon"], limit=4)
    parts = shard(eps, 2)
    cells = [{(e.town, e.weather) for e in p} for p in parts]
    assert not cells[0] & cells[1] and len(cells[0] | cells[1]) == 6  # a cell is never split
    assert sorted(e.index for p in parts for e in p) == list(range(len(eps)))
    assert [len(p) for p in parts] == [12, 12]
    assert [len(p) for p in shard(eps[:3], 2)] == [2, 1]  # one cell: dealt round-robin
    rows = [{"episode": e.index, "key": e.key, "success": e.index % 3 == 0} for e in eps]
    assert [r["episode"] for r in select_episodes(rows, [5, "town_b/ClearNoon/001", 5], 8)] == [5, 13]
    assert [r["episode"] for r in select_episodes(rows, ["failures"], 3)] == [1, 2, 4]
    with pytest.raises(ValueError) as err:
        select_episodes(rows, ["town_c/x/1"], 8)
    assert err.value.value == "town_c/x/1" and "town_a/ClearNoon/000" in str(err.value)  # a key it takes
    with pytest.raises(ValueError) as err:
        select_episodes(rows, [99], 8)
    assert err.value.value == 99 and "0..23" in str(err.value)  # the episodes there are


def test_auto_workers(backend):
    import os

    full = build_suite(backend, ["town_a", "town_b"], ["ClearNoon", "ClearSunset", "MidRainyNoon", "WetCloudySunset"])
    auto = RunnerConfig(workers="auto")
    assert auto.resolve_workers(full, renders=True) == min(os.cpu_count() or 1, 8)
    assert auto.resolve_workers(full, renders=False) == 1  # nothing to render: one process is fastest
    assert auto.resolve_workers(full[:40], renders=True) == 1  # too small to pay for a second process
    assert RunnerConfig(workers=3).resolve_workers(full[:2], renders=True) == 2
    with pytest.raises(ValueError) as err:
        RunnerConfig(workers="many")
    assert (err.value.key, err.value.value) == ("runner.workers", "many")


def test_filming_the_failures_of_a_run_without_one_says_so(tmp_path, capsys):
    import json

    from cicfw.benchmark.finished_run import save_trajectories
    from cicfw.benchmark.video import main

    rows = [{"model": "expert", "episode": 0, "key": "town_a/ClearNoon/000", "town": "town_a", "weather": "ClearNoon",
             "success": True}]
    (tmp_path / "episodes.json").write_text(json.dumps({"episodes": rows, "meta": {}}))
    save_trajectories(tmp_path / "trajectories.npz", rows, {})
    assert main([str(tmp_path)]) == 0
    assert "failures" in capsys.readouterr().err  # what selected nothing, not silence
    assert not (tmp_path / "videos").exists()


def test_filming_an_episode_of_a_town_whose_file_name_is_too_long_is_one_line_before_rendering(tmp_path, capsys,
                                                                                              monkeypatch):
    """An evaluation without maps or videos takes a town file's long stem; filming it later names the episode
    and its town in one line, before a frame is rendered, not a write error after the first film."""
    import json

    import cicfw.benchmark.video as video

    town = "t" * 240  # a legal town file stem (with .yaml), too long for .<stem>_ClearNoon_000.tmp.mp4
    row = {"model": "m", "episode": 0, "key": f"{town}/ClearNoon/000", "town": town, "weather": "ClearNoon", "success": False,
           "reason": "timeout", "route": "r"}
    (tmp_path / "episodes.json").write_text(json.dumps({"episodes": [row], "meta": {}}))
    np.savez(tmp_path / "trajectories.npz", **{"e0.x": np.zeros(2), "e0.y": np.zeros(2), "e0.yaw": np.zeros(2)})
    monkeypatch.setattr(video, "write_video", lambda *a, **k: pytest.fail("rendered"))
    assert video.main([str(tmp_path), "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and row["key"] in err[0] and repr(town) in err[0], err
    assert not (tmp_path / "videos").exists()


def test_filming_a_training_run_folder_points_at_its_evaluation(tmp_path, capsys):
    from cicfw.benchmark.video import main

    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "evaluate").mkdir()
    (tmp_path / "evaluate" / "episodes.json").write_text('{"episodes": [], "meta": {}}')
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / "evaluate") in err[0], err
    assert not (tmp_path / "videos").exists()


@pytest.mark.parametrize("most", ["0", "-1"])
def test_filming_at_most_no_video_is_refused(tmp_path, capsys, most):
    """--max 0 cut the failed episode it chose and then said that 'failures' selected none, exit 0."""
    import json

    from cicfw.benchmark.finished_run import save_trajectories
    from cicfw.benchmark.video import main

    rows = [{"model": "expert", "episode": 0, "key": "town_a/ClearNoon/000", "town": "town_a", "weather": "ClearNoon",
             "success": False}]
    (tmp_path / "episodes.json").write_text(json.dumps({"episodes": rows, "meta": {}}))
    save_trajectories(tmp_path / "trajectories.npz", rows, {})
    assert main([str(tmp_path), "--max", most]) == 2
    assert f"--max={most}" in capsys.readouterr().err
    assert not (tmp_path / "videos").exists()


def test_pairs_the_suite_does_not_drive_are_named_not_dropped_silently(backend, caplog):
    """``suite=single_turn`` drives left and right turns: asked for by number, a straight pair is left out
    with a warning naming it (the episode count alone would not say which)."""
    every = build_suite(backend, ["town_a"], ["ClearNoon"], name="junctions")
    straight = next(e.pair for e in every if e.command == "straight")
    turn = next(e.pair for e in every if e.command in ("left", "right"))
    with caplog.at_level("WARNING", logger="cicfw.benchmark.suite"):
        eps = build_suite(backend, ["town_a"], ["ClearNoon"], pairs=[turn, straight], name="single_turn")
    assert [e.pair for e in eps] == [turn]
    said = [r.getMessage() for r in caplog.records if r.name == "cicfw.benchmark.suite"]
    assert len(said) == 1 and f"pair {straight} (straight)" in said[0] and f"pair {turn}" not in said[0], said
    caplog.clear()
    build_suite(backend, ["town_a"], ["ClearNoon"], name="single_turn")  # the suite's own choice: nothing to say
    assert not [r for r in caplog.records if r.name == "cicfw.benchmark.suite"]


@pytest.mark.parametrize("sim, family", [({"name": "embedded", "weather_family": "harsh"}, "harsh"),
                                         ({"name": "embedded", "weather_family": "carla"}, "carla"),
                                         ({"name": "embedded"}, "harsh")])  # recorded before the families
def test_a_video_renders_the_weather_family_the_run_drove_under(tmp_path, monkeypatch, sim, family):
    """A film of a run under sim.weather_family=harsh was rendered with the default family's MidRainyNoon."""
    import json

    import numpy as np

    import cicfw.benchmark.video as video
    from cicfw.benchmark.finished_run import save_trajectories
    from cicfw.sim.render.weather import WEATHER_FAMILIES

    rows = [{"model": "expert", "episode": 0, "key": "town_a/MidRainyNoon/000", "town": "town_a",
             "weather": "MidRainyNoon", "route": "r", "success": False, "reason": "timeout"}]
    (tmp_path / "episodes.json").write_text(json.dumps({"episodes": rows, "meta": {"sim": sim}}))
    save_trajectories(tmp_path / "trajectories.npz", rows, {rows[0]["key"]: {"x": np.zeros(1)}})
    seen = []

    class Rendered(Exception):
        pass

    def renderer(town, weather, seed, cameras):
        seen.append(weather)
        raise Rendered

    monkeypatch.setattr(video, "get_renderer", renderer)
    with pytest.raises(Rendered):
        video.main([str(tmp_path), "0"])
    assert seen == [WEATHER_FAMILIES[family]["MidRainyNoon"]]
    assert WEATHER_FAMILIES["harsh"]["MidRainyNoon"] != WEATHER_FAMILIES["carla"]["MidRainyNoon"]


def test_a_film_cut_short_leaves_no_half_written_file(tmp_path, monkeypatch):
    """A render that fails after the MP4 writer opened (an error, Ctrl-C) leaves neither the film nor its
    hidden temporary file."""
    import numpy as np

    import cicfw.benchmark.video as video

    class Cut(Exception):
        pass

    class Renderer:
        calls = 0

        def render(self, x, y, yaw, t):
            Renderer.calls += 1
            if Renderer.calls > 2:
                raise Cut
            return {"centre": np.zeros((88, 200, 3), np.uint8)}

    monkeypatch.setattr(video, "get_renderer", lambda *a, **k: Renderer())
    tr = {k: np.zeros(4) for k in ("x", "y", "yaw", "steer", "speed_kmh")}
    tr["command"] = np.full(4, 2)
    row = {"key": "town_a/ClearNoon/000", "route": "r", "success": False, "reason": "timeout"}
    with pytest.raises(Cut):
        video.write_video(tmp_path / "film.mp4", row, tr, None, "ClearNoon")
    assert Renderer.calls == 3 and list(tmp_path.iterdir()) == []
