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


def test_the_suites_parse_cache_reads_an_edited_config_file_anew(tmp_path):
    """conftest keeps each YAML file's parse for the suite's composes: a file written or edited during the
    suite (a user's config, a plugin's) must compose as it now reads, and an empty one as Hydra reads it."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    (tmp_path / "app.yaml").write_text("defaults:\n  - part: one\n  - _self_\nlr: 1\n")
    (tmp_path / "part").mkdir()
    (tmp_path / "part" / "one.yaml").write_text("")

    def composed() -> dict:
        with initialize_config_dir(str(tmp_path), version_base="1.3"):
            return OmegaConf.to_container(compose("app"))

    assert composed() == {"part": {}, "lr": 1}
    (tmp_path / "app.yaml").write_text("defaults:\n  - part: one\n  - _self_\nlr: 0.25\nname: edited\n")
    (tmp_path / "part" / "one.yaml").write_text("width: 3\n")
    assert composed() == {"lr": 0.25, "name": "edited", "part": {"width": 3}}


def test_the_suites_shared_config_store_is_never_written_by_a_compose(monkeypatch):
    """conftest lets each compose share the ``ConfigStore`` instead of copying it: composing the apps'
    configs, with overrides into schema-checked keys, leaves every stored node as it was, and each config
    composes as it does from a copied store."""
    from hydra import compose, initialize_config_module
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    def nodes(tree: dict, prefix: str = "") -> dict:
        out = {}
        for name, item in tree.items():
            if isinstance(item, dict):
                out.update(nodes(item, f"{prefix}{name}/"))
            else:
                out[prefix + name] = (item.group, item.package, OmegaConf.to_yaml(item.node))
        return out

    overrides = {"train": ["mixer=gtu", "mixer.hidden=64", "head=hybrid", "head.W=5", "trainer.max_epochs=3"],
                 "evaluate": ["suite=single_turn", "suite.limit=1", "sim=embedded"]}

    def composed() -> dict:
        with initialize_config_module("cicfw.conf", version_base="1.3"):
            return {app: OmegaConf.to_yaml(compose(app, overrides=o)) for app, o in overrides.items()}

    from cicfw.benchmark.schema import register as evaluate_schema
    from cicfw.train.schema import register as train_schema

    train_schema()  # what the first compose would register, registered now: all of it in the snapshot
    evaluate_schema()
    before = nodes(ConfigStore.instance().repo)
    shared = composed()
    after = nodes(ConfigStore.instance().repo)  # Hydra may add its own plugins' nodes on the way
    assert {name: after.get(name) for name in before} == before
    monkeypatch.delattr(ConfigStore, "__deepcopy__")  # Hydra's own copy of the store, as outside the suite
    assert composed() == shared
