"""What ``train`` returns to an optimising sweeper and the direction it is told to go: the validation error is
minimised, the closed-loop success maximised; the other direction (or ``return_closed_loop`` with no
evaluation to return) would search for the worst model, so it is refused before the first trial."""
from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from cicfw.core.errors import ConfigError
from cicfw.train.app import check_config
from cicfw.train.sweep_direction import check_direction
from conftest import assert_refused, compose_train, run_app_in_process


def _sweep(direction, **top) -> object:
    return OmegaConf.create({"optimized_metric": "val/steer_mae", **top, "hydra": {"sweeper": {"direction": direction}}})


@pytest.mark.parametrize("direction, top", [
    ("minimize", {"evaluate_after": True, "return_closed_loop": True}),
    ("maximize", {}),
    ("maximize", {"evaluate_after": True}),
])
def test_the_direction_that_searches_for_the_worst_model_is_refused(direction, top):
    with pytest.raises(ConfigError) as err:
        check_direction(_sweep(direction, **top))
    assert (err.value.key, err.value.value) == ("hydra.sweeper.direction", direction)


@pytest.mark.parametrize("config", [
    _sweep("minimize"), _sweep("maximize", evaluate_after=True, return_closed_loop=True),
    _sweep(["minimize", "maximize"]), OmegaConf.create({"hydra": {"sweeper": {}}}),
])
def test_the_right_direction_and_sweepers_without_one_pass(config):
    check_direction(config)


def test_return_closed_loop_without_the_evaluation_is_refused():
    with pytest.raises(ConfigError) as err:
        check_config(compose_train("return_closed_loop=true"))
    assert (err.value.key, err.value.value) == ("return_closed_loop", True)


def test_an_optuna_search_minimising_the_success_rate_stops_before_its_first_trial(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    sweep = tmp_path / "sweep"
    # data that is not there: were the direction let through, the trial would stop at once, not train
    result = run_app_in_process("cicfw.train", "hparams_search=optuna", "evaluate_after=true", "return_closed_loop=true",
                                "hydra.sweeper.n_trials=1", "data=cil_hdf5", f"data.path={tmp_path / 'none'}",
                                f"hydra.sweep.dir={sweep}")
    assert_refused(result, "hydra.sweeper.direction", "minimize")
    assert not sweep.exists()


@pytest.mark.parametrize("override, key, value", [
    ("hydra.sweeper.n_trials=0", "hydra.sweeper.n_trials", 0),
    ("hydra.sweeper.n_jobs=-1", "hydra.sweeper.n_jobs", -1),
    ("model.lr=tag(log, interval(0, 1))", "model.lr", "tag(log, interval(0, 1))"),
    ("notes", "hydra.sweeper.storage", None),
])
def test_optuna_settings_it_would_fail_on_mid_sweep_are_one_line_before_the_first_trial(override, key, value, tmp_path):
    """n_trials=0 ended in Optuna's 'No trials are completed yet' traceback, a log interval from 0 in its
    'low value must be larger than 0', a text file as the study's database in an 81-line SQLAlchemy one."""
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    notes = tmp_path / "notes.db"
    notes.write_text("my notes, not a database\n")
    if override == "notes":
        override, value = f"hydra.sweeper.storage=sqlite:///{notes}", f"sqlite:///{notes}"
    sweep = tmp_path / "sweep"
    result = run_app_in_process("cicfw.train", "hparams_search=optuna", override, "data=cil_hdf5",
                                f"data.path={tmp_path / 'none'}", f"hydra.sweep.dir={sweep}")
    assert_refused(result, key, value)
    assert not sweep.exists() and notes.read_text() == "my notes, not a database\n"
