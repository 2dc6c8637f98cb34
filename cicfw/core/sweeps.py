"""One summary row per multirun job, in ``<sweep dir>/summary.csv`` (its columns: docs/sweeps.md).

``SweepSummary`` is a Hydra callback (``hydra.callbacks`` in conf/train.yaml). Every job writes its own
row file (atomically: jobs may run in parallel processes or on other machines) and then rebuilds
``summary.csv`` from all of them under a file lock, so the CSV is complete and current while the sweep
runs, and after a sweep that stops early.
"""
from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
from contextlib import nullcontext
from pathlib import Path
from typing import Any, ContextManager, Iterable, Mapping

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from cicfw.core.files import atomic_write
from cicfw.core.json_files import read_json
from cicfw.core.locks import FolderLock, flock_available

log = logging.getLogger(__name__)

ROWS_DIR = ".summary"
SWEEP_FILE = "sweep.json"  # the sweep's command-line overrides, to tell swept keys from fixed ones
METRICS_FILE = "metrics.json"
CLOSED_LOOP_KEY = "closed_loop/success"  # what an evaluation writes into metrics.json
FIRST = ["job", "status", "value", "metric", "closed_loop_success"]
LAST = ["overrides", "error", "output_dir"]


def write_job_metrics(output_dir: str | Path, metrics: Mapping[str, Any]) -> None:
    """Merge ``metrics`` (name -> number) into ``<output_dir>/metrics.json``; the sweep summary
    adds every key as a column. An evaluation writes ``closed_loop/success`` here."""
    path = Path(output_dir) / METRICS_FILE
    merged = read_job_metrics(path.parent)
    merged.update({str(k): _number(v) for k, v in metrics.items()})
    atomic_write(path, json.dumps(merged, indent=1, sort_keys=True))


def read_job_metrics(output_dir: str | Path) -> dict[str, Any]:
    path = Path(output_dir) / METRICS_FILE
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        log.warning("sweep summary: ignored unreadable %s (%s)", path, err)
        return {}
    return data if isinstance(data, dict) else {}


def _number(value: Any) -> Any:
    """Tensors and numpy scalars as plain floats; everything else unchanged."""
    if hasattr(value, "item") and callable(value.item):
        try:
            return float(value.item())
        except (TypeError, ValueError):
            pass
    return value


def _one_line(err: BaseException) -> str:
    return f"{type(err).__name__}: {' '.join(str(err).split())}"


def job_row(config: DictConfig, job_return: JobReturn) -> dict[str, Any]:
    """The summary row of one finished job."""
    hc = config.hydra
    output_dir = hc.runtime.output_dir
    metrics = read_job_metrics(output_dir)
    failed = job_return.status == JobStatus.FAILED
    value: Any = ""
    error = ""
    if failed:
        error = _one_line(job_return._return_value)  # .return_value would re-raise it
    else:
        value = _number(job_return.return_value)
        try:
            value = float(value)
        except (TypeError, ValueError):
            value = str(value)
    return {
        "job": int(hc.job.num),
        "status": "failed" if failed else "ok",
        "value": value,
        "metric": CLOSED_LOOP_KEY if config.get("evaluate_after") and config.get("return_closed_loop")
        else config.get("optimized_metric", ""),
        "closed_loop_success": metrics.get(CLOSED_LOOP_KEY, ""),
        "overrides": list(job_return.overrides or hc.overrides.task),
        "error": error,
        "output_dir": str(output_dir),
        "metrics": metrics,
    }


class RowsLock(FolderLock):
    """The row files' lock while ``summary.csv`` is rebuilt: jobs finishing at once take turns, silently."""

    lock_name = ".lock"
    wait_level = logging.DEBUG


def taking_turns(folder: Path) -> ContextManager[Any]:
    """``folder`` held for one rebuild of what a sweep's jobs share there (``summary.csv``, a joined table),
    waiting as long as it takes; no lock where flock is missing."""
    return RowsLock(folder, wait=None) if flock_available() else nullcontext()


def _split(override: str) -> tuple[str, str]:
    key, _, value = override.partition("=")
    return key.lstrip("+~"), value


def override_values(overrides: Iterable[str]) -> dict[str, Any]:
    """Overrides (``key=value`` strings) as key -> value as Hydra parses it (so ``false`` and ``False`` compare
    equal; a sweep stays a sweep object), the key without its ``+`` or ``~``; the raw text where parsing
    fails (the app that takes the override refuses it)."""
    parser = OverridesParser.create()
    out: dict[str, Any] = {}
    for text in map(str, overrides):
        key, raw = _split(text)
        try:
            out[key] = parser.parse_override(text).value()
        except Exception:
            out[key] = raw
    return out


def summary_table(rows: list[dict[str, Any]], command_line: list[str] | None = None
                  ) -> tuple[list[str], list[dict[str, Any]]]:
    """Columns and flat rows for the CSV: swept overrides and metrics become columns.

    An override is swept when a job's value differs from the command line's (``head.W=5`` vs
    ``head.W=5,10,15``) or the command line lacks it (a sweeper's parameter); without the command
    line, when its value varies across jobs."""
    rows = sorted(rows, key=lambda r: r["job"])
    per_job = [dict(_split(o) for o in r["overrides"]) for r in rows]
    keys = list(dict.fromkeys(k for d in per_job for k in d))
    if command_line is not None:
        given = override_values(command_line)
        parsed = [override_values(r["overrides"]) for r in rows]
        swept = [k for k in keys if any(p.get(k) != given.get(k) for p in parsed)]
    else:
        swept = [k for k in keys if len({d.get(k) for d in per_job}) > 1]
    swept = [k for k in swept if not k.startswith("hydra.")]
    metric_keys = sorted({k for r in rows for k in r["metrics"]})
    columns = list(dict.fromkeys([*FIRST, *swept, *LAST, *metric_keys]))
    flat = []
    for r, d in zip(rows, per_job):
        out = {k: r[k] for k in FIRST + LAST if k != "overrides"}
        out["overrides"] = " ".join(r["overrides"])
        out.update({k: d.get(k, "") for k in swept})
        out.update({k: r["metrics"].get(k, "") for k in metric_keys if k not in out})
        flat.append(out)
    return columns, flat


def rebuild_summary(sweep_dir: str | Path, filename: str = "summary.csv") -> Path:
    """(Re)write ``<sweep_dir>/<filename>`` from the row files of every job finished so far."""
    sweep_dir = Path(sweep_dir)
    rows_dir = sweep_dir / ROWS_DIR
    with taking_turns(rows_dir):
        command_line = None
        if (rows_dir / SWEEP_FILE).is_file():
            command_line = read_json(rows_dir / SWEEP_FILE)["overrides"]
        rows = _read_rows(rows_dir, say=True)
        columns, flat = summary_table(rows, command_line)
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(flat)
        target = sweep_dir / filename
        atomic_write(target, buf.getvalue())
    return target


def _read_rows(rows_dir: Path, say: bool = False) -> list[dict[str, Any]]:
    """The row files of every job finished so far, unreadable ones skipped (with a warning when ``say``)."""
    rows = []
    for path in sorted(rows_dir.glob("[0-9]*.json")):
        try:
            rows.append(json.loads(path.read_text()))
        except (OSError, ValueError) as err:
            if say:
                log.warning("sweep summary: skipped unreadable row %s (%s)", path, err)
    return rows


#: what an optimising sweeper (Optuna) writes into the sweep folder at its end: the study's best trial
OPTIMIZATION_RESULTS = "optimization_results.yaml"


def _same_value(a: Any, b: Any) -> bool:
    """Whether two parameter values or results are equal, numbers within float rounding."""
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    return a == b


def best_trial_elsewhere(sweep_dir: str | Path) -> str | None:
    """One line when ``<sweep_dir>/optimization_results.yaml`` names a best trial (value and parameters) that
    is none of this sweep's jobs (its row files): the study, shared in a database with earlier sweeps, found
    it in another sweep, whose fixed overrides may differ. None otherwise (a multi-objective result too)."""
    sweep_dir = Path(sweep_dir)
    try:
        result = OmegaConf.to_container(OmegaConf.load(sweep_dir / OPTIMIZATION_RESULTS))
    except Exception:  # none written (no optimising sweeper), or unreadable: nothing to say about it
        return None
    if not isinstance(result, dict) or not isinstance(result.get("best_params"), dict) \
            or not isinstance(result.get("best_value"), (int, float)):
        return None
    best, params = result["best_value"], result["best_params"]
    rows = [r for r in _read_rows(sweep_dir / ROWS_DIR) if r.get("status") == "ok"]
    for r in rows:
        given = override_values(r.get("overrides", []))
        if _same_value(r.get("value"), best) and all(_same_value(given.get(k), v) for k, v in params.items()):
            return None
    shown = " ".join(f"{k}={v}" for k, v in params.items())
    return (f"{sweep_dir / OPTIMIZATION_RESULTS} names the study's best trial (value {best}, {shown}), which is "
            f"none of this sweep's {len(rows)} completed job(s): it came from another sweep of the same study "
            f"(hydra.sweeper.storage, hydra.sweeper.study_name), whose fixed overrides may differ; this sweep's "
            f"own jobs are in {sweep_dir / 'summary.csv'}")


_running: Path | None = None  # the sweep folder of the sweep this process runs (``SweepSummary``), while it runs


def forget_running_sweep() -> None:
    """Forget the sweep ``SweepSummary`` noted: it ended, even where Hydra skipped ``on_multirun_end``
    (its sweeper raised), so that it cannot speak for a later run's error in this process."""
    global _running
    _running = None


def every_job_failed() -> str | None:
    """One line when every job of the sweep this process runs failed (an Optuna search then has no best
    trial and its sweeper raises): how many, and where their errors are; None otherwise."""
    if _running is None:
        return None
    rows = _read_rows(_running / ROWS_DIR)
    if rows and all(r.get("status") == "failed" for r in rows):
        return (f"every one of the sweep's {len(rows)} job(s) failed; their errors: {_running / 'summary.csv'} "
                f"(the error column) and each job's log in its folder (e.g. {rows[0].get('output_dir')})")
    return None


RANK_VARIABLES = ("RANK", "SLURM_PROCID", "LOCAL_RANK", "NODE_RANK")


def is_worker_process() -> bool:
    """True in a DDP worker other than global rank 0 (Lightning's re-launched ranks re-run the
    job, SLURM runs one task per GPU): only rank 0 writes the job's row."""
    return any(os.environ.get(v, "0") not in ("", "0") for v in RANK_VARIABLES)


class SweepSummary(Callback):
    """Hydra callback: ``<sweep dir>/summary.csv``, one row per job (ok or failed) of a multirun."""

    def __init__(self, filename: str = "summary.csv") -> None:
        self.filename = filename

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        if is_worker_process():
            return
        rows_dir = Path(config.hydra.sweep.dir) / ROWS_DIR
        global _running
        _running = rows_dir.parent
        atomic_write(rows_dir / SWEEP_FILE, json.dumps({"overrides": list(config.hydra.overrides.task)}))

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        if config.hydra.mode != RunMode.MULTIRUN or is_worker_process():
            return
        row = job_row(config, job_return)
        sweep_dir = Path(config.hydra.sweep.dir)
        atomic_write(sweep_dir / ROWS_DIR / f"{row['job']:06d}.json", json.dumps(row, default=str))
        target = rebuild_summary(sweep_dir, self.filename)
        shown = row["value"] if row["status"] == "ok" else row["error"]
        log.info("sweep summary: job %d %s (%s) -> %s", row["job"], row["status"], shown, target)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        forget_running_sweep()  # the sweeper returned: its own result stands
        sweep_dir = Path(config.hydra.sweep.dir)
        if not is_worker_process() and (sweep_dir / ROWS_DIR).is_dir():
            target = rebuild_summary(sweep_dir, self.filename)
            with open(target, newline="") as f:
                rows = list(csv.DictReader(f))
            failed = [r for r in rows if r["status"] == "failed"]
            log.info("sweep summary: %d jobs, %d failed: %s", len(rows), len(failed), target)
            elsewhere = best_trial_elsewhere(sweep_dir)
            if elsewhere:
                log.warning("sweep summary: %s", elsewhere)

