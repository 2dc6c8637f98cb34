"""The keys a user set on an app's command line, from Hydra's record of it: what tells a value given on
purpose from one a config file (an experiment) sets."""
from __future__ import annotations

from typing import Any

from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf


def command_line_keys(cfg: Any, config_name: str) -> set[str]:
    """The keys (and config groups) the command line overrides, ``+``/``++``/``~`` dropped: a multirun job's
    config composed with its ``hydra`` node holds its own record (``hydra.overrides.task``), the running app
    Hydra's, when that app composes ``config_name``. Empty for a config composed in Python (``compose``)
    or while another app runs (a reproduction training its cells)."""
    task = OmegaConf.select(cfg, "hydra.overrides.task", default=None)
    if task is None and HydraConfig.initialized() and HydraConfig.get().job.config_name == config_name:
        task = HydraConfig.get().overrides.task
    return {str(o).split("=", 1)[0].lstrip("+~") for o in task or ()}
