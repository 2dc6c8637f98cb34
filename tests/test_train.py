"""Training end to end: fast_dev_run, branch selection, checkpoints, seeding, resume, bad input."""
from __future__ import annotations

import pytest
import torch
from hydra.errors import MissingConfigException

from cicfw.model.module import CICModule
from cicfw.registry import UnknownNameError
from cicfw.train.app import build_model, train
from conftest import assert_refused, compose_train, run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)


def _batch(n=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {
        "image": torch.randint(0, 256, (n, 3, 88, 200), dtype=torch.uint8, generator=g),
        "speed": torch.rand(n, generator=g) * 30,
        "command": torch.arange(n) % 4,
        "steer": torch.rand(n, generator=g) - 0.5,
    }


def test_fast_dev_run_trains(fast_cfg, tmp_path):
    mae = train(fast_cfg, tmp_path / "run")
    assert 0.0 <= mae < 2.0  # one validation batch ran and produced a steering error


def test_loss_of_a_sample_reaches_only_its_branch():
    model = CICModule(mixer_kwargs={"dropout": 0.0})
    b = _batch(4)
    b["command"] = torch.tensor([2, 2, 2, 2])  # every sample says "right"
    model.zero_grad()
    model.head.loss(model(b["image"], b["speed"], b["command"]), b["steer"]).backward()
    for i, branch in enumerate(model.mixer.branches):
        grads = [p.grad for p in branch.parameters()]
        touched = any(g is not None and g.abs().sum() > 0 for g in grads)
        assert touched == (i == 2), f"branch {i} touched={touched}"
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.encoder.parameters())


def test_checkpoint_round_trip_gives_identical_outputs(tmp_path):
    import lightning as L

    model = CICModule(mixer_kwargs={"hidden": 64})
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, max_epochs=0)
    trainer.strategy.connect(model)
    path = tmp_path / "m.ckpt"
    trainer.save_checkpoint(path)
    loaded = CICModule.load_from_checkpoint(path, weights_only=True)
    model.eval(), loaded.eval()
    b = _batch()
    assert torch.equal(model(b["image"], b["speed"], b["command"]), loaded(b["image"], b["speed"], b["command"]))
    assert loaded.hparams.mixer_kwargs == {"hidden": 64}


def _first_epoch_loss(tiny_data, tmp_path, name):
    cfg = compose_train("data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8",
                        "data.batches_per_epoch=3", "trainer.max_epochs=1", "progress_bar=false",
                        "+trainer.limit_val_batches=0", "trainer.log_every_n_steps=1", "seed=7")
    train(cfg, tmp_path / name)
    import csv

    rows = list(csv.DictReader(open(tmp_path / name / "csv" / "metrics.csv")))
    return [r["train/loss"] for r in rows if r.get("train/loss")]


def test_seed_gives_the_same_first_epoch_losses(tiny_data, tmp_path):
    a = _first_epoch_loss(tiny_data, tmp_path, "a")
    b = _first_epoch_loss(tiny_data, tmp_path, "b")
    assert a and a == b


def test_resume_from_last_checkpoint(tiny_data, tmp_path):
    base = ["data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "data.batches_per_epoch=2",
            "data.val_batch_size=16", "progress_bar=false"]
    train(compose_train(*base, "trainer.max_epochs=1", "keep_epoch_checkpoints=[1]"), tmp_path / "r")
    last = tmp_path / "r" / "checkpoints" / "last.ckpt"
    assert last.exists()
    # the best after the first epoch is named as the kept first epoch is: both count whole epochs from 1
    best = [p for p in last.parent.glob("epoch*-mae*.ckpt")]
    assert [p.name[:8] for p in best] == ["epoch001"], best
    kept = torch.load(last.parent / "epoch001.ckpt", weights_only=True)
    assert torch.load(best[0], weights_only=True)["global_step"] == kept["global_step"] == 2
    train(compose_train(*base, "trainer.max_epochs=2", f"ckpt_path={last}"), tmp_path / "r2")
    assert torch.load(tmp_path / "r2" / "checkpoints" / "last.ckpt", weights_only=True)["epoch"] == 1


def test_unknown_registry_name_lists_known(fast_cfg):
    fast_cfg.mixer.name = "gtuu"
    with pytest.raises(UnknownNameError) as err:
        build_model(fast_cfg)
    assert err.value.value == "gtuu" and "independent" in str(err.value)  # the name, and one registered


def test_unknown_group_option_lists_options():
    with pytest.raises(MissingConfigException) as err:
        compose_train("mixer=gtuu")
    assert "independent" in str(err.value)


def test_bad_hyperparameter_fails_at_construction(fast_cfg):
    fast_cfg.model.lr = -1.0
    with pytest.raises(ValueError) as err:
        build_model(fast_cfg)
    assert (err.value.key, err.value.value) == ("model.lr", -1.0)


def test_cli_reports_bad_path_in_one_line(tmp_path):
    r = run_app_in_process("cicfw.train", "data=cil_hdf5", f"data.path={tmp_path}/missing/*.h5",
                           f"hydra.run.dir={tmp_path}/out", env={"HYDRA_FULL_ERROR": "0"})
    assert_refused(r, "data.path", f"{tmp_path}/missing/*.h5")


def test_cli_refuses_a_trainer_value_of_the_wrong_type_in_one_line_before_the_data(tmp_path):
    """``trainer.max_epochs=abc`` passed the trainer's checks, waited for the data (collecting the default
    dataset first) and then ended in a TypeError traceback from the speed settings."""
    r = run_app_in_process("cicfw.train", "data=cil_hdf5", f"data.path={tmp_path}/missing", "progress_bar=false",
                           "trainer.max_epochs=abc", f"hydra.run.dir={tmp_path}/out", env={"HYDRA_FULL_ERROR": "0"})
    assert_refused(r, "trainer.max_epochs", "abc")
    assert not (tmp_path / "out").exists()  # refused while composing: no run folder
