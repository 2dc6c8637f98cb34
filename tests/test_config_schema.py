"""The train config's schema comes from the code it configures (cicfw/train/schema.py): OmegaConf refuses a
wrong type or an unknown key while composing, naming its full key; keys added with ``+`` are refused by
the same schema before any data; a plugin's mixer gets its checks from its own signature. Each test
asserts the refusal's kind and the key it names, not its sentence."""
from __future__ import annotations

import importlib.util

import pytest
from hydra import compose, initialize_config_module
from hydra.errors import HydraException
from omegaconf import OmegaConf

from cicfw.core.config_checks import SchemaError, check_kwargs, config_error, kwargs_schema
from cicfw.train.app import build_model, make_datamodule, trainer_kwargs
from cicfw.train.schema import checked_speed
from conftest import compose_train

HAS_ATTENTION = importlib.util.find_spec("cicfw_attention_mixer") is not None


def refused_while_composing(*overrides: str) -> SchemaError:
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        with pytest.raises(HydraException) as err:
            compose("train", overrides=list(overrides))
    refused = config_error(err.value)
    assert refused is not None, err.value
    assert "\n" not in str(refused)
    return refused


@pytest.mark.parametrize("overrides, kind, key", [
    (["model.lr=abc"], "wrong type", "model.lr"),
    (["model.betas=[0.9,x]"], "wrong type", "model.betas[1]"),
    (["model.betas=abc"], "wrong type", "model.betas"),
    (["model.lrr=1"], "unknown key", "model.lrr"),
    (["trainer.max_epochs=abc"], "wrong type", "trainer.max_epochs"),
    (["trainer.max_epochs=1.5"], "wrong type", "trainer.max_epochs"),
    (["trainer.inference_mode=maybe"], "wrong type", "trainer.inference_mode"),
    (["trainer.max_epoch=3"], "unknown key", "trainer.max_epoch"),
    (["trainer.logger=true"], "not settable", "trainer.logger"),
    (["trainer.callbacks=[]"], "not settable", "trainer.callbacks"),
    (["speed.channels_last=sometimes"], "wrong type", "speed.channels_last"),
    (["speed.keep_memory=maybe"], "wrong type", "speed.keep_memory"),
    (["speed.foo=1"], "unknown key", "speed.foo"),
    (["trainer.compile=true"], "not settable", "trainer.compile"),  # a speed switch: speed.compile
    (["mixer=gtu", "mixer.hiden=64"], "unknown key", "mixer.hiden"),
    (["mixer=gtu", "mixer.hidden=wide"], "wrong type", "mixer.hidden"),
    (["mixer.in_dim=64"], "not settable", "mixer.in_dim"),
    (["head=hybrid", "head.WW=5"], "unknown key", "head.WW"),
    (["head=hybrid", "head.n_classes=many"], "wrong type", "head.n_classes"),  # a base class's argument
    (["encoder.dropout_fc=high"], "wrong type", "encoder.dropout_fc"),
    (["data.batch_size=big"], "wrong type", "data.batch_size"),
    (["data.batches_per_epoch=abc"], "wrong type", "data.batches_per_epoch"),
    (["data.collect.episodes=abc"], "wrong type", "data.collect.episodes"),
    (["data.collect.frames=3"], "unknown key", "data.collect.frames"),
    (["seed=abc"], "wrong type", "seed"),
    (["keep_epoch_checkpoints=[1,x]"], "wrong type", "keep_epoch_checkpoints[1]"),
    (["trainr.max_epochs=1"], "unknown key", "trainr"),
    (["experiment=paper_gtu", "mixer.hiden=3"], "unknown key", "mixer.hiden"),  # the experiment's mixer's schema
])
def test_the_schema_refuses_while_composing(overrides, kind, key):
    refused = refused_while_composing(*overrides)
    assert (refused.kind, refused.key) == (kind, key), refused


def test_an_unknown_key_names_the_close_one_and_what_is_accepted():
    refused = refused_while_composing("mixer=gtu", "mixer.hiden=64")
    assert "'hidden'" in str(refused) and "dropout" in str(refused)  # did you mean, and the accepted keys


@pytest.mark.skipif(not HAS_ATTENTION, reason="the example plugin (plugins/cicfw-attention-mixer) is not installed")
@pytest.mark.parametrize("overrides, kind, key", [
    (["mixer=attention", "mixer.gate_bais=0.5"], "unknown key", "mixer.gate_bais"),
    (["mixer=attention", "mixer.heads=four"], "wrong type", "mixer.heads"),
])
def test_a_plugins_mixer_is_checked_by_its_own_signature(overrides, kind, key):
    refused = refused_while_composing(*overrides)
    assert (refused.kind, refused.key) == (kind, key), refused
    assert "gate_init" in str(refused) or kind == "wrong type"
    cfg = compose_train("mixer=attention", "mixer.heads=2")
    assert OmegaConf.to_container(cfg.mixer)["heads"] == 2


@pytest.mark.parametrize("overrides, kind, key", [
    (["+mixer.foo=1"], "unknown key", "mixer.foo"),
    (["head=hybrid", "+head.foo=1"], "unknown key", "head.foo"),
    (["+encoder.foo=1"], "unknown key", "encoder.foo"),
    (["+model.foo=1"], "unknown key", "model.foo"),
    (["+mixer.in_dim=64"], "not settable", "mixer.in_dim"),
    (["+model.mixer=gtu"], "not settable", "model.mixer"),
    (["mixer.name=gtu", "+mixer.lam=1"], "unknown key", "mixer.lam"),  # checked against the name it builds
])
def test_keys_added_with_plus_are_refused_by_the_same_schema(tmp_path, overrides, kind, key):
    """Hydra lets ``+key=value`` through a structured config; building the model checks the node again."""
    with pytest.raises(SchemaError) as err:
        build_model(compose_train(*overrides))
    assert (err.value.kind, err.value.key) == (kind, key), err.value


def test_the_data_and_trainer_nodes_are_checked_again_when_built(tmp_path):
    with pytest.raises(SchemaError) as err:
        make_datamodule(compose_train("data=cil_hdf5", f"data.path={tmp_path}", "+data.foo=1"))
    assert (err.value.kind, err.value.key) == ("unknown key", "data.foo")
    with pytest.raises(SchemaError) as err:
        trainer_kwargs(compose_train("+trainer.foo=1"))
    assert (err.value.kind, err.value.key) == ("unknown key", "trainer.foo")


@pytest.mark.parametrize("overrides, kind, key", [
    (["+data.collect.sim.typo=1"], "unknown key", "data.collect.sim.typo"),
    (["+data.collect.sim.command_distance=abc"], "wrong type", "data.collect.sim.command_distance"),
    (["data.collect.sim=abc"], "wrong type", "data.collect.sim"),
    (["data.collect.sim.name=carla", "+data.collect.sim.port=abc"], "wrong type", "data.collect.sim.port"),
    (["data.collect.sim.name=carla", "+data.collect.sim.client=1"], "not settable", "data.collect.sim.client"),
])
def test_the_collections_sim_node_is_checked_by_its_backends_schema_before_collecting(overrides, kind, key, tmp_path,
                                                                                   monkeypatch):
    """``data.collect.sim`` gets the collect app's per-backend schema (cicfw/sim/schema.py): refused when the
    datamodule is made, which training does before it collects anything."""
    import cicfw.train.app

    def collect(*args, **kwargs):
        raise AssertionError("the training went on to collect its data")

    monkeypatch.setattr(cicfw.train.app, "ensure_data", collect)
    cfg = compose_train(f"data.path={tmp_path / 'sim'}", *overrides)
    with pytest.raises(SchemaError) as err:
        make_datamodule(cfg)
    assert (err.value.kind, err.value.key) == (kind, key), err.value
    with pytest.raises(SchemaError) as err:
        cicfw.train.app.train(cfg, tmp_path / "run")
    assert err.value.key == key and not (tmp_path / "sim").exists()
    make_datamodule(compose_train("data.collect.sim.name=carla", "+data.collect.sim.port=2000"))  # a good one


@pytest.mark.parametrize("switch", ["compile", "channels_last", "adam", "keep_memory"])
def test_a_speed_switch_under_trainer_names_its_key_in_the_speed_node(switch):
    refused = refused_while_composing(f"trainer.{switch}=true")
    assert (refused.kind, refused.key) == ("not settable", f"trainer.{switch}"), refused
    assert f"speed.{switch}" in str(refused), refused
    with pytest.raises(SchemaError) as err:  # added with +: the trainer node's check says the same
        trainer_kwargs(compose_train(f"+trainer.{switch}=true"))
    assert (err.value.kind, err.value.key) == ("not settable", f"trainer.{switch}"), err.value


@pytest.mark.parametrize("overrides, key", [
    (["speed.compile=maybe"], "speed.compile"),      # true | false | auto: a union the schema leaves open
    (["speed.adam=fusd"], "speed.adam"),
    (["+speed.foo=1"], "speed.foo"),
])
def test_the_speed_node_is_checked_again_when_built(overrides, key):
    with pytest.raises(SchemaError) as err:
        checked_speed(compose_train(*overrides))
    assert err.value.key == key and "\n" not in str(err.value), err.value
    assert err.value.kind == ("unknown key" if key == "speed.foo" else "wrong type"), err.value


def test_the_speed_node_takes_its_defaults_from_speed_config():
    """conf/speed/default.yaml states SpeedConfig's defaults; the trainer node holds Lightning's arguments only."""
    import dataclasses

    from cicfw.model.speed import SPEED_SWITCHES, SpeedConfig

    default = compose_train()
    assert OmegaConf.to_container(default.speed) == dataclasses.asdict(SpeedConfig())
    assert checked_speed(compose_train("speed.compile=true")) == SpeedConfig(compile=True)
    assert not set(SPEED_SWITCHES) & set(trainer_kwargs(default))


@pytest.mark.parametrize("overrides, key", [
    (["trainer.deterministic=sure"], "trainer.deterministic"),  # bool | "warn": a union the schema leaves open
    (["trainer.deterministic=1"], "trainer.deterministic"),
    (["trainer.max_time=5"], "trainer.max_time"),               # str | dict | timedelta: likewise
    (["trainer.max_time=[1]"], "trainer.max_time"),
])
def test_trainer_unions_are_checked_by_what_lightning_takes(overrides, key):
    with pytest.raises(SchemaError) as err:
        trainer_kwargs(compose_train(*overrides))
    assert (err.value.kind, err.value.key) == ("wrong type", key), err.value
    assert "\n" not in str(err.value)
    accepted = "warn" if key == "trainer.deterministic" else "DD:HH:MM:SS"
    assert accepted in str(err.value), err.value  # what it takes


def test_every_lightning_trainer_argument_is_in_the_schema_with_its_default():
    """``trainer.<any Trainer argument>`` without ``+``; the ones cicfw passes itself are not settable."""
    import inspect

    import lightning as L

    kwargs = trainer_kwargs(compose_train("trainer.accumulate_grad_batches=2"))
    params = {n: p.default for n, p in inspect.signature(L.Trainer.__init__).parameters.items() if n != "self"}
    assert set(params) - set(kwargs) == {"logger", "callbacks", "default_root_dir"}
    assert set(kwargs) <= set(params)  # nothing but Lightning's arguments
    assert kwargs["accumulate_grad_batches"] == 2 and kwargs["max_epochs"] == 10  # conf/trainer/default.yaml
    assert kwargs["overfit_batches"] == params["overfit_batches"]  # a default Lightning's signature gives


@pytest.mark.parametrize("key, value, given", [
    ("max_epochs", 3, 3),                      # typed (an int), with a value in conf/trainer/default.yaml
    ("fast_dev_run", "true", True),            # untyped (int or bool), a value by default (false)
    ("limit_train_batches", 3, 3),             # untyped (int or float), null by default
])
@pytest.mark.parametrize("plus", ["", "+"])
def test_every_trainer_argument_takes_a_value_with_or_without_plus(key, value, given, plus):
    from cicfw.train.schema import without_plus_on_trainer

    kwargs = trainer_kwargs(compose_train(*without_plus_on_trainer([f"{plus}trainer.{key}={value}"])))
    assert kwargs[key] == given


def test_plus_stays_on_what_is_no_trainer_argument():
    from cicfw.train.schema import without_plus_on_trainer

    kept = ["+trainer.foo=1", "+trainer.callbacks=[]", "+mixer.hidden=3", "trainer.max_epochs=2"]
    assert without_plus_on_trainer([*kept, "+trainer.max_time=00:00:01:00"]) == [*kept, "trainer.max_time=00:00:01:00"]


def test_the_model_and_the_collection_take_their_defaults_from_the_code():
    import inspect

    from cicfw.collect.config import CollectConfig
    from cicfw.model.module import CICModule

    cfg = compose_train()
    signature = inspect.signature(CICModule.__init__).parameters
    assert cfg.model.lr == signature["lr"].default and list(cfg.model.betas) == list(signature["betas"].default)
    assert OmegaConf.to_container(cfg.data.collect) == OmegaConf.to_container(OmegaConf.structured(CollectConfig))


def test_check_kwargs_names_a_missing_argument_and_one_cicfw_sets():
    class NeedsWidth:
        def __init__(self, in_dim: int, out_dim: int, width: int, hidden: int = 8) -> None:
            pass

    dims = {"in_dim": "set by cicfw", "out_dim": "set by cicfw"}
    cases = [({"hidden": 4}, "missing", "mixer.width"), ({"in_dim": 4, "width": 1}, "not settable", "mixer.in_dim"),
             ({"width": "w"}, "wrong type", "mixer.width"), ({"width": 1, "depth": 2}, "unknown key", "mixer.depth")]
    for kwargs, kind, key in cases:
        with pytest.raises(SchemaError) as err:
            check_kwargs("mixer", "mixer 'wide'", NeedsWidth, kwargs, dims)
        assert (err.value.kind, err.value.key) == (kind, key), err.value
    check_kwargs("mixer", "mixer 'wide'", NeedsWidth, {"width": 4}, dims)


def test_a_schema_reads_optional_unions_and_bases_kwargs():
    from cicfw.model.heads.hybrid import HybridHead

    schema = OmegaConf.structured(kwargs_schema(HybridHead, "head 'hybrid'"))
    assert set(schema) == {"W", "n_classes", "low", "high", "bin_width", "decode"}  # HybridHead(W, **bins_kwargs)

    def fn(a: int | None = None, b: float | str = 1.0) -> None:
        pass

    schema = OmegaConf.structured(kwargs_schema(fn, "fn"))
    schema.a = "3"
    assert schema.a == 3  # int | None: checked as Optional[int]
    schema.b = "anything"  # a union OmegaConf cannot represent: left to fn


def test_a_wrong_type_in_a_config_file_names_the_file_and_the_key(tmp_path):
    from cicfw.core.override_hints import composition_error_line

    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "bad.yaml").write_text("# @package _global_\nmixer:\n  hidden: wide\n")
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        with pytest.raises(HydraException) as err:
            compose("train", overrides=[f"hydra.searchpath=[file://{tmp_path}]", "experiment=bad"])
    refused = config_error(err.value)
    assert (refused.kind, refused.key) == ("wrong type", "mixer.hidden"), refused
    assert composition_error_line(err.value, []).startswith("experiment/bad.yaml: mixer.hidden")


def test_an_omegaconf_error_the_app_raises_itself_keeps_its_report():
    """Only what Hydra refuses while composing becomes a user's one line; a bug reading a missing key
    inside the app is not dressed up as a config mistake."""
    from omegaconf.errors import ConfigAttributeError

    from cicfw.core.override_hints import composition_error_line

    cfg = OmegaConf.create({"a": 1})
    OmegaConf.set_struct(cfg, True)
    with pytest.raises(ConfigAttributeError) as err:
        cfg.b  # noqa: B018
    assert composition_error_line(err.value, []) is None
