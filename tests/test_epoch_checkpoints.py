"""``keep_epoch_checkpoints`` keeps the weights after whole epochs: an epoch that ``trainer.max_steps`` stops
inside writes no ``epochNNN.ckpt``, which would otherwise hold part of an epoch under that epoch's name."""
from __future__ import annotations

import pytest
import torch

from cicfw.train.app import train
from conftest import compose_train, write_tiny_dataset


@pytest.mark.slow  # trains
def test_an_epoch_cut_short_by_max_steps_keeps_no_checkpoint(tmp_path):
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=32)
    cfg = compose_train("data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "data.val_batch_size=8",
                        "progress_bar=false", "speed.compile=false", "trainer.max_epochs=2",
                        "trainer.limit_train_batches=3", "trainer.limit_val_batches=1", "trainer.max_steps=4",
                        "trainer.num_sanity_val_steps=0", "trainer.enable_model_summary=false",
                        "keep_epoch_checkpoints=[1,2]")
    train(cfg, tmp_path / "run")
    ckpts = tmp_path / "run" / "checkpoints"
    assert torch.load(ckpts / "epoch001.ckpt", weights_only=True)["global_step"] == 3  # a whole epoch
    assert not (ckpts / "epoch002.ckpt").exists()  # 1 of its 3 batches


@pytest.mark.slow  # trains
def test_an_epoch_checkpoint_records_its_own_epoch_s_validation(tmp_path):
    """``epochNNN.ckpt`` is written after that epoch's best checkpoint is chosen, so a run resumed from it
    (a reproduce cell killed later) still knows that epoch's validation error and its best file."""
    import csv
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=32)
    cfg = compose_train("data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "data.val_batch_size=8",
                        "progress_bar=false", "speed.compile=false", "trainer.max_epochs=2",
                        "trainer.limit_train_batches=2", "trainer.limit_val_batches=1",
                        "trainer.num_sanity_val_steps=0", "trainer.enable_model_summary=false",
                        "keep_epoch_checkpoints=[1,2]")
    train(cfg, tmp_path / "run")
    rows = list(csv.DictReader((tmp_path / "run" / "csv" / "metrics.csv").open()))
    val = [float(r["val/steer_mae"]) for r in rows if r.get("val/steer_mae")]  # per epoch, as logged
    for epoch in (1, 2):
        ckpt = torch.load(tmp_path / "run" / "checkpoints" / f"epoch{epoch:03d}.ckpt", weights_only=False)
        best = next(s for k, s in ckpt["callbacks"].items() if "val/steer_mae" in k)
        assert float(best["best_model_score"]) == pytest.approx(min(val[:epoch]), abs=1e-7), (epoch, val)
