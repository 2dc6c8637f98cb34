"""The evaluation after training labels the table's "training" columns with the towns and weathers the run's data
was collected in, not the defaults: a model trained in town_b under CloudyNoon is not tested "in its training
town under its training weathers" when it drives town_a under ClearNoon."""
from __future__ import annotations

import json
from types import SimpleNamespace

from omegaconf import OmegaConf

import cicfw.benchmark.app as bench_app
from cicfw.benchmark.trained_sets import training_set_overrides
from conftest import compose_train


def _collected(towns, weathers):
    return OmegaConf.create({"path": "/nowhere", "collect": {"towns": towns, "weathers": weathers}})


def test_the_data_s_towns_and_weathers_become_the_training_sets():
    assert training_set_overrides(_collected(["town_b"], ["ClearNoon", "CloudyNoon"]), []) == [
        "suite.training_towns=[town_b]", "suite.training_weathers=[ClearNoon]"]  # CloudyNoon is not driven
    assert training_set_overrides(_collected(["town_b"], ["CloudyNoon"]), ["suite.weathers=[CloudyNoon]"]) == [
        "suite.training_towns=[town_b]", "suite.training_weathers=[CloudyNoon]"]


def test_the_default_data_keeps_the_default_columns():
    assert training_set_overrides(compose_train().data, []) == [
        "suite.training_towns=[town_a]", "suite.training_weathers=[ClearNoon,ClearSunset]"]


def test_what_the_user_gives_wins_and_other_simulators_are_left_alone():
    data = _collected(["town_b"], ["CloudyNoon"])
    assert training_set_overrides(data, ["suite.training_towns=[town_a]"]) == ["suite.training_weathers=[]"]
    assert training_set_overrides(data, ["sim=carla"]) == []


def test_a_collected_folder_s_metadata_says_it_and_other_data_says_nothing(tmp_path):
    data = OmegaConf.create({"path": str(tmp_path)})
    assert training_set_overrides(data, []) == []
    (tmp_path / "dataset_metadata.json").write_text(json.dumps({"towns": ["town_b"], "weathers": ["MidRainyNoon"]}))
    assert training_set_overrides(data, []) == ["suite.training_towns=[town_b]",
                                                "suite.training_weathers=[MidRainyNoon]"]


def overrides_after_training(tmp_path, monkeypatch, write_best) -> list[str]:
    """The overrides ``evaluate_after_training`` gives the suite (the evaluation itself stood in for) for a run
    whose best checkpoint ``write_best(path)`` writes, its config's data collected in town_b under MidRainyNoon."""
    seen = {}

    def evaluate_checkpoint(path, out, overrides, resume_hint, claim=True):
        seen["overrides"] = list(overrides)
        return {"success": 50.0, "cells": {}}

    monkeypatch.setattr(bench_app, "evaluate_checkpoint", evaluate_checkpoint)
    best = tmp_path / "checkpoints" / "best.ckpt"
    best.parent.mkdir()
    write_best(best)
    trainer = SimpleNamespace(checkpoint_callbacks=[SimpleNamespace(best_model_path=str(best), last_model_path="")],
                              fast_dev_run=False, logger=None, global_step=1)
    cfg = compose_train("++data.collect.towns=[town_b]", "++data.collect.weathers=[MidRainyNoon]",
                        "evaluate_overrides=['suite.limit=1']")
    bench_app.evaluate_after_training(cfg, trainer, tmp_path)
    return seen["overrides"]


def test_the_evaluation_after_training_drives_with_them(tmp_path, monkeypatch):
    overrides = overrides_after_training(tmp_path, monkeypatch, lambda best: best.write_bytes(b"weights"))
    assert overrides == ["suite.limit=1", "suite.training_towns=[town_b]", "suite.training_weathers=[MidRainyNoon]"]


def _run_with_checkpoint(tmp_path, towns, weathers):
    """A run folder as train leaves it: .hydra/config.yaml naming the data's collection, data.json the
    data's absolute path, and a two-step checkpoint in checkpoints/."""
    import lightning as L
    import torch
    from torch.utils.data import DataLoader, TensorDataset

    from cicfw.model.module import CICModule

    class Frames(TensorDataset):
        def __getitem__(self, i):
            return {"image": torch.full((3, 88, 200), i * 20, dtype=torch.uint8), "speed": torch.tensor(10.0),
                    "command": torch.tensor(i % 4), "steer": torch.tensor(0.0)}

    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save({"data": {"path": "relative/data", "collect": {"towns": towns, "weathers": weathers}}},
                   run / ".hydra" / "config.yaml")
    (run / "data.json").write_text(json.dumps({"path": str(tmp_path / "data")}))
    L.seed_everything(0)
    trainer = L.Trainer(max_steps=1, limit_val_batches=0, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, accelerator="cpu")
    trainer.fit(CICModule(), DataLoader(Frames(torch.zeros(4)), batch_size=4))
    ckpt = run / "checkpoints" / "last.ckpt"
    trainer.save_checkpoint(ckpt)
    return ckpt


def test_a_checkpoint_s_evaluation_labels_the_columns_with_its_run_s_data(tmp_path):
    """``cicfw evaluate checkpoint=<run>/checkpoints/last.ckpt``: a model trained in town_b is driven there
    under its "training town" columns, unless the command names the training towns itself. Short episodes
    (6 m before the turn, 2 m off the route): the columns do not depend on how far they drive."""
    from conftest import run_app_in_process

    ckpt = _run_with_checkpoint(tmp_path, ["town_b"], ["ClearNoon"])
    common = [f"checkpoint={ckpt}", "suite.towns=[town_b]", "suite.weathers=[ClearNoon]", "suite.limit=1",
              "progress_bar=false", "maps=false", "runner.threads=1", "sim.route_before=6", "sim.max_deviation=2"]
    for given, town_set in (([], "training"), (["suite.training_towns=[town_a]"], "new")):
        out = tmp_path / f"eval_{town_set}"
        res = run_app_in_process("cicfw.evaluate", *common, *given, f"hydra.run.dir={out}")
        assert res.returncode == 0, res.stderr[-2000:]
        rows = json.loads((out / "episodes.json").read_text())["episodes"]
        assert rows and {r["town_set"] for r in rows} == {town_set}
        assert {r["weather_set"] for r in rows} == {"training"}


def test_a_checkpoints_data_path_is_the_one_its_run_recorded(tmp_path, tiny_data):
    """The saved config's data.path as typed (relative to where the run started) is replaced by the absolute
    path the run recorded in its data.json."""
    from omegaconf import OmegaConf

    from cicfw.benchmark.trained_sets import checkpoint_run_data
    from cicfw.data.provenance import record_data, write_record

    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save(OmegaConf.create({"data": {"path": "data"}}), run / ".hydra" / "config.yaml")
    write_record(run, record_data(tiny_data))
    assert checkpoint_run_data(run / "checkpoints" / "last.ckpt").path == str(tiny_data.resolve())


def _collected_in_town_b(tmp_path):
    data = tmp_path / "data_b"
    data.mkdir()
    (data / "dataset_metadata.json").write_text(json.dumps({"towns": ["town_b"], "weathers": ["MidRainyNoon"]}))
    return {"path": str(data), "files": []}


def test_a_run_that_saved_no_config_still_names_its_data(tmp_path):
    """A run with ``hydra.output_subdir=null`` keeps no .hydra/config.yaml, but its data.json names the data
    folder, whose metadata says where it was collected: a model trained in town_b is not labelled as driving
    a new town there."""
    from cicfw.benchmark.trained_sets import checkpoint_run_data

    run = tmp_path / "run"
    run.mkdir()
    (run / "data.json").write_text(json.dumps(_collected_in_town_b(tmp_path)))
    assert training_set_overrides(checkpoint_run_data(run / "checkpoints" / "last.ckpt"), []) == [
        "suite.training_towns=[town_b]", "suite.training_weathers=[MidRainyNoon]"]


def test_a_checkpoint_copied_into_another_run_keeps_its_own_data(tmp_path):
    """A checkpoint trained on town_b data, copied into a run folder whose config and data.json name the
    default data: its own record of its data says where it trained, not the folder's."""
    import torch

    from cicfw.benchmark.trained_sets import checkpoint_run_data
    from cicfw.data.provenance import CHECKPOINT_KEY

    ckpt = _run_with_checkpoint(tmp_path, ["town_a"], ["ClearNoon"])
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "dataset_metadata.json").write_text(json.dumps({"towns": ["town_a"], "weathers": ["ClearNoon"]}))
    copied = ckpt.with_name("from_b.ckpt")
    torch.save({**torch.load(ckpt, weights_only=True), CHECKPOINT_KEY: _collected_in_town_b(tmp_path)}, copied)
    assert training_set_overrides(checkpoint_run_data(ckpt), [])[0] == "suite.training_towns=[town_a]"
    assert training_set_overrides(checkpoint_run_data(copied), []) == [
        "suite.training_towns=[town_b]", "suite.training_weathers=[MidRainyNoon]"]


def test_an_exported_model_s_evaluation_labels_the_columns_with_its_sidecar_s_data(tmp_path):
    """``checkpoint=<model.onnx>`` (or .pt): the sidecar export wrote names the data the model trained on, even
    when the model sits in another run's folder."""
    from cicfw.benchmark.trained_sets import checkpoint_run_data

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "data.json").write_text(json.dumps({"path": str(tmp_path / "elsewhere"), "files": []}))  # not its data
    model = run / "checkpoints" / "model.onnx"
    model.write_bytes(b"onnx")
    (run / "checkpoints" / "model.onnx.json").write_text(json.dumps(
        {"training_dataset": {"path": _collected_in_town_b(tmp_path)["path"], "hash": None}}))
    assert training_set_overrides(checkpoint_run_data(model), []) == [
        "suite.training_towns=[town_b]", "suite.training_weathers=[MidRainyNoon]"]


def test_data_that_says_nothing_leaves_the_default_columns_with_a_warning(tmp_path, caplog):
    """Data without a collection's metadata (a public CIL folder, one whose metadata was lost): the default
    training columns are kept, and the evaluation says they are the defaults, not the data's."""
    data = OmegaConf.create({"path": str(tmp_path)})
    with caplog.at_level("WARNING", logger="cicfw.benchmark.trained_sets"):
        assert training_set_overrides(data, []) == []
    assert [r for r in caplog.records if str(tmp_path) in r.getMessage() and "defaults" in r.getMessage()]
    caplog.clear()
    with caplog.at_level("WARNING", logger="cicfw.benchmark.trained_sets"):  # the user named both: nothing to say
        training_set_overrides(data, ["suite.training_towns=[town_b]", "suite.training_weathers=[ClearNoon]"])
    assert not caplog.records


def _columns(out):
    rows = json.loads((out / "episodes.json").read_text())["episodes"]
    return sorted((r["town_set"], r["weather_set"]) for r in rows)


def test_the_columns_are_the_sets_the_checkpoint_recorded_not_the_metadata_edited_since(tmp_path):
    """A run trained on town_a / ClearNoon data; its data's metadata then edited to name town_b and MidRainyNoon
    too (its HDF5 files unchanged, so the checkpoint's data hash still matches): the evaluation still drives one
    episode in each of the four columns, and says the metadata now names other sets. One training step, and
    short episodes (6 m before the turn, 2 m off the route): the columns do not depend on how far they drive."""
    from conftest import TINY_TRAIN, run_app_in_process

    from cicfw.data.provenance import SETS_KEY
    from cicfw.testing import write_tiny_dataset
    from cicfw.train.app import train

    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=32)
    meta = data / "dataset_metadata.json"
    meta.write_text(json.dumps({"towns": ["town_a"], "weathers": ["ClearNoon"]}))
    cfg = compose_train(*TINY_TRAIN, f"data.path={data}", "trainer.limit_train_batches=1")
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")
    train(cfg, run, refuse_finished=True, claim=False)  # as the app, which claimed it before .hydra was written
    assert json.loads((run / "data.json").read_text())[SETS_KEY] == {"towns": ["town_a"], "weathers": ["ClearNoon"]}
    evaluate = [f"checkpoint={run}", "suite=single_turn", "suite.limit=1", "suite.weathers=[ClearNoon,MidRainyNoon]",
                "runner.workers=1", "progress_bar=false", "maps=false", "sim.route_before=6", "sim.max_deviation=2"]
    four = [("new", "new"), ("new", "training"), ("training", "new"), ("training", "training")]
    res = run_app_in_process("cicfw.evaluate", *evaluate, f"hydra.run.dir={tmp_path / 'before'}")
    assert res.returncode == 0, res.stderr[-2000:]
    assert _columns(tmp_path / "before") == four
    meta.write_text(json.dumps({"towns": ["town_a", "town_b"], "weathers": ["ClearNoon", "MidRainyNoon"]}))
    res = run_app_in_process("cicfw.evaluate", *evaluate, f"hydra.run.dir={tmp_path / 'after'}")
    assert res.returncode == 0, res.stderr[-2000:]
    assert _columns(tmp_path / "after") == four
    logged = "".join(f.read_text() for f in (tmp_path / "after").glob("*.log")).splitlines()
    said = [line for line in logged if "recorded when its training started" in line]
    assert said and "town_b" in said[0] and "MidRainyNoon" in said[0] and str(run) in said[0]


def test_a_checkpoint_that_recorded_no_sets_falls_back_to_the_metadata_and_says_so(tmp_path, caplog):
    """A checkpoint written before records held the towns and weathers: its data's metadata now, with a line."""
    from cicfw.benchmark.trained_sets import checkpoint_run_data, checkpoint_sets

    ckpt = _run_with_checkpoint(tmp_path, ["town_b"], ["ClearNoon"])  # its run's data.collect: the data now
    assert checkpoint_sets(ckpt) is None
    with caplog.at_level("INFO", logger="cicfw.benchmark.trained_sets"):
        found = training_set_overrides(checkpoint_run_data(ckpt), [], checkpoint_sets(ckpt), whose=f"checkpoint {ckpt}")
    assert found == ["suite.training_towns=[town_b]", "suite.training_weathers=[ClearNoon]"]
    assert [r for r in caplog.records if str(ckpt) in r.getMessage() and "records no" in r.getMessage()]


def test_the_recorded_sets_win_over_the_metadata_and_the_user_s_over_both(tmp_path):
    """A checkpoint's own record of its sets labels the columns; suite.training_towns on the command line still
    wins over it, as it does over the metadata."""
    import torch

    from cicfw.benchmark.trained_sets import checkpoint_run_data, checkpoint_sets
    from cicfw.data.provenance import CHECKPOINT_KEY, SETS_KEY

    ckpt = _run_with_checkpoint(tmp_path, ["town_a"], ["ClearNoon"])
    data = _collected_in_town_b(tmp_path)  # its metadata now: town_b, MidRainyNoon
    torch.save({**torch.load(ckpt, weights_only=True),
                CHECKPOINT_KEY: {**data, SETS_KEY: {"towns": ["town_a"], "weathers": ["ClearSunset"]}}}, ckpt)
    recorded = checkpoint_sets(ckpt)
    assert recorded == (["town_a"], ["ClearSunset"])
    run_data = checkpoint_run_data(ckpt)
    assert training_set_overrides(run_data, [], recorded) == [
        "suite.training_towns=[town_a]", "suite.training_weathers=[ClearSunset]"]
    assert training_set_overrides(run_data, ["suite.training_towns=[town_b]"], recorded) == [
        "suite.training_weathers=[ClearSunset]"]
