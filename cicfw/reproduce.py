"""``python -m cicfw.reproduce``: the paper's Table 4 as rows x seeds x one budget, with intervals and verdicts.

    python -m cicfw.reproduce rows=[cil,gtu] seeds=3 budget=laptop
    python -m cicfw.reproduce budget=smoke rows=[cil,gtu] seeds=2 results_dir=/tmp/smoke
    python -m cicfw.reproduce launcher=joblib hydra.launcher.n_jobs=4      # cells in parallel processes

Before any cell runs, the app checks the rows, seeds and budget, collects the budget's dataset once
(every row trains on it) and pins the results folder to this budget, suite and dataset
(``reproduce.json``): a folder made with another one is refused. Then each (row, seed) cell is one job
of Hydra's launcher (``cell.row``/``cell.seed`` swept), so ``launcher=joblib|slurm`` spreads cells with
no other change. A cell trains, drives the suite and writes ``cell.json`` last: a finished cell is
skipped, a killed one resumes from its last epoch checkpoint (and its evaluation from the episodes it
kept), a failed one records its one-line error and the others go on. The report
(``cicfw.bench.results``) is written at the end, and by ``cicfw report <results_dir>`` at any time.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import hydra
from omegaconf import DictConfig, OmegaConf

from cicfw.bench.runs import atomic_write

log = logging.getLogger("cicfw.reproduce")

MANIFEST = "reproduce.json"
CELL_FILE = "cell.json"


class ReproduceError(ValueError):
    """A bad row, seed count, budget or results folder: one clear line."""


# ------------------------------------------------------------------------------------------------
# the plan: checked before anything runs


def known_budgets() -> list[str]:
    from importlib.resources import files

    return sorted(p.name[:-5] for p in files("cicfw.conf").joinpath("budget").iterdir() if p.name.endswith(".yaml"))


def compose_plan(overrides: Sequence[str]) -> DictConfig:
    """conf/reproduce.yaml with the user's overrides (``hydra.*`` and ``-m`` left to the launch)."""
    from hydra import compose, initialize_config_module
    from hydra.errors import MissingConfigException

    plain = [o for o in overrides if not o.lstrip("+~").startswith("hydra.") and o not in ("-m", "--multirun")]
    for o in plain:
        if o.split("=", 1)[0].lstrip("+~") == "budget" and "=" in o and o.split("=", 1)[1] not in known_budgets():
            raise ReproduceError(f"unknown budget {o.split('=', 1)[1]!r}; known budgets: {', '.join(known_budgets())}")
    try:
        with initialize_config_module("cicfw.conf", version_base="1.3"):
            return compose("reproduce", overrides=plain)
    except MissingConfigException as err:
        raise ReproduceError(str(err).splitlines()[0]) from None


def check_plan(cfg: DictConfig) -> tuple[list[str], list[int]]:
    """The rows and seeds to run, or one error naming what is wrong and what is accepted."""
    catalogue = cfg.catalogue
    rows = [str(r) for r in (cfg.rows if OmegaConf.is_list(cfg.rows) else [cfg.rows])]
    if not rows:
        raise ReproduceError(f"rows is empty; known rows: {', '.join(catalogue)}")
    for r in rows:
        if r not in catalogue:
            raise ReproduceError(f"unknown row {r!r}; known rows: {', '.join(catalogue)}")
    if len(set(rows)) != len(rows):
        raise ReproduceError(f"rows lists a row twice: {rows}")
    seeds = cfg.seeds
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise ReproduceError(f"seeds must be a whole number >= 1 (seeds 0..seeds-1 per row), got {seeds!r}")
    return rows, list(range(int(seeds)))


def row_overrides(cfg: DictConfig, row: str, seed: int) -> list[str]:
    """conf/train.yaml overrides of one cell: the row's experiment, the budget, the seed."""
    entry = cfg.catalogue[row]
    return [f"experiment={entry.experiment}", *[str(o) for o in entry.get("overrides") or []],
            *[str(o) for o in cfg.budget.train], f"seed={seed}", f"progress_bar={str(bool(cfg.progress_bar)).lower()}"]


def compose_train(cfg: DictConfig, row: str, seed: int) -> DictConfig:
    """The cell's training config; it keeps a checkpoint after every epoch (``epochNNN.ckpt``): the final
    weights, the learning curve's points, and where a killed cell resumes."""
    from hydra import compose

    tcfg = compose("train", overrides=row_overrides(cfg, row, seed))
    tcfg.keep_epoch_checkpoints = list(range(1, int(tcfg.trainer.max_epochs) + 1))
    return tcfg


def fingerprint(cfg: DictConfig, dataset: dict[str, Any]) -> dict[str, Any]:
    """What a results folder is pinned to: the budget's training and suite settings and the dataset."""
    budget = OmegaConf.to_container(cfg.budget, resolve=True)
    pinned = {"budget": budget["name"], "train": budget["train"], "suite": budget["suite"],
              "dataset": dataset.get("config_hash")}
    pinned["hash"] = hashlib.sha256(json.dumps(pinned, sort_keys=True).encode()).hexdigest()[:16]
    return pinned


def prepare(cfg: DictConfig, rows: list[str]) -> dict[str, Any]:
    """Collect the budget's dataset once, then pin (or check) the results folder; returns the manifest."""
    from hydra import initialize_config_module

    from cicfw.train import ensure_data

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        tcfg = compose_train(cfg, rows[0], 0)
        evcfg = compose_eval(cfg, [])
        n_episodes = count_episodes(evcfg)
    results_dir = Path(cfg.results_dir)
    check_folder(results_dir)
    ensure_data(tcfg.data)  # every row of the budget trains on this one dataset
    dataset = dataset_info(Path(tcfg.data.path).expanduser())
    pinned = fingerprint(cfg, dataset)
    path = results_dir / MANIFEST
    if path.is_file():
        old = json.loads(path.read_text())
        if old.get("pinned", {}).get("hash") != pinned["hash"]:
            diff = [k for k in ("budget", "train", "suite", "dataset") if old.get("pinned", {}).get(k) != pinned[k]]
            raise ReproduceError(
                f"results folder {str(results_dir)!r} was made with budget={old.get('budget')} and another "
                f"{'/'.join(diff)}; start a new folder (results_dir=<new path>) or delete this one")
        return old
    manifest = {"budget": pinned["budget"], "pinned": pinned, "suite": OmegaConf.to_container(evcfg.suite, resolve=True),
                "episodes": n_episodes, "dataset": dataset,
                "dataset_summary": f"{dataset.get('episodes')} episodes of {dataset.get('seconds')} s in "
                                   f"{'/'.join(dataset.get('towns') or [])} under {'/'.join(dataset.get('weathers') or [])}, "
                                   f"{dataset.get('samples')} samples in {dataset.get('files')} files",
                "machine": machine(), "created": time.strftime("%Y-%m-%d %H:%M:%S")}
    atomic_write(path, json.dumps(manifest, indent=1))
    return manifest


def check_folder(results_dir: Path) -> None:
    """A results folder must be writable (or creatable) before anything is collected or trained."""
    p = results_dir
    while not p.exists():
        p = p.parent
    if not p.is_dir() or not os.access(p, os.W_OK):
        raise ReproduceError(f"results_dir {str(results_dir)!r} cannot be written ({str(p)!r} is not a writable "
                             f"folder); give results_dir=<a writable path>")


def dataset_info(path: Path) -> dict[str, Any]:
    """What a results folder pins of its dataset: a hash of its files' names and sizes, plus the collector's
    metadata (episodes, seconds, towns, weathers, samples) for the report."""
    meta = {}
    for name in ("dataset_metadata.json", "metadata.json"):
        if (path / name).is_file():
            meta = json.loads((path / name).read_text())
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
    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"{os.cpu_count()} cores ({cpu}), {gpu}, Python {platform.python_version()}, torch {torch.__version__}"


# ------------------------------------------------------------------------------------------------
# one cell


def compose_eval(cfg: DictConfig, extra: Sequence[str]) -> DictConfig:
    from hydra import compose

    return compose("evaluate", overrides=[*[str(o) for o in cfg.budget.suite], "progress_bar=false", "maps=false",
                                          *extra])


def count_episodes(evcfg: DictConfig) -> int:
    from cicfw.bench.suite import build_suite, make_backend

    return len(build_suite(make_backend(OmegaConf.to_container(evcfg.sim, resolve=True)),
                           **OmegaConf.to_container(evcfg.suite, resolve=True)))


def run_cell(cfg: DictConfig, cell_dir: Path) -> str:
    """Train and drive one (row, seed) cell into ``cell_dir``; ``cell.json`` is written last."""
    row, seed = str(cfg.cell.row), int(cfg.cell.seed)
    done = cell_dir / CELL_FILE
    if done.is_file() and json.loads(done.read_text()).get("status") == "ok":
        log.info("cell %s seed %d: finished before, skipped", row, seed)
        return "skipped"
    t0 = time.time()
    try:
        result = _train_and_drive(cfg, row, seed, cell_dir)
        status = "ok"
    except Exception as err:  # recorded with its one-line error (and the whole text); the other cells go on
        import traceback

        lines = [ln.strip() for ln in str(err).strip().splitlines() if ln.strip()]
        # a worker's error is "evaluation worker k failed:" + its traceback: its last line says what failed
        line = lines[0] if len(lines) < 2 or not lines[0].endswith(":") else f"{lines[0]} {lines[-1]}"
        result = {"error": f"{type(err).__name__}: {line}",
                  "detail": "".join(traceback.format_exception(err))[-4000:]}
        status = "failed"
        log.error("cell %s seed %d failed: %s\n%s", row, seed, result["error"], result["detail"])
    atomic_write(done, json.dumps({"row": row, "seed": seed, "status": status, "finished_s": round(time.time() - t0, 1),
                                   **result}, indent=1))
    return status


def _train_and_drive(cfg: DictConfig, row: str, seed: int, cell_dir: Path) -> dict[str, Any]:
    import torch

    from cicfw.evaluate import evaluate
    from cicfw.train import train

    tcfg = compose_train(cfg, row, seed)
    train_dir, ckpts = cell_dir / "train", cell_dir / "train" / "checkpoints"
    trained = cell_dir / "train" / "trained.json"
    epochs = int(tcfg.trainer.max_epochs)
    if not trained.is_file():
        saved = sorted(ckpts.glob("epoch[0-9][0-9][0-9].ckpt"))
        if saved:  # a killed cell: resume its training from the latest epoch it saved
            log.info("cell %s seed %d: resuming training from %s", row, seed, saved[-1])
            tcfg.ckpt_path = str(saved[-1])
        log.info("cell %s seed %d: training (%s)", row, seed, tcfg.experiment if "experiment" in tcfg else row)
        t = time.time()
        val = train(tcfg, train_dir)
        atomic_write(trained, json.dumps({"train_s": round(time.time() - t, 1), "val_steer_mae": val,
                                          "resumed": bool(tcfg.get("ckpt_path"))}))
    info = json.loads(trained.read_text())
    final = ckpts / f"epoch{epochs:03d}.ckpt"  # the final weights (last.ckpt follows the best-val checkpoints)

    def drive(ckpt: Path, out: Path) -> tuple[dict, float]:
        t = time.time()
        evcfg = compose_eval(cfg, [f"checkpoint='{ckpt}'", f"name={row}"])
        summary = evaluate(evcfg, out)
        return summary, time.time() - t

    log.info("cell %s seed %d: driving the suite", row, seed)
    summary, eval_s = drive(final, cell_dir / "evaluate")
    episodes = _episodes(cell_dir / "evaluate")
    ck = torch.load(final, map_location="cpu", weights_only=True)
    batch = int(tcfg.data.batch_size)
    curve, curve_s = [], 0.0
    if seed in [int(s) for s in cfg.budget.get("curve_seeds") or []]:
        for e in cfg.budget.get("curve_epochs") or []:
            p = ckpts / f"epoch{int(e):03d}.ckpt"
            if int(e) >= epochs or not p.is_file():
                continue
            s, dt = drive(p, cell_dir / "curve" / f"epoch{int(e):03d}")
            curve_s += dt
            curve.append(_curve_point(p, s, batch))
        curve.append(_curve_point(final, summary, batch))
    hp = ck.get("hyper_parameters", {})
    return {"decoder": (hp.get("head_kwargs") or {}).get("decode"), "head": hp.get("head"), "mixer": hp.get("mixer"),
            "epochs": int(ck.get("epoch", -1)) + 1, "samples_seen": int(ck.get("global_step", 0)) * batch,
            "val_steer_mae": info.get("val_steer_mae"), "success": summary["success"],
            "cells": {k: v["rate"] for k, v in summary["cells"].items()},
            "wall_s": {"train": info.get("train_s"), "evaluate": round(eval_s, 1), "curve": round(curve_s, 1)},
            "curve": curve, "episodes": episodes, "machine": machine()}


def _curve_point(ckpt: Path, summary: dict, batch: int) -> dict[str, Any]:
    import torch

    from cicfw.bench.results import COLUMNS

    ck = torch.load(ckpt, map_location="cpu", weights_only=True)
    rates = {k: v["rate"] for k, v in summary["cells"].items()}
    return {"epoch": int(ck.get("epoch", -1)) + 1, "samples": int(ck.get("global_step", 0)) * batch,
            **rates, "overall": round(sum(rates.get(c, 0.0) for c in COLUMNS) / len(COLUMNS), 2)}


def _episodes(run_dir: Path) -> dict[str, dict[str, Any]]:
    from cicfw.bench.runs import cell_key, load_run

    return {r["key"]: {"success": bool(r["success"]), "column": cell_key(r["town_set"], r["weather_set"]),
                       "command": r["command"], "reason": r["reason"]}
            for r in load_run(run_dir).rows}


# ------------------------------------------------------------------------------------------------
# the app


@hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="reproduce")
def _cell_job(cfg: DictConfig) -> str:
    from hydra.core.hydra_config import HydraConfig

    if cfg.cell.row is None:
        raise ReproduceError("cell.row is set by `python -m cicfw.reproduce` itself; give rows=[...] instead")
    return run_cell(cfg, Path(HydraConfig.get().runtime.output_dir))


def write_report(cfg: DictConfig) -> dict[str, Any] | None:
    from cicfw.bench.results import publish, write_report as write

    results_dir = Path(cfg.results_dir)
    catalogue = OmegaConf.to_container(cfg.catalogue, resolve=True)
    data = write(results_dir, catalogue)
    if cfg.get("publish_dir"):
        publish(results_dir, Path(cfg.publish_dir))
    return data


def main(argv: Sequence[str] | None = None) -> int:
    """Check the plan, collect the data, run every cell through Hydra's launcher, write the report."""
    from cicfw.errors import USER_ERRORS

    args = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "--hydra-help", "--info", "-c", "--cfg", "--resolve") or a.startswith("--cfg")
           for a in args):
        sys.argv = [sys.argv[0], *args]
        _cell_job()
        return 0
    args = [a for a in args if a not in ("-m", "--multirun")]
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s", datefmt="%H:%M:%S")
    try:
        cfg = compose_plan(args)
        rows, seeds = check_plan(cfg)
        manifest = prepare(cfg, rows)
    except USER_ERRORS as err:
        msg = err.args[0] if isinstance(err, (KeyError, FileNotFoundError)) and err.args else err
        print(f"cicfw: error: {msg}", file=sys.stderr)
        return 2
    log.info("%d rows x %d seeds on budget %s (%d episodes per cell) into %s", len(rows), len(seeds),
             manifest["budget"], manifest["episodes"], cfg.results_dir)
    # seeds outermost: cells run seed by seed (cil/0, gtu/0, cil/1 ...), so a run stopped early still
    # compares every row on the same seeds
    sys.argv = [sys.argv[0], "-m", *args, f"cell.seed={','.join(map(str, seeds))}", f"cell.row={','.join(rows)}"]
    t0 = time.time()
    try:
        _cell_job()
    except SystemExit as e:  # Hydra exits on a launcher error; the cells that finished are still reported
        if e.code not in (0, None):
            log.error("the launcher stopped (exit %s); reporting the cells that finished", e.code)
    finally:
        try:
            data = write_report(cfg)
            log.info("%d cells in %.0f s; report: %s", sum(len(r["seeds"]) for r in data["rows"]),
                     time.time() - t0, Path(cfg.results_dir) / "RESULTS.md")
        except ValueError as err:
            log.error("no report: %s", err)
    return 0


if __name__ == "__main__":
    from cicfw.registry import guard_hydra_plugins

    guard_hydra_plugins()  # a plugin whose Hydra module fails to import: one warning, not a stopped app
    sys.exit(main())
