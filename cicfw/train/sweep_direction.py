"""An optimising sweeper's direction (Optuna's ``hydra.sweeper.direction``) against what ``train`` returns:
the validation metric, lower is better, or with ``evaluate_after=true return_closed_loop=true`` the
closed-loop success, higher is better. The wrong one searches for the worst model without a word, so it is
refused before the first trial."""
from __future__ import annotations

from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import OmegaConf

from cicfw.core.errors import ConfigError
from cicfw.core.run_folder import refuse_before_any_job


def wanted_direction(config: Any) -> str:
    """``maximize`` when ``train`` returns the closed-loop success rate, else ``minimize``."""
    return "maximize" if config.get("evaluate_after") and config.get("return_closed_loop") else "minimize"


def check_direction(config: Any) -> None:
    """A ``ConfigError`` naming ``hydra.sweeper.direction`` when it is a single direction other than
    ``wanted_direction`` (a sweeper without one, or a multi-objective list, is not checked)."""
    direction = OmegaConf.select(config, "hydra.sweeper.direction", default=None)
    if direction is None or OmegaConf.is_list(direction) or isinstance(direction, (list, tuple)):
        return
    said = str(getattr(direction, "name", direction)).lower()
    want = wanted_direction(config)
    if said != want:
        returns = ("the closed-loop success rate (evaluate_after=true return_closed_loop=true: higher is better)"
                   if want == "maximize" else f"optimized_metric={config.get('optimized_metric')} (lower is better)")
        raise ConfigError("hydra.sweeper.direction", said, f"{want}: train returns {returns}, so {said} would search "
                          f"for the worst model")


class SweepDirectionCheck(Callback):
    """Hydra callback: ``check_direction`` on the sweep's config before the first job; one ``cicfw: error:``
    line, exit status 2, and no sweep folder left."""

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        try:
            check_direction(config)
        except ConfigError as err:
            refuse_before_any_job(str(err))
