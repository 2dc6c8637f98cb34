"""The state a run depends on is recorded where it is used: last.ckpt holds the last epoch trained
whatever the validation schedule; a resume that cannot honour a changed optimizer value, or has
nothing left to train, is refused; the evaluation after training drives this run's checkpoint only;
the run's last line says what was written."""
from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pytest
import torch

from cicfw.train.app import build_model, check_resume_checkpoint, load_checkpoint_safely, train, train_in_folder
from conftest import compose_train, write_tiny_dataset

BASE = ("data=cil_hdf5", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false", "speed.compile=false",
        "trainer.limit_train_batches=1", "trainer.limit_val_batches=1", "trainer.num_sanity_val_steps=0",
        "trainer.enable_model_summary=false")


def _cfg(data: Path, *overrides: str):
    return compose_train(*BASE, f"data.path={data}", *overrides)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, Path]:
    """Three epochs, validated every second one: (the run folder, the data)."""
    root = tmp_path_factory.mktemp("state")
    data = write_tiny_dataset(root / "data", n_files=4, n=16)
    train(_cfg(data, "trainer.max_epochs=3", "trainer.check_val_every_n_epoch=2"), root / "run")
    return root / "run", data


def test_last_ckpt_is_the_last_epoch_trained_when_validation_skips_it(run):
    last = load_checkpoint_safely(run[0] / "checkpoints" / "last.ckpt")
    assert last["epoch"] == 2 and last["global_step"] == 3, (last["epoch"], last["global_step"])


def test_resuming_with_another_optimizer_value_is_refused_naming_each_key(run, no_data, tmp_path):
    last = run[0] / "checkpoints" / "last.ckpt"
    cfg = _cfg(run[1], "trainer.max_epochs=4", f"ckpt_path={last}", "model.lr=0.01", "model.betas=[0.9,0.999]")
    with pytest.raises(ValueError) as err:
        train(cfg, tmp_path / "resumed")
    text = str(err.value)
    assert (err.value.key, str(err.value.value)) == ("ckpt_path", str(last)), text
    assert "model.lr=0.01" in text and "0.0002" in text and "model.betas=[0.9, 0.999]" in text  # each key, both values
    assert "model.weight_decay" not in text


def test_resuming_a_checkpoint_with_nothing_left_to_train_is_refused(run, no_data, tmp_path):
    last = run[0] / "checkpoints" / "last.ckpt"
    for limit in ("trainer.max_epochs=3", "trainer.max_epochs=2"):
        with pytest.raises(ValueError) as err:
            train_in_folder(_cfg(run[1], limit, f"ckpt_path={last}"), tmp_path / "resumed")
        key, value = limit.split("=")
        assert (err.value.key, err.value.value) == (key, int(value)), str(err.value)
        assert f"ckpt_path={last}" in str(err.value), str(err.value)
    with pytest.raises(ValueError) as err:
        train_in_folder(_cfg(run[1], "trainer.max_epochs=9", "trainer.max_steps=3", f"ckpt_path={last}"),
                        tmp_path / "r")
    assert (err.value.key, err.value.value) == ("trainer.max_steps", 3)


def test_resuming_with_nothing_left_says_so_where_it_is_not_refused(run, tmp_path, caplog):
    last = run[0] / "checkpoints" / "last.ckpt"
    with caplog.at_level(logging.INFO, logger="cicfw.train"):
        value = train(_cfg(run[1], "trainer.max_epochs=3", f"ckpt_path={last}"), tmp_path / "resumed")
    line = [r.getMessage() for r in caplog.records if r.name == "cicfw.train"][-1]
    assert value != value and line == "val/steer_mae: no value (no validation ran); no checkpoint written", line


def test_a_diverged_run_says_so_rather_than_that_no_validation_ran(tmp_path, caplog):
    """A validation whose steering is NaN is a diverged model, not a missing validation."""
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    with caplog.at_level(logging.INFO, logger="cicfw.train"):
        value = train(_cfg(data, "trainer.max_epochs=1", "trainer.limit_train_batches=2", "model.lr=1e30"),
                      tmp_path / "run")
    line = [r.getMessage() for r in caplog.records if r.name == "cicfw.train"][-1]
    assert value in (float("inf"), float("nan")) or value != value, value
    assert "diverged" in line and "no validation ran" not in line, line


def test_a_run_folder_moved_and_resumed_there_keeps_one_best_checkpoint(tmp_path):
    """Lightning forgets the best seen so far when the run folder's path changed: a moved run resumed there
    saved a second best checkpoint and reported the later epoch's value as the run's."""
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    train(_cfg(data, "trainer.max_epochs=1"), tmp_path / "before")
    shutil.copytree(tmp_path / "before", tmp_path / "moved")
    last = tmp_path / "moved" / "checkpoints" / "last.ckpt"
    value = train(_cfg(data, "trainer.max_epochs=2", f"ckpt_path={last}"), tmp_path / "moved")
    best = sorted(p.name for p in last.parent.glob("epoch*-mae*.ckpt"))
    assert len(best) == 1 and best[0].endswith(f"mae{value:.4f}.ckpt"), (best, value)


def test_a_resume_with_the_checkpoints_values_and_epochs_left_passes(run):
    last = run[0] / "checkpoints" / "last.ckpt"
    cfg = _cfg(run[1], "trainer.max_epochs=4", f"ckpt_path={last}")
    assert check_resume_checkpoint(cfg.ckpt_path, build_model(cfg), cfg.trainer) == str(last)


def test_the_last_line_says_no_checkpoint_was_written_by_a_fast_dev_run(tmp_path, caplog):
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    with caplog.at_level(logging.INFO, logger="cicfw.train"):
        train(_cfg(data, "debug=fast"), tmp_path / "run")
    line = [r.getMessage() for r in caplog.records if r.name == "cicfw.train"][-1]
    assert line.endswith("; no checkpoint written (trainer.fast_dev_run saves none)"), line
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_the_last_line_names_the_checkpoints_written(run, caplog, tmp_path):
    with caplog.at_level(logging.INFO, logger="cicfw.train"):
        train(_cfg(run[1], "trainer.max_epochs=1"), tmp_path / "run")
    line = [r.getMessage() for r in caplog.records if r.name == "cicfw.train"][-1]
    assert f"; checkpoints written in {tmp_path / 'run' / 'checkpoints'}: " in line and "last.ckpt" in line, line


# ---- the evaluation after training --------------------------------------------------------------


@pytest.mark.parametrize("override, message", [
    ("checkpoint=other.ckpt", "evaluate_overrides: checkpoint=other.ckpt cannot be given: it drives this run's best"),
    ("+checkpoint=other.ckpt", "evaluate_overrides: +checkpoint=other.ckpt cannot be given: it drives this run's"),
    ("policy.checkpoint=other.ckpt", "evaluate_overrides: policy.checkpoint=other.ckpt cannot be given: it drives"),
    ("policy=expert", "evaluate_overrides: policy=expert cannot be given: it drives this run's checkpoint"),
    ("hydra.run.dir=elsewhere", "evaluate_overrides: hydra.run.dir=elsewhere cannot be given: it writes into the"),
    ("hydra/launcher=joblib", "evaluate_overrides: hydra/launcher=joblib cannot be given: it writes into the"),
])
def test_evaluate_overrides_that_would_drive_something_else_or_be_ignored_are_refused(tmp_path, no_data, override,
                                                                                       message):
    cfg = _cfg(tmp_path / "data", "evaluate_after=true", f"evaluate_overrides=[{override!r}]")
    with pytest.raises(ValueError) as err:
        train(cfg, tmp_path / "run")
    assert str(err.value).startswith(message), str(err.value)


def test_a_cuda_device_on_a_machine_without_one_is_refused_before_training(tmp_path, no_data, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = _cfg(tmp_path / "data", "evaluate_after=true", "evaluate_overrides=['policy.device=cuda']")
    with pytest.raises(ValueError) as err:
        train(cfg, tmp_path / "run")
    assert str(err.value).startswith("evaluate_overrides: policy.device='cuda' needs a CUDA GPU"), str(err.value)


def test_the_last_line_says_what_evaluate_after_will_save_after_a_fast_dev_run(tmp_path):
    """With evaluate_after, "no checkpoint written" is followed by what the evaluation writes and drives."""
    from types import SimpleNamespace

    from cicfw.train.app import outcome

    trainer = SimpleNamespace(fast_dev_run=True, checkpoint_callbacks=[])
    line = outcome("val/steer_mae", None, tmp_path, {}, trainer, evaluate_after=True)
    assert "no checkpoint written" in line and line.endswith("checkpoints/final.ckpt and drives them"), line
    assert "final.ckpt" not in outcome("val/steer_mae", None, tmp_path, {}, trainer)


def test_the_last_line_promises_no_final_ckpt_when_an_earlier_last_ckpt_is_driven(tmp_path):
    """A resumed run that trained no further wrote no checkpoint, yet evaluate_after drives its last.ckpt."""
    from types import SimpleNamespace

    from cicfw.train.app import checkpoint_files, outcome

    last = tmp_path / "checkpoints" / "last.ckpt"
    last.parent.mkdir()
    last.write_bytes(b"weights")
    trainer = SimpleNamespace(fast_dev_run=False,
                              checkpoint_callbacks=[SimpleNamespace(best_model_path=str(last), last_model_path="")])
    line = outcome("val/steer_mae", None, tmp_path, checkpoint_files(tmp_path), trainer, evaluate_after=True)
    assert "no checkpoint written" in line and "final.ckpt" not in line, line
