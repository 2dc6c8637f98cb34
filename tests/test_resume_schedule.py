"""A resumed run under a cosine schedule or a warm-up keeps the run length its schedule was spread over: other
epochs or batches would recompute the schedule mid-run (the rate rising again after it had decayed), so they
are refused before any data is read; a constant rate trains on for as long as asked."""
from __future__ import annotations

import shutil

import pytest
import torch

from cicfw.core.errors import CicfwError
from cicfw.train.app import build_model, check_resume_checkpoint, train
from cicfw.train.schedule_record import SCHEDULE_KEY, horizon_settings
from conftest import TINY_TRAIN, compose_train, train_tiny_run

SHORT = [*TINY_TRAIN, "trainer.limit_train_batches=2", "model.lr_schedule=cosine"]


@pytest.fixture(scope="module")
def cosine_run(tmp_path_factory) -> dict:
    """A one-epoch cosine run with its saved config, as the app leaves it."""
    return train_tiny_run(tmp_path_factory.mktemp("cosine"), *SHORT)


@pytest.mark.slow  # trains
def test_resuming_a_cosine_run_for_more_epochs_is_refused_before_anything_is_written(cosine_run, tmp_path):
    assert torch.load(cosine_run["last"], weights_only=True)[SCHEDULE_KEY]["trainer.max_epochs"] == 1
    cfg = compose_train(*SHORT, f"data.path={cosine_run['data']}", f"ckpt_path={cosine_run['last']}",
                        "trainer.max_epochs=2")
    with pytest.raises(CicfwError) as err:
        train(cfg, tmp_path / "run", refuse_finished=True)
    assert (err.value.key, err.value.value) == ("trainer.max_epochs", 2)
    assert not (tmp_path / "run").exists()


@pytest.mark.slow  # trains
@pytest.mark.parametrize("override, key, value", [("trainer.limit_train_batches=3", "trainer.limit_train_batches", 3),
                                                 ("data.batch_size=12", "data.batch_size", 12),
                                                 ("trainer.max_steps=5", "trainer.max_steps", 5)])
def test_other_batches_per_run_are_refused(cosine_run, override, key, value):
    cfg = compose_train(*SHORT, f"data.path={cosine_run['data']}", override)
    with pytest.raises(CicfwError) as err:
        check_resume_checkpoint(cosine_run["last"], build_model(cfg), horizon=horizon_settings(cfg))
    assert (err.value.key, err.value.value) == (key, value)


@pytest.mark.slow  # trains
def test_the_same_run_length_resumes(cosine_run):
    cfg = compose_train(*SHORT, f"data.path={cosine_run['data']}")
    assert check_resume_checkpoint(cosine_run["last"], build_model(cfg), horizon=horizon_settings(cfg))


@pytest.mark.slow  # trains
def test_an_older_checkpoint_s_run_length_is_read_from_its_run_config(cosine_run, tmp_path):
    run = tmp_path / "older"
    shutil.copytree(cosine_run["run"], run)
    last = run / "checkpoints" / "last.ckpt"
    ckpt = torch.load(last, weights_only=True)
    del ckpt[SCHEDULE_KEY]
    torch.save(ckpt, last)
    cfg = compose_train(*SHORT, f"data.path={cosine_run['data']}", "trainer.max_epochs=3")
    with pytest.raises(CicfwError) as err:
        check_resume_checkpoint(last, build_model(cfg), horizon=horizon_settings(cfg))
    assert (err.value.key, err.value.value) == ("trainer.max_epochs", 3)


def test_a_constant_rate_may_train_on_and_a_warm_up_may_not():
    from cicfw.train.schedule_record import check_resumed_horizon

    saved = {SCHEDULE_KEY: horizon_settings(compose_train("trainer.max_epochs=2"))}
    longer = horizon_settings(compose_train("trainer.max_epochs=4"))
    check_resumed_horizon("last.ckpt", saved, {"lr_schedule": "constant", "lr_warmup_fraction": 0.0}, longer)
    with pytest.raises(CicfwError) as err:
        check_resumed_horizon("last.ckpt", saved, {"lr_schedule": "constant", "lr_warmup_fraction": 0.1}, longer)
    assert (err.value.key, err.value.value) == ("trainer.max_epochs", 4)
