"""The export app's config schema, taken from ``cicfw.export.app.export_model``'s arguments, and registered with
Hydra.

conf/export.yaml puts this package on its search path, so Hydra imports it (registering ``cicfw_export`` in
its ConfigStore) before it composes an export config, and lays it under the config first: its keys are
``export_model``'s arguments (``format`` for its ``fmt``; the paths as strings), so OmegaConf refuses an
unknown key or a value of the wrong type while composing, naming its key. ``check`` looks at the composed
config only for a key added with ``+`` (which composing lets through); conf/export.yaml's first callback runs
it before the checkpoint is read.
"""
from __future__ import annotations

from typing import Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig

from cicfw.core.config_checks import check_composed, kwargs_schema
from cicfw.export.app import export_model

#: the paths are given as text on the command line; ``format`` is ``export_model``'s ``fmt``
EXPORT = kwargs_schema(export_model, "the export (export_model)", exclude=("fmt",), fields={
    "checkpoint": (Optional[str], MISSING), "format": (str, MISSING), "out": (Optional[str], MISSING),
    "frames": (Optional[str], MISSING)})


def check(cfg: DictConfig) -> None:
    """What composing let through in an export config (a key added with ``+``): one ``SchemaError`` naming it."""
    check_composed(cfg, EXPORT)


ConfigStore.instance().store(name="cicfw_export", node=EXPORT, provider="cicfw")
