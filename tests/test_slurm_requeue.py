"""A SLURM job requeued after pre-emption runs the same command into the same run folder, which holds its
HPC checkpoint: the train app takes that folder as the run's own and resumes, while another run's folder
stays refused under SLURM as anywhere else."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from cicfw.core.run_folder import RunFolderError, check_no_other_run
from cicfw.core.slurm_requeue import is_requeued_run, newest_hpc_checkpoint
from conftest import TINY_TRAIN, assert_refused, compose_train, run_app_in_process, write_tiny_dataset

#: what ``SLURMEnvironment.detect()`` reads: a job started with srun, one task (None: unset)
SLURM = {"SLURM_NTASKS": "1", "SLURM_JOB_NAME": "train", "SLURM_PROCID": "0", "SLURM_LOCALID": "0",
         "SLURM_NODEID": "0", "SLURM_NTASKS_PER_NODE": None, "SLURM_NNODES": None}
NO_SLURM = {name: None for name in SLURM}
#: two epochs of one step, the first kept (checkpoints/epoch001.ckpt): where a pre-empted job stops
COMMAND = [*TINY_TRAIN, "trainer.limit_train_batches=1", "trainer.max_epochs=2", "keep_epoch_checkpoints=[1]"]


def _slurm(monkeypatch, on: bool) -> None:
    for name, value in (SLURM if on else NO_SLURM).items():
        monkeypatch.setenv(name, value) if value is not None else monkeypatch.delenv(name, raising=False)


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> dict:
    """A run of ``COMMAND`` through the app, in its own folder as Hydra leaves it (``.hydra``, the log)."""
    root = tmp_path_factory.mktemp("requeue")
    data = write_tiny_dataset(root / "data", n_files=4, n=32)
    run = root / "run"
    args = [*COMMAND, f"data.path={data}"]
    result = run_app_in_process("cicfw.train", *args, f"hydra.run.dir={run}", env=NO_SLURM)
    assert result.returncode == 0, result.stderr[-3000:]
    return {"args": args, "run": run}


@pytest.fixture
def preempted(finished, tmp_path) -> dict:
    """A copy of ``finished`` as a pre-empted job leaves it: the HPC checkpoint Lightning saved after the
    first epoch, and the lock record of its killed process."""
    run = tmp_path / "run"
    shutil.copytree(finished["run"], run)
    shutil.copy(run / "checkpoints" / "epoch001.ckpt", run / "hpc_ckpt_1.ckpt")
    (run / ".train.lock").write_text('{"pid": 4242, "host": "node-that-died", "started": "2026-01-01 00:00:00"}')
    return {**finished, "run": run}


@pytest.mark.slow  # trains
def test_a_requeued_job_goes_on_in_its_own_folder_from_its_hpc_checkpoint(preempted, monkeypatch):
    from cicfw.model.module import CICModule

    run = preempted["run"]
    steps, step = [], CICModule.training_step
    monkeypatch.setattr(CICModule, "training_step", lambda self, *a, **k: steps.append(1) or step(self, *a, **k))
    result = run_app_in_process("cicfw.train", *preempted["args"], f"hydra.run.dir={run}", env=SLURM)
    assert result.returncode == 0, result.stderr[-3000:]
    last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)
    assert (len(steps), last["global_step"]) == (1, 2)  # the second epoch only: resumed, not started afresh


@pytest.mark.slow  # trains
@pytest.mark.parametrize("change, slurm", [("seed=1", True), (None, False)], ids=["another-run", "no-slurm"])
def test_another_run_or_no_slurm_is_refused_as_before(preempted, change, slurm):
    run = preempted["run"]
    saved = (run / ".hydra" / "config.yaml").read_bytes()
    args = [*preempted["args"], *([change] if change else [])]
    result = run_app_in_process("cicfw.train", *args, f"hydra.run.dir={run}", env=SLURM if slurm else NO_SLURM)
    assert_refused(result, "hydra.run.dir", run)
    assert (run / ".hydra" / "config.yaml").read_bytes() == saved  # the other run's record untouched


def _run_folder(root: Path, *overrides: str) -> tuple[Path, object]:
    """A folder holding a run of ``overrides`` (its saved config, a checkpoint) and the composed config."""
    cfg = compose_train(*overrides)
    (root / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, root / ".hydra" / "config.yaml")
    (root / "checkpoints").mkdir()
    (root / "checkpoints" / "last.ckpt").write_bytes(b"x")
    return root, cfg


def test_only_slurm_an_hpc_checkpoint_and_the_same_config_make_the_folder_the_run_s(tmp_path, monkeypatch):
    run, cfg = _run_folder(tmp_path / "run", "model.lr=0.001")
    _slurm(monkeypatch, True)
    assert not is_requeued_run(run, cfg)  # no HPC checkpoint: a finished run, not a pre-empted one
    (run / "hpc_ckpt_2.ckpt").write_bytes(b"x")
    (run / "hpc_ckpt_10.ckpt").write_bytes(b"x")
    assert newest_hpc_checkpoint(run) == run / "hpc_ckpt_10.ckpt"
    assert is_requeued_run(run, cfg)
    check_no_other_run(run, None, "hydra.run.dir", cfg)
    for other in (compose_train("model.lr=0.002"), compose_train("model.lr=0.001", "seed=3"), None):
        assert not is_requeued_run(run, other)
        with pytest.raises(RunFolderError) as err:
            check_no_other_run(run, None, "hydra.run.dir", other)
        assert (err.value.key, err.value.value) == ("hydra.run.dir", run)
    _slurm(monkeypatch, False)
    assert not is_requeued_run(run, cfg)
    (run / ".hydra" / "config.yaml").unlink()
    _slurm(monkeypatch, True)
    assert not is_requeued_run(run, cfg)  # no record of the run there: nothing says it is this one


@pytest.mark.slow  # runs the app
def test_slurm_variables_without_srun_are_one_line_and_leave_no_run_folder(tmp_path):
    """An salloc shell: SLURM's variables for two tasks, the command not started by srun. Lightning's Trainer
    would fail with a traceback (``--ntasks=2 ... not supported``) after the run folder was written."""
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    run = tmp_path / "run"
    env = {**NO_SLURM, "SLURM_JOB_ID": "4242", "SLURM_NTASKS": "2", "SLURM_JOB_NAME": "train", "SLURM_PROCID": "1",
           "HYDRA_FULL_ERROR": "0"}
    r = run_app_in_process("cicfw.train", *COMMAND, f"data.path={data}", f"hydra.run.dir={run}", env=env)
    assert r.returncode == 2, r.stderr[-3000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "SLURM_NTASKS=2" in lines[0] and "srun" in lines[0], r.stderr[-3000:]
    assert not run.exists() or not any(run.iterdir())  # nothing of a run that never was


def test_a_single_run_s_failure_passes_the_job_failure_callback_as_it_is():
    """The multirun callback that words a job's failure in one line leaves a single run's error alone (it
    has no job number: reading one raised inside Hydra's callback)."""
    from hydra.core.utils import JobReturn, JobStatus

    from cicfw.core.override_hints import OneLineJobFailure

    config = OmegaConf.create({"hydra": {"job": {"num": "???", "name": "train"},
                                         "runtime": {"output_dir": "/nowhere"}, "sweep": {"dir": "/nowhere"}}})
    err = RuntimeError("boom")
    ret = JobReturn(overrides=[], status=JobStatus.FAILED, _return_value=err)
    OneLineJobFailure().on_job_end(config, ret)
    assert ret._return_value is err
