"""A config Hydra cannot compose as one line, and hints for what the line cannot say.

Apps call ``run_app(main, "train")`` instead of ``main()``: an override Hydra cannot parse (a value with a
space the shell split: ``model.lr=1 e-3``), an unknown key or a value of the wrong type (OmegaConf's refusal,
with the schema's accepted keys or type: ``config_checks.config_error``) and an unknown option of a config
group each end the app as one ``cicfw: error:`` line, exit status 2, before Hydra creates any run folder;
an option that needs an optional extra (``hparams_search=optuna`` without ``cicfw[sweeps]``) adds a hint.
``override_hints`` (the keys that exist where a mistyped override points, from a second composition) serves
a config composed inside an app (``evaluate_overrides``). ``OneLineJobFailure`` (a Hydra callback) ends a
multirun whose job failed with one line instead of the job's traceback.
"""
from __future__ import annotations

import dataclasses
import difflib
import functools
import os
import re
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

from hydra.errors import CompactHydraException
from hydra.experimental.callback import Callback
from omegaconf import OmegaConf, open_dict

CONFIG_MODULE = "cicfw.conf"

# Options that need a Hydra plugin from an optional extra: option -> (plugin module, extra).
NEEDS_EXTRA = {
    "hparams_search=optuna": ("hydra_plugins.hydra_optuna_sweeper", "sweeps"),
    "launcher=joblib": ("hydra_plugins.hydra_joblib_launcher", "sweeps"),
    "launcher=slurm": ("hydra_plugins.hydra_submitit_launcher", "slurm"),
}


def missing_extras(args: list[str]) -> list[str]:
    """A hint per chosen option whose Hydra plugin is not installed."""
    from importlib.util import find_spec

    hints = []
    for arg in args:
        module, extra = NEEDS_EXTRA.get(arg.replace(" ", ""), (None, None))
        if module is None:
            continue
        try:
            found = find_spec(module) is not None
        except ModuleNotFoundError:
            found = False
        if not found:
            hints.append(f"cicfw: hint: {arg} needs the '{extra}' extra: pip install \"cicfw[{extra}]\" "
                         f"(or pip install -e \".[{extra}]\" in a clone)")
    return hints


def _parse(args: list[str]) -> list[Any]:
    """Hydra overrides among command-line ``args`` (flags like ``-m`` or ``--cfg job`` skipped)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    out = []
    for arg in args:
        if arg.startswith("-") or "=" not in arg:
            continue
        try:
            out.append(parser.parse_override(arg))
        except Exception:
            continue  # Hydra reports unparsable overrides itself
    return out


def _describe(path: str, missing: str, keys: list[str], groups: list[str]) -> str:
    where = f"'{path}'" if path else "the top level of the config"
    close = difflib.get_close_matches(missing, list(dict.fromkeys(keys + groups)), n=3, cutoff=0.6)
    msg = f"cicfw: hint: {where} has no key '{missing}'"
    if close:
        msg += "; did you mean " + " or ".join(f"'{c}'" for c in close) + "?"
    if keys:
        msg += f"\n  keys there: {', '.join(sorted(keys))}"
    if groups:
        msg += f"\n  config groups there (choose with group=option): {', '.join(sorted(groups))}"
    return msg


def _describe_empty(path: str, override: str) -> str:
    """The hint for a key under an empty node (``data.collect: {}``): its keys are the app's, added with ``+``."""
    return (f"cicfw: hint: '{path}' is empty in the config (the keys it takes are documented beside it), so a key "
            f"under it is added with '+': +{override}")


def _is_open(cfg: Any, path: list[str]) -> bool:
    """Whether the config node at ``path`` accepts new keys (its struct flag is explicitly off)."""
    node = OmegaConf.select(cfg, ".".join(path)) if path else cfg
    return OmegaConf.is_dict(node) and node._get_node_flag("struct") is False


@contextmanager
def hydra_context(config_module: str = CONFIG_MODULE) -> Iterator[None]:
    """Hydra initialised for ``compose``: the running app's (inside ``cicfw train``, composing the
    evaluation's config up front), else ``config_module`` for the duration."""
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        yield
        return
    with initialize_config_module(config_module, version_base="1.3"):
        yield


def override_hints(config_name: str, args: list[str], config_module: str = CONFIG_MODULE) -> list[str]:
    """One hint per override in ``args`` whose key the composed config lacks (added ``+key`` and
    ``hydra.*`` keys excepted)."""
    from hydra import compose
    from hydra.core.global_hydra import GlobalHydra

    overrides = _parse(args)
    if not overrides:
        return []
    hints: list[str] = []
    with hydra_context(config_module):
        loader = GlobalHydra.instance().config_loader()

        def groups_at(path: str) -> list[str]:
            """The config groups under ``path`` that this app's defaults use (not every group in conf/)."""
            prefix = path.replace(".", "/") + "/" if path else ""
            try:
                return [g for g in loader.list_groups(prefix.rstrip("/")) if f"{prefix}{g}" in used]
            except Exception:
                return []

        def is_group(key: str) -> bool:
            return bool(loader.get_group_options(key.replace(".", "/")))

        choices = [o.input_line for o in overrides if is_group(o.key_or_group) and not o.is_sweep_override()]
        try:
            cfg = compose(config_name, overrides=choices, return_hydra_config=True)
        except Exception:
            return []  # a bad group choice: Hydra's own message lists the options
        used = {g for g in cfg.hydra.runtime.choices if not g.startswith("hydra/")}
        with open_dict(cfg):
            del cfg["hydra"]
        tree = OmegaConf.to_container(cfg, resolve=False)  # plain dicts: '???' values count as present
        for o in overrides:
            key = o.key_or_group
            if o.is_add() or o.is_force_add() or key.startswith("hydra.") or key == "hydra" or is_group(key):
                continue
            node: Any = tree
            parts = key.split(".")
            for i, part in enumerate(parts):
                if _is_open(cfg, parts[:i]):
                    break  # an open node (trainer: any Trainer argument) takes new keys; the app checks them
                if not isinstance(node, dict) or part not in node:
                    path = ".".join(parts[:i])
                    keys = [str(k) for k in node] if isinstance(node, dict) else []
                    if path and node == {} and not groups_at(path):
                        hints.append(_describe_empty(path, o.input_line))
                    else:
                        hints.append(_describe(path, part, keys, groups_at(path)))
                    break
                node = node[part]
    return hints


@functools.lru_cache(maxsize=8)
def top_level_keys(config_name: str, config_module: str = CONFIG_MODULE) -> tuple[str, ...] | None:
    """The top-level keys of ``config_name`` composed with its defaults (its own keys and its config
    groups' nodes): the keys the app reads. None when it cannot be composed here."""
    from hydra import compose

    try:
        with hydra_context(config_module):
            return tuple(compose(config_name))
    except Exception:  # another app's config search path: the check is skipped, not the run
        return None


def check_top_level_keys(cfg: Any, config_name: str, where: str = "") -> None:
    """One ``ValueError`` for a top-level key ``config_name`` does not have (``+evaluate_aftr=true``:
    added with ``+``, never read, so it would silently change nothing), naming the accepted keys, as
    ``cicfw collect`` does for its keys. ``where`` prefixes the message (``evaluate_overrides: ``)."""
    typed = OmegaConf.get_type(cfg)  # a config with a schema (train's) knows its keys; else compose the app's
    accepted = tuple(f.name for f in dataclasses.fields(typed)) if dataclasses.is_dataclass(typed) else \
        top_level_keys(config_name)
    if accepted is None:
        return
    unknown = [str(k) for k in cfg if str(k) not in accepted and str(k) != "hydra"]
    if unknown:
        close = difflib.get_close_matches(unknown[0], list(accepted), n=1, cutoff=0.6)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise ValueError(f"{where}unknown top-level key {unknown[0]!r}; {hint}accepted top-level keys: "
                         f"{', '.join(sorted(accepted))}")


def composition_error_line(err: BaseException, args: list[str]) -> str | None:
    """What Hydra refused before running the app, as one line: an argument it cannot parse (``args``: the
    command line, to show it quoted), a key or value the config refuses, an unknown option of a config
    group; None for anything else."""
    from hydra.errors import ConfigCompositionException, MissingConfigException, OverrideParseException

    from cicfw.config_checks import config_error

    if isinstance(err, OverrideParseException):
        return _unparsable(err.override, err.message, args)
    if not isinstance(err, ConfigCompositionException):
        return None  # raised by the app itself (its own errors keep their report)
    where = re.match(r"In '([^']+)': ", str(err))  # a value in a config file, not on the command line
    refused = config_error(err, f"{where.group(1)}.yaml: " if where else "")
    if refused is not None:
        return str(refused)
    if isinstance(err, MissingConfigException) and err.options is not None:
        group, _, option = str(err.missing_cfg_file or "").rpartition("/")
        return f"{group}={option}: no option {option!r} in config group {group!r}; options: {', '.join(err.options)}"
    return " ".join(str(err).split())


def _unparsable(override: str, message: str, args: list[str]) -> str:
    """``model.lr=1 e-3`` typed without quotes reaches Hydra as ``model.lr=1`` and ``e-3``: say which
    argument, and that such a value is one quoted argument."""
    said = [ln.strip() for ln in message.splitlines()[1:] if ln.strip() and not ln.startswith("See https://")]
    reason = said[0] if said else "not in Hydra's override grammar"
    line = f"cannot parse the argument {override!r} ({reason})"
    i = args.index(override) if override in args else -1
    if i > 0 and "=" not in override:
        return f"{line}: a value holding spaces must be quoted as one argument, e.g. '{args[i - 1]} {override}'"
    if 0 <= i < len(args) - 1 and "=" in override:
        return f"{line}: a value holding spaces must be quoted as one argument, e.g. '{override} {args[i + 1]}'"
    return f"{line}: a value holding spaces must be quoted as one argument, e.g. 'key=a b'"


@contextmanager
def one_line_config_errors() -> Iterator[None]:
    """Inside, what Hydra refuses before running the app (``composition_error_line``) is printed as one
    ``cicfw: error:`` line and ends the app with status 2, instead of Hydra's message and its advice to set
    HYDRA_FULL_ERROR; a sweep folder made before Hydra refused a job's config is removed again
    (``run_folder.undo_noted_folders``). Hydra calls its ``run_and_report``
    around composing and running: that is where this steps in (HYDRA_FULL_ERROR=1 still shows it all)."""
    import hydra._internal.utils as hydra_utils

    from cicfw.run_folder import undo_noted_folders

    report = hydra_utils.run_and_report

    def one_line(func: Callable[[], Any]) -> Any:
        try:
            return func()
        except Exception as err:
            line = None if os.environ.get("HYDRA_FULL_ERROR") == "1" else composition_error_line(err, sys.argv[1:])
            if line is None:
                raise
            print(f"cicfw: error: {line}", file=sys.stderr)
            undo_noted_folders()  # a sweep folder made before Hydra refused a job's config
            sys.exit(2)

    hydra_utils.run_and_report = lambda func: report(lambda: one_line(func))
    try:
        yield
    finally:
        hydra_utils.run_and_report = report


def run_app(main: Callable[[], Any], config_name: str, config_module: str = CONFIG_MODULE) -> None:
    """Run a ``@hydra.main`` app: what Hydra refuses is one line (``one_line_config_errors``); a failure
    that names an option needing an optional extra adds a hint. A plugin whose Hydra module fails to
    import is skipped with one warning first (it would stop the app)."""
    from cicfw.registry import guard_hydra_plugins

    guard_hydra_plugins()
    try:
        with one_line_config_errors():
            main()
    except SystemExit as exit_:
        if exit_.code not in (None, 0, 130, 143):  # interrupted (Ctrl-C, SIGTERM): no config to hint at
            for hint in missing_extras(sys.argv[1:]):
                print(hint, file=sys.stderr)
        raise


class JobFailed(CompactHydraException):
    """A multirun job's failure as one line: Hydra prints a compact exception without a traceback."""


def failure_line(err: BaseException) -> str:
    """A job's exception in one line: a user error's message, else its type and message."""
    from cicfw.errors import USER_ERRORS

    text = err.args[0] if isinstance(err, (KeyError, FileNotFoundError)) and err.args else err
    line = " ".join(str(text).split())
    return line if isinstance(err, USER_ERRORS) else f"{type(err).__name__}: {line}"


class OneLineJobFailure(Callback):
    """Hydra callback: a failed multirun job's exception, which the sweeper raises once the batch of jobs
    is done (Hydra would print its traceback), becomes one ``cicfw: error:`` line naming the job, its
    overrides and its log. The job stays failed (the sweep summary, listed after this callback, records
    its own error; Optuna marks the trial failed); its log keeps the whole story."""

    def on_job_end(self, config: Any, job_return: Any, **kwargs: Any) -> None:
        from hydra.core.utils import JobStatus

        err = getattr(job_return, "_return_value", None)
        if job_return.status != JobStatus.FAILED or not isinstance(err, Exception) or isinstance(err, JobFailed):
            return
        hc = config.hydra
        log_file = Path(str(hc.runtime.output_dir)) / f"{hc.job.name}.log"
        summary = Path(str(hc.sweep.dir)) / "summary.csv"
        every = f"; every job's status: {summary}" if summary.is_file() else ""
        overrides = " ".join(job_return.overrides or [])
        job_return._return_value = JobFailed(f"cicfw: error: job {hc.job.num} ({overrides}) failed: "
                                             f"{failure_line(err)} (its log: {log_file}){every}")
