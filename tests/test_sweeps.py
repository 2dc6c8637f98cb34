"""Sweeps: a basic multirun and an Optuna search on tiny data write one summary row per job; a
failing job is recorded as failed and the others run; launcher configs compose."""
from __future__ import annotations

import csv
import json
import math
import threading
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_module
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from cicfw.core import errors
from cicfw.registry import MIXERS
from cicfw.core.files import atomic_write
from cicfw.core.sweeps import ROWS_DIR, best_trial_elsewhere, rebuild_summary, summary_table, write_job_metrics
from conftest import AppResult, assert_refused, run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

TINY = ["data=cil_hdf5", "data.batch_size=8", "data.val_batch_size=8", "debug=fast", "progress_bar=false"]


def _multirun(tmp_path: Path, tiny_data: Path, *args: str) -> tuple[AppResult, list[dict]]:
    """``python -m cicfw.train <args>`` in this interpreter (the sweep's jobs run in-process as they would
    in the app's own process), and the sweep's summary rows."""
    sweep = tmp_path / "sweep"
    run = run_app_in_process("cicfw.train", *args, *TINY, f"data.path={tiny_data}", f"hydra.sweep.dir={sweep}",
                             cwd=tmp_path)
    summary = sweep / "summary.csv"
    assert summary.is_file(), run.stdout[-3000:] + run.stderr[-3000:]
    with open(summary, newline="") as f:
        return run, list(csv.DictReader(f))


def test_basic_multirun_records_a_failed_job_and_runs_the_others(tmp_path, tiny_data):
    """A job that fails on its data (a filter leaving no sample: found once the files are read, not by the
    config check every job passes before the first trains) is recorded as failed, and the others run."""
    run, rows = _multirun(tmp_path, tiny_data, "-m", "mixer=independent", "data.max_abs_steer=0.0001,0.8,0.9")
    assert [r["job"] for r in rows] == ["0", "1", "2"]
    assert [r["status"] for r in rows] == ["failed", "ok", "ok"]
    assert [r["data.max_abs_steer"] for r in rows] == ["0.0001", "0.8", "0.9"]  # the swept key is a column
    assert "mixer" not in rows[0]  # fixed on the command line: in `overrides`, not a column
    kind, _, text = rows[0]["error"].partition(": ")
    assert kind == "CicfwError" and text.startswith("the filters leave no sample") and rows[0]["value"] == ""
    for r in rows[1:]:
        assert r["error"] == "" and 0.0 <= float(r["value"]) < 2.0 and r["metric"] == "val/steer_mae"
        assert f"data.max_abs_steer={r['data.max_abs_steer']}" in r["overrides"].split()
    assert "job failed: the filters leave no sample" in (tmp_path / "sweep" / "0" / "train.log").read_text()
    assert run.returncode == 1  # Hydra's basic sweeper exits non-zero when a job failed, after all ran


def test_optuna_two_trials_write_the_summary(tmp_path, tiny_data):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="needs the sweeps extra: pip install -e .[sweeps]")
    # the mixer dimension narrowed to `independent` to keep the test fast (no mixer heatmaps)
    run, rows = _multirun(tmp_path, tiny_data, "hparams_search=optuna", "hydra.sweeper.n_trials=2",
                          "hydra.sweeper.params.mixer='choice(independent)'")
    assert run.returncode == 0, run.stderr[-3000:]
    assert [r["status"] for r in rows] == ["ok", "ok"]
    for r in rows:
        assert 2e-5 <= float(r["model.lr"]) <= 2e-3 and r["head.W"] in {"5", "10", "15"} and r["mixer"] == "independent"
    best = yaml.safe_load((tmp_path / "sweep" / "optimization_results.yaml").read_text())
    assert math.isclose(best["best_value"], min(float(r["value"]) for r in rows))


def test_a_shared_study_s_best_trial_from_an_earlier_sweep_is_said(tmp_path, tiny_data):
    """A study in a database shared by sweeps: optimization_results.yaml names the study's best trial, here an
    earlier sweep's (planted with a value no training reaches), and the summary says it is none of this sweep's."""
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="needs the sweeps extra: pip install -e .[sweeps]")
    import optuna
    from optuna.distributions import LogUniformDistribution
    from optuna.trial import create_trial

    storage = f"sqlite:///{tmp_path / 'study.db'}"
    study = optuna.create_study(study_name="s1", storage=storage, direction="minimize")
    study.add_trial(create_trial(params={"model.lr": 1e-4}, value=-1.0,
                                 distributions={"model.lr": LogUniformDistribution(2e-5, 2e-3)}))
    run, rows = _multirun(tmp_path, tiny_data, "hparams_search=optuna", "hydra.sweeper.n_trials=1",
                          "hydra.sweeper.params.mixer='choice(independent)'", f"hydra.sweeper.storage={storage}",
                          "hydra.sweeper.study_name=s1")
    assert run.returncode == 0 and [r["status"] for r in rows] == ["ok"], run.stderr[-3000:]
    assert yaml.safe_load((tmp_path / "sweep" / "optimization_results.yaml").read_text())["best_value"] == -1.0
    said = [line for line in (run.stdout + run.stderr).splitlines() if "optimization_results.yaml" in line]
    assert len(said) == 1 and "-1.0" in said[0] and "model.lr=0.0001" in said[0], run.stdout[-3000:]


def _sweep_with_best(folder: Path, best_value: float, best_params: dict) -> Path:
    row = {"job": 0, "status": "ok", "value": 0.25, "overrides": ["model.lr=0.0001", "head.W=10", "mixer=gtu"]}
    atomic_write(folder / ROWS_DIR / "000000.json", json.dumps(row))
    failed = {"job": 1, "status": "failed", "value": "", "overrides": ["model.lr=0.001", "head.W=5", "mixer=gtu"]}
    atomic_write(folder / ROWS_DIR / "000001.json", json.dumps(failed))
    OmegaConf.save(OmegaConf.create({"name": "optuna", "best_params": best_params, "best_value": best_value}),
                   folder / "optimization_results.yaml")
    return folder


def test_the_best_trial_is_this_sweep_s_only_where_a_job_has_its_value_and_parameters(tmp_path):
    own = {"model.lr": 1e-4, "head.W": 10, "mixer": "gtu"}
    assert best_trial_elsewhere(_sweep_with_best(tmp_path / "a", 0.25, own)) is None
    assert best_trial_elsewhere(tmp_path / "none") is None  # no optimising sweeper, nothing to say
    assert "0.2," in best_trial_elsewhere(_sweep_with_best(tmp_path / "b", 0.2, own))  # another value
    other = best_trial_elsewhere(_sweep_with_best(tmp_path / "c", 0.25, {**own, "head.W": 15}))
    assert "head.W=15" in other  # this sweep's value, another trial's parameters
    assert "head.W=5" in best_trial_elsewhere(_sweep_with_best(tmp_path / "d", 0.25, {**own, "head.W": 5}))  # failed job


def test_an_optuna_search_whose_every_trial_fails_ends_in_one_line(tmp_path, tiny_data):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="needs the sweeps extra: pip install -e .[sweeps]")
    run, rows = _multirun(tmp_path, tiny_data, "hparams_search=optuna", "hydra.sweeper.n_trials=2",
                          "hydra.sweeper.params.mixer='choice(independent)'", "data.max_abs_steer=0.0001")
    assert [r["status"] for r in rows] == ["failed", "failed"]
    assert_refused(run, tmp_path / "sweep" / "summary.csv", "2 job(s)", status=1)


def test_a_failed_sweep_does_not_speak_for_a_later_run_in_the_process(tmp_path, tiny_data, monkeypatch):
    """A basic sweep whose job failed ends without Hydra's on_multirun_end; a later run's own ``ValueError`` in
    the same process (here a planted bug, which reaches the same handler as Optuna's "no trial is completed")
    keeps its traceback, and is not reported as "every job failed"."""
    import cicfw.train.app

    run, rows = _multirun(tmp_path, tiny_data, "-m", "mixer=independent", "data.max_abs_steer=0.0001")
    assert [r["status"] for r in rows] == ["failed"] and run.returncode == 1

    def planted(*_args, **_kwargs):
        raise ValueError("planted bug")

    monkeypatch.setattr(cicfw.train.app, "train_in_folder", planted)
    later = run_app_in_process("cicfw.train", *TINY, f"data.path={tiny_data}", f"hydra.run.dir={tmp_path / 'run'}",
                               cwd=tmp_path)
    assert later.returncode == 1 and "Traceback" in later.stderr and "planted bug" in later.stderr, later.stderr
    assert "every one of the sweep" not in later.stderr


def test_summary_columns_are_the_swept_overrides_and_metrics(tmp_path):
    rows = [
        {"job": 1, "status": "ok", "value": 0.2, "metric": "val/steer_mae", "closed_loop_success": 0.75,
         "overrides": ["mixer=gtu", "head.W=10", "seed=1", "model.lr=0.001"], "error": "", "output_dir": "b",
         "metrics": {"closed_loop/success": 0.75}},
        {"job": 0, "status": "failed", "value": "", "metric": "val/steer_mae", "closed_loop_success": "",
         "overrides": ["mixer=gtu", "head.W=5", "seed=1", "model.lr=0.002"], "error": "ValueError: x", "output_dir": "a",
         "metrics": {}},
    ]
    columns, flat = summary_table(rows, command_line=["mixer=gtu", "head.W=5,10", "seed=1"])
    assert columns[:5] == ["job", "status", "value", "metric", "closed_loop_success"]
    assert {"head.W", "model.lr"} <= set(columns) and "seed" not in columns and "mixer" not in columns
    assert [f["job"] for f in flat] == [0, 1] and flat[1]["closed_loop/success"] == 0.75
    assert flat[0]["overrides"] == "mixer=gtu head.W=5 seed=1 model.lr=0.002"


def test_concurrent_jobs_all_land_in_the_summary(tmp_path):
    rows_dir = tmp_path / ROWS_DIR

    def job(i: int) -> None:
        row = {"job": i, "status": "ok", "value": i / 10, "metric": "m", "closed_loop_success": "",
               "overrides": [f"x={i}"], "error": "", "output_dir": str(i), "metrics": {}}
        atomic_write(rows_dir / f"{i:06d}.json", json.dumps(row))
        rebuild_summary(tmp_path)

    threads = [threading.Thread(target=job, args=(i,)) for i in range(12)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    with open(tmp_path / "summary.csv", newline="") as f:
        got = list(csv.DictReader(f))
    assert [int(r["x"]) for r in got] == list(range(12))
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # no temporary left behind


def test_job_metrics_merge(tmp_path):
    write_job_metrics(tmp_path, {"val/steer_mae": 0.1})
    write_job_metrics(tmp_path, {"closed_loop/success": 0.5})
    assert json.loads((tmp_path / "metrics.json").read_text()) == {"closed_loop/success": 0.5, "val/steer_mae": 0.1}


def test_multirun_jobs_fail_instead_of_returning_nan(monkeypatch):
    monkeypatch.setattr(errors, "_in_multirun", lambda: True)
    assert errors.report_user_errors(lambda: 0.5)() == 0.5
    with pytest.raises(errors.NonFiniteResult, match="nan"):
        errors.report_user_errors(lambda: float("nan"))()  # Optuna's sweeper would crash on a nan
    with pytest.raises(errors.CicfwError, match="bad value"):  # re-raised: Hydra marks the job FAILED
        errors.report_user_errors(lambda: (_ for _ in ()).throw(errors.CicfwError("bad value")))()
    monkeypatch.setattr(errors, "_in_multirun", lambda: False)
    with pytest.raises(SystemExit) as exit_:
        errors.report_user_errors(lambda: (_ for _ in ()).throw(errors.CicfwError("bad value")))()
    assert exit_.value.code == 2


def _hydra_cfg(*overrides: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("train", overrides=list(overrides), return_hydra_config=True)


def test_optuna_search_space_names_real_options():
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="needs the sweeps extra")
    cfg = _hydra_cfg("hparams_search=optuna")
    sweeper = cfg.hydra.sweeper
    assert "OptunaSweeper" in sweeper._target_ and sweeper.direction == "minimize"
    assert cfg.head.name == "hybrid" and "W" in cfg.head
    params = sweeper.params
    assert set(params) == {"model.lr", "head.W", "mixer"}
    mixers = params["mixer"][len("choice("):-1].split(",")
    assert mixers and all(m.strip() in MIXERS for m in mixers)


def test_launcher_configs_compose():
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="needs the sweeps extra")
    cfg = _hydra_cfg("launcher=joblib")
    assert "JoblibLauncher" in cfg.hydra.launcher._target_ and cfg.hydra.launcher.n_jobs == 2
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="needs the slurm extra")
    cfg = _hydra_cfg("launcher=slurm", "trainer=ddp", "hydra.launcher.gpus_per_node=4", "hydra.launcher.nodes=2")
    assert "SlurmLauncher" in cfg.hydra.launcher._target_
    HydraConfig.instance().set_config(cfg)  # what Hydra does in each job: the trainer follows the launcher
    trainer = OmegaConf.to_container(cfg.trainer, resolve=True)
    assert trainer["devices"] == 4 and trainer["num_nodes"] == 2 and cfg.hydra.launcher.tasks_per_node == 4


def test_job_row_reads_status_error_and_closed_loop_success(tmp_path):
    from hydra.core.utils import JobReturn, JobStatus

    from cicfw.core.sweeps import job_row

    def config(num: int, out: Path, **top):
        return OmegaConf.create({"optimized_metric": "val/steer_mae", **top, "hydra": {
            "job": {"num": num}, "runtime": {"output_dir": str(out)}, "overrides": {"task": ["mixer=gtu"]}}})

    write_job_metrics(tmp_path / "0", {"closed_loop/success": 81.25})  # what evaluate_after writes
    ok = JobReturn(overrides=["mixer=gtu"], status=JobStatus.COMPLETED, _return_value=0.25)
    row = job_row(config(0, tmp_path / "0"), ok)
    assert (row["status"], row["value"], row["closed_loop_success"], row["error"]) == ("ok", 0.25, 81.25, "")
    bad = JobReturn(overrides=["mixer=gtu"], status=JobStatus.FAILED, _return_value=RuntimeError("out of\nmemory"))
    row = job_row(config(1, tmp_path / "1", evaluate_after=True, return_closed_loop=True), bad)
    assert (row["status"], row["value"], row["error"]) == ("failed", "", "RuntimeError: out of memory")
    assert row["metric"] == "closed_loop/success"
