"""The evaluate app's config schema, taken from what each node builds, and registered with Hydra.

conf/evaluate.yaml puts this package on its search path (cicfw.evaluate imports it too), so Hydra imports it
(registering the schema in its ConfigStore) before it composes an evaluate config, and the defaults list
lays the schema under the config: ``cicfw_evaluate`` under the whole of it (``runner``: ``RunnerConfig``'s
fields, ``suite``: ``build_suite``'s arguments) and ``cicfw_schema/sim/<name>`` under the chosen simulator
(the registered backend's arguments, plugins' included: ``cicfw.sim.schema``, shared with the collect app).
OmegaConf then refuses an unknown key or a value of the wrong type while composing, naming its full key.
``check`` looks at a composed config only for what composing lets through, once: keys added with ``+``, a
``sim.name`` other than the option file's, and ``runner.workers``, whose union OmegaConf cannot type;
conf/evaluate.yaml's first callback (``cicfw.core.override_hints.SchemaCheck``) runs it before Hydra creates
the run folder.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from cicfw.benchmark.runner import RunnerConfig
from cicfw.benchmark.suite import build_suite
from cicfw.core.config_checks import SchemaError, check_composed, kwargs_schema
from cicfw.core.hydra_plugins import guard_hydra_plugins
from cicfw.sim.schema import check_sim_node, store_backend_schemas

RUNNER = kwargs_schema(RunnerConfig, "the runner", not_settable={
    "seed": "it is the top-level seed=...", "progress_bar": "it is the top-level progress_bar=..."})
SUITE = kwargs_schema(build_suite, "the suite (build_suite)", exclude=("backend",))


@dataclass
class EvaluateConfig:
    """conf/evaluate.yaml: its own keys (their values are written there) and the nodes of what it builds."""

    __cicfw_what__ = "the evaluate config"

    checkpoint: Optional[str] = MISSING
    name: Optional[str] = MISSING
    seed: int = MISSING
    # the registered policy's arguments; open here: a plugin's policy takes its own, and the expert hands
    # **kwargs on to ExpertParams. cicfw.benchmark.app.plan_evaluation checks them before the checkpoint is read.
    policy: Any = MISSING
    sim: Any = MISSING  # cicfw_schema/sim/<name>, then the chosen option
    suite: SUITE = field(default_factory=SUITE)  # type: ignore[valid-type]
    runner: RUNNER = field(default_factory=RUNNER)  # type: ignore[valid-type]
    video: Optional[list[Any]] = MISSING
    video_max: int = MISSING
    maps: bool = MISSING
    progress_bar: bool = MISSING


def register() -> None:
    """``cicfw_evaluate`` and ``cicfw_schema/sim/<name>`` for every registered backend in the ConfigStore,
    the plugins' Hydra modules guarded first, as the train schema does."""
    guard_hydra_plugins()
    store = ConfigStore.instance()
    store.store(name="cicfw_evaluate", node=EvaluateConfig, provider="cicfw")
    store_backend_schemas()


def check_workers(workers: Any) -> None:
    """``runner.workers``: ``auto``, a whole number >= 1, or (sim=carla) a list of server ports, as
    ``RunnerConfig`` takes them; else one ``SchemaError`` naming ``runner.workers``."""
    try:
        RunnerConfig(workers=workers)
    except ValueError as err:
        raise SchemaError(str(err), "runner.workers", "wrong type") from None


def check(cfg: DictConfig) -> None:
    """What composing let through in an evaluate config (``check_composed``): a key added with ``+`` (policy
    excepted: its node is open), the ``sim`` node against the backend its ``name`` builds, and
    ``runner.workers``. One ``SchemaError`` naming the full key."""
    check_composed(cfg, EvaluateConfig, skip=("sim",))
    check_sim_node(cfg.get("sim"))
    workers = (cfg.get("runner") or {}).get("workers", 1)
    check_workers(OmegaConf.to_container(workers) if OmegaConf.is_config(workers) else workers)


register()
