"""A training run owns its folder: it refuses a folder another run holds or wrote into (unless it
resumes from that folder's own checkpoint), before Hydra writes there; an empty CICFW_CACHE means the
default cache, not the file-system root."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from cicfw.core.locks import FolderBusy
from cicfw.core.run_folder import (RunFolderError, TrainFolderLock, TrainRunFolderCheck, hold_train_folder,
                              release_run_folder)
from conftest import assert_refused, run_app_in_process, write_tiny_dataset

ENV = {"HYDRA_FULL_ERROR": "0"}  # changes to the environment, for run_app_in_process


def _errors(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("cicfw:")]


# ---- train: one run per folder -----------------------------------------------------------------


def _train_args(data: Path, run: Path, *extra: str) -> list[str]:
    return ["data=cil_hdf5", f"data.path={data}", "data.batch_size=8",
            "data.val_batch_size=8", "progress_bar=false", "speed.compile=false", "trainer.max_epochs=1",
            "trainer.limit_train_batches=1", "trainer.limit_val_batches=1", "trainer.num_sanity_val_steps=0",
            "trainer.enable_model_summary=false", f"hydra.run.dir={run}", *extra]


@pytest.mark.slow  # trains (the app, run in this process)
def test_a_second_run_into_the_same_folder_is_refused_and_leaves_the_first_whole(tmp_path):
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    run = tmp_path / "run"
    first = run_app_in_process("cicfw.train", *_train_args(data, run), env=ENV)
    assert first.returncode == 0, first.stderr[-3000:]
    kept = {p: p.read_bytes() for p in (run / "csv" / "metrics.csv", run / "checkpoints" / "last.ckpt",
                                        run / ".hydra" / "config.yaml")}
    second = run_app_in_process("cicfw.train", *_train_args(data, run, "seed=1"), env=ENV)
    line = assert_refused(second, "hydra.run.dir", run)
    assert f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}" in line  # the override that resumes it
    assert {p: p.read_bytes() for p in kept} == kept  # metrics, checkpoint and .hydra as the first run left them
    assert not (run / ".train.lock").exists()


def test_resuming_from_the_folders_own_checkpoint_is_allowed(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"x")
    for other in (None, tmp_path / "elsewhere" / "last.ckpt"):
        with pytest.raises(RunFolderError) as err:
            hold_train_folder(run, other)
        assert (err.value.key, err.value.value) == ("hydra.run.dir", run)
    for own in (run / "checkpoints" / "last.ckpt", "last"):
        hold_train_folder(run, own)
        release_run_folder(run)


def test_a_folder_another_run_holds_is_refused(tmp_path):
    run = tmp_path / "run"
    other = TrainFolderLock(run, "hydra.run.dir").acquire()  # what a run started in the same second holds
    try:
        with pytest.raises(FolderBusy) as err:
            hold_train_folder(run)
        assert (err.value.key, err.value.value) == ("hydra.run.dir", run)
        assert f"pid {os.getpid()}" in str(err.value) and "hydra.run.dir=<new folder>" in str(err.value)
    finally:
        other.release()
    hold_train_folder(run)  # free again
    release_run_folder(run)


def test_a_ddp_worker_rank_shares_the_folder_its_rank_0_holds(tmp_path, monkeypatch):
    run = tmp_path / "run"
    rank0 = TrainFolderLock(run, "hydra.run.dir").acquire()
    try:
        monkeypatch.setenv("LOCAL_RANK", "1")  # Lightning's DDP re-runs the app per rank, into the same folder
        hold_train_folder(run)
        release_run_folder(run)
        assert (run / ".train.lock").exists()  # still rank 0's
    finally:
        rank0.release()


def test_a_ddp_worker_rank_is_not_refused_as_another_app_in_its_rank_0_run(tmp_path, monkeypatch):
    """Lightning re-runs the app per rank with hydra.job.name=train_ddp_process_<k>, into rank 0's folder."""
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save({"hydra": {"job": {"name": "train"}}}, run / ".hydra" / "hydra.yaml")
    (run / "train.log").write_text("")
    config = OmegaConf.create({"ckpt_path": None, "hydra": {"run": {"dir": str(run)},
                                                            "job": {"name": "train_ddp_process_1"}}})
    monkeypatch.setenv("LOCAL_RANK", "1")
    TrainRunFolderCheck.claim(config)  # no SystemExit
    monkeypatch.delenv("LOCAL_RANK")
    with pytest.raises(SystemExit):  # the same job name outside DDP is another app's
        TrainRunFolderCheck.claim(config)


def test_the_apps_callback_refuses_a_held_folder_in_one_line_before_hydra_writes_there(tmp_path, capsys):
    run = tmp_path / "run"
    config = OmegaConf.create({"ckpt_path": None, "hydra": {"run": {"dir": str(run)}, "job": {"name": "train"}}})
    other = TrainFolderLock(run, "hydra.run.dir").acquire()
    try:
        with pytest.raises(SystemExit) as stop:
            TrainRunFolderCheck().on_run_start(config)
    finally:
        other.release()
    assert stop.value.code == 2
    errors = _errors(capsys.readouterr().err)
    assert len(errors) == 1 and str(run) in errors[0] and "hydra.run.dir" in errors[0], errors
    assert not (run / ".hydra").exists()


# ---- a refused run leaves nothing behind ----------------------------------------------------------


@pytest.mark.slow  # runs the app (in this process)
def test_a_refused_run_puts_a_folder_that_existed_back_as_it_was(tmp_path):
    """A run refused after Hydra wrote ``.hydra`` and its log (a value a constructor refuses) restores
    them: the folder holds what it held, byte for byte, and nothing else."""
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    before = {run / ".hydra" / "config.yaml": b"seed: 7\n", run / "train.log": b"an earlier line\n",
              run / "notes.txt": b"mine\n"}
    for path, data_ in before.items():
        path.write_bytes(data_)
    proc = run_app_in_process("cicfw.train", *_train_args(data, run, "data.batch_size=6"), env=ENV)
    assert_refused(proc, "data.batch_size", 6)
    assert {p for p in run.rglob("*") if p.is_file()} == set(before)
    assert {p: p.read_bytes() for p in before} == before


def test_undo_removes_a_new_folder_and_the_parents_made_for_it_only(tmp_path):
    from cicfw.core.run_folder import note_run_folder, undo_run_folder

    (tmp_path / "outputs").mkdir()
    run = tmp_path / "outputs" / "day" / "time"
    note_run_folder(run)
    (run / ".hydra").mkdir(parents=True)
    (run / "train.log").write_text("")
    (tmp_path / "outputs" / "kept.txt").write_text("not the run's")
    undo_run_folder(run)
    assert sorted(p.name for p in (tmp_path / "outputs").iterdir()) == ["kept.txt"]  # outputs/ existed before
    undo_run_folder(tmp_path / "outputs")  # never noted: left alone
    assert (tmp_path / "outputs" / "kept.txt").exists()


@pytest.mark.slow  # runs the app (in this process)
def test_a_sweep_folder_holding_another_multirun_is_refused_before_hydra_writes_there(tmp_path):
    sweep = tmp_path / "sweep"
    (sweep / "0" / ".hydra").mkdir(parents=True)
    kept = {sweep / "multirun.yaml": b"hydra: {}\n", sweep / "0" / ".hydra" / "config.yaml": b"seed: 0\n"}
    for path, data in kept.items():
        path.write_bytes(data)
    proc = run_app_in_process("cicfw.train", "-m", "data=cil_hdf5", f"data.path={tmp_path}/none",
                              f"hydra.sweep.dir={sweep}", "mixer=independent,gtu", env=ENV)
    assert_refused(proc, "hydra.sweep.dir", sweep)
    assert {p for p in sweep.rglob("*") if p.is_file()} == set(kept)
    assert {p: p.read_bytes() for p in kept} == kept


@pytest.mark.slow  # runs the app (in this process)
def test_a_sweep_whose_job_config_is_refused_leaves_no_sweep_folder(tmp_path):
    """Hydra checks every job's config before the first runs, after the sweep folder and its
    multirun.yaml are written: a refused sweep removes them, so the same folder takes the fixed command."""
    sweep = tmp_path / "sweeps" / "one"
    proc = run_app_in_process("cicfw.train", "-m", "data=cil_hdf5", f"data.path={tmp_path}/none",
                              f"hydra.sweep.dir={sweep}", "model.lr=0.001,abc", env=ENV)
    assert_refused(proc, "model.lr", "abc")
    assert not (tmp_path / "sweeps").exists()


def test_a_ddp_worker_rank_rerunning_its_sweep_is_not_refused(tmp_path, monkeypatch):
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text("hydra: {}\n")  # written by rank 0 of the same sweep
    config = OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}, "job": {"name": "train"}}})
    with pytest.raises(SystemExit):
        TrainRunFolderCheck().on_multirun_start(config)
    monkeypatch.setenv("LOCAL_RANK", "1")
    TrainRunFolderCheck().on_multirun_start(config)


# ---- the cache folder ----------------------------------------------------------------------------


@pytest.mark.slow  # runs the app (in this process)
def test_an_empty_cicfw_cache_means_the_default_cache(tmp_path):
    env = {**ENV, "CICFW_CACHE": "", "HOME": str(tmp_path)}
    res = run_app_in_process("cicfw.train", "--cfg", "job", "--resolve", env=env)
    assert res.returncode == 0, res.stderr[-2000:]
    path = OmegaConf.create(res.stdout).data.path
    assert path == f"{tmp_path}/.cache/cicfw/datasets/sim_default", res.stdout
