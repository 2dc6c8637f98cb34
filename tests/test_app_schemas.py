"""The collect, export and diagnose configs are checked by their schemas (cicfw/collect/schema.py,
cicfw/export/schema.py, cicfw/diagnose/schema.py; the collect app's ``sim`` node by cicfw/sim/schema.py, as the
evaluate app's): OmegaConf refuses a wrong type or an unknown key in any node while composing, naming its
full key, and what composing lets through (keys added with ``+``) is refused by the same schema before the
run folder exists or anything is read. Each test asserts the refusal's kind and the key it names, not its
sentence."""
from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import pytest
from conftest import AppResult, run_app_in_process
from hydra import compose, initialize_config_module
from hydra.errors import HydraException

from cicfw.core.config_checks import SchemaError, config_error
from cicfw.registry import SIM_BACKENDS

CHECKS = {"collect": "cicfw.collect.schema", "export": "cicfw.export.schema", "diagnose": "cicfw.diagnose.schema"}


def compose_app(app: str, *overrides: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose(app, overrides=list(overrides))


def refused_while_composing(app: str, *overrides: str) -> SchemaError:
    with pytest.raises(HydraException) as err:
        compose_app(app, *overrides)
    refused = config_error(err.value)
    assert refused is not None and "\n" not in str(refused), err.value
    return refused


def refused_by_check(app: str, *overrides: str) -> SchemaError:
    import importlib

    cfg = compose_app(app, *overrides)
    with pytest.raises(SchemaError) as err:
        importlib.import_module(CHECKS[app]).check(cfg)
    assert "\n" not in str(err.value)
    return err.value


@pytest.mark.parametrize("app, overrides, kind, key", [
    ("collect", ["episodes=abc"], "wrong type", "episodes"),
    ("collect", ["verify=perhaps"], "wrong type", "verify"),
    ("collect", ["out_dir=[1]"], "wrong type", "out_dir"),
    ("collect", ["lock_wait=soon"], "wrong type", "lock_wait"),
    ("collect", ["noise.frequency=abc"], "wrong type", "noise.frequency"),
    ("collect", ["noise.typo=1"], "unknown key", "noise.typo"),
    ("collect", ["expert.cruise_kmh=abc"], "wrong type", "expert.cruise_kmh"),
    ("collect", ["expert.typo=1"], "unknown key", "expert.typo"),
    ("collect", ["sim.command_distance=abc"], "wrong type", "sim.command_distance"),
    ("collect", ["sim.typo=1"], "unknown key", "sim.typo"),
    ("collect", ["sim=carla", "sim.port=abc"], "wrong type", "sim.port"),
    ("collect", ["sim=carla", "sim.settle_ticks=1.5"], "wrong type", "sim.settle_ticks"),
    ("collect", ["episods=3"], "unknown key", "episods"),
    ("export", ["n_frames=abc"], "wrong type", "n_frames"),
    ("export", ["n_frames=1.5"], "wrong type", "n_frames"),
    ("export", ["tolerance=abc"], "wrong type", "tolerance"),
    ("export", ["opset=abc"], "wrong type", "opset"),
    ("export", ["out=[1]"], "wrong type", "out"),
    ("export", ["frames=[1]"], "wrong type", "frames"),
    ("export", ["checkpoint=[1]"], "wrong type", "checkpoint"),
    ("export", ["fromat=onnx"], "unknown key", "fromat"),
    ("diagnose", ["batch_size=abc"], "wrong type", "batch_size"),
    ("diagnose", ["max_frames=abc"], "wrong type", "max_frames"),
    ("diagnose", ["threads=abc"], "wrong type", "threads"),
    ("diagnose", ["fuse=perhaps"], "wrong type", "fuse"),
    ("diagnose", ["plot=perhaps"], "wrong type", "plot"),
    ("diagnose", ["checkpoint=[1]"], "wrong type", "checkpoint"),
    ("diagnose", ["phases.exit_s=abc"], "wrong type", "phases.exit_s"),
    ("diagnose", ["phases.approach_m=abc"], "wrong type", "phases.approach_m"),
    ("diagnose", ["phases.typo=1"], "unknown key", "phases.typo"),
    ("diagnose", ["data.seed=abc"], "wrong type", "data.seed"),
    ("diagnose", ["data.val_fraction=abc"], "wrong type", "data.val_fraction"),
    ("diagnose", ["data.max_abs_steer=abc"], "wrong type", "data.max_abs_steer"),
    ("diagnose", ["data.cameras=abc"], "wrong type", "data.cameras"),
    ("diagnose", ["data.typo=1"], "unknown key", "data.typo"),
    ("diagnose", ["progress_bar=false"], "unknown key", "progress_bar"),
])
def test_the_schema_refuses_while_composing(app, overrides, kind, key):
    refused = refused_while_composing(app, *overrides)
    assert (refused.kind, refused.key) == (kind, key), refused


@pytest.mark.parametrize("app, overrides, kind, key", [
    ("collect", ["+foo=1"], "unknown key", "foo"),
    ("collect", ["+noise.foo=1"], "unknown key", "noise.foo"),
    ("collect", ["+expert.foo=1"], "unknown key", "expert.foo"),
    ("collect", ["+sim.foo=1"], "unknown key", "sim.foo"),
    ("collect", ["sim.name=carla"], "unknown key", "sim.weather_family"),  # checked against the backend it builds
    ("collect", ["sim=carla", "+sim.client=1"], "not settable", "sim.client"),
    ("export", ["+foo=1"], "unknown key", "foo"),
    ("diagnose", ["+foo=1"], "unknown key", "foo"),
    ("diagnose", ["+data.foo=1"], "unknown key", "data.foo"),
    ("diagnose", ["+phases.foo=1"], "unknown key", "phases.foo"),
    ("collect", ["expert.cruise_kmh=???"], "missing", "expert.cruise_kmh"),  # a value left ??? on the command line
    ("collect", ["sim.success_radius=???"], "missing", "sim.success_radius"),
    ("diagnose", ["phases.dt_s=???"], "missing", "phases.dt_s"),
])
def test_what_composing_lets_through_is_refused_by_the_same_schema(app, overrides, kind, key):
    refused = refused_by_check(app, *overrides)
    assert (refused.kind, refused.key) == (kind, key), refused


@pytest.mark.parametrize("app", CHECKS)
def test_the_default_config_passes_its_check(app):
    import importlib

    importlib.import_module(CHECKS[app]).check(compose_app(app))


def test_the_nodes_take_their_keys_from_the_code():
    from cicfw.collect.config import CollectConfig
    from cicfw.export.app import export_model
    from cicfw.diagnose.steer_diagnostic import DataSettings, measure

    collect = compose_app("collect")
    assert set(collect) == {f.name for f in dataclasses.fields(CollectConfig)} | {"out_dir", "verify"}
    for name in ("embedded", "carla"):
        sim = compose_app("collect", f"sim={name}").sim
        assert set(sim) == set(inspect.signature(SIM_BACKENDS.get(name)).parameters) - {"client"} | {"name"}
    assert set(compose_app("export")) == set(inspect.signature(export_model).parameters) - {"fmt"} | {"format"}
    diagnose = compose_app("diagnose")
    assert set(diagnose.data) == {f.name for f in dataclasses.fields(DataSettings)}
    assert set(diagnose.phases) == {"approach_m", "exit_s", "dt_s"} <= set(inspect.signature(measure).parameters)


def _app(app: str, args: list[str], cwd: Path) -> AppResult:
    return run_app_in_process(f"cicfw.{app}", *args, cwd=cwd, env={"HYDRA_FULL_ERROR": "0"})


@pytest.mark.slow
@pytest.mark.parametrize("app, override, key", [
    ("collect", "+foo=1", "'foo'"),
    ("collect", "sim.command_distance=abc", "sim.command_distance"),
    ("collect", "+sim.foo=1", "sim.foo"),
    ("export", "+foo=1", "'foo'"),
    ("export", "n_frames=abc", "n_frames"),
    ("diagnose", "+foo=1", "'foo'"),
    ("diagnose", "fuse=perhaps", "fuse"),
    ("diagnose", "+data.foo=1", "data.foo"),
])
def test_the_app_refuses_in_one_line_before_its_folder_and_reading_nothing(tmp_path, app, override, key):
    """Status 2 and one line naming the key; no run or output folder, and the checkpoint (missing here,
    which would be the error otherwise) is not looked at."""
    nope = tmp_path / "nope.ckpt"
    args = {"collect": [f"out_dir={tmp_path / 'out'}"],
            "export": [f"checkpoint={nope}", f"out={tmp_path / 'm.onnx'}"],
            "diagnose": [f"checkpoint={nope}", f"hydra.run.dir={tmp_path / 'run'}"]}[app]
    r = _app(app, [*args, override], tmp_path)
    assert r.returncode == 2, r.stderr[-800:]
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith("cicfw: error: ") and key in line and "nope.ckpt" not in line, line
    assert list(tmp_path.iterdir()) == [], list(tmp_path.iterdir())  # no out_dir, outputs/, run folder or model
