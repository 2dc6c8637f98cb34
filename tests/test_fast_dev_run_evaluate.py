"""``cicfw train debug=fast evaluate_after=true``: a fast_dev_run trains one batch and saves no checkpoint,
so the evaluation after it saves the final weights as ``checkpoints/final.ckpt`` and says so, then drives a
short suite (the first pair of each town), not the whole 480 episodes, unless evaluate_overrides size it."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from types import SimpleNamespace

import pytest
from omegaconf import OmegaConf

import cicfw.benchmark.app as evaluate

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")


def _after_training(tmp_path: Path, monkeypatch, overrides: list[str], fast_dev_run) -> dict:
    """evaluate_after_training with a stand-in trainer and evaluation; returns what it drove (``path``,
    ``overrides``) and the resume hint it gave."""
    seen = {}

    def drive(path, out, overrides, resume_hint=None, claim=True):
        seen.update(path=path, overrides=list(overrides), hint=resume_hint, claim=claim)
        return {"success": 50.0, "cells": {}}

    monkeypatch.setattr(evaluate, "evaluate_checkpoint", drive)
    saved = []
    trainer = SimpleNamespace(checkpoint_callbacks=[], fast_dev_run=fast_dev_run, logger=None, global_step=1,
                              save_checkpoint=saved.append)
    evaluate.evaluate_after_training(OmegaConf.create({"evaluate_overrides": overrides}), trainer, tmp_path)
    assert saved == [str(tmp_path / "checkpoints" / "final.ckpt")] == [seen["path"]]
    assert seen["claim"] is False  # <run>/evaluate lies in the training run's folder, which the run holds
    return seen


def test_a_fast_dev_run_drives_a_short_suite_and_says_what_it_wrote(tmp_path, monkeypatch, caplog):
    with caplog.at_level(logging.INFO, logger="cicfw.evaluate"):
        got = _after_training(tmp_path, monkeypatch, ["suite.towns=[town_a]"], True)
    assert got["overrides"] == ["suite.towns=[town_a]", "suite.limit=1"]
    assert "'suite.towns=[town_a]' suite.limit=1 hydra.run.dir=" in got["hint"]  # a resume drives the same episodes
    said = [r.getMessage() for r in caplog.records if r.name == "cicfw.evaluate"]
    final = tmp_path / "checkpoints" / "final.ckpt"
    assert said[0] == (f"training wrote no checkpoint (trainer.fast_dev_run saves none): wrote its final weights "
                       f"to {final} for the closed-loop evaluation"), said
    assert said[1].startswith(f"closed-loop evaluation of {final}: a short suite after trainer.fast_dev_run "
                              f"(suite.limit=1: the first pair of each town;"), said


@pytest.mark.parametrize("given", ["suite.limit=3", "suite.pairs=[0,5]", "suite.limit=null"])
def test_a_suite_size_given_in_evaluate_overrides_is_driven_as_given(given, tmp_path, monkeypatch):
    assert _after_training(tmp_path, monkeypatch, [given], 1)["overrides"] == [given]


def test_a_real_training_drives_the_whole_suite_it_is_given(tmp_path, monkeypatch):
    got = _after_training(tmp_path, monkeypatch, ["suite.towns=[town_a]"], False)
    assert got["overrides"] == ["suite.towns=[town_a]"]


@pytest.mark.slow  # trains one batch and drives the suite
def test_debug_fast_with_evaluate_after_drives_the_first_pair(tiny_data: Path, tmp_path: Path):
    from cicfw.train.app import train
    from conftest import compose_train

    # 36 pairs in this town: the whole suite would drive 36 episodes. The untrained model's episode, short: 6 m
    # before its turn, ended 2 m off its route
    overrides = [f"suite.towns=[{TOWN}]", "suite.weathers=[MidRainyNoon]", "progress_bar=false", "maps=false",
                 "runner.threads=1", "sim.route_before=6", "sim.max_deviation=2"]
    cfg = compose_train("data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "data.val_batch_size=8",
                        "debug=fast", "progress_bar=false", "evaluate_after=true",
                        f"evaluate_overrides=[{','.join(repr(o) for o in overrides)}]")
    train(cfg, tmp_path / "run")
    s = json.loads((tmp_path / "run" / "evaluate" / "summary.json").read_text())
    assert s["episodes"] == 1 and s["complete"] is True
    assert Path(s["checkpoint"]) == tmp_path / "run" / "checkpoints" / "final.ckpt"


@pytest.mark.slow  # trains one step and drives one episode
def test_a_training_without_validation_drives_its_last_checkpoint_without_a_copy(tiny_data: Path, tmp_path: Path):
    from cicfw.train.app import train
    from conftest import compose_train

    overrides = [f"suite.towns=[{TOWN}]", "suite.weathers=[MidRainyNoon]", "suite.limit=1", "maps=false",
                 "runner.threads=1", "sim.route_before=6", "sim.max_deviation=2"]  # a short episode
    cfg = compose_train("data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "progress_bar=false",
                        "trainer.max_steps=1", "trainer.limit_val_batches=0", "evaluate_after=true",
                        f"evaluate_overrides=[{','.join(repr(o) for o in overrides)}]")
    train(cfg, tmp_path / "run")
    checkpoints = tmp_path / "run" / "checkpoints"
    assert sorted(p.name for p in checkpoints.iterdir()) == ["last.ckpt"]  # no final.ckpt beside it
    s = json.loads((tmp_path / "run" / "evaluate" / "summary.json").read_text())
    assert Path(s["checkpoint"]) == checkpoints / "last.ckpt"


@pytest.mark.slow  # trains one step
def test_a_ddp_worker_rank_leaves_the_evaluation_after_training_to_rank_0(tiny_data, tmp_path, monkeypatch):
    import cicfw.train.app as train_app
    from conftest import compose_train

    drove = []
    monkeypatch.setattr(train_app, "evaluate_after_training", lambda *a: drove.append(a) or {"success": 0.0})
    monkeypatch.setenv("LOCAL_RANK", "1")  # what Lightning sets in the rank it re-runs the app as
    cfg = compose_train("data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "progress_bar=false",
                        "trainer.max_steps=1", "trainer.limit_val_batches=0", "evaluate_after=true")
    train_app.train(cfg, tmp_path / "run")
    assert drove == []
