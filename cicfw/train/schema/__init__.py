"""The train app's config schema, taken from what each node builds, and registered with Hydra.

conf/train.yaml puts this package on its search path, so Hydra imports it (registering the schema in its
ConfigStore) before it composes a train config, and the defaults list lays the schema under the config:
``cicfw_train`` under the whole of it (``model``: ``CICModule``'s arguments, ``data``: ``CILDataModule``'s,
``trainer``: ``lightning.Trainer``'s, ``speed``: cicfw's speed switches from ``SpeedConfig``), and
``cicfw_schema/<group>/<name>`` under each chosen encoder, mixer and head option (the registered class's
arguments, plugins' included).
OmegaConf then refuses an unknown key or a value of the wrong type while composing, naming its full key,
before any run folder exists: each value is checked there once. The ``checked_*`` functions look only at
what composing lets through, and at the values a type cannot say.
"""
from __future__ import annotations

import dataclasses
import functools
import re
from dataclasses import dataclass, field
from typing import Sequence
from typing import Any, Optional

import lightning as L
from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from cicfw.collect.config import CollectConfig
from cicfw.core.config_checks import SchemaError, check_composed, composed_values, kwargs_schema
from cicfw.core.errors import ConfigError
from cicfw.core.hydra_plugins import guard_hydra_plugins
from cicfw.data.datamodule import CILDataModule
from cicfw.model.module import CICModule
from cicfw.model.speed import SPEED_SWITCHES, SpeedConfig
from cicfw.registry import ENCODERS, HEADS, MIXERS, Registry
from cicfw.sim.schema import check_sim_node

#: the model's parts: config group -> registry
PARTS: dict[str, Registry] = {"encoder": ENCODERS, "mixer": MIXERS, "head": HEADS}
#: arguments cicfw passes itself, and what to do instead
NOT_SETTABLE = {
    "mixer": dict.fromkeys(("in_dim", "out_dim"), "cicfw sets it from the encoder's and the head's sizes"),
    "model": dict.fromkeys(("encoder", "encoder_kwargs", "mixer", "mixer_kwargs", "head", "head_kwargs"),
                           "choose it with the encoder/mixer/head config groups (mixer=gtu mixer.hidden=128)"),
    "trainer": {
        "default_root_dir": "cicfw uses the run folder (hydra.run.dir=...)",
        "logger": "choose the logger with logger=csv, logger=tensorboard or logger=null",
        "callbacks": "cicfw adds its checkpoint and diagnostics callbacks (progress_bar=false drops the bar)",
        **{k: f"it is a cicfw speed switch, not a Lightning Trainer argument; did you mean speed.{k}?"
           for k in SPEED_SWITCHES},
    },
}


@functools.lru_cache(maxsize=None)
def part(group: str, name: str) -> type:
    """The schema of the ``group`` option that builds registered ``name``: its class's arguments and
    ``name``. An unknown name is the registry's ``UnknownNameError``, listing the registered ones."""
    return kwargs_schema(PARTS[group].get(name), f"{group} {name!r}", fields={"name": (str, name)},
                         not_settable=NOT_SETTABLE.get(group))


MODEL = kwargs_schema(CICModule, "the model (CICModule)", not_settable=NOT_SETTABLE["model"])
TRAINER = kwargs_schema(L.Trainer, "the Lightning Trainer", not_settable=NOT_SETTABLE["trainer"],
                        is_not="a Lightning Trainer argument")
SPEED = kwargs_schema(SpeedConfig, "cicfw's speed switches", is_not="one of cicfw's speed switches")
DATA = dataclasses.make_dataclass(  # data=sim_default collects its data: data.collect is a collection's config
    "CILDataModuleConfig", [("collect", Optional[CollectConfig], field(default=None))],
    bases=(kwargs_schema(CILDataModule, "the CIL datamodule"),))


@dataclass
class LoggerConfig:
    name: str = MISSING  # cicfw.train.app.LOGGERS: csv | tensorboard


@dataclass
class TrainConfig:
    """conf/train.yaml: its own keys (their values are written there) and the nodes of what it builds."""

    __cicfw_what__ = "the train config"

    seed: int = MISSING
    model: MODEL = field(default_factory=MODEL)  # type: ignore[valid-type]
    ckpt_path: Optional[str] = MISSING
    resume_on_other_data: bool = MISSING
    optimized_metric: str = MISSING
    progress_bar: bool = MISSING
    keep_epoch_checkpoints: Optional[list[int]] = MISSING
    evaluate_after: bool = MISSING
    evaluate_overrides: Any = MISSING  # conf/evaluate.yaml's overrides (cicfw.evaluate checks them)
    return_closed_loop: bool = MISSING
    encoder: Any = MISSING  # cicfw_schema/encoder/<name>, then the chosen option
    mixer: Any = MISSING
    head: Any = MISSING
    data: DATA = field(default_factory=DATA)  # type: ignore[valid-type]
    trainer: TRAINER = field(default_factory=TRAINER)  # type: ignore[valid-type]
    speed: SPEED = field(default_factory=SPEED)  # type: ignore[valid-type]
    logger: Optional[LoggerConfig] = None


def register() -> None:
    """``cicfw_train`` and ``cicfw_schema/<group>/<name>`` for every registered part in the ConfigStore. The
    plugins' Hydra modules are guarded first (``guard_hydra_plugins``), as the apps do before Hydra starts:
    a distribution whose entry point and Hydra module both fail to load is then named in one warning."""
    guard_hydra_plugins()
    store = ConfigStore.instance()
    store.store(name="cicfw_train", node=TrainConfig, provider="cicfw")
    for group, registry in PARTS.items():
        for name in registry.names():
            store.store(group=f"cicfw_schema/{group}", name=name, node=part(group, name), provider="cicfw")


def check_top_level(cfg: DictConfig) -> None:
    """What composing let through at the top of a train config (``check_composed``): a key added with ``+``
    (``+evaluate_aftr=true`` would silently skip the evaluation), a value left ``???``; the nodes under it
    are checked as they are built (``checked_part``, ``checked_node``)."""
    check_composed(cfg, TrainConfig, skip=tuple(top_level_keys()))


def checked_part(cfg: DictConfig, group: str) -> tuple[str, dict[str, Any]]:
    """The registered name and the keyword arguments of ``cfg[group]``, checked against its name's schema
    once (``composed_values``: what composing let through, or the whole node where composing typed it as
    another name's): one ``SchemaError`` naming the full key."""
    node = cfg[group]
    if not isinstance(node, DictConfig) or "name" not in node:
        raise SchemaError(f"{group} must be a config node with a 'name:' key naming the registered {group}, "
                          f"got {OmegaConf.to_container(node) if OmegaConf.is_config(node) else node!r}",
                          f"{group}.name", "missing")
    kwargs = composed_values(node, part(group, str(node["name"])), group)
    return str(kwargs.pop("name")), kwargs


def checked_node(cfg: DictConfig, key: str, schema: type) -> dict[str, Any]:
    """``cfg[key]`` as plain data, checked against ``schema`` once (``composed_values``: ``model``, ``data``,
    ``trainer``, ``speed``)."""
    return composed_values(cfg[key], schema, key)


def checked_data(cfg: DictConfig) -> dict[str, Any]:
    """``cfg.data`` as ``checked_node`` gives it, and ``data.collect.sim`` against the backend its ``name``
    builds (the collect app's schemas, ``cicfw.sim.schema``): the node is open in ``CollectConfig``, so a key
    added with ``+`` or a wrong type there is refused here, before anything is collected."""
    kwargs = checked_node(cfg, "data", DATA)
    if kwargs.get("collect") is None:  # data=cil_hdf5: the user's files, nothing collected
        return kwargs
    sim = kwargs["collect"]["sim"]
    if not isinstance(sim, dict):
        raise SchemaError(f"data.collect.sim must be a simulator backend's node (e.g. {{name: embedded}}), got "
                          f"{sim!r}", "data.collect.sim", "wrong type")
    check_sim_node({"name": "embedded", **sim}, "data.collect.sim")
    return kwargs


def _is_one_of(value: Any, accepted: tuple[Any, ...]) -> bool:
    return any(type(value) is type(a) and value == a for a in accepted)  # True is not 1


def checked_trainer(cfg: DictConfig) -> dict[str, Any]:
    """``cfg.trainer`` as ``checked_node`` gives it, and the Trainer arguments whose union type the schema
    leaves open (``Any``) checked by what Lightning takes: ``deterministic``, ``max_time``; ``max_epochs``
    >= 1 (Lightning would take -1, training forever, and 0, training nothing); ``limit_train_batches`` > 0
    (0 trains nothing, and the run ends without a checkpoint); ``accumulate_grad_batches``
    and ``check_val_every_n_epoch`` >= 1 (0 fails in the first step, after the run folder is written);
    ``gradient_clip_val`` >= 0 or null (Lightning ignores a negative one, and NaN fails mid-step);
    ``min_epochs`` / ``min_steps`` at most ``max_epochs`` / ``max_steps`` (Lightning ignores the excess)."""
    kwargs = checked_node(cfg, "trainer", TRAINER)
    max_epochs = kwargs.get("max_epochs")
    if max_epochs is not None and max_epochs < 1:  # Lightning's -1 trains forever, 0 trains nothing
        raise ConfigError("trainer.max_epochs", max_epochs, "an integer >= 1, the epochs to train "
                          "(trainer.max_steps or trainer.max_time may stop training sooner)")
    for low, high in (("min_epochs", "max_epochs"), ("min_steps", "max_steps")):  # Lightning stops at the
        least, most = kwargs.get(low), kwargs.get(high)                          # max without a word
        if isinstance(least, int) and isinstance(most, int) and most >= 0 and least > most:
            raise ConfigError(f"trainer.{low}", least, f"at most trainer.{high}={most} (training stops at "
                              f"trainer.{high}, so more would never run), or null")
    limit = kwargs.get("limit_train_batches")  # Lightning takes 0 and trains nothing: no checkpoint, exit 0
    if isinstance(limit, (int, float)) and not isinstance(limit, bool) and \
            (limit <= 0 or (limit > 1 and limit % 1 != 0)):
        raise ConfigError("trainer.limit_train_batches", limit, "an integer >= 1 (batches per epoch), a fraction "
                          "in (0, 1] of the epoch's batches, or null (all of them)")
    for key, what in (("accumulate_grad_batches", "batches a step accumulates"),
                      ("check_val_every_n_epoch", "epochs between validations, or null")):
        value = kwargs.get(key)  # Lightning takes 0 and fails on it in its first step (integer modulo by zero)
        if isinstance(value, int) and not isinstance(value, bool) and value < 1:
            raise ConfigError(f"trainer.{key}", value, f"an integer >= 1 ({what})")
    clip = kwargs.get("gradient_clip_val")  # Lightning skips clipping at <= 0 without a word; NaN fails mid-step
    if isinstance(clip, (int, float)) and not isinstance(clip, bool) and not clip >= 0:
        raise ConfigError("trainer.gradient_clip_val", clip, "a number >= 0 (the norm or value gradients are "
                          "clipped to), or null or 0 for no clipping")
    deterministic, max_time = kwargs.get("deterministic"), kwargs.get("max_time")
    if not _is_one_of(deterministic, (True, False, "warn", None)):
        raise SchemaError(f"trainer.deterministic must be true, false, warn or null, got {deterministic!r}",
                          "trainer.deterministic", "wrong type")
    if max_time is not None and not isinstance(max_time, (str, dict)):
        raise SchemaError(f'trainer.max_time must be a "DD:HH:MM:SS" string (e.g. 00:12:00:00), a mapping of '
                          f"days/hours/minutes/seconds (e.g. {{days:1,hours:2}}) or null, got {max_time!r}",
                          "trainer.max_time", "wrong type")
    return kwargs


def checked_speed(cfg: DictConfig) -> SpeedConfig:
    """``cfg.speed`` checked against its schema, then its values (``speed.compile=maybe``, ``speed.adam=fusd``)
    by ``SpeedConfig``: one ``SchemaError`` naming the full key."""
    return SpeedConfig(**checked_node(cfg, "speed", SPEED))


def without_plus_on_trainer(overrides: Sequence[str]) -> list[str]:
    """``overrides`` with ``+trainer.X=...`` spelled ``trainer.X=...`` for every Lightning Trainer argument X.
    The schema holds all of them, so ``+`` (add a key) names a key that is there: Hydra would refuse it
    where the argument has a value (``+trainer.fast_dev_run=true``) and take it where it is null
    (``+trainer.limit_train_batches=3``); spelled without ``+``, every argument behaves alike. A key that
    is no Trainer argument (``+trainer.foo=1``), or one cicfw sets itself, keeps its ``+`` and the schema
    refuses it."""
    arguments = {f.name for f in dataclasses.fields(TRAINER)}
    spelled = re.compile(r"^\+trainer\.(\w+)(=.*)$", re.S)
    return [f"trainer.{m[1]}{m[2]}" if (m := spelled.match(o)) and m[1] in arguments else o for o in overrides]


def top_level_keys() -> list[str]:
    """The top-level keys of a train config."""
    return [f.name for f in dataclasses.fields(TrainConfig)]


register()
