"""Every app writes only into a path it owns: empty, or holding its own earlier output of the same settings.
export's ``out=``, reproduce's ``publish_dir``, evaluate's run folder (``.hydra/`` included) and report's
``--out`` refuse anything else before writing a byte; a run that fails leaves its folder as the rerun it
advises needs it."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from cicfw.core.errors import USER_ERRORS

pytestmark = pytest.mark.slow  # exports, trains, drives or runs an app

ENV = {**os.environ, "HYDRA_FULL_ERROR": "0"}


def _errors(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("cicfw:")]


def save_checkpoint(path: Path, seed: int = 0) -> Path:
    """A CIL-size regression checkpoint as Lightning saves one (weights and hyper-parameters)."""
    from cicfw.model.module import CICModule

    torch.manual_seed(seed)
    model = CICModule()
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams), "epoch": 0,
                "global_step": 1}, path)
    return path


#: one episode of the expert: a finished evaluation in seconds
ONE_EPISODE = ["policy=expert", "suite.towns=[town_a]", "suite.weathers=[ClearNoon]", "suite.limit=1", "maps=false",
               "progress_bar=false"]


def _evaluate(run: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cicfw.evaluate", *ONE_EPISODE, f"hydra.run.dir={run}", *extra],
                          capture_output=True, text=True, env=ENV, timeout=600)


def _hydra_state(run: Path) -> dict[str, bytes]:
    """What Hydra writes into a run folder: ``.hydra``'s files, and the log."""
    return {str(p.relative_to(run)): p.read_bytes() for p in [*(run / ".hydra").glob("*"), run / "evaluate.log"]
            if p.is_file()}


# ---- export: out= -----------------------------------------------------------------------------------


def test_export_refuses_an_existing_file_it_did_not_write(tmp_path):
    from cicfw.export.app import export_model

    ckpt = save_checkpoint(tmp_path / "run" / "last.ckpt")
    other = tmp_path / "other_run.pt"
    other.write_bytes(b"another run's weights")
    with pytest.raises(Exception) as err:
        export_model(ckpt, "torchscript", other, n_frames=2)
    assert isinstance(err.value, USER_ERRORS) and getattr(err.value, "key", None) == "out"
    assert str(other) in str(err.value) and "overwrite=true" in str(err.value)
    assert other.read_bytes() == b"another run's weights"
    assert not other.with_name(other.name + ".json").exists()


def test_export_refuses_a_sidecar_it_did_not_write(tmp_path):
    from cicfw.export.app import export_model

    ckpt = save_checkpoint(tmp_path / "run" / "last.ckpt")
    out = tmp_path / "model.pt"
    out.with_name("model.pt.json").write_text('{"mine": true}')
    with pytest.raises(Exception) as err:
        export_model(ckpt, "torchscript", out, n_frames=2)
    assert isinstance(err.value, USER_ERRORS) and getattr(err.value, "key", None) == "out"
    assert "model.pt.json" in str(err.value)
    assert out.with_name("model.pt.json").read_text() == '{"mine": true}' and not out.exists()


def test_export_writes_over_its_own_export_of_the_same_checkpoint_or_with_overwrite(tmp_path):
    from cicfw.export.app import export_model

    ckpt = save_checkpoint(tmp_path / "run" / "last.ckpt")
    out = tmp_path / "model.pt"
    out.write_bytes(b"x")
    export_model(ckpt, "torchscript", out, n_frames=2, overwrite=True)  # on purpose
    export_model(ckpt, "torchscript", out, n_frames=2)  # its own earlier export of this checkpoint
    other = save_checkpoint(tmp_path / "run2" / "last.ckpt", seed=1)
    before = out.read_bytes()
    with pytest.raises(Exception) as err:  # another checkpoint's export: not the same settings
        export_model(other, "torchscript", out, n_frames=2)
    assert getattr(err.value, "key", None) == "out" and out.read_bytes() == before


# ---- reproduce: publish_dir --------------------------------------------------------------------------


@pytest.fixture
def no_collect(monkeypatch):
    import cicfw.reproduction.app
    import cicfw.train.app

    def collect(*args, **kwargs):
        raise AssertionError("the app went on to collect the dataset")

    monkeypatch.setattr(cicfw.train.app, "ensure_data", collect)
    monkeypatch.setattr(cicfw.reproduction.app, "ensure_data", collect)  # the app imported it by name


def published(folder: Path, budget: str, cells: tuple[str, ...] = ("cil/seed0",)) -> dict[Path, bytes]:
    """A published folder as ``publish`` writes it, pinned to ``budget``; returns its files' bytes."""
    from cicfw.reproduction import app as reproduce

    cfg = reproduce.compose_plan([f"budget={budget}"])
    pin = reproduce.fingerprint(cfg, {"config_hash": "0123456789abcdef"})
    folder.mkdir(parents=True)
    (folder / "reproduce.json").write_text(json.dumps({"budget": budget, "pinned": pin}))
    (folder / "RESULTS.md").write_text(f"# {budget}\n")
    for cell in cells:
        row, seed = cell.split("/")
        p = folder / "cells" / row / seed / "cell.json"
        p.parent.mkdir(parents=True)
        p.write_text(json.dumps({"status": "ok", "row": row, "seed": int(seed[4:])}))
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _refused(args: list[str], capsys) -> str:
    from cicfw.reproduction import app as reproduce

    assert reproduce.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cicfw: error: "), err
    return err[0]


def test_publish_dir_of_another_budget_is_refused_before_anything_is_written(no_collect, tmp_path, capsys):
    pub = tmp_path / "published"
    kept = published(pub, "converged")
    line = _refused(["budget=smoke", "rows=[cil]", "seeds=1", f"publish_dir={pub}",
                     f"results_dir={tmp_path / 'results'}"], capsys)
    assert f"publish_dir={str(pub)!r}" in line and "budget=converged" in line
    assert {p: p.read_bytes() for p in pub.rglob("*") if p.is_file()} == kept


def test_publish_dir_holding_cells_this_run_does_not_have_is_refused(no_collect, tmp_path, capsys):
    """The same budget, but cells another reproduction published: this run's RESULTS.md would sit beside
    them; continuing that folder (continue_from) is the way to add to it."""
    pub = tmp_path / "published"
    kept = published(pub, "smoke", cells=("gtu/seed0", "gtu/seed1"))
    line = _refused(["budget=smoke", "rows=[cil]", "seeds=1", f"publish_dir={pub}",
                     f"results_dir={tmp_path / 'results'}"], capsys)
    assert f"publish_dir={str(pub)!r}" in line and "gtu/seed0" in line and "continue_from=" in line
    assert {p: p.read_bytes() for p in pub.rglob("*") if p.is_file()} == kept


def test_publish_dir_holding_files_of_no_reproduction_is_refused(no_collect, tmp_path, capsys):
    pub = tmp_path / "notes"
    pub.mkdir()
    (pub / "RESULTS.md").write_text("my own notes\n")
    line = _refused(["budget=smoke", "rows=[cil]", "seeds=1", f"publish_dir={pub}",
                     f"results_dir={tmp_path / 'results'}"], capsys)
    assert f"publish_dir={str(pub)!r}" in line and "RESULTS.md" in line
    assert (pub / "RESULTS.md").read_text() == "my own notes\n"


def test_publish_dir_a_run_may_write(tmp_path):
    """Empty, missing, or its own earlier publication: accepted (the check itself, no cell run)."""
    from cicfw.reproduction import app as reproduce

    for args in ([f"publish_dir={tmp_path / 'new'}"], [f"publish_dir={tmp_path / 'empty'}"]):
        (tmp_path / "empty").mkdir(exist_ok=True)
        cfg = reproduce.compose_plan(["budget=smoke", f"results_dir={tmp_path / 'results'}", *args])
        reproduce.check_publish_dir(cfg)
    pub = tmp_path / "published"
    published(pub, "smoke", cells=("cil/seed0",))
    results = tmp_path / "results"
    published(results, "smoke", cells=("cil/seed0",))
    cfg = reproduce.compose_plan(["budget=smoke", f"results_dir={results}", f"publish_dir={pub}"])
    reproduce.check_publish_dir(cfg)  # every cell there is this run's
    cfg = reproduce.compose_plan(["budget=smoke", f"results_dir={tmp_path / 'r2'}", f"publish_dir={pub}",
                                  f"continue_from={pub}"])
    reproduce.check_publish_dir(cfg)  # growing a published folder


# ---- report: --out -------------------------------------------------------------------------------


def test_report_out_holding_files_it_did_not_write_is_refused(tmp_path, capsys):
    """``cicfw report <runs> --out <a run folder>`` would replace that run's own table with other runs'."""
    from cicfw.benchmark.evaluation_report import main as report

    run = tmp_path / "eval"
    res = _evaluate(run)
    assert res.returncode == 0, res.stderr[-3000:]
    other = tmp_path / "other_run"
    other.mkdir()
    (other / "table.md").write_text("| another run's table |\n")
    assert report([str(run), "--out", str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0] and str(other) in err[0] and "table.md" in err[0], err
    assert (other / "table.md").read_text() == "| another run's table |\n"
    out = tmp_path / "report"
    assert report([str(run), "--out", str(out)]) == 0 and (out / "table.md").is_file()
    assert report([str(run), "--out", str(out)]) == 0  # its own earlier report of the same runs
    assert report([str(run), "--out", str(other), "--overwrite"]) == 0  # on purpose


# ---- evaluate: the run folder, .hydra included -----------------------------------------------------


def test_an_evaluation_of_other_options_into_a_finished_folder_leaves_its_hydra_files(tmp_path):
    run = tmp_path / "eval"
    first = _evaluate(run)
    assert first.returncode == 0, first.stderr[-3000:]
    kept = _hydra_state(run)
    assert ".hydra/config.yaml" in kept and ".hydra/overrides.yaml" in kept
    second = _evaluate(run, "seed=5", "name=OTHER")
    assert second.returncode == 2, second.stderr[-3000:]
    errors = _errors(second.stderr)
    assert len(errors) == 1 and str(run) in errors[0] and "seed" in errors[0], second.stderr[-3000:]
    assert _hydra_state(run) == kept  # the folder still names seed 0, as its results are


def test_an_evaluation_into_a_folder_another_is_writing_is_refused_before_hydra_writes(tmp_path):
    from cicfw.benchmark.journal import RunFolderLock

    run = tmp_path / "eval"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text("seed: 0\n")
    (run / ".hydra" / "overrides.yaml").write_text("[]\n")
    kept = _hydra_state(run)
    held = RunFolderLock(run).acquire()  # the other evaluation
    try:
        res = _evaluate(run, "seed=5")
    finally:
        held.release()
    assert res.returncode == 2, res.stderr[-3000:]
    errors = _errors(res.stderr)
    assert len(errors) == 1 and f"pid {os.getpid()}" in errors[0] and str(run) in errors[0], res.stderr[-3000:]
    assert _hydra_state(run) == kept and not (run / "evaluate.log").exists()


def test_an_evaluation_of_a_bad_checkpoint_leaves_no_run_folder(tmp_path):
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"not a checkpoint")
    run = tmp_path / "outputs" / "eval"
    res = subprocess.run([sys.executable, "-m", "cicfw.evaluate", f"checkpoint={bad}", "suite.limit=1",
                          f"hydra.run.dir={run}"], capture_output=True, text=True, env=ENV, timeout=600)
    assert res.returncode == 2, res.stderr[-3000:]
    errors = _errors(res.stderr)
    assert len(errors) == 1 and str(bad) in errors[0], res.stderr[-3000:]
    assert not run.exists() and not (tmp_path / "outputs").exists()


# ---- train: a failed run leaves a folder the advised rerun accepts ---------------------------------

from test_hostile_train import full_disk  # noqa: E402,F401  (the fixture)


def test_a_full_disk_at_the_first_checkpoint_leaves_a_folder_the_same_command_accepts(tmp_path, full_disk):
    from hydra import compose, initialize_config_module

    from cicfw.testing import write_tiny_dataset
    from cicfw.train.app import train_in_folder

    data = write_tiny_dataset(tmp_path / "data")
    run = tmp_path / "run"
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("train", overrides=[
            "data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false",
            "speed.compile=false", "trainer.max_epochs=1", "trainer.limit_train_batches=1",
            "trainer.limit_val_batches=1", "trainer.num_sanity_val_steps=0"])
    full_disk(run / "checkpoints")
    with pytest.raises(Exception) as err:
        train_in_folder(cfg, run)
    assert isinstance(err.value, USER_ERRORS) and "run the same command again" in str(err.value), str(err.value)
    full_disk(tmp_path / "elsewhere")  # space freed
    train_in_folder(cfg, run)  # the same command, as advised
    assert (run / "checkpoints" / "last.ckpt").is_file()
