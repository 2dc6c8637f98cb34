"""The collect app's config schema, registered with Hydra.

conf/collect.yaml puts this package on its search path, so Hydra imports it (registering the schema in its
ConfigStore) before it composes a collect config, and the defaults list lays the schema under the config:
``cicfw_collect`` under the whole of it (``CollectConfig``, the one source of a collection's keys, types and
defaults, plus the app's ``out_dir`` and ``verify``), and ``cicfw_schema/sim/<name>`` under the chosen
simulator (the registered backend's arguments: ``cicfw.sim.schema``, as in the evaluate app). OmegaConf then
refuses an unknown key or a value of the wrong type while composing, naming its full key. ``check`` looks at
the composed config only for what composing lets through, once (keys added with ``+``, a ``sim.name`` other
than the option file's); conf/collect.yaml's first callback runs it before Hydra creates the run folder.
"""
from __future__ import annotations

from dataclasses import dataclass

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig

from cicfw.collect.config import CollectConfig
from cicfw.core.config_checks import check_composed
from cicfw.core.hydra_plugins import guard_hydra_plugins
from cicfw.sim.schema import check_sim_node, store_backend_schemas


@dataclass
class CollectAppConfig(CollectConfig):
    """conf/collect.yaml: a collection, the folder it goes to, and the switch that checks a collected folder
    instead (the app's two keys take their values there)."""

    out_dir: str = MISSING
    verify: bool = MISSING


def register() -> None:
    """``cicfw_collect`` and ``cicfw_schema/sim/<name>`` for every registered backend in the ConfigStore, the
    plugins' Hydra modules guarded first, as the train schema does."""
    guard_hydra_plugins()
    ConfigStore.instance().store(name="cicfw_collect", node=CollectAppConfig, provider="cicfw")
    store_backend_schemas()


def check(cfg: DictConfig) -> None:
    """What composing let through in a collect config (``check_composed``): a key added with ``+`` anywhere,
    and the ``sim`` node against the backend its ``name`` builds. One ``SchemaError`` naming the full key."""
    check_composed(cfg, CollectAppConfig, skip=("sim",))
    check_sim_node(cfg.get("sim"))


register()
