"""The reproduction app (``python -m cicfw.reproduce`` runs it): the paper's Table 4 as rows x seeds x one
budget, with intervals and verdicts.

    python -m cicfw.reproduce rows=[cil,gtu] seeds=3 budget=laptop
    python -m cicfw.reproduce budget=smoke rows=[cil,gtu] seeds=2 results_dir=/tmp/smoke
    python -m cicfw.reproduce launcher=joblib hydra.launcher.n_jobs=4      # cells in parallel processes

    python -m cicfw.reproduce budget=converged continue_from=docs/results/converged \
        publish_dir=docs/results/converged                                   # grow a published table

Before anything is collected or trained, the app checks the plan: the config against its schema
(cicfw/reproduction/schema.py: an unknown key or a wrong type anywhere is refused), the rows (each custom row's
experiment, head, mixer and overrides compose), the seeds, the budget's curve, the claims, ``publish_dir`` and
``continue_from``; it takes the results folder's lock and ``publish_dir``'s, for the whole run (one run per folder:
``reproduce.lock`` names the holder; a stale lock, whose process on this host is gone, is taken over with a warning)
and checks a folder (or a published one to continue) made with another budget or suite. Then it collects the
budget's dataset once (every row trains on it), makes every cell's train/validation split of it (a seed whose split
cannot train is refused before any cell trains) and pins the results folder to this budget, suite and dataset
(``reproduce.json``): a folder made with another dataset is refused, and so is a finished cell trained on another
dataset, for other epochs, driven under another weather family, with another model configuration (its ``recipe``)
or with other training overrides of its row (its ``overrides``):
``cells.check_cell_pin``, the check ``cicfw report`` makes against the folder's pin. Each
(row, seed) cell is one job of Hydra's launcher (``cell.row``/``cell.seed`` swept), so
``launcher=joblib|slurm`` spreads cells with no other change. A cell trains, drives the suite and writes
``cell.json`` last: a finished cell is skipped, a killed one resumes from its last epoch checkpoint (marked
``resumed`` in cell.json and in the report: resuming does not restore the data pipeline's random state) and
its evaluation from the episodes it kept, a failed one
records its one-line error and the others go on (the app then exits 1, naming the cells that did not finish).
The report (``cicfw.reproduction.report``) is written at the end, and by ``cicfw report <results_dir>`` at any
time.
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import logging
import os
import platform
import subprocess
import sys
import time
import traceback
from importlib.resources import files
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import hydra
import torch
from hydra import compose, initialize_config_module
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException, MissingConfigException, OverrideParseException
from hydra.utils import to_absolute_path
from omegaconf import DictConfig, OmegaConf

import cicfw
from cicfw.benchmark.app import compose_config, evaluate
from cicfw.benchmark.finished_run import cell_key, load_run
from cicfw.benchmark.suite import build_suite, make_backend, named_weather_family, with_weather_family
from cicfw.core.config_checks import config_error
from cicfw.core.errors import USER_ERRORS, CicfwError, ConfigError, Interrupted, debugging, on_interrupt
from cicfw.core.files import atomic_write, remove_stale_temps
from cicfw.core.json_files import read_json
from cicfw.core.run_folder import HYDRA_RECORDS, check_name_lengths, claim_folder
from cicfw.core.override_hints import register_help
from cicfw.data.frames import chosen_cameras, load_frames, split_by_episode
from cicfw.model.checkpoint import samples_seen
from cicfw.reproduction.catalogue import budget_settings_in_row, row_overrides, speed_node_spelling, trained_overrides
from cicfw.reproduction.cells import (COLUMNS, FAMILY_KEY, OVERRIDES_KEY, RECIPE, RECIPE_DATA_SKIP, CellPin,
                                     check_cell_pin, finished_cells, flat, override_values)
from cicfw.reproduction.claims import load_claims
from cicfw.reproduction.lock import RunLocks
from cicfw.reproduction.published import (MANIFEST, check_no_other_cells, check_publish_outside, continue_published,
                                         publish_target_manifest, published_manifest)
from cicfw.reproduction.report import REPORT_OVERRIDES, report_overrides, write_configured
from cicfw.reproduction.schema import check, seed_list
from cicfw.sim.render.weather import LEGACY_FAMILY
from cicfw.train.app import build_model, ensure_data, make_datamodule, train, trainer_kwargs
from cicfw.train.schema import check_top_level, checked_speed, without_plus_on_trainer

log = logging.getLogger("cicfw.reproduce")

CELL_FILE = "cell.json"


class ReproduceError(CicfwError):
    """A bad row, seed count, budget or results folder: one clear line."""


# ------------------------------------------------------------------------------------------------
# the plan: checked before anything runs


def known_budgets() -> list[str]:
    return sorted(p.name[:-5] for p in files("cicfw.conf").joinpath("budget").iterdir() if p.name.endswith(".yaml"))


def _hydra_line(err: BaseException) -> str:
    """A Hydra composition error as one line: an unknown option of a config group as ``unknown <group>
    '<option>'; known <group>s: ...`` (Hydra's own list of the group's options)."""
    group, _, option = str(getattr(err, "missing_cfg_file", None) or "").rpartition("/")
    if group and getattr(err, "options", None) is not None:
        return f"unknown {group} {option!r}; known {group}s: {', '.join(err.options)}"
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    return " ".join(ln for ln in lines[:2] if not ln.startswith("See https://")) or type(err).__name__


#: Hydra's options that point an app at another config: reproduce composes the shipped conf/ only
CONFIG_OPTIONS = ("--config-dir", "-cd", "--config-path", "-cp", "--config-name", "-cn")


def refuse_options(args: Sequence[str]) -> None:
    """An option (``-x``, ``--x``) among the overrides is one line: Hydra's config options (``CONFIG_OPTIONS``)
    say that reproduce composes the shipped configs only and how a row is added instead; another names the
    options reproduce takes. Hydra's grammar would call either an override to quote."""
    for a in args:
        if not a.startswith("-"):
            continue
        name = a.split("=", 1)[0]
        if name in CONFIG_OPTIONS:
            raise ReproduceError(f"python -m cicfw.reproduce composes the shipped configs (cicfw/conf) only and takes "
                                 f"no {name}: add a row on the command line instead, e.g. '+catalogue.mine="
                                 f"{{experiment: paper_gtu, overrides: [\"head=hybrid\"], label: GTU+hybrid}}' "
                                 f"rows=[cil,mine] (conf/reproduce.yaml, catalogue)", key=name, value=a)
        raise ReproduceError(f"python -m cicfw.reproduce takes no option {name!r}: it takes overrides (key=value), "
                             f"-m, and --help, --cfg job or --info to show its config", key=name, value=a)


#: Hydra's folder keys: reproduce writes its cells (``cells/<row>/seed<k>``), manifest and report under
#: ``results_dir`` alone, so one of these would scatter cells where no report reads them, or be ignored
FOLDER_KEYS = ("hydra.run.dir", "hydra.sweep.dir", "hydra.sweep.subdir")


def refuse_folder_keys(overrides: Sequence[str]) -> None:
    """An override of a Hydra folder key (``FOLDER_KEYS``, with or without ``+``/``++``/``~``) is one line
    naming it and saying that ``results_dir`` is the key that places a reproduction."""
    for o in overrides:
        key, _, value = o.lstrip("+~").partition("=")
        key = key.strip()
        if key in FOLDER_KEYS:
            folder = value if value and key != "hydra.sweep.subdir" else "<folder>"
            raise ReproduceError(f"{key}={value}: python -m cicfw.reproduce writes its cells, manifest and report "
                                 f"under results_dir only (cells/<row>/seed<k>), so {key} has no say; give "
                                 f"results_dir={folder} instead", key=key, value=value)


def _parse(overrides: Sequence[str]) -> None:
    """Each override parsed by Hydra's grammar; an unparsable one is one line naming it."""
    parser = OverridesParser.create()
    for o in overrides:
        try:
            parser.parse_overrides([o])
        except OverrideParseException as err:
            raise ReproduceError(
                f"cannot parse the override {o!r}: {str(err).splitlines()[0]}; quote a value that holds '=', "
                f"spaces or brackets, e.g. '+catalogue.mine={{experiment: paper_gtu, overrides: [\"head=hybrid\"], "
                f"label: GTU+hybrid}}'") from None


def compose_plan(overrides: Sequence[str]) -> DictConfig:
    """conf/reproduce.yaml with the user's overrides (``hydra.*`` and ``-m`` left to the launch, but Hydra's
    folder keys, refused), checked by its schema (``cicfw.reproduction.schema``): an unparsable override, an
    unknown key (``+foo=1`` too) or a wrong type is one error naming it."""
    refuse_folder_keys(overrides)
    plain = [o for o in overrides if not o.lstrip("+~").startswith("hydra.") and o not in ("-m", "--multirun")]
    refuse_options(plain)
    _parse(plain)
    try:
        with initialize_config_module("cicfw.conf", version_base="1.3"):
            cfg = compose("reproduce", overrides=plain)
    except HydraException as err:
        raise config_error(err) or ReproduceError(_hydra_line(err)) from None
    check(cfg)
    return cfg


def check_plan(cfg: DictConfig) -> tuple[list[str], list[int]]:
    """The rows and seeds to run, or one error naming what is wrong and what is accepted: the values the
    schema cannot say (a row not in the catalogue, an unknown claim column)."""
    catalogue = cfg.catalogue
    rows = [str(r) for r in cfg.rows]
    if not rows:
        raise ReproduceError(f"rows is empty; known rows: {', '.join(catalogue)}")
    for r in rows:
        if r not in catalogue:
            raise ReproduceError(f"unknown row {r!r}; known rows: {', '.join(catalogue)}")
    if len(set(rows)) != len(rows):
        raise ReproduceError(f"rows lists a row twice: {rows}")
    labels: dict[str, str] = {}  # the report names rows by label: two rows of one label would read as one
    for r, entry in catalogue.items():
        label = str(entry.get("label", r))
        if "\n" in label or "\r" in label:  # a table row is one line
            raise ConfigError(f"catalogue.{r}.label", label, "a label on one line: the report's tables name "
                              "each row by its label")
        if label in labels:
            raise ConfigError(f"catalogue.{r}.label", label, f"a label no other row has (catalogue."
                              f"{labels[label]} has it): the report names each row by its label")
        labels[label] = str(r)
    for r in rows:
        clash = budget_settings_in_row(cfg, r)
        if clash:
            ours, theirs = clash[0]
            raise ReproduceError(f"catalogue.{r}.overrides sets {ours}, which the cell sets after it ({theirs}, "
                                 f"budget={cfg.budget.name}), so the row's value has no say, equal or not: every row of "
                                 f"a budget trains with the budget's settings and seeds; give the row other keys, or a "
                                 f"budget of its own", key=f"catalogue.{r}.overrides", value=ours)
    seeds = seed_list(cfg.seeds)
    load_claims(OmegaConf.to_container(cfg.claims, resolve=True))  # a bad claim: one line, now
    return rows, seeds


#: what ``relation_candidates`` accepts
FINE_TUNING_ROWS = "catalogue rows that train fine tuning's mixer (mixer=re), such as re_all, re_pairs, re_none"


def check_rows(cfg: DictConfig, rows: Sequence[str]) -> list[str]:
    """Every row's training config composes and names a registered encoder, mixer and head: a custom row
    with an unknown experiment, head or mixer is refused before anything is collected or trained. Returns
    the rows' data folders (``data.path``), which no output folder may be. A row among fine tuning's
    ``relation_candidates`` must train the ``re`` mixer: the report names the one chosen as the fine-tuning row
    (a candidate that is not a row trains no cell here and is not composed: each compose costs a third of a second;
    its cells an earlier run left, here or in ``continue_from``, are chosen among all the same: their mixer must be
    ``re`` too)."""
    data: list[str] = []
    candidates = [str(c) for c in cfg.get("relation_candidates") or []]
    for folder in (cfg.results_dir, cfg.get("continue_from")):
        for key, cell in finished_cells(Path(folder)).items() if folder else ():
            row = key.split("/seed")[0]
            if row in candidates and row not in rows and cell.get("mixer") not in (None, "re"):
                raise ConfigError("relation_candidates", row, f"{FINE_TUNING_ROWS} ({row}'s cells in {folder} trained "
                                  f"mixer={cell.get('mixer')})")
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        for r in rows:
            entry = cfg.catalogue[r]
            ov = [str(o) for o in entry.get("overrides") or []]
            what = f"row {r!r} (experiment {entry.experiment}" + (f", overrides {ov})" if ov else ")")
            try:
                tcfg = compose_train(cfg, r, 0)
            except MissingConfigException as err:
                line = _hydra_line(err)
                where = f"row {r!r}" if line.startswith("unknown experiment") else what  # its overrides: no matter
                raise ReproduceError(f"{where}: {line}") from None
            except HydraException as err:
                schema = config_error(err)  # a wrong type or unknown key the train schema refused
                raise ReproduceError(f"{what}: {schema if schema is not None else _hydra_line(err)}") from None
            except ValueError as err:  # e.g. trainer.max_epochs=abc, read as a whole number here
                raise ReproduceError(f"{what}: {_error_line(err)}") from None
            if r in candidates and tcfg.mixer.get("name") != "re":
                raise ConfigError("relation_candidates", r, FINE_TUNING_ROWS)
            try:
                check_training(tcfg)
            except (ValueError, TypeError) as err:  # an unknown encoder, mixer or head too
                raise ReproduceError(f"{what}: {_error_line(err)}") from None
            epochs = int(tcfg.trainer.max_epochs)  # a curve point past the training is never driven
            beyond = [int(e) for e in cfg.budget.get("curve_epochs") or [] if int(e) > epochs]
            if beyond:
                raise ConfigError("budget.curve_epochs", beyond[0], f"epochs 1 to {epochs}: {what} trains "
                                  f"trainer.max_epochs={epochs}, so no checkpoint of a later epoch exists to drive")
            data.append(str(Path(str(tcfg.data.path)).expanduser()))
    return data


def check_training(tcfg: DictConfig) -> None:
    """What ``cicfw.train.app.train`` checks before it reads any data (top-level keys, the model's names, keys
    and values, the data and trainer arguments), so a row's bad value (``model.lr=abc``) is refused before
    the dataset is collected rather than failing every cell of the row."""
    check_top_level(tcfg)
    build_model(tcfg)
    make_datamodule(tcfg)
    trainer_kwargs(tcfg)
    checked_speed(tcfg)


def check_outputs(cfg: DictConfig, data: Sequence[str] = ()) -> None:
    """results_dir and publish_dir writable folders (or creatable) that are a reproduction's own
    (``claim_folder``: not the rows' ``data`` folders, another app's run or files of none), continue_from a
    published folder: checked before any cell, so nothing fails after the work is done."""
    check_not_results_dir(cfg)
    claim_folder(Path(cfg.results_dir), "reproduce", "results_dir", data=data)
    check_folder(Path(cfg.results_dir))
    if cfg.get("publish_dir"):
        pub = Path(cfg.publish_dir)
        claim_folder(pub, "reproduce", "publish_dir", data=data)
        check_folder(pub, "publish_dir")
        check_publish_dir(cfg)
    if cfg.get("continue_from"):
        published_manifest(Path(cfg.continue_from))
    if cfg.get("continue_machine") is not None:
        check_continue_machine(cfg)


def check_folder_names(cfg: DictConfig) -> None:
    """results_dir, publish_dir and continue_from with no name longer than their filesystem takes: one line
    naming the key before any of them is looked up (a traceback, ``File name too long``, otherwise)."""
    for key in ("results_dir", "publish_dir", "continue_from"):
        if cfg.get(key):
            check_name_lengths(Path(str(cfg[key])).expanduser(), key)


def check_not_results_dir(cfg: DictConfig) -> None:
    """``publish_dir`` or ``continue_from`` at the results folder itself (links and ``..`` resolved) would copy
    the folder onto itself: harmless but meaningless, so almost surely a mistyped path; refused in one line.
    A ``publish_dir`` inside it (a cell's folder, say) would put a published copy among the run's own files,
    where a later report reads them as cells: refused too."""
    results = Path(cfg.results_dir).expanduser().resolve()
    if cfg.get("publish_dir"):
        check_publish_outside(cfg.results_dir, cfg.publish_dir, "publish_dir")
    why = {"publish_dir": "the report is written there already; give publish_dir=<another folder> "
                          "(e.g. docs/results/<budget>) or leave it out",
           "continue_from": "its finished cells are kept and skipped by a rerun already; give continue_from="
                            "<a published folder> (e.g. docs/results/<budget>) or leave it out"}
    for key, fix in why.items():
        value = cfg.get(key)
        if value and Path(str(value)).expanduser().resolve() == results:
            raise ReproduceError(f"{key}={str(value)!r} is the results folder itself (results_dir="
                                 f"{str(cfg.results_dir)!r}, {results}): {fix}", key=key, value=str(value))


def check_publish_dir(cfg: DictConfig, dataset: str | None = None) -> None:
    """``publish_dir`` is this reproduction's to write: missing, empty of what ``publish`` writes, or an
    earlier publication of the same budget, training and suite (and dataset,
    once known) whose every finished cell this run holds or continues (``continue_from``). Anything else,
    another reproduction's results, or files of none, is refused in one line before anything is written."""
    pub, results_dir = Path(cfg.publish_dir), Path(cfg.results_dir)
    # (the results folder itself was refused by check_not_results_dir)
    manifest = publish_target_manifest(pub, "publish_dir")
    if manifest is None:
        return
    where, fix = f"publish_dir={str(pub)!r}", "give another publish_dir (or grow that one with continue_from=<it>)"
    theirs = manifest.get("pinned") or {}
    ours = fingerprint(cfg, None if dataset is None else {"config_hash": dataset})
    refuse_other_pin(where, fix, theirs, ours, cfg, ("budget", "train", "suite") + (("dataset",) if dataset else ()))
    ours_cells = set(finished_cells(results_dir)) if results_dir.is_dir() else set()
    if cfg.get("continue_from"):
        ours_cells |= set(finished_cells(Path(cfg.continue_from)))
    check_no_other_cells(pub, results_dir, ours_cells, "publish_dir",
                         f"add to that folder with continue_from={pub} publish_dir={pub}")


def check_continue_machine(cfg: DictConfig) -> None:
    """``continue_machine`` filters the cells of ``continue_from``: without it, or matching none of its
    finished cells, it is a typo, refused in one line that lists the machines there."""
    text = str(cfg.continue_machine)
    if not cfg.get("continue_from"):
        raise ReproduceError(f"continue_machine={text!r} selects cells of a published folder; give "
                             f"continue_from=<folder> too, or drop continue_machine")
    machines = sorted({str(d.get("machine")) for d in finished_cells(Path(cfg.continue_from)).values()})
    if not text or not any(text in m for m in machines):
        raise ReproduceError(f"continue_machine={text!r} is in no finished cell's machine of "
                             f"{str(cfg.continue_from)!r}; its machines: {'; '.join(machines) or 'none'}")


#: while a plan is checked (``checking_the_plan``): each cell's training config by its overrides
_PLANNED: dict[tuple[str, ...], DictConfig] | None = None


@contextlib.contextmanager
def checking_the_plan() -> Iterator[None]:
    """Compose each cell's training config once while the plan is checked: check_rows, check_cells, prepare
    and check_splits read a cell's config up to four times before anything trains (a Hydra compose, ~0.1 s,
    against ~3 ms for a copy). Outside it, as when a cell trains, every call composes afresh."""
    global _PLANNED
    _PLANNED = {}
    try:
        yield
    finally:
        _PLANNED = None


def compose_train(cfg: DictConfig, row: str, seed: int) -> DictConfig:
    """The cell's training config; it keeps a checkpoint after every epoch (``epochNNN.ckpt``): the final
    weights, the learning curve's points, and where a killed cell resumes."""
    overrides = without_plus_on_trainer(row_overrides(cfg, row, seed))
    if _PLANNED is None:
        tcfg = compose("train", overrides=overrides)
    else:
        if tuple(overrides) not in _PLANNED:
            _PLANNED[tuple(overrides)] = compose("train", overrides=overrides)
        tcfg = copy.deepcopy(_PLANNED[tuple(overrides)])
    tcfg.keep_epoch_checkpoints = list(range(1, int(tcfg.trainer.max_epochs) + 1))
    return tcfg


def suite_overrides(cfg: DictConfig) -> list[str]:
    """The budget's evaluate overrides with the embedded simulator's weather family named (``weather_family``,
    else the simulator's default): what every cell drives, and what a folder is pinned to."""
    family = cfg.get("weather_family")
    return with_weather_family(OmegaConf.to_container(cfg.budget.suite, resolve=True),
                               None if family is None else str(family))


def with_legacy_family(pinned: Mapping[str, Any]) -> Mapping[str, Any]:
    """A folder's pinned fingerprint with its weather family named: a folder pinned before the families
    names none and was driven under the legacy (harsh) presets."""
    if pinned.get("suite") is None:
        return pinned
    return {**pinned, "suite": with_weather_family(pinned["suite"], default=LEGACY_FAMILY)}


def suite_difference(theirs: Sequence[str], ours: Sequence[str]) -> str:
    """How two pinned suites differ, for a refusal: their weather families when those differ, else both lists."""
    a, b = named_weather_family(theirs), named_weather_family(ours)
    if a != b:
        return f" (weather_family={a} there, {b} here: name it with weather_family={a})"
    return f" (suite {list(theirs)} there, {list(ours)} here)"


def fingerprint(cfg: DictConfig, dataset: Mapping[str, Any] | None) -> dict[str, Any]:
    """What a results folder is pinned to: the budget's training and suite settings and the dataset (None:
    not known yet). The training overrides are kept as written (``${oc.env:CICFW_CACHE,...}`` unresolved),
    so that a folder made on one machine is the same plan on another; ``train_resolved`` is compared too,
    for folders pinned before that."""
    budget = OmegaConf.to_container(cfg.budget, resolve=False)
    pinned = {"budget": cfg.budget.name, "train": [str(o) for o in budget["train"]],
              "suite": suite_overrides(cfg), "dataset": None if dataset is None else dataset.get("config_hash")}
    pinned["hash"] = hashlib.sha256(json.dumps(pinned, sort_keys=True).encode()).hexdigest()[:16]
    return pinned


def pinned_differences(theirs: Mapping[str, Any], ours: Mapping[str, Any], cfg: DictConfig,
                       keys: Sequence[str] = ("budget", "train", "suite", "dataset")) -> list[str]:
    """Which of ``keys`` a folder's pinned fingerprint (``theirs``) has otherwise than this plan's."""
    resolved = speed_node_spelling(OmegaConf.to_container(cfg.budget.train, resolve=True))
    theirs = with_legacy_family(theirs)
    diff = []
    for k in keys:
        pinned = theirs.get("train")
        if k == "train" and isinstance(pinned, list) and speed_node_spelling(pinned) in (
                speed_node_spelling(ours["train"]), resolved):
            continue
        if theirs.get(k) != ours.get(k):
            diff.append(k)
    return diff


def refuse_other_pin(where: str, fix: str, theirs: Mapping[str, Any], ours: Mapping[str, Any], cfg: DictConfig,
                     keys: Sequence[str]) -> None:
    """One line when a folder (``where``) is pinned to another budget, training, suite or dataset."""
    diff = pinned_differences(theirs, ours, cfg, keys)
    if not diff:
        return
    if "budget" in diff:
        rest = [k for k in diff if k != "budget"]
        raise ReproduceError(f"{where} was made with budget={theirs.get('budget')}, this run asks for "
                             f"budget={ours['budget']}" + (f" (another {'/'.join(rest)})" if rest else "") + f"; {fix}")
    data = (f" (dataset {theirs.get('dataset')} there, {ours.get('dataset')} here)" if "dataset" in diff else "")
    if "suite" in diff:
        data += suite_difference(with_legacy_family(theirs)["suite"], ours["suite"])
    raise ReproduceError(f"{where} was made with budget={theirs.get('budget')} and another {'/'.join(diff)}{data}; "
                         f"{fix}")


def recipe(tcfg: DictConfig) -> dict[str, Any]:
    """The cell's ``recipe``: what decides its model besides the seed (a continued cell is checked against it)."""
    out = {k: OmegaConf.to_container(tcfg[k], resolve=True) for k in RECIPE if k in tcfg}
    for k in RECIPE_DATA_SKIP:
        (out.get("data") or {}).pop(k, None)
    return json.loads(json.dumps(out))


def check_cells(folder: Path, fix: str, cfg: DictConfig, dataset: str, pins: dict[str, CellPin]) -> None:
    """Every finished cell under ``folder`` was made as this run makes its row: its dataset, weather family,
    epochs, recipe and its row's training overrides, ``trainer.*`` too (``check_cell_pin``, the check ``cicfw
    report`` makes against a folder's pin), else one line naming the cell's file, the key and both values.
    ``pins``: row -> its pin, composed once per row."""
    family = named_weather_family(suite_overrides(cfg))
    for name, d in finished_cells(folder).items():
        row = str(d.get("row"))
        if row not in pins:
            if row in cfg.catalogue:
                with initialize_config_module("cicfw.conf", version_base="1.3"):
                    tcfg = compose_train(cfg, row, 0)
                pins[row] = CellPin(dataset=dataset, weather_family=family, family_known=True,
                                    epochs=int(tcfg.trainer.max_epochs), recipe=flat(recipe(tcfg)),
                                    overrides=override_values(trained_overrides(cfg, row)))
            else:  # a row this run does not know: what the whole run pins
                pins[row] = CellPin(dataset=dataset, weather_family=family, family_known=True)
        check_cell_pin(folder / "cells" / name / CELL_FILE, d, pins[row], f"this run makes row {row} with", fix)


def prepare(cfg: DictConfig, rows: list[str]) -> dict[str, Any]:
    """Check the results folder (and the published folder to continue) against this plan's budget and
    suite, collect the budget's dataset once, check its hash and the finished cells, copy a published
    folder's finished cells in, then pin the folder; returns the manifest. Everything that can be checked
    before collecting is."""
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        tcfg = compose_train(cfg, rows[0], 0)
        evcfg = compose_eval(cfg, [])
        n_episodes = count_episodes(evcfg)
    results_dir = Path(cfg.results_dir)
    path = results_dir / MANIFEST
    old = read_json(path, default=None, kind=dict)
    src = Path(cfg.continue_from) if cfg.get("continue_from") else None
    only = None if cfg.get("continue_machine") is None else str(cfg.continue_machine)
    published = published_manifest(src) if src is not None else None
    folders = []  # (where, what to do instead, its pinned fingerprint)
    if old is not None:
        folders.append((f"results folder {str(results_dir)!r}",
                        "start a new folder (results_dir=<new path>) or delete this one", old.get("pinned") or {}))
    if published is not None:
        folders.append((f"continue_from={str(src)!r}", f"continue it with budget={(published.get('pinned') or {}).get('budget')} "
                        "and its dataset, or start a new folder without continue_from", published.get("pinned") or {}))
    ours = fingerprint(cfg, None)
    for where, fix, theirs in folders:  # before collecting: another budget, training or suite
        refuse_other_pin(where, fix, theirs, ours, cfg, ("budget", "train", "suite"))
    data_path = Path(tcfg.data.path).expanduser()
    if folders and dataset_is_complete(data_path):  # collected before: its hash is known without collecting
        early = fingerprint(cfg, dataset_info(data_path))
        for where, fix, theirs in folders:
            refuse_other_pin(where, fix, theirs, early, cfg, ("dataset",))
    ensure_data(tcfg.data)  # every row of the budget trains on this one dataset
    finished = set(finished_cells(results_dir)) if results_dir.is_dir() else set()
    if src is not None:
        finished |= {k for k, d in finished_cells(src).items() if only is None or only in str(d.get("machine") or "")}
    check_splits(cfg, rows, seed_list(cfg.seeds), finished)  # a seed whose split cannot train: before any cell
    dataset = dataset_info(data_path)
    pinned = fingerprint(cfg, dataset)
    for where, fix, theirs in folders:
        refuse_other_pin(where, fix, theirs, pinned, cfg, ("budget", "train", "suite", "dataset"))
    if cfg.get("publish_dir"):  # published from another dataset: refused before the first cell too
        check_publish_dir(cfg, pinned["dataset"])
    pins: dict[str, CellPin] = {}
    for where, fix, _ in folders:
        folder = src if where.startswith("continue_from") else results_dir
        check_cells(folder, fix, cfg, pinned["dataset"], pins)
    manifest = old or {
        "budget": pinned["budget"], "pinned": pinned, "suite": OmegaConf.to_container(evcfg.suite, resolve=True),
        "episodes": n_episodes, "dataset": dataset,
        "dataset_summary": f"{dataset.get('episodes')} episodes of {dataset.get('seconds')} s in "
                           f"{'/'.join(dataset.get('towns') or [])} under {'/'.join(dataset.get('weathers') or [])}, "
                           f"{dataset.get('samples')} samples in {dataset.get('files')} files",
        "machine": machine(), "code": code(), "created": time.strftime("%Y-%m-%d %H:%M:%S")}
    changed = old is None
    if src is not None:
        got = continue_published(src, results_dir, machine=only)
        log.info("continue_from=%s: %d finished cell(s) copied, %d already here%s", src, len(got["copied"]),
                 len(got["kept"]), f", {len(got['other_machine'])} left out (machine without {only!r})"
                 if only is not None else "")
        if got["copied"]:
            entry = {"from": shown_path(src), "cells": got["copied"], "date": time.strftime("%Y-%m-%d %H:%M:%S"),
                     "machine": (published or {}).get("machine"), "created": (published or {}).get("created")}
            if only is not None:
                entry["only_machine"] = only
            manifest.setdefault("continued_from", []).append(entry)
            changed = True
    if changed:
        atomic_write(path, json.dumps(manifest, indent=1))
    return manifest


def keep_report_overrides(results_dir: Path, overrides: Sequence[str]) -> None:
    """Record in the folder's reproduce.json the overrides its report is written with (a row of one's own and its
    label, another margin or claims), so that ``cicfw report`` rewrites the report as this run writes it."""
    path = Path(results_dir) / MANIFEST
    manifest = read_json(path, default=None, kind=dict)
    wanted = report_overrides(overrides)
    if not isinstance(manifest, dict) or manifest.get(REPORT_OVERRIDES, []) == wanted:
        return
    manifest[REPORT_OVERRIDES] = wanted
    atomic_write(path, json.dumps(manifest, indent=1))


def check_splits(cfg: DictConfig, rows: Sequence[str], seeds: Sequence[int], finished: set[str] = frozenset()) -> None:
    """Each cell's train/validation split of the collected dataset, made now as its training will make it
    (``split_by_episode`` seeded by the cell's ``data.seed``, then its ``data.val_cameras``), without training
    anything: a seed whose split cannot train (its train split lacks a command, its validation split a
    camera) is refused in one ``ReproduceError`` line naming the seed(s), what is missing and what to do,
    before any cell trains, rather than failing every row's cell of that seed after the others trained.
    ``finished``: ``row/seedK`` of finished cells, which train nothing."""
    frames: dict[tuple, Any] = {}
    failed: dict[tuple[str, int], str] = {}
    todo = [(row, seed) for seed in seeds for row in rows if f"{row}/seed{seed}" not in finished]
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        for row, seed in todo:
            dm = make_datamodule(compose_train(cfg, row, seed))
            key = (dm.path, dm.max_abs_steer, dm.side_camera_correction, dm.cameras)
            if key not in frames:
                frames[key] = load_frames(*key)  # the targets only: no image is read
            try:
                _, val = split_by_episode(frames[key], dm.val_fraction, dm.seed)
                if dm.val_cameras is not None:
                    chosen_cameras(val.camera, dm.val_cameras, "val_cameras", "validation samples: they")
            except ValueError as err:
                failed[(row, seed)] = str(err).split("; ")[0]  # what is missing; the advice is the reproduction's
    if not failed:
        return
    bad = sorted({seed for _, seed in failed})
    whole = all((row, seed) in failed or f"{row}/seed{seed}" in finished for seed in bad for row in rows)
    where = {k: f"seed {k[1]}" if whole else f"{k[0]}/seed{k[1]}" for k in failed}
    said = dict.fromkeys((where[k], why) for k, why in sorted(failed.items(), key=lambda kv: kv[0][::-1]))
    reasons = "; ".join(f"{at}: {why}" if len({at for at, _ in said}) > 1 else why for at, why in said)
    what = (f"seed{'s' if len(bad) > 1 else ''} {', '.join(map(str, bad))}" if whole
            else f"cell{'s' if len(failed) > 1 else ''} {', '.join(dict.fromkeys(where.values()))}")
    ok = [s for s in seeds if s not in bad]
    fewer = f"run only the seeds that split (seeds=[{','.join(map(str, ok))}])" if ok else "run other seeds"
    groups = {int(len(set(f.group.tolist()))) for f in frames.values()}
    others = [b for b in known_budgets() if b != str(cfg.budget.get("name"))]
    raise ReproduceError(
        f"{what} cannot train on budget {cfg.budget.get('name')}'s dataset ({'/'.join(map(str, sorted(groups)))} "
        f"episodes in {next(iter(frames))[0]}): {reasons}; nothing was trained: give the budget more data (more "
        f"episodes), {fewer}, or choose another budget ({', '.join(others)})", key="seeds", value=bad)


def shown_path(folder: Path) -> str:
    """``folder`` as a published manifest records it: relative to the git work tree that holds it (what a
    clone elsewhere can follow), else its absolute path; a machine's absolute path means nothing on the next one."""
    folder = Path(folder).resolve()
    for top in (folder, *folder.parents):
        if (top / ".git").exists():
            return folder.relative_to(top).as_posix()
    return str(folder)


def dataset_is_complete(path: Path) -> bool:
    """Whether the collector's metadata says the dataset at ``path`` is complete (then collecting is a no-op)."""
    for name in ("dataset_metadata.json", "metadata.json"):
        try:
            return bool(json.loads((path / name).read_text()).get("complete"))
        except (OSError, ValueError, AttributeError):
            continue
    return False


def check_folder(folder: Path, key: str = "results_dir") -> None:
    """A folder must be writable (or creatable) before anything is collected or trained."""
    p = folder
    while not p.exists():
        p = p.parent
    if not p.is_dir() or not os.access(p, os.W_OK):
        raise ReproduceError(f"{key} {str(folder)!r} cannot be written ({str(p)!r} is not a writable "
                             f"folder); give {key}=<a writable path>")


# ------------------------------------------------------------------------------------------------
# where a folder and its cells were made: the dataset, the machine, the code


def dataset_info(path: Path) -> dict[str, Any]:
    """What a results folder pins of its dataset: a hash of its files' names and sizes, plus the collector's
    metadata (episodes, seconds, towns, weathers, samples) for the report."""
    meta = {}
    for name in ("dataset_metadata.json", "metadata.json"):
        if (path / name).is_file():
            meta = read_json(path / name)
            break
    files = sorted(path.rglob("*.h5")) + sorted(path.rglob("*.hdf5"))
    chash = hashlib.sha256("".join(f"{f.name}:{f.stat().st_size}" for f in files).encode()).hexdigest()[:16]
    counts = meta.get("counts") or {}
    cfg = meta.get("config") or {}
    return {"path": str(path), "files": len(files), "samples": counts.get("samples"), "episodes": counts.get("episodes"),
            "seconds": cfg.get("seconds"), "towns": cfg.get("towns"), "weathers": cfg.get("weathers"),
            "config_hash": chash, "collect_config_hash": meta.get("config_hash"), "complete": meta.get("complete")}


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"{os.cpu_count()} cores ({cpu}), {gpu}, Python {platform.python_version()}, torch {torch.__version__}"


def code() -> dict[str, Any]:
    """Which cicfw made a cell: its version and, in a git clone, the commit and whether files differed from it.

    Cells of one folder may come from several machines and commits (``continue_from``); this says which."""
    here = Path(cicfw.__file__).resolve().parent.parent
    out: dict[str, Any] = {"version": cicfw.__version__, "commit": None, "modified": None}
    try:
        git = ["git", "-C", str(here)]
        top = subprocess.run([*git, "rev-parse", "--show-toplevel"], capture_output=True, text=True, timeout=10)
        if top.returncode != 0 or Path(top.stdout.strip()).resolve() != here:
            return out  # not a clone of cicfw (an installed wheel, or a clone of something else around it)
        head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        diff = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                              text=True, timeout=10)
        if head.returncode == 0:
            out["commit"] = head.stdout.strip()
            out["modified"] = bool(diff.stdout.strip()) if diff.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        pass  # no git on this machine: the version alone
    return out


# ------------------------------------------------------------------------------------------------
# one cell


def compose_eval(cfg: DictConfig, extra: Sequence[str]) -> DictConfig:
    """A cell's evaluate config: the budget's suite overrides, then ``extra``, checked (``compose_config``)."""
    return compose_config([*suite_overrides(cfg), "progress_bar=false", "maps=false", *extra])


def count_episodes(evcfg: DictConfig) -> int:
    return len(build_suite(make_backend(OmegaConf.to_container(evcfg.sim, resolve=True)),
                           **OmegaConf.to_container(evcfg.suite, resolve=True)))


def run_cell(cfg: DictConfig, cell_dir: Path) -> str:
    """Train and drive one (row, seed) cell into ``cell_dir``; ``cell.json`` is written last."""
    row, seed = str(cfg.cell.row), int(cfg.cell.seed)
    done = cell_dir / CELL_FILE
    if done.is_file() and read_json(done).get("status") == "ok":
        log.info("cell %s seed %d: finished before, skipped", row, seed)
        return "skipped"
    t0 = time.time()
    try:
        pinned = json.loads((Path(cfg.results_dir) / MANIFEST).read_text()).get("pinned") or {}
    except (OSError, ValueError):
        pinned = {}
    try:
        result = _train_and_drive(cfg, row, seed, cell_dir)
        status = "ok"
    except Exception as err:  # recorded with its one-line error (and the whole text); the other cells go on

        lines = [ln.strip() for ln in str(err).strip().splitlines() if ln.strip()]
        # a worker's error is "evaluation worker k failed:" + its traceback: its last line says what failed
        line = lines[0] if len(lines) < 2 or not lines[0].endswith(":") else f"{lines[0]} {lines[-1]}"
        result = {"error": f"{type(err).__name__}: {line}",
                  "detail": "".join(traceback.format_exception(err))[-4000:]}
        status = "failed"
        log.error("cell %s seed %d failed: %s\n%s", row, seed, result["error"], result["detail"])
    atomic_write(done, json.dumps({"row": row, "seed": seed, "status": status, "finished_s": round(time.time() - t0, 1),
                                   "dataset": pinned.get("dataset"), **result,
                                   OVERRIDES_KEY: trained_overrides(cfg, row)}, indent=1))
    return status


def _train_and_drive(cfg: DictConfig, row: str, seed: int, cell_dir: Path) -> dict[str, Any]:
    tcfg = compose_train(cfg, row, seed)
    train_dir, ckpts = cell_dir / "train", cell_dir / "train" / "checkpoints"
    trained = cell_dir / "train" / "trained.json"
    epochs = int(tcfg.trainer.max_epochs)
    if not trained.is_file():
        # resumed from the last epoch's checkpoint, training has nothing left to train or validate (its
        # val_steer_mae NaN), so a cell killed after that file was written trains its last epoch again
        saved = [p for p in sorted(ckpts.glob("epoch[0-9][0-9][0-9].ckpt")) if int(p.stem[len("epoch"):]) < epochs]
        resumed = None
        if saved:  # a killed cell: resume its training from the latest epoch it saved
            log.info("cell %s seed %d: resuming training from %s (the batch order and augmentation after it will "
                     "not be the uninterrupted run's: the cell is marked resumed)", row, seed, saved[-1])
            tcfg.ckpt_path = str(saved[-1])
            resumed = {"training": {"from_epoch": int(saved[-1].stem[len("epoch"):])}}
        log.info("cell %s seed %d: training (%s)", row, seed, tcfg.experiment if "experiment" in tcfg else row)
        t = time.time()
        val = train(tcfg, train_dir, claim=False)  # the cell is this run's: results_dir is claimed and locked
        atomic_write(trained, json.dumps({"train_s": round(time.time() - t, 1), "val_steer_mae": val,
                                          "resumed": resumed}))
    info = read_json(trained)
    resumed = info.get("resumed")
    if resumed is True:  # written by cicfw before the epoch was recorded
        resumed = {"training": {"from_epoch": None}}
    final = ckpts / f"epoch{epochs:03d}.ckpt"  # the final weights (last.ckpt follows the best-val checkpoints)

    def drive(ckpt: Path, out: Path) -> tuple[dict, float]:
        t = time.time()
        evcfg = compose_eval(cfg, [f"checkpoint='{ckpt}'", f"name={row}"])
        summary = evaluate(evcfg, out, claim=False)  # inside the cell, as its training
        return summary, time.time() - t

    log.info("cell %s seed %d: driving the suite", row, seed)
    summary, eval_s = drive(final, cell_dir / "evaluate")
    episodes = _episodes(cell_dir / "evaluate")
    ck = torch.load(final, map_location="cpu", weights_only=True)
    batch = int(tcfg.data.batch_size)
    accumulate = int(OmegaConf.select(tcfg, "trainer.accumulate_grad_batches", default=None) or 1)
    curve, curve_s = [], 0.0
    if seed in [int(s) for s in cfg.budget.get("curve_seeds") or []]:
        for e in cfg.budget.get("curve_epochs") or []:
            p = ckpts / f"epoch{int(e):03d}.ckpt"
            if int(e) >= epochs or not p.is_file():
                continue
            s, dt = drive(p, cell_dir / "curve" / f"epoch{int(e):03d}")
            curve_s += dt
            curve.append(_curve_point(p, s, batch, accumulate))
        curve.append(_curve_point(final, summary, batch, accumulate))
    hp = ck.get("hyper_parameters", {})
    family = named_weather_family(suite_overrides(cfg))  # the report refuses a cell of another family's folder
    return {**({FAMILY_KEY: family} if family else {}),
            "decoder": (hp.get("head_kwargs") or {}).get("decode"), "head": hp.get("head"), "mixer": hp.get("mixer"),
            "epochs": int(ck.get("epoch", -1)) + 1, "samples_seen": samples_seen(ck, batch, accumulate),
            "val_steer_mae": info.get("val_steer_mae"), "success": summary["success"],
            "cells": {k: v["rate"] for k, v in summary["cells"].items()},
            "wall_s": {"train": info.get("train_s"), "evaluate": round(eval_s, 1), "curve": round(curve_s, 1)},
            "curve": curve, "episodes": episodes, "machine": machine(), "code": code(), "resumed": resumed or None,
            "recipe": recipe(tcfg)}


def _curve_point(ckpt: Path, summary: dict, batch: int, accumulate: int) -> dict[str, Any]:
    ck = torch.load(ckpt, map_location="cpu", weights_only=True)
    rates = {k: v["rate"] for k, v in summary["cells"].items()}
    # the report's overall: the mean of the four columns; a column the suite lacks has no rate (not 0)
    overall = round(sum(rates[c] for c in COLUMNS) / len(COLUMNS), 2) if all(c in rates for c in COLUMNS) else None
    return {"epoch": int(ck.get("epoch", -1)) + 1, "samples": samples_seen(ck, batch, accumulate),
            **rates, "overall": overall}


def _episodes(run_dir: Path) -> dict[str, dict[str, Any]]:
    return {r["key"]: {"success": bool(r["success"]), "column": cell_key(r["town_set"], r["weather_set"]),
                       "command": r["command"], "reason": r["reason"]}
            for r in load_run(run_dir).rows}


# ------------------------------------------------------------------------------------------------
# the app


@hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="reproduce")
def _cell_job(cfg: DictConfig) -> str:
    if cfg.cell.row is None:
        raise ReproduceError("cell.row is set by `python -m cicfw.reproduce` itself; give rows=[...] instead")
    hydra_cfg = HydraConfig.get()
    for key in ("results_dir", "publish_dir"):  # as given where the run started, not in the cell's folder
        if cfg.get(key) is not None:  # that hydra.job.chdir=true moves into (its manifest unread, unpinned)
            cfg[key] = to_absolute_path(str(cfg[key]))
    status = run_cell(cfg, Path(hydra_cfg.runtime.output_dir))
    if status == "skipped":  # Hydra rewrote its records with this run's command before the job began
        put_back_records(Path(hydra_cfg.runtime.output_dir))
    # cells one after another in this process: the report as it stands after each one. Cells in parallel
    # (joblib, SLURM) would write it side by side; their run's report comes at its end.
    if status != "skipped" and str(hydra_cfg.launcher.get("_target_", "")).endswith("BasicLauncher"):
        report_so_far(cfg)
    return status


#: the ``.hydra`` records of the cells finished before this run, by cell folder (None: a record the cell lacks,
#: a cell continued from a published folder): Hydra rewrites them for every job it launches, a skipped cell's too
_KEPT_RECORDS: dict[str, dict[str, bytes | None]] = {}


def keep_records(results_dir: Path, rows: Sequence[str], seeds: Sequence[int]) -> None:
    """Note the ``.hydra`` records of the plan's finished cells, which this run skips, before its jobs start."""
    _KEPT_RECORDS.clear()
    for seed in seeds:
        for row in rows:
            cell = results_dir / "cells" / row / f"seed{seed}"
            if not unfinished_cells(results_dir, [row], [seed]):
                hydra = cell / ".hydra"
                _KEPT_RECORDS[os.path.abspath(cell)] = {n: (hydra / n).read_bytes() if (hydra / n).is_file() else None
                                                        for n in HYDRA_RECORDS}


def put_back_records(cell: Path | None = None) -> None:
    """A skipped cell's ``.hydra`` records as they were before this run (every noted cell's when ``cell`` is
    None): they keep the command the cell was trained with, not the one that skipped it."""
    keys = list(_KEPT_RECORDS) if cell is None else [k for k in [os.path.abspath(cell)] if k in _KEPT_RECORDS]
    for key in keys:
        hydra = Path(key) / ".hydra"
        for name, data in _KEPT_RECORDS[key].items():
            if data is None:
                (hydra / name).unlink(missing_ok=True)
            elif not (hydra / name).is_file() or (hydra / name).read_bytes() != data:
                atomic_write(hydra / name, data)
        if all(data is None for data in _KEPT_RECORDS[key].values()):
            try:  # the folder Hydra made for a cell that had none
                hydra.rmdir()
            except OSError:
                pass


def report_so_far(cfg: DictConfig) -> None:
    """The report (and ``publish_dir``) as the finished cells stand: a run of many hours stopped at any
    point has its table up to date. A report that cannot be written is logged and the cells go on (the
    report at the end of the run says so in its exit status)."""
    try:
        write_configured(Path(cfg.results_dir), cfg, cfg.get("publish_dir"))
    except (ValueError, OSError) as err:
        log.error("the report after this cell was not written: %s", _error_line(err))


def _error_line(err: BaseException) -> str:
    if isinstance(err, OSError) and err.strerror and not isinstance(err, FileNotFoundError):
        return f"cannot write {err.filename!r}: {err.strerror}" if err.filename else str(err.strerror)
    return str(err.args[0] if isinstance(err, (KeyError, FileNotFoundError)) and err.args else err)


#: the run's own log in its results folder, appended per run: its start, each cell's progress logged in this
#: process, the final summary line and the error lines it ends with (a cell's own log is in its folder)
LOG_FILE = "reproduce.log"
LOG_FORMAT = "[%(asctime)s][%(name)s] %(message)s"


class _LogFile(logging.FileHandler):
    """The run's log file: a line it cannot write (a full disk) is lost there alone, never printed as a
    logging traceback beside the run's own one-line error."""

    def handleError(self, record: logging.LogRecord) -> None:
        pass


def open_log(results_dir: Path) -> logging.Handler:
    """A handler appending to ``<results_dir>/reproduce.log``, put on ``cicfw.reproduce``'s logger (not the
    root's, which Hydra reconfigures for every cell run in this process): a piped or ``nohup`` run keeps how it
    ended in its results folder."""
    handler = _LogFile(results_dir / LOG_FILE, mode="a", encoding="utf-8")
    handler.setFormatter(logging.Formatter(LOG_FORMAT, datefmt="%Y-%m-%d %H:%M:%S"))
    log.addHandler(handler)
    return handler


def _said(line: str, handler: logging.Handler) -> None:
    """``line`` on stderr, and in the run's log (``handler``) too."""
    print(line, file=sys.stderr)
    handler.handle(log.makeRecord(log.name, logging.ERROR, __file__, 0, "%s", (line,), None))


def main(argv: Sequence[str] | None = None) -> int:
    """Check the plan, take the results folder, collect the data, run every cell through Hydra's launcher,
    write the report (and publish it)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "--hydra-help", "--info", "-c", "--cfg", "--resolve") or a.startswith("--cfg")
           for a in args):
        register_help()  # --help lists the reproduce config's groups
        sys.argv = [sys.argv[0], *args]
        _cell_job()
        return 0
    args = [a for a in args if a not in ("-m", "--multirun")]
    logging.basicConfig(level=logging.INFO, format=LOG_FORMAT, datefmt="%H:%M:%S")
    lock = None
    try:
        with checking_the_plan():
            cfg = compose_plan(args)
            check_folder_names(cfg)
            rows, seeds = check_plan(cfg)
            check_outputs(cfg, data=check_rows(cfg, rows))
            # publish_dir too, for the whole run: another run never takes it between this check and a publish
            lock = RunLocks(Path(cfg.results_dir), cfg.get("publish_dir")).acquire()
            # held: a temporary file of a dead writer (a cell killed while saving a checkpoint) is debris that
            # no cell's own training would meet again once the cell finishes
            remove_stale_temps(cfg.results_dir)
            manifest = prepare(cfg, rows)
        keep_report_overrides(Path(cfg.results_dir), args)
    except BaseException as err:
        if lock is not None:
            lock.release()
        if not isinstance(err, USER_ERRORS):
            raise
        if debugging():
            traceback.print_exc()
        print(f"cicfw: error: {_error_line(err)}", file=sys.stderr)
        return 2
    try:  # the plan passed and the folder is this run's (its manifest): from here on, its log is there too
        handler = open_log(Path(cfg.results_dir))
    except OSError as err:
        lock.release()
        print(f"cicfw: error: {_error_line(err)}", file=sys.stderr)
        return 2
    try:
        return _run_cells(cfg, args, rows, seeds, manifest, lock, handler)
    finally:
        log.removeHandler(handler)
        handler.close()


def _run_cells(cfg: DictConfig, args: list[str], rows: Sequence[str], seeds: Sequence[int], manifest: Mapping[str, Any],
               lock: Any, handler: logging.Handler) -> int:
    """Every cell through Hydra's launcher, then the report; the exit status (1: no report, or a cell that
    did not finish). ``handler``: the run's log, where the closing lines go too."""
    log.info("%d rows x %d seeds on budget %s (%d episodes per cell) into %s", len(rows), len(seeds),
             manifest["budget"], manifest["episodes"], cfg.results_dir)
    # seeds outermost: cells run seed by seed (cil/0, gtu/0, cil/1 ...), so a run stopped early still
    # compares every row on the same seeds
    sys.argv = [sys.argv[0], "-m", *args, f"cell.seed={','.join(map(str, seeds))}", f"cell.row={','.join(rows)}"]
    t0 = time.time()
    code, stopped = 0, None
    keep_records(Path(cfg.results_dir), rows, seeds)
    try:
        _cell_job()
    except SystemExit as e:  # Hydra exits on a launcher error; the cells that finished are still reported
        if e.code not in (0, None):
            log.error("the launcher stopped (exit %s); reporting the cells that finished", e.code)
    except KeyboardInterrupt:  # a cell's own advice (train's ckpt_path=...) is not this app's
        stopped = (f"the finished cells are kept in {cfg.results_dir}; run the same command again: it skips them and "
                   f"resumes the unfinished cell from its last epoch checkpoint")
        raise Interrupted(stopped) from None
    finally:
        try:  # cells in other processes (joblib, SLURM) put back none themselves
            put_back_records()
        except OSError as err:
            _said(f"cicfw: error: {_error_line(err)}", handler)
            code = 1
        try:
            publish = f" --publish {cfg.publish_dir}" if cfg.get("publish_dir") else ""
            report = f"write their report with cicfw report {cfg.results_dir}{publish}"
            # a second Ctrl-C here keeps the first one's advice (how to resume) and adds how to write the report
            with on_interrupt(f"{stopped}; the report was not written: {report}" if stopped else
                              f"the finished cells are kept in {cfg.results_dir}; {report}, or run the same command again"):
                data = write_configured(Path(cfg.results_dir), cfg, cfg.get("publish_dir"))
            log.info("%d cells in %.0f s; report: %s", sum(len(r["seeds"]) for r in data["rows"]),
                     time.time() - t0, Path(cfg.results_dir) / "RESULTS.md")
        except ValueError as err:  # the cells are kept; the report refused them (copied seeds, another pin)
            _said(f"cicfw: error: no report: {_error_line(err)}", handler)
            code = 1
        except OSError as err:  # a publish_dir that became unwritable, a full disk: one line, the cells are kept
            _said(f"cicfw: error: {_error_line(err)}", handler)
            code = 1
        finally:
            lock.release()
    unfinished = unfinished_cells(Path(cfg.results_dir), rows, seeds)
    if unfinished:
        _said(f"cicfw: error: {len(unfinished)} of {len(rows) * len(seeds)} cells did not finish "
              f"({', '.join(unfinished[:6])}{', ...' if len(unfinished) > 6 else ''}): their cell.json or the log "
              f"above says why; a rerun of the same command retries them", handler)
        code = 1
    return code


def unfinished_cells(results_dir: Path, rows: Sequence[str], seeds: Sequence[int]) -> list[str]:
    """``row/seedK`` of this run's cells without a finished ``cell.json`` (failed, or never run because the
    launcher stopped): the app then exits 1, so that a script sees the table is incomplete."""
    out = []
    for seed in seeds:
        for row in rows:
            p = results_dir / "cells" / row / f"seed{seed}" / CELL_FILE
            try:
                ok = json.loads(p.read_text()).get("status") == "ok"
            except (OSError, ValueError, AttributeError):
                ok = False
            if not ok:
                out.append(f"{row}/seed{seed}")
    return out

