"""The evaluate config's schema comes from the code it configures (cicfw/benchmark/schema.py): OmegaConf refuses
a wrong type or an unknown key while composing, naming its full key; what composing lets through (keys
added with ``+``, ``runner.workers``) is refused by the same schema before the run folder exists. Each test
asserts the refusal's kind and the key it names, not its sentence."""
from __future__ import annotations

import dataclasses
import inspect
import os

import pytest
from conftest import run_app_in_process
from omegaconf import OmegaConf

from cicfw.benchmark.runner import RunnerConfig
from cicfw.benchmark.suite import build_suite
from cicfw.core.config_checks import SchemaError
from cicfw.benchmark.app import check_evaluation_overrides, compose_config
from cicfw.benchmark.schema import check
from cicfw.registry import SIM_BACKENDS


def refused(*overrides: str) -> SchemaError:
    with pytest.raises(SchemaError) as err:
        check(compose_config(list(overrides)))
    assert "\n" not in str(err.value)
    return err.value


@pytest.mark.parametrize("overrides, kind, key", [
    (["runner.workrs=2"], "unknown key", "runner.workrs"),
    (["runner.batch_size=abc"], "wrong type", "runner.batch_size"),
    (["runner.off_road_s=long"], "wrong type", "runner.off_road_s"),
    (["runner.seed=1"], "not settable", "runner.seed"),
    (["suite.limit=x"], "wrong type", "suite.limit"),
    (["suite.foo=1"], "unknown key", "suite.foo"),
    (["suite=single_turn", "suite.limit=x"], "wrong type", "suite.limit"),
    (["maps=perhaps"], "wrong type", "maps"),
    (["seed=abc"], "wrong type", "seed"),
    (["video=3"], "wrong type", "video"),
    (["video_max=abc"], "wrong type", "video_max"),
    (["suitee=single_turn"], "unknown key", "suitee"),
    (["sim.foo=1"], "unknown key", "sim.foo"),
    (["sim=carla", "sim.port=x"], "wrong type", "sim.port"),
    (["sim=carla", "sim.client=1"], "not settable", "sim.client"),
])
def test_the_schema_refuses_while_composing(overrides, kind, key):
    err = refused(*overrides)
    assert (err.kind, err.key) == (kind, key), err


def test_an_unknown_key_names_the_close_one_and_what_is_accepted():
    assert "'suite'" in str(refused("suitee=single_turn")) and "runner" in str(refused("suitee=single_turn"))
    assert "'workers'" in str(refused("runner.workrs=2")) and "batch_size" in str(refused("runner.workrs=2"))


@pytest.mark.parametrize("overrides, kind, key", [
    (["+foo=1"], "unknown key", "foo"),
    (["+vide=[0]"], "unknown key", "vide"),
    (["+runner.foo=1"], "unknown key", "runner.foo"),
    (["+suite.foo=1"], "unknown key", "suite.foo"),
    (["+sim.foo=1"], "unknown key", "sim.foo"),
    (["sim.name=carla"], "unknown key", "sim.weather_family"),  # checked against the backend it builds
    (["runner.workers=abc"], "wrong type", "runner.workers"),
    (["runner.workers=0"], "wrong type", "runner.workers"),
    (["runner.workers=1.5"], "wrong type", "runner.workers"),
])
def test_what_composing_lets_through_is_refused_by_the_same_schema(overrides, kind, key):
    err = refused(*overrides)
    assert (err.kind, err.key) == (kind, key), err


def test_runner_workers_takes_auto_a_number_or_server_ports():
    for workers in ("auto", "4", "[2000,2002]"):
        check(compose_config([f"runner.workers={workers}"]))
    assert "'auto'" in str(refused("runner.workers=abc"))


def test_the_nodes_take_their_defaults_from_the_code():
    cfg = compose_config()
    runner = RunnerConfig()
    assert {k: cfg.runner[k] for k in ("batch_size", "off_road_s", "off_road_level", "threads")} == \
        {k: getattr(runner, k) for k in ("batch_size", "off_road_s", "off_road_level", "threads")}
    assert set(cfg.suite) == set(inspect.signature(build_suite).parameters) - {"backend"}
    for name in ("embedded", "carla"):
        sim = compose_config([f"sim={name}"]).sim
        assert set(sim) == set(inspect.signature(SIM_BACKENDS.get(name)).parameters) - {"client"} | {"name"}


def test_the_policy_node_is_open_and_checked_by_the_policy_it_builds():
    """A policy's options are its registered class's arguments (a plugin's own): not in the schema, checked
    before the checkpoint is read."""
    check(compose_config(["+policy.foo=1"]))
    with pytest.raises(SchemaError) as err:
        check_evaluation_overrides(["+policy.foo=1"])
    assert (err.value.kind, err.value.key) == ("unknown key", "policy.foo")


@pytest.mark.parametrize("overrides, kind, key", [
    (["suite.foo=1"], "unknown key", "suite.foo"),
    (["suite.limit=x"], "wrong type", "suite.limit"),
    (["+foo=1"], "unknown key", "foo"),
    (["+runner.foo=1"], "unknown key", "runner.foo"),
    (["runner.workers=abc"], "wrong type", "runner.workers"),
    (["seed=abc"], "wrong type", "seed"),
])
def test_the_evaluation_after_training_is_checked_by_the_schema(overrides, kind, key):
    with pytest.raises(SchemaError) as err:
        check_evaluation_overrides(overrides)
    assert (err.value.kind, err.value.key) == (kind, key), err.value
    assert str(err.value).startswith("evaluate_overrides: ") and "\n" not in str(err.value)


def test_the_schema_is_a_dataclass_of_the_configs_top_level_keys():
    from cicfw.benchmark.schema import EvaluateConfig

    keys = {f.name for f in dataclasses.fields(EvaluateConfig)}
    assert keys == set(OmegaConf.load(os.path.join(os.path.dirname(__file__), "..", "conf", "evaluate.yaml"))) \
        - {"defaults", "hydra"} | {"policy", "sim", "suite"}


@pytest.mark.slow
@pytest.mark.parametrize("override, key", [
    ("runner.workrs=2", "runner.workrs"),
    ("runner.batch_size=abc", "runner.batch_size"),
    ("+foo=1", "'foo'"),
    ("suite.limit=x", "suite.limit"),
    ("maps=perhaps", "maps"),
    ("runner.workers=abc", "runner.workers"),
])
def test_the_app_refuses_in_one_line_before_the_run_folder(tmp_path, override, key):
    r = run_app_in_process("cicfw.evaluate", "policy=expert", override, f"hydra.run.dir={tmp_path}/run",
                           env={"HYDRA_FULL_ERROR": "0"})
    assert r.returncode == 2, r.stderr[-800:]
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith("cicfw: error: ") and key in line, line
    assert not (tmp_path / "run").exists()
