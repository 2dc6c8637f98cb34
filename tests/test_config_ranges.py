"""Ranges and names a type cannot say, refused where the value is consumed, naming the full key and the value:
the simulator's distances, the suite's training towns and weathers, the epochs to train and to keep, the
agent's speed range (the data reader's), runs of different suites in one report, and every job of a multirun
before the first one trains."""
from __future__ import annotations

import math

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


@pytest.mark.parametrize("radius", [25.0, 100.0])
def test_a_success_radius_reaching_back_before_the_turn_is_refused(radius):
    """A radius of 100 m made a car that always steers hard left succeed in every episode at its first step:
    the goal lies route_after (25 m) past the junction."""
    from cicfw.benchmark.suite import make_backend

    with pytest.raises(ConfigError) as err:
        make_backend({"name": "embedded", "success_radius": radius})
    assert (err.value.key, err.value.value) == ("sim.success_radius", radius)
    assert make_backend({"name": "embedded", "success_radius": 24.0}).success_radius == 24.0


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


def test_a_python_caller_s_suite_labels_the_training_town_as_the_app_does():
    """``evaluate_policy``'s suite without ``training_towns`` (as docs/evaluation.md's example) counted
    town_a, where the default data is collected, as a new town; it is the training town, as conf/suite/ says."""
    from cicfw.benchmark.suite import build_suite, make_backend

    eps = build_suite(make_backend(None), towns=["town_a", "town_b"], weathers=["ClearNoon"], limit=1)
    assert {(e.town, e.town_set) for e in eps} == {("town_a", "training"), ("town_b", "new")}
    eps = build_suite(make_backend(None), towns=["town_a"], weathers=["ClearNoon"], limit=1, training_towns=[])
    assert {e.town_set for e in eps} == {"new"}  # said on purpose: no training town


def test_the_default_training_weathers_stand_where_the_simulator_lacks_them():
    """A CARLA server given other weathers (sim.weathers=[ClearNoon,HardRainNoon]) keeps the default training
    weathers working: they are the paper's, named, not a typo."""
    from cicfw.benchmark.suite import TRAINING_WEATHERS, build_suite, make_backend

    class OtherWeathers:
        def __init__(self):
            self._b = make_backend(None)

        def weathers(self):
            return ["ClearNoon", "HardRainNoon"]

        def __getattr__(self, name):
            return getattr(self._b, name)

    eps = build_suite(OtherWeathers(), towns=["town_a"], weathers=["ClearNoon", "HardRainNoon"], limit=1,
                      training_towns=["town_a"], training_weathers=TRAINING_WEATHERS)
    assert {e.weather: e.weather_set for e in eps} == {"ClearNoon": "training", "HardRainNoon": "new"}


def _run(label: str, suite: dict, checkpoint: str = "/runs/x/checkpoints/last.ckpt"):
    from cicfw.benchmark.evaluation_report import Run

    row = {"episode": 0, "key": "town_a/ClearNoon/000", "town": "town_a", "weather": "ClearNoon",
           "town_set": "training", "weather_set": "training", "pair": 0, "route": "town_a/j/a>b/left",
           "command": "left", "success": True, "reason": "success", "time_s": 1.0, "timeout_s": 30.0,
           "distance_m": 50.0, "route_length_m": 50.0, "goal_distance_m": 1.0, "progress": 1.0,
           "offroad_fraction": 0.0, "opposite_lane_fraction": 0.0, "steps": 10}
    return Run(label, [row], {"checkpoint": checkpoint, "suite": suite})


def test_report_refuses_runs_of_different_suites(tmp_path, capsys):
    from cicfw.benchmark import evaluation_report as report

    single = {**SUITE, "name": "single_turn", "limit": None}
    report.write_run(tmp_path / "a", _run("independent+regression (last)", single))
    report.write_run(tmp_path / "b", _run("independent+regression (last)", {**single, "name": "junctions"}))
    assert report.main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "out"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "single_turn" in err and "junctions" in err
    assert str(tmp_path / "a") in err and str(tmp_path / "b") in err
    with pytest.raises(CicfwError) as raised:
        report.find_runs([tmp_path / "a", tmp_path / "b"])
    assert raised.value.key == "suite.name"
    # the same suite joins, each row named apart even where label and checkpoint name are the same
    report.write_run(tmp_path / "c", _run("independent+regression (last)", single, "/runs/y/checkpoints/last.ckpt"))
    labels = [r.label for r in report.find_runs([tmp_path / "a", tmp_path / "c"])]
    assert len(set(labels)) == 2


def test_report_refuses_two_different_towns_of_one_name(tmp_path):
    """Two evaluations on files named town_x.yaml with other roads were joined into one table, their rates side by
    side under one "New town" column of one town name."""
    from cicfw.benchmark import evaluation_report as report

    def run(folder: str, digest: str):
        r = _run("constant steer +0.00", SUITE)
        r.meta["fingerprint"] = {"town_files": {f"/towns/{folder}/town_x.yaml": digest}}
        report.write_run(tmp_path / folder, r)

    run("a", "1a7c89bda792d776")
    run("b", "0c1d2e3f40516273")
    run("c", "1a7c89bda792d776")  # the same file contents elsewhere: the same town
    with pytest.raises(CicfwError) as raised:
        report.find_runs([tmp_path / "a", tmp_path / "b"])
    assert (raised.value.key, raised.value.value) == ("suite.towns", "/towns/b/town_x.yaml")
    assert len(report.find_runs([tmp_path / "a", tmp_path / "c"])) == 2


# ---- training: the epochs to train and to keep -----------------------------------------------------------


@pytest.mark.parametrize("value", [-1, 0, -5])
def test_max_epochs_is_at_least_one(fast_cfg, tmp_path, value, no_data):
    from cicfw.train.app import train

    fast_cfg.trainer.max_epochs = value
    with pytest.raises(ConfigError) as err:
        train(fast_cfg, tmp_path / "run")
    assert (err.value.key, err.value.value) == ("trainer.max_epochs", value)


@pytest.mark.parametrize("key", ["accumulate_grad_batches", "check_val_every_n_epoch"])
@pytest.mark.parametrize("value", [0, -2])
def test_trainer_counts_lightning_divides_by_are_at_least_one(fast_cfg, tmp_path, key, value, no_data):
    """Lightning takes 0 here and fails in the first step (integer modulo by zero), after the run folder
    is written: refused before the data is read."""
    from cicfw.train.app import train

    fast_cfg.trainer[key] = value
    with pytest.raises(ConfigError) as err:
        train(fast_cfg, tmp_path / "run")
    assert (err.value.key, err.value.value) == (f"trainer.{key}", value)


@pytest.mark.parametrize("low,high,least,most", [("min_epochs", "max_epochs", 3, 1), ("min_steps", "max_steps", 5, 2)])
def test_a_minimum_beyond_the_maximum_is_refused(fast_cfg, tmp_path, low, high, least, most, no_data):
    """Lightning stops at max_epochs / max_steps and drops a larger minimum without a word: refused."""
    from cicfw.train.app import check_config, train

    fast_cfg.trainer[low], fast_cfg.trainer[high] = least, most
    with pytest.raises(ConfigError) as err:
        train(fast_cfg, tmp_path / "run")
    assert (err.value.key, err.value.value) == (f"trainer.{low}", least)
    fast_cfg.trainer[low] = most  # equal is fine
    check_config(fast_cfg, refuse_finished=False)


@pytest.mark.parametrize("value", [-1.0, float("nan")])
def test_gradient_clip_below_zero_or_nan_is_refused(fast_cfg, tmp_path, value, no_data):
    """Lightning skips clipping for a negative value without a word (the run trains unclipped) and fails
    mid-step on NaN: refused before the data is read; 0 and null stay "no clipping"."""
    import math

    from cicfw.train.app import check_config, train

    fast_cfg.trainer.gradient_clip_val = value
    with pytest.raises(ConfigError) as err:
        train(fast_cfg, tmp_path / "run")
    assert err.value.key == "trainer.gradient_clip_val"
    assert err.value.value == value or (math.isnan(value) and math.isnan(err.value.value))
    for fine in (0.0, 0.5, None):
        fast_cfg.trainer.gradient_clip_val = fine
        check_config(fast_cfg, refuse_finished=False)


def test_epochs_to_keep_are_within_max_epochs(fast_cfg, tmp_path, no_data):
    from cicfw.train.app import train

    fast_cfg.trainer.max_epochs = 1
    fast_cfg.keep_epoch_checkpoints = [1, 5]
    with pytest.raises(ConfigError) as err:
        train(fast_cfg, tmp_path / "run")
    assert (err.value.key, err.value.value) == ("keep_epoch_checkpoints", 5)


# ---- the agent's speed range is the data reader's ---------------------------------------------------------


@pytest.mark.parametrize("speed", [1e6, 300.5, -301.0])
def test_the_agent_refuses_speeds_the_data_reader_refuses(speed):
    from cicfw.data.frames import MAX_ABS_SPEED_KMH
    from cicfw.export.agent import check_inputs

    assert abs(speed) > MAX_ABS_SPEED_KMH
    img = np.zeros((88, 200, 3), np.uint8)
    with pytest.raises(CicfwError) as err:
        check_inputs(img, speed, 3)
    assert err.value.key == "speed_kmh" and err.value.value == pytest.approx(speed)
    check_inputs(img, -12.0, 3)  # a car rolling backwards: the reader keeps such rows, so does the agent
    check_inputs(img, 300.0, 3)


# ---- a multirun: every job checked before the first trains -------------------------------------------------


@pytest.mark.slow
def test_a_multirun_checks_every_job_before_the_first_trains(tiny_data, tmp_path):
    from conftest import run_app_in_process

    sweep = tmp_path / "sweep"
    r = run_app_in_process("cicfw.train", "-m", "data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8",
                           "data.val_batch_size=8", "debug=fast", "progress_bar=false", "head=hybrid", "head.W=5,-1,10",
                           f"hydra.sweep.dir={sweep}", env={"HYDRA_FULL_ERROR": "0"})
    assert r.returncode == 2, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "head.W" in lines[0] and "-1" in lines[0], r.stderr[-2000:]
    assert not sweep.exists()  # no job ran, no sweep folder left


@pytest.mark.slow
def test_a_multirun_checks_every_jobs_data_path_before_the_first_trains(tiny_data, tmp_path):
    """A data folder without an HDF5 file in the last job failed only after job 0 had trained."""
    from conftest import run_app_in_process

    empty, sweep = tmp_path / "empty", tmp_path / "sweep"
    empty.mkdir()
    (empty / "notes.txt").write_text("no episodes here\n")
    r = run_app_in_process("cicfw.train", "-m", "data=cil_hdf5", f"data.path={tiny_data},{empty}", "data.batch_size=8",
                           "data.val_batch_size=8", "debug=fast", "progress_bar=false", f"hydra.sweep.dir={sweep}",
                           env={"HYDRA_FULL_ERROR": "0"})
    assert r.returncode == 2, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "job 1" in lines[0] and f"data.path={str(empty)!r}" in lines[0], r.stderr[-2000:]
    assert not sweep.exists()  # no job ran, no sweep folder left


@pytest.mark.parametrize("swept, key", [("runner.threads=1,0", "runner.threads"),
                                         ("suite.limit=1,0", "suite.limit")])
def test_an_evaluate_multirun_checks_every_job_before_the_first_drives(tmp_path, swept, key):
    from conftest import run_app_in_process

    sweep = tmp_path / "sweep"
    limit = [] if key == "suite.limit" else ["suite.limit=1"]
    r = run_app_in_process("cicfw.evaluate", "-m", "policy=expert", "suite.towns=[town_a]",
                           "suite.weathers=[ClearNoon]", *limit, "progress_bar=false", "maps=false",
                           swept, f"hydra.sweep.dir={sweep}")
    assert r.returncode == 2, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cicfw: error: job 1") and key in lines[0], r.stderr[-2000:]
    assert not sweep.exists()  # job 0 did not drive, no sweep folder left


# ---- values that pass a "<= 0" test as NaN, and the off-road level's range ---------------------------------


@pytest.mark.parametrize("key,value", [("off_road_s", math.nan), ("off_road_s", math.inf), ("off_road_s", 0.0),
                                       ("off_road_level", -1.0), ("off_road_level", 0.0), ("off_road_level", 2.0),
                                       ("off_road_level", math.nan), ("target_speed_kmh", math.nan),
                                       ("target_speed_kmh", math.inf), ("target_speed_kmh", -5.0),
                                       ("target_speed_kmh", 1000.0)])  # beyond the car's top speed
def test_the_runners_rules_refuse_values_that_would_switch_them_off(key, value):
    from cicfw.benchmark.runner import RunnerConfig

    with pytest.raises(ConfigError) as err:
        RunnerConfig(**{key: value})
    assert err.value.key == f"runner.{key}" and (err.value.value == value or math.isnan(value))


def test_the_runners_defaults_and_ordinary_values_pass():
    from cicfw.benchmark.runner import RunnerConfig

    RunnerConfig(off_road_s=1.5, off_road_level=1.0, target_speed_kmh=30.0)
    RunnerConfig()


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_a_side_camera_correction_that_is_not_finite_is_refused(tiny_data, value):
    from cicfw.data.datamodule import CILDataModule

    with pytest.raises(ConfigError) as err:
        CILDataModule(path=str(tiny_data), side_camera_correction=value)
    assert err.value.key == "data.side_camera_correction"


@pytest.mark.parametrize("key, value", [("towns", ["town_a", "town_a"]), ("weathers", ["ClearNoon", "ClearNoon"])])
def test_a_town_or_weather_named_twice_is_refused(key, value):
    from cicfw.benchmark.suite import build_suite, make_backend

    with pytest.raises(ConfigError) as err:
        build_suite(make_backend(None), **{**SUITE, key: value})
    assert (err.value.key, err.value.value) == (f"suite.{key}", value)


def test_a_validation_interval_beyond_the_epoch_is_one_line(tmp_path):
    """Lightning checks val_check_interval against the epoch's batches only once the data is read, and
    raised a ValueError (exit 1); it is now a CicfwError naming the key."""
    from conftest import TINY_TRAIN, train_tiny_run

    from cicfw.core.errors import CicfwError

    with pytest.raises(CicfwError) as err:
        train_tiny_run(tmp_path, *TINY_TRAIN, "trainer.val_check_interval=100")
    assert (err.value.key, err.value.value) == ("trainer.val_check_interval", 100)
