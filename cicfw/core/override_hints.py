"""A config Hydra cannot compose as one line, and hints for what the line cannot say.

Apps call ``run_app(main, "train")`` instead of ``main()``: an override Hydra cannot parse (a value with a
space the shell split: ``model.lr=1 e-3``), an unknown key or a value of the wrong type (OmegaConf's refusal,
with the schema's accepted keys or type: ``config_checks.config_error``) and an unknown option of a config
group each end the app as one ``cicfw: error:`` line, exit status 2, before Hydra creates any run folder;
an option that needs an optional extra (``hparams_search=optuna`` without ``cicfw[sweeps]``) adds a hint.
``SchemaCheck`` (a Hydra callback) runs an app's schema check on the composed config before the run
folder is created; ``OneLineJobFailure`` (another) ends a multirun whose job failed with one line instead
of the job's traceback. A ``--config-dir`` file that a built-in config of the same name would hide is refused
in one line (``refuse_shadowed_config_dir``).
"""
from __future__ import annotations

import copy
import os
import re
import shlex
import sys
from contextlib import contextmanager
from importlib.util import find_spec
from pathlib import Path
from typing import Any, Callable, Iterator

import hydra._internal.utils as hydra_utils
from hydra._internal.config_repository import ConfigRepository
from hydra._internal.config_search_path_impl import ConfigSearchPathImpl
from hydra._internal.hydra import Hydra
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.config_search_path import ConfigSearchPath
from hydra.core.default_element import GroupDefault
from hydra.core.global_hydra import GlobalHydra
from hydra.core.object_type import ObjectType
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobReturn, JobStatus
from hydra.errors import (CompactHydraException, ConfigCompositionException, MissingConfigException,
                          OverrideParseException)
from hydra.experimental.callback import Callback
from hydra.utils import get_method
from omegaconf import OmegaConf

from cicfw.core.config_checks import SchemaError, config_error
from cicfw.core.errors import USER_ERRORS, CicfwError
from cicfw.core.hydra_plugins import guard_hydra_plugins
from cicfw.core.run_folder import refuse_before_any_job
from cicfw.core.sweeps import every_job_failed, forget_running_sweep, is_worker_process

# Options that need a Hydra plugin from an optional extra: option -> (plugin module, extra).
NEEDS_EXTRA = {
    "hparams_search=optuna": ("hydra_plugins.hydra_optuna_sweeper", "sweeps"),
    "launcher=joblib": ("hydra_plugins.hydra_joblib_launcher", "sweeps"),
    "launcher=slurm": ("hydra_plugins.hydra_submitit_launcher", "slurm"),
}


def missing_extras(args: list[str]) -> list[str]:
    """A hint per chosen option whose Hydra plugin is not installed."""
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


def composition_error(err: BaseException, args: list[str]) -> CicfwError | None:
    """What Hydra refused before running the app, as the error the CLI prints (for code that composes a config
    itself too: ``cicfw.testing.fast_dev_run``): an argument it cannot parse (``args``: the command line, to
    show it quoted), a key or value the config refuses (a ``SchemaError`` naming the key), an unknown option
    of a config group (its key and value: the group and the option); None for anything else."""
    if isinstance(err, OverrideParseException):
        return CicfwError(_unparsable(err.override, err.message, args))
    if not isinstance(err, ConfigCompositionException):
        return None  # raised by the app itself (its own errors keep their report)
    where = re.match(r"In '([^']+)': ", str(err))  # a value in a config file, not on the command line
    refused = config_error(err, f"{where.group(1)}.yaml: " if where else "")
    if refused is not None:
        return refused
    other = re.match(r"Could not override '([^']+)'\. No match in the defaults list", str(err))
    if other is not None and _other_apps_group(other.group(1)):
        group = other.group(1)
        value = next((a.split("=", 1)[1] for a in args if a.split("=", 1)[0].lstrip("+~") == group and "=" in a), "")
        return CicfwError(f"{group}={value}: this app reads no config group {group!r} (another cicfw app's option: "
                          f"a checkpoint's model, for instance, comes from its checkpoint); --help lists this app's "
                          f"groups", key=group, value=value)
    if isinstance(err, MissingConfigException) and err.options is not None:
        group, _, option = str(err.missing_cfg_file or "").rpartition("/")
        return CicfwError(f"{group}={option}: no option {option!r} in config group {group!r}; options: "
                          f"{', '.join(err.options)}", key=group, value=option)
    return CicfwError(" ".join(str(err).split()))


def _other_apps_group(name: str) -> bool:
    """Whether ``name`` is a config group of cicfw's config tree whose options fill a node of their own
    (``mixer``, ``head``: another app's settings), where Hydra's advice to append it with ``+name=...`` would
    only fail again on that node's keys. A group of ``@package _global_`` options (``launcher``,
    ``experiment``) keeps Hydra's advice: ``+launcher=joblib`` works for any app that sweeps."""
    try:
        loader = GlobalHydra.instance().config_loader()
        options = loader.get_group_options(name)
        header = loader.repository.load_config(f"{name}/{options[0]}").header if options else None
    except Exception:  # Hydra not initialised, or no such group
        return False
    return header is not None and header.get("package") != "_global_"


def composition_error_line(err: BaseException, args: list[str]) -> str | None:
    """``composition_error`` as the one line the CLI prints; None where it has none."""
    refused = composition_error(err, args)
    return None if refused is None else str(refused)


def _unparsable(override: str, message: str, args: list[str]) -> str:
    """One line for an argument Hydra cannot parse: which, Hydra's reason, and a hint only where the cause is
    known: a value the shell split at a space (``model.lr=1 e-3`` typed without quotes reaches Hydra as
    ``model.lr=1`` and ``e-3``: joined again they parse), a list element holding ``=`` (it must be quoted),
    brackets left open, a '~' (the shell expands it only at the start of a word)."""
    lines = message.splitlines()
    said = [ln.strip() for ln in lines[1:] if ln.strip() and not ln.startswith("See https://")]
    reason = said[0] if said else "not in Hydra's override grammar"
    bad = None  # the character the lexer cannot read
    if reason == "^":  # the lexer's: the argument's first line ends the message's, the caret under what it cannot read
        caret = next(ln for ln in lines[1:] if ln.strip())  # after an argument ending in a line break, a blank line
        at = caret.index("^") - len(lines[0]) + len((override.splitlines() or [""])[0])
        bad = override[at:at + 1]
        reason = f"{bad!r} at character {at + 1} is not in Hydra's override grammar"
    line = f"cannot parse the argument {override!r} ({reason})"
    joined = _rejoined(override, args)
    if joined is not None:
        return f"{line}: a value holding spaces must be quoted as one argument, e.g. '{joined}'"
    key, eq, value = override.partition("=")
    quoted = _quoted_elements(key, value) if eq else None
    if quoted is not None:
        return f"{line}: a list element holding '=' must be quoted, e.g. '{quoted}'"
    if any(value.count(a) != value.count(b) for a, b in ("[]", "{}", "()")):
        return f"{line}: its brackets do not close"
    if eq and (value == "~" or value.startswith("~/")):  # ~name is name's home, not $HOME
        return f"{line}: the shell expands '~' only at the start of a word; write $HOME, e.g. {key}=$HOME{value[1:]}"
    if bad and bad.isprintable():  # a line break or another control character: quoting keeps it, no fix
        named = key if eq and bad not in key else "key"  # a key itself takes no such character
        example = _quoted_value(override, args) or f"\"{named}='...'\""
        return f"{line}: a value holding {bad!r} must be quoted, e.g. {example}"
    return line


def _quoted_value(override: str, args: list[str]) -> str | None:
    """``key=value`` with its value quoted for Hydra (``key='a ü'``), as the shell argument that parses:
    ``override`` alone, or joined with the argument before it where the shell split the value at a space
    (``checkpoint=/tmp/run ü=1`` typed unquoted); None when neither parses so."""
    i = args.index(override) if override in args else -1
    texts = [override] + ([f"{args[i - 1]} {override}"] if i > 0 else [])
    for text in texts:
        key, eq, value = text.partition("=")
        if not eq:
            continue
        for hydra in (f"{key}='{value}'", f'{key}="{value}"'):
            if _parses(hydra):  # as the shell takes it: in double quotes where they keep it as it is
                return f'"{hydra}"' if not set(hydra) & set('"$`\\!') else shlex.quote(hydra)
    return None


def _parses(text: str) -> bool:
    try:
        OverridesParser.create().parse_override(text)
    except Exception:
        return False
    return True


def _rejoined(override: str, args: list[str]) -> str | None:
    """``override`` joined with its neighbours in ``args`` at a space, as one argument that parses (the
    longest such run), or None when no space explains the failure."""
    i = args.index(override) if override in args else -1
    if i < 0:
        return None
    for start in (i - 1, i):  # the value began in the argument before, or in this one
        if start < 0 or (start == i and i == len(args) - 1):
            continue
        end = i + 1 if start < i else i + 2
        if not _parses(" ".join(args[start:end])):
            continue
        while end < len(args) and "=" not in args[end] and _parses(" ".join(args[start:end + 1])):
            end += 1
        return " ".join(args[start:end])
    return None


def _quoted_elements(key: str, value: str) -> str | None:
    """``key=[a=1,b]`` as ``key=["a=1","b"]``, when that parses and an element holds ``=``; else None."""
    if not (value.startswith("[") and value.endswith("]") and "=" in value):
        return None
    elements = [e.strip().strip("'\"") for e in value[1:-1].split(",") if e.strip()]
    fixed = f"{key}=[" + ",".join(f'"{e}"' for e in elements) + "]"
    return fixed if _parses(fixed) else None


@contextmanager
def one_line_config_errors() -> Iterator[None]:
    """Inside, what Hydra refuses before running the app (``composition_error_line``) is printed as one
    ``cicfw: error:`` line and ends the app with status 2, instead of Hydra's message and its advice to set
    HYDRA_FULL_ERROR; a sweep folder made before Hydra refused a job's config is removed again
    (``run_folder.undo_noted_folders``); a sweep whose every job failed ends in one line saying so and where
    their errors are (``sweeps.every_job_failed``, status 1). Hydra calls its ``run_and_report``
    around composing and running: that is where this steps in (HYDRA_FULL_ERROR=1 still shows it all)."""
    report = hydra_utils.run_and_report

    def one_line(func: Callable[[], Any]) -> Any:
        forget_running_sweep()  # only a sweep this call runs speaks for its error (not one an earlier call ran)
        try:
            return func()
        except Exception as err:
            if os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            if isinstance(err, UserJobFailed):  # a job's user error: its one line, not Hydra's report around it
                print(err, file=sys.stderr)
                sys.exit(1)
            # Optuna's "no trial is completed" (a ValueError) when every trial failed: not its traceback
            failed = every_job_failed() if isinstance(err, ValueError) and not isinstance(err, JobFailed) else None
            if failed is not None:
                print(f"cicfw: error: {failed}", file=sys.stderr)
                sys.exit(1)
            line = composition_error_line(err, sys.argv[1:])
            if line is None:
                raise
            refuse_before_any_job(line)
        finally:
            forget_running_sweep()

    hydra_utils.run_and_report = lambda func: report(lambda: one_line(func))
    try:
        yield
    finally:
        hydra_utils.run_and_report = report


#: the resolver conf/hydra/help/cicfw.yaml lists an app's config groups with
HELP_RESOLVER = "cicfw_app_groups"


def app_groups(config_name: str) -> str:
    """``group: option, option`` per config group that the app config ``config_name`` reads: the groups of
    its defaults list and, through its options' defaults lists, the groups they reach (an experiment's
    ``override /mixer``), as Hydra's ``--help`` lists groups; Hydra's own groups and the schemas'
    (``cicfw_schema/...``) left out, and so are the other apps'."""
    repo = GlobalHydra.instance().config_loader().repository  # one repository: the loader makes one per call

    def options(group: str) -> list[str]:
        return repo.get_group_options(group, ObjectType.CONFIG)

    groups: set[str] = set()
    todo = [(config_name, "")]  # (config path, the group it is an option of)
    while todo:
        path, parent = todo.pop()
        found = repo.load_config(path)
        for d in (found.defaults_list if found is not None else None) or []:
            if not isinstance(d, GroupDefault):
                continue
            group = d.group[1:] if d.group.startswith("/") else "/".join(filter(None, (parent, d.group)))
            if group in groups or group.split("/")[0] in ("hydra", "cicfw_schema"):
                continue
            groups.add(group)
            todo += [(f"{group}/{option}", group) for option in options(group)]
    lines = [f"{g}: {', '.join(sorted(options(g)))}" for g in sorted(groups)]
    return "\n".join(lines) or "(none: every key is set as key=value)"


def register_help() -> None:
    """The resolver of an app's ``--help`` (``app_groups``), registered by the app's ``main`` (``run_app``).
    Hydra's ``get_help`` also lists every group of the tree, twice, whether the template prints the
    listings or not (most of ``--help``'s 11 s here); where the template prints neither, they are skipped."""
    if not OmegaConf.has_resolver(HELP_RESOLVER):
        OmegaConf.register_new_resolver(HELP_RESOLVER, app_groups, use_cache=True)  # the template is read twice
    if not getattr(Hydra.get_help, "skips_unprinted_groups", False):
        Hydra.get_help = _without_unprinted_groups(Hydra.get_help)


def _without_unprinted_groups(get_help: Callable[..., str]) -> Callable[..., str]:
    """``Hydra.get_help`` with its group listings empty when the help template prints neither."""
    def wrapped(self: Hydra, help_cfg: Any, *args: Any, **kwargs: Any) -> str:
        if "CONFIG_GROUPS" not in str(help_cfg.template):
            self = copy.copy(self)  # this call only: Hydra's --hydra-help still lists them
            self.format_config_groups = lambda *a, **k: ""
        return get_help(self, help_cfg, *args, **kwargs)
    wrapped.skips_unprinted_groups = True  # type: ignore[attr-defined]
    return wrapped


#: the provider of the folder Hydra's ``--config-dir`` (``-cd``) puts on the search path
CONFIG_DIR_PROVIDER = "command-line"


def refuse_shadowed_config_dir(search_path: ConfigSearchPath) -> None:
    """A ``CicfwError`` naming a ``--config-dir`` file that a config of the same name earlier on Hydra's search
    path hides: Hydra puts that folder after the app's own configs and the plugins', and the first match wins,
    so a file named like a built-in option (``mixer/gtu.yaml``) would be ignored without a word."""
    entries = search_path.get_path()
    at = next((i for i, e in enumerate(entries) if e.provider == CONFIG_DIR_PROVIDER), None)
    if at is None or entries[at].path is None or not entries[at].path.startswith("file://"):
        return
    folder = Path(entries[at].path[len("file://"):])
    before = ConfigSearchPathImpl()
    for entry in entries[:at]:
        before.append(entry.provider, entry.path)
    sources = ConfigRepository(before).get_sources()
    shadowed = []  # (the file's name in the folder, the source whose file of that name wins)
    groups = [""]  # the folder's subfolders that are a config group earlier too (others hold only new names)
    while groups:
        group = groups.pop(0)
        try:
            entries = sorted((folder / group).iterdir())
        except OSError:  # unreadable: Hydra cannot read its files either
            continue
        for entry in entries:
            name = f"{group}/{entry.name}" if group else entry.name
            if entry.is_dir() and any(s.is_group(name) for s in sources):
                groups.append(name)
            elif entry.suffix == ".yaml" and entry.is_file():
                winner = next((s for s in sources if s.is_config(name[:-5])), None)
                if winner is not None:
                    shadowed.append((name[:-5], winner))
    if not shadowed:
        return
    name, winner = shadowed[0]
    owner = {"main": "cicfw", "hydra": "Hydra"}.get(winner.provider, f"plugin {winner.provider}")
    group, _, option = name.rpartition("/")
    what = f"{owner}'s option {group}={option}" if group else f"{owner}'s app config {option!r}"
    fix = (f"give the file a name of its own ({group}/<name>.yaml, chosen with {group}=<name>)" if group else
           "give the file a name of its own and choose it with --config-name <name>")
    package = winner.load_config(name).header.get("package") if group else None
    if group and package in (None, "_group_", "_global_"):  # where the option's keys land: its group's node, or the top
        key = "<key>" if package == "_global_" else f"{group.replace('/', '.')}.<key>"
        fix += f" or set the option's keys on the command line ({key}=<value>)"
    others = [f"{n}.yaml" for n, _ in shadowed[1:]]  # named as in the folder
    also = f" (and so would {', '.join(others)})" if others else ""
    raise CicfwError(f"--config-dir: {folder / name}.yaml would be ignored{also}: Hydra reads {what} "
                     f"({winner.full_path()}/{name}.yaml) first, as it reads the --config-dir folder after the app's "
                     f"own configs and the plugins'; {fix}", key="--config-dir", value=str(folder / f"{name}.yaml"))


@contextmanager
def config_dir_checked() -> Iterator[None]:
    """Inside, an app that Hydra starts with a ``--config-dir`` holding a file a built-in hides
    (``refuse_shadowed_config_dir``) ends with one ``cicfw: error:`` line, status 2, before it composes
    anything. Hydra hands the finished search path, the command line's folder included, to
    ``Hydra.create_main_hydra2``: that is where this looks."""
    create = Hydra.__dict__["create_main_hydra2"]

    def checked(task_name: str, config_search_path: ConfigSearchPath) -> Hydra:
        try:
            refuse_shadowed_config_dir(config_search_path)
        except CicfwError as err:
            refuse_before_any_job(str(err))
        return create.__get__(None, Hydra)(task_name, config_search_path)

    Hydra.create_main_hydra2 = checked  # type: ignore[method-assign]
    try:
        yield
    finally:
        Hydra.create_main_hydra2 = create  # type: ignore[method-assign]


def run_app(main: Callable[[], Any], config_name: str) -> None:
    """Run a ``@hydra.main`` app: what Hydra refuses is one line (``one_line_config_errors``); a failure
    that names an option needing an optional extra adds a hint. A plugin whose Hydra module fails to
    import is skipped with one warning first (it would stop the app). ``--help`` lists the app's config
    groups (``register_help``). A ``--config-dir`` file named like a config a built-in has is refused
    (``config_dir_checked``)."""
    guard_hydra_plugins()
    register_help()
    try:
        with one_line_config_errors(), config_dir_checked():
            main()
    except SystemExit as exit_:
        if exit_.code not in (None, 0, 130, 143):  # interrupted (Ctrl-C, SIGTERM): no config to hint at
            for hint in missing_extras(sys.argv[1:]):
                print(hint, file=sys.stderr)
        raise


class SchemaCheck(Callback):
    """Hydra callback, listed first in an app config's callbacks: ``check`` (the dotted path of a function
    taking the composed config) before the run or sweep folder is created, for what composing lets through
    (keys added with ``+``); its ``SchemaError`` is one ``cicfw: error:`` line, exit status 2."""

    def __init__(self, check: str) -> None:
        self.check = check

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        self._check(config)

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        self._check(config)

    def _check(self, config: Any) -> None:
        try:
            get_method(self.check)(config)
        except SchemaError as err:
            print(f"cicfw: error: {err}", file=sys.stderr)
            sys.exit(2)


#: the sweeper whose jobs are known before the first runs (the default; Optuna's are drawn as trials end)
BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


def sweep_jobs(config: Any) -> list[list[str]] | None:
    """The overrides of every job a multirun's ``config`` will launch, as Hydra's basic sweeper expands them
    (``head.W=5,-1,10``: three jobs); None for another sweeper, which chooses its jobs as it goes."""
    if str(config.hydra.sweeper.get("_target_")) != BASIC_SWEEPER:
        return None
    params = config.hydra.sweeper.get("params") or {}
    arguments = [f"{k}={v}" for k, v in params.items()]
    arguments += list(OmegaConf.to_container(config.hydra.overrides.task, resolve=False))
    parsed = OverridesParser.create().parse_overrides(arguments)
    return [list(job) for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


class SweepJobsCheck(Callback):
    """Hydra callback: in a multirun, every job's config composed and given to ``check`` (the dotted path
    of a function taking a composed config, e.g. ``cicfw.train.app.check_config``) before the first job
    runs, so a bad value in the last job (``head.W=5,-1,10``) does not wait for the others to train. A
    refusal is one ``cicfw: error:`` line naming the job and its overrides, exit status 2, before the sweep
    folder is made. With a sweeper that picks its jobs as it goes (Optuna) nothing is checked up front.
    ``data_check`` (optional, the same kind of path): run on every job once every job's config passed, so
    that a config error is named before a missing input (train's empty data folder)."""

    def __init__(self, check: str, data_check: str | None = None) -> None:
        self.check, self.data_check = check, data_check

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        jobs = sweep_jobs(config) if not is_worker_process() else None
        if not jobs or len(jobs) < 2:
            return  # one job: it checks itself before it trains
        loader = GlobalHydra.instance().config_loader()
        checks = [get_method(self.check)] + ([get_method(self.data_check)] if self.data_check else [])
        configs = []
        for check in checks:
            for num, job in enumerate(jobs):
                if len(configs) == num:
                    configs.append(loader.load_sweep_config(master_config=config, sweep_overrides=job))
                try:
                    check(configs[num])
                except CicfwError as err:
                    refuse_before_any_job(f"job {num} ({' '.join(job)}): {' '.join(str(err).split())}; no job ran")


class JobFailed(CompactHydraException):
    """A multirun job's failure as one line: Hydra prints a compact exception without a traceback."""


class UserJobFailed(JobFailed):
    """A multirun job's user error (a ``CicfwError``) as one line: ``one_line_config_errors`` prints it alone,
    without Hydra's "Error executing job" line and HYDRA_FULL_ERROR advice around it (exit status 1)."""


class _QuietJobReturn(JobReturn):
    """A failed job's return whose error the sweeper raises without Hydra's "Error executing job with
    overrides" line: the cicfw line (``UserJobFailed``) names the job and its overrides already."""

    @property
    def return_value(self) -> Any:
        if self.status == JobStatus.COMPLETED:
            return self._return_value
        raise self._return_value

    @return_value.setter
    def return_value(self, value: Any) -> None:
        self._return_value = value


def failure_line(err: BaseException) -> str:
    """A job's exception in one line: a user error's message, else its type and message."""
    text = err.args[0] if isinstance(err, (KeyError, FileNotFoundError)) and err.args else err
    line = " ".join(str(text).split())
    return line if isinstance(err, USER_ERRORS) else f"{type(err).__name__}: {line}"


class OneLineJobFailure(Callback):
    """Hydra callback: a failed multirun job's exception, which the sweeper raises once the batch of jobs
    is done (Hydra would print its traceback), becomes one ``cicfw: error:`` line naming the job, its
    overrides and its log. The job stays failed (the sweep summary, listed after this callback, records
    its own error; Optuna marks the trial failed); its log keeps the whole story. A user error is that line
    alone (``UserJobFailed``); a bug keeps Hydra's report around it. A single run's failure is left as it
    is (no job number; the app's own handler words it)."""

    def on_job_end(self, config: Any, job_return: Any, **kwargs: Any) -> None:
        err = getattr(job_return, "_return_value", None)
        if job_return.status != JobStatus.FAILED or not isinstance(err, Exception) or isinstance(err, JobFailed):
            return
        if OmegaConf.select(config, "hydra.job.num", default=None) is None:  # a single run, not a multirun's job
            return
        hc = config.hydra
        log_file = Path(str(hc.runtime.output_dir)) / f"{hc.job.name}.log"
        summary = Path(str(hc.sweep.dir)) / "summary.csv"
        every = f"; every job's status: {summary}" if summary.is_file() else ""
        overrides = " ".join(job_return.overrides or [])
        user = isinstance(err, USER_ERRORS) and os.environ.get("HYDRA_FULL_ERROR") != "1"
        job_return._return_value = (UserJobFailed if user else JobFailed)(
            f"cicfw: error: job {hc.job.num} ({overrides}) failed: {failure_line(err)} (its log: {log_file}){every}")
        if user:  # a bug keeps Hydra's report around its line
            job_return.__class__ = _QuietJobReturn
