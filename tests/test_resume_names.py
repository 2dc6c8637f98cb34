"""``ckpt_path=last`` (and ``hpc``), the names Lightning resolves in the run's folder, resume only after the
checks a checkpoint file gets; ``best``, which never resumes, is one line."""
from __future__ import annotations


import pytest
import torch

from cicfw.core.errors import CicfwError
from cicfw.train.app import train
from cicfw.train.resume_names import own_checkpoint, with_checkpoint_file
from conftest import TINY_TRAIN, compose_train, train_tiny_run

SHORT = [*TINY_TRAIN, "trainer.limit_train_batches=1", "model.ema_decay=0.5"]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> dict:
    """A one-step run with weight averaging, its data and its folder."""
    return train_tiny_run(tmp_path_factory.mktemp("named"), *SHORT)


@pytest.mark.slow  # trains
@pytest.mark.parametrize("override, key, value", [("data.val_fraction=0.5", "data.val_fraction", 0.5),
                                                 ("model.ema_decay=0.0", "ckpt_path", None)])
def test_resuming_by_name_gets_the_checks_a_file_gets(run, override, key, value):
    cfg = compose_train(*SHORT, f"data.path={run['data']}", "ckpt_path=last", "trainer.max_epochs=2", override)
    with pytest.raises(CicfwError) as err:
        train(cfg, run["run"], refuse_finished=True)
    assert err.value.key == key
    assert err.value.value == (value if value is not None else str(run["run"] / "checkpoints" / "last.ckpt"))


@pytest.mark.slow  # trains
def test_best_is_refused_and_hpc_without_a_checkpoint_too(run):
    for name in ("best", "hpc"):
        cfg = compose_train(*SHORT, f"data.path={run['data']}", f"ckpt_path={name}", "trainer.max_epochs=2")
        with pytest.raises(CicfwError) as err:
            train(cfg, run["run"], refuse_finished=True)
        assert (err.value.key, err.value.value) == ("ckpt_path", name)


@pytest.mark.slow  # trains
def test_last_resumes_the_run_with_its_settings(run, tmp_path):
    import shutil

    folder = tmp_path / "run"
    shutil.copytree(run["run"], folder)
    cfg = compose_train(*SHORT, f"data.path={run['data']}", "ckpt_path=last", "trainer.max_epochs=2")
    train(cfg, folder, refuse_finished=True)
    last = torch.load(folder / "checkpoints" / "last.ckpt", weights_only=True)
    assert last["global_step"] == 2 and "current_model_state" in last  # one step more, still averaged


def test_last_names_the_newest_checkpoint_file_and_none_starts_afresh(tmp_path):
    ckpts = tmp_path / "checkpoints"
    ckpts.mkdir()
    cfg = compose_train("ckpt_path=last")
    assert with_checkpoint_file(cfg, tmp_path).ckpt_path is None  # nothing there yet
    (ckpts / "last.ckpt").write_bytes(b"x")
    (ckpts / ".last.ckpt.tmp.ckpt").write_bytes(b"half")  # a checkpoint being written is not one
    assert own_checkpoint("last", tmp_path) == ckpts / "last.ckpt"
    assert with_checkpoint_file(cfg, tmp_path).ckpt_path == str(ckpts / "last.ckpt")
    assert cfg.ckpt_path == "last"  # the caller's config is left as it was


def _touched(path, step: int, year: int):
    """A checkpoint recording ``step``, its modification time in ``year``."""
    import os
    import time

    torch.save({"global_step": step}, path)
    t = time.mktime((year, 1, 1, 0, 0, 0, 0, 0, -1))
    os.utime(path, (t, t))
    return path


def test_last_is_last_ckpt_never_a_newer_modified_file(tmp_path, caplog):
    ckpts = tmp_path / "checkpoints"
    ckpts.mkdir()
    last = _touched(ckpts / "last.ckpt", 4, 2020)
    _touched(ckpts / "last-v1.ckpt", 2, 2030)  # an older state, copied in and touched
    _touched(tmp_path / "hpc_ckpt_1.ckpt", 3, 2030)  # an HPC checkpoint of an earlier step
    assert own_checkpoint("last", tmp_path) == last
    with caplog.at_level("INFO", logger="cicfw.train"):
        assert with_checkpoint_file(compose_train("ckpt_path=last"), tmp_path).ckpt_path == str(last)
    assert any(str(last) in r.getMessage() for r in caplog.records)  # one line names the file resumed from
    hpc = _touched(tmp_path / "hpc_ckpt_2.ckpt", 5, 2000)  # a later step, whatever its time
    assert own_checkpoint("last", tmp_path) == hpc


def test_last_without_last_ckpt_but_other_last_files_is_refused(tmp_path):
    ckpts = tmp_path / "checkpoints"
    ckpts.mkdir()
    _touched(ckpts / "last-v1.ckpt", 2, 2030)
    with pytest.raises(CicfwError) as err:
        with_checkpoint_file(compose_train("ckpt_path=last"), tmp_path)
    assert (err.value.key, err.value.value) == ("ckpt_path", "last")
    assert "last-v1.ckpt" in str(err.value)


@pytest.fixture
def slurm_requeue(run, tmp_path, monkeypatch) -> dict:
    """A copy of ``run`` that holds an HPC checkpoint (what Lightning saves before SLURM requeues a job), in an
    environment where ``SLURMEnvironment.detect()`` finds SLURM: a requeued job, run with no ``ckpt_path``."""
    import shutil

    folder = tmp_path / "run"
    shutil.copytree(run["run"], folder)
    shutil.copy(folder / "checkpoints" / "last.ckpt", folder / "hpc_ckpt_1.ckpt")
    for name, value in (("SLURM_NTASKS", "1"), ("SLURM_JOB_NAME", "train"), ("SLURM_PROCID", "0"),
                        ("SLURM_LOCALID", "0"), ("SLURM_NODEID", "0")):
        monkeypatch.setenv(name, value)
    for name in ("SLURM_NTASKS_PER_NODE", "SLURM_NNODES"):
        monkeypatch.delenv(name, raising=False)
    return {**run, "run": folder, "hpc": folder / "hpc_ckpt_1.ckpt"}


@pytest.mark.slow  # trains
def test_lightning_s_own_resume_under_slurm_gets_the_checks_hpc_gets(slurm_requeue):
    req = slurm_requeue
    cfg = compose_train(*SHORT, f"data.path={req['data']}", "trainer.max_epochs=2", "model.ema_decay=0.0")
    with pytest.raises(CicfwError) as err:
        train(cfg, req["run"], refuse_finished=True, claim=False)  # held as the app holds its requeued folder
    assert (err.value.key, err.value.value) == ("ckpt_path", str(req["hpc"]))


@pytest.mark.slow  # trains
def test_lightning_s_own_resume_under_slurm_resumes_the_checked_file(slurm_requeue, monkeypatch):
    from cicfw.model.module import CICModule

    req = slurm_requeue
    steps, step = [], CICModule.training_step
    monkeypatch.setattr(CICModule, "training_step", lambda self, *a, **k: steps.append(1) or step(self, *a, **k))
    cfg = compose_train(*SHORT, f"data.path={req['data']}", "trainer.max_epochs=2")
    train(cfg, req["run"], refuse_finished=True, claim=False)  # held as the app holds its requeued folder
    last = torch.load(req["run"] / "checkpoints" / "last.ckpt", weights_only=True)
    assert (len(steps), last["global_step"]) == (1, 2)  # one step on from the HPC checkpoint's (afresh: 2 and 2)
