"""export owns the path it writes: never over the checkpoint it reads (by any name), never a model under
the other format's suffix; both refused in one line before anything is loaded."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from cicfw.export.app import ExportError, export_model


@pytest.fixture
def checkpoint(tmp_path: Path) -> Path:
    """A file where a checkpoint is expected: the checks under test run before it is loaded."""
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"checkpoint bytes")
    return ckpt


def test_export_refuses_to_write_over_its_checkpoint(checkpoint):
    same = [checkpoint, checkpoint.parent / ".." / "checkpoints" / "last.ckpt"]
    os.link(checkpoint, checkpoint.parent / "linked.ckpt")  # another name for the same file
    same.append(checkpoint.parent / "linked.ckpt")
    for out in same:
        with pytest.raises(ExportError) as err:
            export_model(checkpoint, "onnx", out)
        assert (err.value.key, str(err.value.value)) == ("out", str(out)), str(err.value)
        assert str(checkpoint) in str(err.value), str(err.value)
    assert checkpoint.read_bytes() == b"checkpoint bytes"


def _hydra_run(folder: Path, job: str) -> Path:
    """A folder as Hydra leaves a run of the cicfw app ``job`` (its record lists a cicfw callback)."""
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "hydra.yaml").write_text("hydra:\n  callbacks:\n    run_folder:\n      _target_: "
                                                  f"cicfw.core.run_folder.LockedRunFolderCheck\n  job:\n    name: {job}\n")
    return folder


@pytest.mark.parametrize("inside", ["results", "results/cells", "other", "other/checkpoints", "evaluation"])
def test_export_refuses_an_out_inside_another_apps_run(checkpoint, tmp_path, inside):
    """A model written among a reproduction's results, another training run's files or an evaluation's is
    refused before the checkpoint is read, naming out; nothing is written."""
    (tmp_path / "results" / "cells" / "cil" / "seed0").mkdir(parents=True)
    (tmp_path / "results" / "reproduce.json").write_text("{}")
    (_hydra_run(tmp_path / "other", "train") / "checkpoints").mkdir()
    _hydra_run(tmp_path / "evaluation", "evaluate")
    before = sorted(tmp_path.rglob("*"))
    out = tmp_path / inside / "model.pt"
    with pytest.raises(ExportError) as err:
        export_model(checkpoint, "torchscript", out)
    assert (err.value.key, str(err.value.value)) == ("out", str(out)), str(err.value)
    assert str(tmp_path / inside.split("/")[0]) in str(err.value), str(err.value)  # the run it lies in
    assert sorted(tmp_path.rglob("*")) == before


def test_export_writes_beside_its_checkpoint_inside_its_own_run(tmp_path):
    """The default out (beside the checkpoint) and any out inside the checkpoint's own run pass, a
    reproduction's cell included."""
    from cicfw.export.app import check_outside_other_runs

    run = _hydra_run(tmp_path / "run", "train")
    ckpt = run / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir()
    for out in (ckpt.with_suffix(".pt"), run / "model.pt"):
        check_outside_other_runs(out, ckpt)
    cell = _hydra_run(tmp_path / "results" / "cells" / "cil" / "seed0" / "train", "train")
    (tmp_path / "results" / "reproduce.json").write_text("{}")
    check_outside_other_runs(cell / "checkpoints" / "best.onnx", cell / "checkpoints" / "best.ckpt")


@pytest.mark.parametrize("fmt, out, wants", [("torchscript", "x.onnx", ".pt"), ("onnx", "x.pt", ".onnx"),
                                             ("onnx", "x", ".onnx")])
def test_export_refuses_an_out_suffix_of_the_other_format(checkpoint, tmp_path, fmt, out, wants):
    with pytest.raises(ExportError) as err:
        export_model(checkpoint, fmt, tmp_path / out)
    text = str(err.value)
    assert (err.value.key, str(err.value.value)) == ("out", str(tmp_path / out)), text
    assert f"format={fmt}" in text and wants in text, text
    assert all(s in text for s in ("format=onnx", ".onnx", "format=torchscript", ".pt")), text  # each format's suffix
    assert not (tmp_path / out).exists()


def test_agent_load_of_a_folder_without_a_checkpoint_says_what_it_holds_and_what_loads(tmp_path):
    from cicfw.export.agent import Agent
    from cicfw.model.checkpoint import CheckpointError

    for name in ("m.onnx", "m.onnx.json"):
        (tmp_path / name).write_bytes(b"x")
    with pytest.raises(CheckpointError) as err:
        Agent.load(tmp_path)
    text = str(err.value)
    assert str(err.value.value) == str(tmp_path) and "m.onnx, m.onnx.json" in text, text
    assert all(s in text for s in (".ckpt", ".pt", ".onnx", "run folder")), text


@pytest.mark.parametrize("name", ["model.pt", "model.onnx", "last.ckpt"])
def test_agent_load_of_a_missing_file_names_it_and_every_format_it_loads(tmp_path, name):
    from cicfw.export.agent import Agent

    missing = tmp_path / name
    with pytest.raises(FileNotFoundError) as err:
        Agent.load(missing)
    text = str(err.value)
    assert str(missing) in text, text
    assert all(s in text for s in (".ckpt", ".pt", ".onnx", "run folder")), text


def test_a_dataset_record_holding_no_object_gives_no_collector_hash(tmp_path: Path):
    """The sidecar's dataset: a dataset_metadata.json holding null (edited by hand) carries no collector hash;
    the files' hash is still given (it used to end in an AttributeError traceback)."""
    from cicfw.export.app import dataset_hash

    data = tmp_path / "data"
    data.mkdir()
    (data / "data_00000.h5").write_bytes(b"x" * 10)
    (data / "dataset_metadata.json").write_text("null\n")
    cfg = tmp_path / "config.yaml"
    cfg.write_text(f"data:\n  path: {data}\n")
    got = dataset_hash(cfg)
    assert got["files"] == 1 and got["hash"] and got["collect_config_hash"] is None
