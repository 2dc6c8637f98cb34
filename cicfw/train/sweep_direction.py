"""An optimising sweeper's direction (Optuna's ``hydra.sweeper.direction``) against what ``train`` returns:
the validation metric, lower is better, or with ``evaluate_after=true return_closed_loop=true`` the
closed-loop success, higher is better. The wrong one searches for the worst model without a word, so it is
refused before the first trial; so are the sweeper's settings Optuna would fail on mid-sweep with a traceback
(``check_sweeper_settings``)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import IntervalSweep
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


#: the first bytes of every SQLite database file
SQLITE_HEADER = b"SQLite format 3\x00"


def check_sweeper_settings(config: Any) -> None:
    """A ``ConfigError`` naming the key for an Optuna setting it fails on only once the sweep runs, with a
    traceback: ``n_trials`` or ``n_jobs`` below 1, a ``sqlite:///`` storage naming a file that is not a
    database, a log-scaled interval reaching 0 or below. A sweeper without these keys is not checked."""
    sweeper = OmegaConf.select(config, "hydra.sweeper", default=None)
    if sweeper is None or "n_trials" not in sweeper:
        return
    for key in ("n_trials", "n_jobs"):
        value = sweeper.get(key)
        if value is not None and (not isinstance(value, int) or isinstance(value, bool) or value < 1):
            raise ConfigError(f"hydra.sweeper.{key}", value, "a whole number >= 1")
    storage = sweeper.get("storage")
    if isinstance(storage, str) and storage.startswith("sqlite:///"):
        path = Path(storage[len("sqlite:///"):]).expanduser()
        try:
            head = path.read_bytes()[:len(SQLITE_HEADER)] if path.is_file() else None
        except OSError:
            head = None
        if head is not None and path.stat().st_size > 0 and head != SQLITE_HEADER:
            raise ConfigError("hydra.sweeper.storage", storage, "a new file or an SQLite database (Optuna's study); "
                              f"{path} is another kind of file")
    parser = OverridesParser.create()
    given = [(f"hydra.sweeper.params.{k}", f"{k}={v}", v) for k, v in (sweeper.get("params") or {}).items()]
    given += [(o.split("=", 1)[0], o, o.split("=", 1)[1])  # a sweep given on the command line, as Optuna takes it
              for o in OmegaConf.select(config, "hydra.overrides.task", default=None) or [] if "=" in o]
    for key, override, value in given:
        try:
            sweep = parser.parse_override(override).value()
        except Exception:  # Hydra's own parse reports it, naming the override
            continue
        if isinstance(sweep, IntervalSweep) and "log" in (sweep.tags or ()) and min(sweep.start, sweep.end) <= 0:
            raise ConfigError(key, value, "a log-scaled interval above 0 (e.g. tag(log, interval(1e-5, 1e-2)))")


class SweepDirectionCheck(Callback):
    """Hydra callback: ``check_direction`` and ``check_sweeper_settings`` on the sweep's config before the
    first job; one ``cicfw: error:`` line, exit status 2, and no sweep folder left."""

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        try:
            check_direction(config)
            check_sweeper_settings(config)
        except ConfigError as err:
            refuse_before_any_job(str(err))
