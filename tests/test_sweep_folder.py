"""A multirun's ``hydra.sweep.dir`` holds its job folders and what it writes beside them: a folder that is one
run (an evaluation, a training run), a dataset or the data folder is refused before any job, where the sweep
would have written inside it (an evaluate sweep even joined that run as its only row, not its own jobs)."""
from __future__ import annotations

from pathlib import Path

import pytest

from cicfw.core.run_folder import RunFolderError, claim_sweep_folder
from conftest import TINY_TRAIN, assert_refused, run_app_in_process, write_tiny_dataset

EXPERT = ["policy=expert", "suite.towns=[town_a]", "suite.weathers=[ClearNoon]", "runner.workers=1",
          "progress_bar=false", "maps=false"]


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_an_evaluate_sweep_into_an_evaluation_run_is_refused(tmp_path):
    run = tmp_path / "run"
    assert run_app_in_process("cicfw.evaluate", *EXPERT, "suite.limit=1", f"hydra.run.dir={run}").returncode == 0
    before = _files(run)
    res = run_app_in_process("cicfw.evaluate", "-m", *EXPERT, "suite.limit=1,2", f"hydra.sweep.dir={run}")
    assert_refused(res, "hydra.sweep.dir", run)
    assert _files(run) == before  # no job folder, no table written over the run's


def test_a_sweep_into_the_data_folder_or_a_training_run_is_refused(tmp_path):
    data = write_tiny_dataset(tmp_path / "data", n_files=2, n=8)
    res = run_app_in_process("cicfw.train", "-m", "data=cil_hdf5", f"data.path={data}", "seed=0,1",
                             "trainer.max_epochs=1", "trainer.limit_train_batches=1", "trainer.limit_val_batches=1",
                             "data.batch_size=8", "progress_bar=false", f"hydra.sweep.dir={data}")
    assert_refused(res, "hydra.sweep.dir", data)
    assert sorted(p.name for p in data.iterdir()) == ["data_00000.h5", "data_00001.h5"]
    trained = tmp_path / "trained"
    (trained / ".hydra").mkdir(parents=True)
    (trained / ".hydra" / "hydra.yaml").write_text("hydra:\n  job:\n    name: train\n")
    (trained / "checkpoints").mkdir()
    res = run_app_in_process("cicfw.evaluate", "-m", *EXPERT, "suite.limit=1,2", f"hydra.sweep.dir={trained}")
    assert_refused(res, "hydra.sweep.dir", trained)
    assert sorted(p.name for p in trained.iterdir()) == [".hydra", "checkpoints"]


def test_an_evaluate_sweep_still_resumes_in_its_own_folder(tmp_path):
    sweep = tmp_path / "sweep"
    args = ["-m", *EXPERT, "suite.limit=1,2", f"hydra.sweep.dir={sweep}"]
    assert run_app_in_process("cicfw.evaluate", *args).returncode == 0
    again = run_app_in_process("cicfw.evaluate", *args)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "Expert" in (sweep / "table.md").read_text()


def test_an_evaluate_sweep_s_jobs_take_turns_joining(tmp_path, monkeypatch):
    """Jobs of a parallel launcher finishing at once each join the sweep's runs: a join read while another job
    was still driving must not be written after that job's complete one, so each reads and writes holding
    the sweep folder."""
    from types import SimpleNamespace

    from hydra.types import RunMode

    import cicfw.benchmark.app as bench_app
    from cicfw.core.locks import FolderBusy
    from cicfw.core.sweeps import RowsLock

    hydra_cfg = SimpleNamespace(mode=RunMode.MULTIRUN, job=SimpleNamespace(config_name="evaluate"),
                                sweep=SimpleNamespace(dir=str(tmp_path)))
    monkeypatch.setattr(bench_app, "HydraConfig", SimpleNamespace(initialized=lambda: True, get=lambda: hydra_cfg))
    held = []

    def holding(*args, **kwargs):
        try:
            RowsLock(tmp_path, wait=0).acquire().release()
            held.append(False)
        except FolderBusy:
            held.append(True)
        return []

    monkeypatch.setattr(bench_app, "find_runs", holding)
    monkeypatch.setattr(bench_app, "write_joined", holding)
    bench_app.join_sweep()
    assert held == [True, True]


def _user_folder(folder: Path, files: dict[str, str]) -> dict[str, bytes]:
    folder.mkdir()
    for name, text in files.items():
        (folder / name).write_text(text)
    return _files(folder)


def test_a_sweep_into_a_folder_of_user_files_is_refused_before_any_job(tmp_path, tiny_data):
    """A sweep writes summary.csv, optimization_results.yaml or the joined table.md/.csv into its folder: one
    holding files no sweep of that app wrote is refused, as a single run's folder is, leaving them as they were."""
    train = ["data=cil_hdf5", f"data.path={tiny_data}", *TINY_TRAIN[1:]]
    ud3 = tmp_path / "ud3"
    before = _user_folder(ud3, {"summary.csv": "my summary\n"})
    res = run_app_in_process("cicfw.train", "-m", "mixer=independent", *train, f"hydra.sweep.dir={ud3}")
    assert_refused(res, "hydra.sweep.dir", ud3)
    assert "summary.csv" in res.stderr and _files(ud3) == before
    ud5 = tmp_path / "ud5"
    before = _user_folder(ud5, {"table.md": "my table\n", "table.csv": "my csv\n"})
    res = run_app_in_process("cicfw.evaluate", "-m", *EXPERT[1:], "policy=expert,constant", "suite.limit=1",
                             f"hydra.sweep.dir={ud5}")
    assert_refused(res, "hydra.sweep.dir", ud5)
    assert "table.md" in res.stderr and _files(ud5) == before
    ud6 = tmp_path / "ud6"
    before = _user_folder(ud6, {"notes.txt": "mine\n"})
    res = run_app_in_process("cicfw.diagnose", "-m", f"checkpoint={tmp_path}/a.ckpt,{tmp_path}/b.ckpt",
                             f"hydra.sweep.dir={ud6}")
    assert_refused(res, "hydra.sweep.dir", ud6)
    assert "notes.txt" in res.stderr and _files(ud6) == before


def test_an_optuna_search_into_a_folder_of_user_files_is_refused(tmp_path, tiny_data):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="needs the sweeps extra: pip install -e .[sweeps]")
    ud2 = tmp_path / "ud2"
    before = _user_folder(ud2, {"summary.csv": "mine\n", "optimization_results.yaml": "mine\n"})
    res = run_app_in_process("cicfw.train", "hparams_search=optuna", "hydra.sweeper.n_trials=1",
                             "hydra.sweeper.params.mixer='choice(independent)'", "data=cil_hdf5",
                             f"data.path={tiny_data}", *TINY_TRAIN[1:], f"hydra.sweep.dir={ud2}", cwd=tmp_path)
    assert_refused(res, "hydra.sweep.dir", ud2)
    assert "optimization_results.yaml" in res.stderr and _files(ud2) == before


def test_which_sweep_folders_a_sweep_may_use(tmp_path):
    """Only an earlier sweep of the same app may hold what it likes; another app's sweep is refused; cicfw runs
    or sweeps below the folder, or the rows of a sweep stopped before Hydra wrote its record, are cicfw's."""
    other = tmp_path / "other"
    other.mkdir()
    (other / "multirun.yaml").write_text("hydra:\n  job:\n    name: train\n")
    (other / "summary.csv").write_text("job\n")
    claim_sweep_folder(other, app="train")
    with pytest.raises(RunFolderError) as err:
        claim_sweep_folder(other, app="diagnose")
    assert err.value.key == "hydra.sweep.dir" and "multirun.yaml" in str(err.value)
    below = tmp_path / "below"
    (below / "old" / ".hydra").mkdir(parents=True)
    (below / "old" / ".hydra" / "hydra.yaml").write_text("hydra:\n  callbacks:\n    run_folder:\n      _target_: "
                                                          "cicfw.core.run_folder.LockedRunFolderCheck\n"
                                                          "  job:\n    name: evaluate\n")  # a cicfw evaluation's
    (below / ".summary").mkdir()
    (below / ".summary" / "sweep.json").write_text('{"overrides": []}')
    claim_sweep_folder(below, app="evaluate")
    (below / "notes").mkdir()  # a folder of no cicfw app
    with pytest.raises(RunFolderError, match="notes"):
        claim_sweep_folder(below, app="evaluate")


def test_a_folder_of_dated_runs_and_sweeps_is_cicfws_at_any_of_hydras_levels(tmp_path):
    """Hydra's own layout puts runs two levels down (``multirun/<date>/<time>``): sweeping into ``multirun``
    beside earlier sweeps was refused as "files that no cicfw train sweep wrote (2026-12-07)". A user's file
    at any of those levels is still refused."""
    multirun = tmp_path / "multirun"
    (multirun / "2026-12-07" / "10-00-00").mkdir(parents=True)
    (multirun / "2026-12-07" / "10-00-00" / "multirun.yaml").write_text("hydra:\n  job:\n    name: train\n")
    run = multirun / "2026-12-07" / "11-00-00"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "hydra.yaml").write_text("hydra:\n  job:\n    name: train\n")
    claim_sweep_folder(multirun, app="train")
    (multirun / "2026-12-07" / "notes.txt").write_text("mine\n")
    with pytest.raises(RunFolderError, match="2026-12-07"):
        claim_sweep_folder(multirun, app="train")
