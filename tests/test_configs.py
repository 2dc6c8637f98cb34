"""Every option of every config group composes, and the part it selects can be built."""
from __future__ import annotations

from pathlib import Path

import lightning as L
import pytest

import cicfw.conf
from cicfw.data.datamodule import CILDataModule
from cicfw.train.app import build_model, build_trainer
from conftest import compose_train

CONF = Path(cicfw.conf.__file__).parent


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def test_conf_ships_in_the_package():
    assert (CONF / "train.yaml").exists()
    for group in ("encoder", "mixer", "head", "data", "trainer", "speed", "logger", "debug", "experiment"):
        assert options(group) or group == "experiment", f"conf/{group}/ is empty"


@pytest.mark.parametrize("group", ["encoder", "mixer", "head"])
def test_model_parts_build(group):
    for option in options(group):
        cfg = compose_train(f"{group}={option}")
        model = build_model(cfg)
        assert cfg[group].name == getattr(model.hparams, group)


@pytest.mark.parametrize("option", options("experiment"))
def test_experiments_build(option):
    build_model(compose_train(f"experiment={option}"))


@pytest.mark.parametrize("option", options("data"))
def test_data_options_build(option, tmp_path):
    cfg = compose_train(f"data={option}", f"data.path={tmp_path}")
    kwargs = dict(cfg.data)
    kwargs.pop("collect", None)
    CILDataModule(**kwargs)


@pytest.mark.parametrize("option", options("trainer"))
def test_trainer_options_build(option, tmp_path):
    cfg = compose_train(f"trainer={option}")
    if cfg.trainer.get("strategy", "auto") not in ("auto", None) or cfg.trainer.get("devices", 1) not in (1, "1"):
        pytest.skip("multi-process trainers are exercised by tests/test_ddp.py")
    assert isinstance(build_trainer(cfg, tmp_path), L.Trainer)


@pytest.mark.parametrize("option", options("logger"))
def test_logger_options_build(option, tmp_path):
    trainer = build_trainer(compose_train(f"logger={option}"), tmp_path)
    assert trainer.logger is not None


@pytest.mark.parametrize("option", options("debug"))
def test_debug_options_compose(option):
    assert compose_train(f"debug={option}").trainer
