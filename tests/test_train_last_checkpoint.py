"""``checkpoints/last.ckpt`` is always the latest epoch, whatever the validation error
does. With ``ModelCheckpoint(monitor=..., save_last=True)`` Lightning refreshes ``last.ckpt`` only when
a best-so-far checkpoint is saved, so after a run whose validation error rises at the end it held an
older epoch: evaluating it, or resuming from it, silently used an older model."""
from __future__ import annotations

import lightning as L
import pytest
import torch

import cicfw.train.app as train_mod
from cicfw.train.app import load_checkpoint_safely, train
from conftest import compose_train, write_tiny_dataset

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

# validation error per epoch: best after epoch 2, then it rises to the end
VAL_ERRORS = [0.50, 0.30, 0.40, 0.60]


class RisingValError(L.Callback):
    """Replaces the monitored metric by ``VAL_ERRORS[epoch]`` before the checkpoint callbacks read it
    (Lightning runs checkpoint callbacks after the others)."""

    def on_validation_end(self, trainer, pl_module):
        if not trainer.sanity_checking:
            trainer.callback_metrics["val/steer_mae"] = torch.tensor(VAL_ERRORS[min(trainer.current_epoch, len(VAL_ERRORS) - 1)])


def _cfg(tmp_path, *extra):
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    return compose_train("data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "data.val_batch_size=8",
                         "progress_bar=false", "speed.compile=false",
                         f"trainer.max_epochs={len(VAL_ERRORS)}", "trainer.limit_train_batches=1",
                         "trainer.limit_val_batches=1", "trainer.num_sanity_val_steps=0",
                         "trainer.enable_model_summary=false", *extra)


def test_last_ckpt_is_the_latest_epoch_when_the_validation_error_rises_at_the_end(tmp_path, monkeypatch):
    build = train_mod.build_callbacks
    monkeypatch.setattr(train_mod, "build_callbacks", lambda cfg, run_dir: [*build(cfg, run_dir), RisingValError()])
    run = tmp_path / "run"
    best = train(_cfg(tmp_path), run)
    assert abs(best - 0.30) < 1e-6  # the best checkpoint is still the best epoch's
    ckpts = run / "checkpoints"
    last = load_checkpoint_safely(ckpts / "last.ckpt")
    assert last["epoch"] == len(VAL_ERRORS) - 1, f"last.ckpt holds epoch {last['epoch'] + 1} of {len(VAL_ERRORS)}"
    assert last["global_step"] == len(VAL_ERRORS)  # one batch an epoch
    best_files = [p.name for p in ckpts.glob("epoch*-mae*.ckpt")]
    assert best_files == ["epoch002-mae0.3000.ckpt"], best_files  # the second epoch, counted as the kept ones are
    assert load_checkpoint_safely(ckpts / best_files[0])["epoch"] == 1  # Lightning's 0-based index


def test_resuming_from_last_ckpt_does_not_retrain_finished_epochs(tmp_path, monkeypatch):
    build = train_mod.build_callbacks
    monkeypatch.setattr(train_mod, "build_callbacks", lambda cfg, run_dir: [*build(cfg, run_dir), RisingValError()])
    run = tmp_path / "run"
    train(_cfg(tmp_path), run)
    steps = []

    class CountSteps(L.Callback):
        def on_train_batch_end(self, trainer, *args):
            steps.append(trainer.global_step)

    monkeypatch.setattr(train_mod, "build_callbacks",
                        lambda cfg, run_dir: [*build(cfg, run_dir), RisingValError(), CountSteps()])
    train(_cfg(tmp_path, f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}",
               f"trainer.max_epochs={len(VAL_ERRORS) + 1}"), tmp_path / "resumed")
    assert steps == [len(VAL_ERRORS) + 1]  # only the new epoch is trained
