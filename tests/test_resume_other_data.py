"""A run resumed on other data (``resume_on_other_data=true``): its validation errors are measured on another
split, so the best checkpoint is chosen among its own validations only (the run's value, its last line and the
run folder's checkpoint), and the model trained on both data sets: the table's training columns are the union."""
from __future__ import annotations

import logging
import shutil

import pytest
import torch

from conftest import compose_train
from test_data_provenance import SHORT, trained  # noqa: F401  (the module's trained run, as a fixture)
from test_diagnose import write_episodes
from test_trained_sets import overrides_after_training

#: an earlier best no validation on the new data can beat: kept, it would stay the run's best
UNBEATABLE = 1e-6


def _with_earlier_best(last, score: float) -> None:
    """``last``'s best checkpoint state saying its best scored ``score``, as a better earlier run would have."""
    ckpt = torch.load(last, map_location="cpu", weights_only=True)
    (state,) = [v for k, v in ckpt["callbacks"].items() if "val/steer_mae" in k]
    state["best_model_score"] = torch.tensor(score)
    state["best_k_models"] = {p: torch.tensor(score) for p in state["best_k_models"]}
    torch.save(ckpt, last)


@pytest.mark.slow
def test_a_resume_on_other_data_ranks_its_own_validations_only(trained, tmp_path, caplog):  # noqa: F811
    from cicfw.model.checkpoint import resolve_checkpoint
    from cicfw.train.app import train

    run = tmp_path / "run"
    shutil.copytree(trained["run"], run)
    earlier = [p.name for p in (run / "checkpoints").glob("epoch*-mae*.ckpt")]
    assert len(earlier) == 1
    _with_earlier_best(run / "checkpoints" / "last.ckpt", UNBEATABLE)
    other = write_episodes(tmp_path / "other", n_files=8, seed=5)
    cfg = compose_train(*SHORT, f"data.path={other}", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}",
                        "trainer.max_epochs=2", "resume_on_other_data=true")
    with caplog.at_level(logging.INFO, logger="cicfw.train"):
        value = train(cfg, run, refuse_finished=True)
    assert value > UNBEATABLE  # this segment's validation, not the earlier data's best
    new = sorted(p.name for p in (run / "checkpoints").glob("epoch*-mae*.ckpt") if p.name not in earlier)
    assert len(new) == 1 and new[0].startswith("epoch002-") and (run / "checkpoints" / earlier[0]).is_file()
    assert resolve_checkpoint(run).name == new[0]  # the run folder's best, for export and evaluate
    last = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    (state,) = [v for k, v in last["callbacks"].items() if "val/steer_mae" in k]
    assert state["best_model_path"].endswith(new[0]) and float(state["best_model_score"]) == pytest.approx(value)
    lines = [r.getMessage() for r in caplog.records]
    assert any("resuming on other data" in line and "val/steer_mae" in line for line in lines), lines
    assert f"best val/steer_mae = {value:.4f} ({new[0]})" in lines[-1], lines[-1]


@pytest.mark.slow
def test_a_same_data_resume_says_which_checkpoint_its_value_is_of(trained, tmp_path, caplog):  # noqa: F811
    from cicfw.train.app import train

    run = tmp_path / "run"
    shutil.copytree(trained["run"], run)
    (best,) = [p.name for p in (run / "checkpoints").glob("epoch*-mae*.ckpt")]
    _with_earlier_best(run / "checkpoints" / "last.ckpt", UNBEATABLE)
    cfg = compose_train(*SHORT, f"data.path={trained['data']}", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}",
                        "trainer.max_epochs=2")
    with caplog.at_level(logging.INFO, logger="cicfw.train"):
        assert train(cfg, run, refuse_finished=True) == pytest.approx(UNBEATABLE)  # the same data: one ranking
    line = [r.getMessage() for r in caplog.records][-1]
    assert f"best val/steer_mae = {UNBEATABLE:.4f} ({best})" in line and "last.ckpt" in line, line


def _record(path: str, towns: list[str], weathers: list[str]) -> dict:
    return {"path": path, "files": [], "hash": path, "collected_in": {"towns": towns, "weathers": weathers}}


def test_the_training_columns_are_the_union_over_the_data_a_resumed_run_trained_on(tmp_path, monkeypatch, caplog):
    record = {**_record("/data/b", ["town_b"], ["MidRainyNoon"]),
              "before": [_record("/data/a", ["town_a"], ["ClearNoon"])]}
    with caplog.at_level(logging.INFO, logger="cicfw.evaluate"):
        overrides = overrides_after_training(tmp_path, monkeypatch, lambda best: torch.save({"cicfw_data": record}, best))
    assert overrides == ["suite.limit=1", "suite.training_towns=[town_a,town_b]",
                         "suite.training_weathers=[ClearNoon,MidRainyNoon]"]
    named = [r.getMessage() for r in caplog.records if "training columns" in r.getMessage()]
    assert len(named) == 1 and "union over all 2 data sets" in named[0], named


def test_an_exported_model_of_a_resumed_run_keeps_the_union(tmp_path):
    """The sidecar of a model exported from a run resumed on other data records the earlier data's towns and
    weathers too: an evaluation of the exported model labels the same training columns as the checkpoint's."""
    import json

    from cicfw.benchmark.trained_sets import checkpoint_sets, earlier_data
    from cicfw.export.app import training_dataset
    from cicfw.model.checkpoint import CheckpointBytes

    record = {**_record("/data/b", ["town_b"], ["MidRainyNoon"]),
              "before": [_record("/data/a", ["town_a"], ["ClearNoon"])]}
    ckpt = tmp_path / "best.ckpt"
    torch.save({"cicfw_data": record}, ckpt)
    model = tmp_path / "model.onnx"
    model.write_bytes(b"an exported model")
    sidecar = {"training_dataset": training_dataset(CheckpointBytes.read(ckpt), None)}
    model.with_name("model.onnx.json").write_text(json.dumps(sidecar))
    assert checkpoint_sets(model) == (["town_a", "town_b"], ["ClearNoon", "MidRainyNoon"])
    assert checkpoint_sets(ckpt) == checkpoint_sets(model) and earlier_data(model) == earlier_data(ckpt) == 1
