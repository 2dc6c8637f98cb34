"""Every app writes only into a path it owns: empty, or holding its own earlier output of the same settings.
export's ``out=``, reproduce's ``publish_dir``, evaluate's run folder (``.hydra/`` included) and report's
``--out`` refuse anything else before writing a byte; a run that fails leaves its folder as the rerun it
advises needs it. Under these, one rule (``claim_folder``): another app's run, a dataset, a report's own
inputs or files of no app are refused by every app; a report joins each run once. Beside them: the values
the Agent API and evaluate refuse, and what the suite's training-weathers error lists."""
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


def _evaluate(run: Path, *extra: str, process: bool = False):
    """``python -m cicfw.evaluate`` of one expert episode into ``run``: in this interpreter unless ``process``
    (a test where another process must hold what this one holds)."""
    if not process:
        return run_app_in_process("cicfw.evaluate", *ONE_EPISODE, f"hydra.run.dir={run}", *extra, env=IN_PROCESS)
    return subprocess.run([sys.executable, "-m", "cicfw.evaluate", *ONE_EPISODE, f"hydra.run.dir={run}", *extra],
                          capture_output=True, text=True, env=ENV, timeout=600)


@pytest.fixture(scope="module")
def one_episode_eval(tmp_path_factory) -> Path:
    """A finished evaluation of one expert episode, shared: a test that writes into it works on a copy."""
    run = tmp_path_factory.mktemp("eval") / "eval"
    res = _evaluate(run)
    assert res.returncode == 0, res.stderr[-3000:]
    return run


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


def test_publish_dir_at_another_runs_results_folder_is_refused(tmp_path):
    """``continue_from=res results_dir=new publish_dir=res`` would replace res's reproduce.json, report and
    cell.json files beside its checkpoints: a folder whose cells hold their runs (train/, evaluate/) is a
    results folder, never a publication, and is refused before anything is written."""
    from cicfw.core.errors import CicfwError
    from cicfw.reproduction import app as reproduce

    res = tmp_path / "res"
    files = published(res, "smoke", cells=("cil/seed0",))
    (res / "cells" / "cil" / "seed0" / "train").mkdir()
    cfg = reproduce.compose_plan(["budget=smoke", f"results_dir={tmp_path / 'new'}", f"publish_dir={res}",
                                  f"continue_from={res}"])
    with pytest.raises(CicfwError) as err:
        reproduce.check_publish_dir(cfg)
    assert (err.value.key, err.value.value) == ("publish_dir", str(res)) and "cells/cil/seed0/train" in str(err.value)
    assert {p: p.read_bytes() for p in res.rglob("*") if p.is_file()} == files


# ---- report: --out -------------------------------------------------------------------------------


def test_report_out_holding_files_it_did_not_write_is_refused(one_episode_eval, tmp_path, capsys):
    """``cicfw report <runs> --out <a run folder>`` would replace that run's own table with other runs'."""
    from cicfw.benchmark.evaluation_report import main as report

    run = one_episode_eval  # read only: every report here writes elsewhere
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


def test_report_into_the_folder_given_keeps_a_users_file_of_a_tables_name(one_episode_eval, tmp_path, capsys):
    """``cicfw report <folder holding runs>`` writes into that folder by default: a table.md of the user's
    there (no report of these runs wrote it) is refused as ``--out`` refuses it; the one run's own folder and
    the folder's own earlier report are still rewritten."""
    import shutil

    from cicfw.benchmark.evaluation_report import main as report

    folder = tmp_path / "mine"
    shutil.copytree(one_episode_eval, folder / "run")
    (folder / "table.md").write_text("my notes\n")
    assert report([str(folder)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(folder) in err[0] and "table.md" in err[0], err
    assert (folder / "table.md").read_text() == "my notes\n" and not (folder / "table.csv").exists()
    assert report([str(folder), "--overwrite"]) == 0  # on purpose
    assert report([str(folder)]) == 0  # now the folder's own report of the same runs
    assert report([str(folder / "run")]) == 0  # a run's own tables, which its evaluation wrote
    (tmp_path / "fake").mkdir()
    shutil.copytree(one_episode_eval, tmp_path / "fake" / "run")
    (tmp_path / "fake" / "multirun.yaml").touch()  # the name of a sweep's record, not one
    (tmp_path / "fake" / "table.md").write_text("mine\n")
    assert report([str(tmp_path / "fake")]) == 2 and "table.md" in capsys.readouterr().err
    assert (tmp_path / "fake" / "table.md").read_text() == "mine\n"
    (tmp_path / "fake" / "multirun.yaml").write_text("hydra:\n  job:\n    name: evaluate\n")  # a sweep's record
    assert report([str(tmp_path / "fake")]) == 0  # an evaluation sweep's folder: its join is cicfw's to rewrite
    (tmp_path / "notes").mkdir()
    shutil.copytree(one_episode_eval, tmp_path / "notes" / "run")
    (tmp_path / "notes" / "report.json").write_text('{"mine": 1}\n')  # no table, a record of the user's
    assert report([str(tmp_path / "notes")]) == 2 and "report.json" in capsys.readouterr().err
    assert (tmp_path / "notes" / "report.json").read_text() == '{"mine": 1}\n'


# ---- evaluate: the run folder, .hydra included -----------------------------------------------------


def test_an_evaluation_of_other_options_into_a_finished_folder_leaves_its_hydra_files(one_episode_eval, tmp_path):
    import shutil

    run = tmp_path / "eval"
    shutil.copytree(one_episode_eval, run)
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
        res = _evaluate(run, "seed=5", process=True)  # this process holds the lock
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
    res = run_app_in_process("cicfw.evaluate", f"checkpoint={bad}", "suite.limit=1", f"hydra.run.dir={run}",
                             env=IN_PROCESS)
    assert res.returncode == 2, res.stderr[-3000:]
    errors = _errors(res.stderr)
    assert len(errors) == 1 and str(bad) in errors[0], res.stderr[-3000:]
    assert not run.exists() and not (tmp_path / "outputs").exists()


@pytest.mark.parametrize("app", ["cicfw.evaluate", "cicfw.diagnose"])
def test_a_checkpoint_whose_hyper_parameters_do_not_build_is_one_line_and_no_run_folder(tmp_path, app):
    """A head kwarg its constructor refuses, edited into the checkpoint: one line naming the key, exit 2, and the
    run folder Hydra made is gone again."""
    path = save_checkpoint(tmp_path / "edited.ckpt")
    ckpt = torch.load(path, weights_only=True)
    ckpt["hyper_parameters"]["head_kwargs"] = {"loss": "mse", "decode": "argmax"}
    torch.save(ckpt, path)
    run = tmp_path / "outputs" / "run"
    extra = ["suite.limit=1"] if app == "cicfw.evaluate" else []
    res = run_app_in_process(app, f"checkpoint={path}", *extra, f"hydra.run.dir={run}", env=IN_PROCESS)
    assert res.returncode == 2, res.stderr[-3000:]
    errors = _errors(res.stderr)
    assert len(errors) == 1 and "head_kwargs.decode" in errors[0] and str(path) in errors[0], res.stderr[-3000:]
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


def test_a_full_disk_at_the_first_checkpoint_from_python_leaves_a_folder_the_same_call_accepts(tmp_path, full_disk):
    """``train(cfg, run_dir)`` stopped before its first checkpoint says to run the same call again: the folder it
    leaves (its data record, Lightning's csv/hparams.yaml) is its own, not "files no cicfw app wrote"."""
    from cicfw.testing import write_tiny_dataset
    from cicfw.train.app import train

    cfg = _tiny_train_cfg(write_tiny_dataset(tmp_path / "data"))  # defined below
    run = tmp_path / "run"
    full_disk(run / "checkpoints")
    with pytest.raises(Exception) as err:
        train(cfg, run)
    assert isinstance(err.value, USER_ERRORS) and "run the same command again" in str(err.value), str(err.value)
    assert (run / "data.json").is_file()  # written once every check passed, before training started
    full_disk(tmp_path / "elsewhere")  # space freed
    train(cfg, run)  # the same call, as advised
    assert torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)["epoch"] == 0


def test_train_from_python_stopped_in_its_first_batch_leaves_a_folder_the_same_call_accepts(tmp_path, monkeypatch):
    """Stopped before Lightning made ``checkpoints/`` (an out-of-memory error in the first batch), the folder holds
    the call's data record and csv/hparams.yaml alone: train's own, which the same call trains into; another app
    is still refused there."""
    import lightning as L

    import cicfw.train.app as train_app
    from cicfw.core.run_folder import RunFolderError, claim_folder
    from cicfw.testing import write_tiny_dataset

    class OutOfMemory(L.Callback):
        def on_train_batch_start(self, *args, **kwargs):
            raise MemoryError("the first batch")

    cfg = _tiny_train_cfg(write_tiny_dataset(tmp_path / "data"))
    run = tmp_path / "run"
    callbacks = train_app.build_callbacks
    monkeypatch.setattr(train_app, "build_callbacks", lambda c, d: [*callbacks(c, d), OutOfMemory()])
    with pytest.raises(MemoryError):
        train_app.train(cfg, run)
    monkeypatch.setattr(train_app, "build_callbacks", callbacks)
    assert (run / "data.json").is_file() and not (run / "checkpoints").exists()
    with pytest.raises(RunFolderError) as err:
        claim_folder(run, "evaluate", "run_dir")
    assert err.value.key == "run_dir" and "cicfw train" in str(err.value)
    train_app.train(cfg, run)  # the same call
    assert torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)["epoch"] == 0


# ---- one rule for every app: a folder that is not the app's own is refused -------------------------

from conftest import assert_refused, run_app_in_process, write_tiny_dataset  # noqa: E402

IN_PROCESS = {"HYDRA_FULL_ERROR": "0"}  # changes to the environment, for run_app_in_process


def _files(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _one_error(text: str) -> str:
    errors = _errors(text)
    assert len(errors) == 1 and "Traceback" not in text, text[-3000:]
    return errors[0]


def _rows(n: int = 2) -> list[dict]:
    return [{"episode": k, "key": f"town_a/ClearNoon/{k:03d}", "town": "town_a", "weather": "ClearNoon",
             "town_set": "training", "weather_set": "training", "pair": k, "route": "town_a/j/a>b/left",
             "command": "left", "success": k % 2 == 0, "reason": "success" if k % 2 == 0 else "off_route",
             "time_s": 10.0, "timeout_s": 30.0, "distance_m": 50.0, "route_length_m": 60.0, "goal_distance_m": 1.0,
             "progress": 1.0, "offroad_fraction": 0.0, "opposite_lane_fraction": 0.0, "steps": 100}
            for k in range(n)]


def published_results(folder: Path, label: str = "CIL") -> Path:
    """Evaluation results as a user publishes them: episodes, summary and tables, no ``.hydra``."""
    from cicfw.benchmark.evaluation_report import Run, write_run

    write_run(folder, Run(label, _rows()))
    return folder


#: the first line of an evaluation's episode log (``cicfw.benchmark.journal``), all a run interrupted before its
#: first episode holds
EPISODE_LOG_HEADER = '{"format": "cicfw-episode-log/1", "fingerprint": {}, "info": {}}\n'


def data_record(path: str) -> dict:
    """A training run's record of no files at ``path``, with every key ``cicfw.data.provenance`` writes."""
    return {"path": path, "root": path, "hash": "e3b0c44298fc1c14", "hash_of": "the files' names, sizes and SHA-256",
            "n_files": 0, "bytes": 0, "collect_config_hash": None, "recorded": "2026-01-01 00:00:00", "files": []}


def hydra_run(folder: Path, job: str, *outputs: str) -> dict[Path, bytes]:
    """A run folder as Hydra leaves it for the app ``job`` (its ``.hydra`` records and log), with ``outputs``."""
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "hydra.yaml").write_text(f"hydra:\n  callbacks:\n    run_folder:\n      _target_: "
                                                  f"cicfw.core.run_folder.RunFolderCheck\n  job:\n    name: {job}\n")
    (folder / ".hydra" / "config.yaml").write_text(f"# the {job} run's config\nseed: 3\n")
    (folder / f"{job}.log").write_text("a line\n")
    for name in outputs:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(b"the run's own " + name.encode())
    return _files(folder)


def test_evaluate_into_a_published_results_folder_is_refused(tmp_path):
    run = published_results(tmp_path / "published")
    kept = _files(run)
    res = run_app_in_process("cicfw.evaluate", *ONE_EPISODE, f"hydra.run.dir={run}", env=IN_PROCESS)
    assert res.returncode == 2, res.stderr[-3000:]
    line = _one_error(res.stderr)
    assert f"hydra.run.dir={str(run)!r}" in line and "episodes.json" in line, line
    assert _files(run) == kept and not (run / ".hydra").exists()


def test_evaluate_into_a_training_runs_folder_keeps_its_hydra_config(tmp_path):
    run = tmp_path / "train_run"
    kept = hydra_run(run, "train", "checkpoints/last.ckpt", "csv/metrics.csv")
    res = run_app_in_process("cicfw.evaluate", *ONE_EPISODE, f"hydra.run.dir={run}", env=IN_PROCESS)
    assert res.returncode == 2, res.stderr[-3000:]
    line = _one_error(res.stderr)
    assert f"hydra.run.dir={str(run)!r}" in line and "outputs of cicfw train" in line, line
    assert _files(run) == kept  # diagnose still finds the training config


def test_diagnose_into_the_training_run_it_diagnoses_is_refused(tmp_path):
    run = tmp_path / "train_run"
    kept = hydra_run(run, "train", "checkpoints/last.ckpt")
    res = run_app_in_process("cicfw.diagnose", f"checkpoint={run / 'checkpoints' / 'last.ckpt'}",
                             f"hydra.run.dir={run}", env=IN_PROCESS)
    assert res.returncode == 2, res.stderr[-3000:]
    line = _one_error(res.stderr)
    assert f"hydra.run.dir={str(run)!r}" in line and "outputs of cicfw train" in line, line
    assert _files(run) == kept


def _train_args(data: Path, run: Path, *extra: str) -> list[str]:
    return ["data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "data.val_batch_size=8",
            "progress_bar=false", "speed.compile=false", "trainer.max_epochs=1", "trainer.limit_train_batches=1",
            "trainer.limit_val_batches=1", "trainer.num_sanity_val_steps=0", "trainer.enable_model_summary=false",
            f"hydra.run.dir={run}", *extra]


def test_train_into_an_evaluations_folder_keeps_its_hydra_config(tmp_path):
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    run = tmp_path / "eval_run"
    kept = hydra_run(run, "evaluate", "episodes.json", "summary.json", "table.md")
    res = run_app_in_process("cicfw.train", *_train_args(data, run), env=IN_PROCESS)
    assert res.returncode == 2, res.stderr[-3000:]
    line = _one_error(res.stderr)
    assert f"hydra.run.dir={str(run)!r}" in line and "outputs of cicfw evaluate" in line, line
    assert _files(run) == kept


def test_train_into_its_data_folder_is_refused(tmp_path):
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    kept = _files(data)
    res = run_app_in_process("cicfw.train", *_train_args(data, data), env=IN_PROCESS)
    assert res.returncode == 2, res.stderr[-3000:]
    line = _one_error(res.stderr)
    assert f"hydra.run.dir={str(data)!r}" in line and "data" in line, line
    assert _files(data) == kept and not (data / ".hydra").exists()


def test_a_data_folder_not_yet_collected_is_no_run_folder(tmp_path):
    """``data.path`` names a folder the default data collects into: a run folder there is refused before
    it exists."""
    from cicfw.core.run_folder import RunFolderError, claim_folder

    data = tmp_path / "datasets" / "smoke"
    with pytest.raises(RunFolderError) as err:
        claim_folder(tmp_path / "datasets" / ".." / "datasets" / "smoke", "train", "hydra.run.dir", data=[data])
    assert err.value.key == "hydra.run.dir" and "smoke" in err.value.value
    assert not data.exists()


def test_reproduce_results_dir_holding_a_users_results_is_refused(no_collect, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "RESULTS.md").write_text("my results\n")
    (mine / "results.csv").write_text("row,rate\nmine,1\n")
    kept = _files(mine)
    line = _refused(["budget=smoke", "rows=[cil]", "seeds=1", f"results_dir={mine}"], capsys)
    assert f"results_dir={str(mine)!r}" in line and "RESULTS.md" in line and "results.csv" in line, line
    assert _files(mine) == kept


def test_reproduce_into_the_budgets_data_folder_is_refused(no_collect, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CICFW_CACHE", str(tmp_path / "cache"))  # smoke's data: <cache>/datasets/smoke
    data = tmp_path / "cache" / "datasets" / "smoke"
    line = _refused(["budget=smoke", "rows=[cil]", "seeds=1", f"results_dir={data}"], capsys)
    assert f"results_dir={str(data)!r}" in line and "data.path" in line, line
    assert not data.exists()


def _report(args: list[str], capsys) -> tuple[int, str]:
    from cicfw.benchmark.evaluation_report import main as report

    code = report([*map(str, args), "--no-plots"])
    return code, capsys.readouterr().err


def test_report_out_equal_to_one_of_its_inputs_is_refused(tmp_path, capsys):
    a = published_results(tmp_path / "a", "A")
    b = published_results(tmp_path / "b", "B")
    kept = _files(a)
    (tmp_path / "link").symlink_to(a)
    for out in (a, tmp_path / "link", tmp_path / "b" / ".." / "a"):
        code, err = _report([a, b, "--out", out], capsys)
        assert code == 2, err
        line = _one_error(err)
        assert f"--out={str(out)!r}" in line, line
        code, err = _report([a, b, "--out", out, "--overwrite"], capsys)  # not another's table to replace
        assert code == 2, err
    assert _files(a) == kept


def test_report_into_a_data_folder_is_refused_even_with_overwrite(tmp_path, capsys):
    a = published_results(tmp_path / "a")
    data = write_tiny_dataset(tmp_path / "data", n_files=2, n=8)
    kept = _files(data)
    for extra in ([], ["--overwrite"]):
        code, err = _report([a, "--out", data, *extra], capsys)
        assert code == 2, err
        line = _one_error(err)
        assert f"--out={str(data)!r}" in line and "dataset" in line, line
    assert _files(data) == kept


def test_report_joining_a_run_with_itself_is_refused(tmp_path, capsys):
    a = published_results(tmp_path / "a")
    (tmp_path / "link").symlink_to(a)
    sweep = tmp_path / "sweep"
    published_results(sweep / "0")
    for twice in ([a, a], [a, tmp_path / "link"], [a, tmp_path / "a" / ".." / "a"], [sweep, sweep / "0"]):
        code, err = _report([*twice, "--out", tmp_path / "joined"], capsys)
        assert code == 2, err
        line = _one_error(err)
        assert str(twice[1]) in line and "same run" in line, line
        assert not (tmp_path / "joined").exists()


def test_the_folders_an_app_may_write(tmp_path):
    """Missing, empty (locks aside), or the app's own kind of run (Hydra's job name, or its log beside a
    ``.hydra`` without one; a report's report.json): accepted, the app's own checks then apply."""
    from cicfw.core.run_folder import RunFolderError, claim_folder

    claim_folder(tmp_path / "missing", "train", "hydra.run.dir")
    (tmp_path / "locked").mkdir()
    (tmp_path / "locked" / ".evaluate.lock").write_text("")
    claim_folder(tmp_path / "locked", "evaluate", "hydra.run.dir")
    hydra_run(tmp_path / "ev", "evaluate", "episodes.jsonl")
    claim_folder(tmp_path / "ev", "evaluate", "hydra.run.dir")
    api = published_results(tmp_path / "api")
    (api / "episodes.jsonl").write_text(EPISODE_LOG_HEADER)  # driven through the Python API: its log, no .hydra
    claim_folder(api, "evaluate", "hydra.run.dir")
    old = tmp_path / "old"
    hydra_run(old, "train", "notes.txt")
    (old / ".hydra" / "hydra.yaml").unlink()  # its train.log still names it
    claim_folder(old, "train", "hydra.run.dir")
    with pytest.raises(RunFolderError) as err:
        claim_folder(old, "evaluate", "hydra.run.dir")
    assert err.value.key == "hydra.run.dir" and err.value.value == str(old)
    (tmp_path / "rep").mkdir()
    (tmp_path / "rep" / "report.json").write_text('{"written_by": "cicfw report", "runs": []}')
    claim_folder(tmp_path / "rep", "report", "--out")


# ---- the Agent API, evaluate's video_max, the suite's training weathers ----------------------------


def test_the_agent_takes_only_real_numbers_as_a_speed(tmp_path):
    import numpy as np

    from cicfw.export.agent import Agent, AgentInputError

    agent = Agent.load(save_checkpoint(tmp_path / "m.ckpt"))
    frame = np.zeros((88, 200, 3), np.uint8)
    for speed in (True, "10", [10, "x"], None):
        with pytest.raises(AgentInputError) as err:
            agent.act(frame, speed, 2)
        assert err.value.key == "speed_kmh", speed
    assert np.isfinite(agent.act(frame, 10, 2)) and np.isfinite(agent.act(frame, np.float64(12.5), 2))


def test_evaluate_refuses_a_negative_video_max(tmp_path):
    run = tmp_path / "eval"
    res = run_app_in_process("cicfw.evaluate", *ONE_EPISODE, "video_max=-1", f"hydra.run.dir={run}", env=IN_PROCESS)
    assert res.returncode == 2, res.stderr[-3000:]
    line = _one_error(res.stderr)
    assert "video_max" in line and "-1" in line, line
    assert not (run / "episodes.json").exists()


def test_the_training_weathers_error_lists_the_suites_own_weathers():
    from cicfw.benchmark.suite import build_suite, make_backend
    from cicfw.core.errors import ConfigError

    with pytest.raises(ConfigError) as err:
        build_suite(make_backend(None), towns=["town_a"], weathers=["CloudyNoon", "HardRainNoon"], limit=1,
                    training_weathers=["Foggy"])
    assert (err.value.key, err.value.value) == ("suite.training_weathers", "Foggy")
    listed = str(err.value).split("(", 1)[1].split(")", 1)[0]
    assert listed == "CloudyNoon, HardRainNoon", str(err.value)


def test_a_run_folder_under_a_literal_tilde_is_refused(tmp_path):
    """Hydra does not expand '~' in hydra.run.dir: the run would land in a folder named '~' under the working
    directory (one a later `rm -rf ~` would aim at the home folder instead); refused before anything is made."""
    from conftest import assert_refused

    res = run_app_in_process("cicfw.evaluate", "policy=expert", "suite.limit=1", 'hydra.run.dir="~/runs/x"',
                             cwd=tmp_path, env=IN_PROCESS)
    assert_refused(res, "hydra.run.dir", "~/runs/x")
    assert not list(tmp_path.iterdir())


# ---- a dataset or a cache inside another app's run ------------------------------------------------


def results_folder(folder: Path) -> dict[Path, bytes]:
    """A reproduction's results folder as a run leaves it: its manifest and one cell with its training run."""
    folder.mkdir(parents=True)
    (folder / "reproduce.json").write_text(json.dumps({"budget": "smoke"}))
    cell = folder / "cells" / "cil" / "seed0"
    cell.mkdir(parents=True)
    (cell / "cell.json").write_text(json.dumps({"status": "ok", "row": "cil", "seed": 0}))
    (cell / "train" / "checkpoints").mkdir(parents=True)
    (cell / "train" / "checkpoints" / "last.ckpt").write_bytes(b"weights")
    (cell / "train" / "data.json").write_text(json.dumps(data_record("/data")))
    return _files(folder)


COLLECT_ONE = ["episodes=1", "seconds=2", "workers=0", "weathers=[ClearNoon]", "cameras=[centre]"]


@pytest.mark.parametrize("inside", ["run/checkpoints", "results/cells", "results/cells/cil/seed0/train/checkpoints",
                                    "run/checkpoints/new/deeper"])
def test_collect_into_a_folder_inside_another_apps_run_is_refused(tmp_path, inside):
    """A dataset among a training run's checkpoints or a reproduction's cells: refused before anything is
    written, the run's files untouched and no collect run folder left."""
    hydra_run(tmp_path / "run", "train", "checkpoints/last.ckpt")
    results_folder(tmp_path / "results")
    kept, paths = _files(tmp_path), sorted(tmp_path.rglob("*"))
    out = tmp_path / inside
    res = run_app_in_process("cicfw.collect", f"out_dir={out}", f"hydra.run.dir={tmp_path / 'collect_run'}",
                             *COLLECT_ONE, cwd=tmp_path, env=IN_PROCESS)
    assert_refused(res, "out_dir", out)
    assert _files(tmp_path) == kept and sorted(tmp_path.rglob("*")) == paths  # no folder made, no collect run


def test_a_folder_beside_a_stray_dataset_or_a_cells_folder_is_inside_no_run(tmp_path):
    """What makes a folder a run above another is that app's record: a folder merely named cells, a stray
    HDF5 file or a dataset above it is none (a dataset may be collected below another)."""
    from cicfw.core.run_folder import enclosing_run

    (tmp_path / "lab" / "cells" / "notes").mkdir(parents=True)
    (tmp_path / "lab" / "stray.h5").write_bytes(b"")
    assert enclosing_run(tmp_path / "lab" / "datasets" / "mine") is None
    (tmp_path / "lab" / "cells" / "cil" / "seed0").mkdir(parents=True)  # a reproduction's cell tree now
    assert enclosing_run(tmp_path / "lab" / "datasets" / "mine") == (tmp_path / "lab", "reproduce")
    hydra_run(tmp_path / "ev", "evaluate", "episodes.jsonl")
    assert enclosing_run(tmp_path / "ev") is None
    assert enclosing_run(tmp_path / "ev", include_self=True) == (tmp_path / "ev", "evaluate")


def test_a_project_folder_holding_files_other_tools_name_alike_is_no_run_above(tmp_path):
    """A project or home folder with some tool's report.json, a train.log beside checkpoints/ or an
    episodes.jsonl is no cicfw run: a collect or a cache below it goes ahead. Such names make an output
    folder itself someone's (``folder_owner``), never a folder above it."""
    from cicfw.core.run_folder import claim_outside_runs, enclosing_run

    proj = tmp_path / "proj"
    (proj / "checkpoints").mkdir(parents=True)
    (proj / "train.log").write_text("epoch 1 loss 0.3\n")
    (proj / "report.json").write_text('{"eslint": []}')
    (proj / "episodes.jsonl").write_text("{}\n")
    assert enclosing_run(proj / "data" / "sim") is None
    claim_outside_runs(proj / "data" / "sim", "collect", "out_dir")  # no refusal
    hydra_run(proj / "runs" / "a", "train", "checkpoints")  # a real cicfw run below it still counts
    assert enclosing_run(proj / "runs" / "a" / "checkpoints" / "x") == (proj / "runs" / "a", "train")


@pytest.mark.parametrize("cache", ["results", "results/cells/cil", "run/cache"])
def test_a_cache_inside_a_run_or_results_folder_is_refused_naming_the_variable(tmp_path, cache):
    """data=sim_default collects into $CICFW_CACHE/datasets/...: under a reproduction's results or a training
    run, the dataset would lie among that run's files."""
    hydra_run(tmp_path / "run", "train", "checkpoints/last.ckpt")
    results_folder(tmp_path / "results")
    kept, paths = _files(tmp_path), sorted(tmp_path.rglob("*"))
    args = ["trainer.fast_dev_run=true", "progress_bar=false", "speed.compile=false", "data.collect.episodes=1",
            "data.collect.seconds=2", f"hydra.run.dir={tmp_path / 'new_run'}"]
    res = run_app_in_process("cicfw.train", *args, cwd=tmp_path,
                             env={**IN_PROCESS, "CICFW_CACHE": str(tmp_path / cache)})
    assert_refused(res, "CICFW_CACHE", tmp_path / cache)
    assert _files(tmp_path) == kept and sorted(tmp_path.rglob("*")) == paths  # no dataset, no new run folder


@pytest.mark.parametrize("inside", ["run/checkpoints", "results/newdata", "run"])
def test_train_collecting_into_a_data_path_inside_another_apps_run_is_refused(tmp_path, inside):
    """data=sim_default collects into data.path: a folder inside (or being) a training run or a
    reproduction's results is refused as collect refuses its out_dir, naming data.path, before anything
    is collected and with no new run folder left."""
    hydra_run(tmp_path / "run", "train", "checkpoints/last.ckpt")
    results_folder(tmp_path / "results")
    kept, paths = _files(tmp_path), sorted(tmp_path.rglob("*"))
    data = tmp_path / inside
    args = ["trainer.fast_dev_run=true", "progress_bar=false", "speed.compile=false", "data.collect.episodes=1",
            "data.collect.seconds=2", f"data.path={data}", f"hydra.run.dir={tmp_path / 'new_run'}"]
    res = run_app_in_process("cicfw.train", *args, cwd=tmp_path,
                             env={**IN_PROCESS, "CICFW_CACHE": str(tmp_path / "cache")})
    assert_refused(res, "data.path", data)
    assert _files(tmp_path) == kept and sorted(tmp_path.rglob("*")) == paths  # no dataset, no new run folder


def test_a_collected_dataset_inside_a_run_is_still_read_by_train(tmp_path):
    """Only a folder train would collect into is claimed: a dataset already there (collect's own) passes."""
    from cicfw.train.app import make_collect_folder

    hydra_run(tmp_path / "run", "train", "checkpoints/last.ckpt")
    data = tmp_path / "run" / "mine"
    data.mkdir()
    (data / "dataset_metadata.json").write_text(json.dumps({"complete": True}))
    make_collect_folder(data)  # no refusal


# ---- the Python API owns its folder as its app does ----------------------------------------------
from conftest import TINY_TRAIN, compose_train  # noqa: E402


def api_train_run(folder: Path) -> dict[Path, bytes]:
    """A finished training run through the Python API (``train``), of other settings: its data record beside
    its checkpoint and metrics, no ``.hydra``."""
    outputs = {"checkpoints/last.ckpt": b"the other run's weights", "csv/metrics.csv": b"epoch,val/steer_mae\n0,0.5\n",
               "data.json": json.dumps(data_record("/elsewhere/data")).encode()}
    for name, data in outputs.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
    return _files(folder)


def users_files(folder: Path, *names: str) -> dict[Path, bytes]:
    """A folder holding a user's own files (no cicfw app wrote them)."""
    folder.mkdir(parents=True)
    for name in names:
        (folder / name).write_text(f"the user's own {name}\n")
    return _files(folder)


OTHER_FOLDERS = {
    "api training run": api_train_run,
    "app training run": lambda run: hydra_run(run, "train", "checkpoints/last.ckpt", "csv/metrics.csv"),
    "user's files": lambda run: users_files(run, "notes.md", "results.csv"),
}


def _tiny_train_cfg(data: Path, *extra: str):
    return compose_train(*TINY_TRAIN, f"data.path={data}", "trainer.limit_train_batches=1", *extra)


@pytest.mark.parametrize("other", list(OTHER_FOLDERS))
def test_train_from_python_into_another_runs_or_a_users_folder_is_refused(tmp_path, other):
    """``train(cfg, run_dir)`` claims and holds its folder as the app does, before it writes anything: the
    other run's checkpoint, metrics and data record (or the user's files) stay byte for byte."""
    from cicfw.core.run_folder import RunFolderError
    from cicfw.train.app import train

    cfg = _tiny_train_cfg(write_tiny_dataset(tmp_path / "data", n_files=4, n=16))
    run = tmp_path / "run"
    kept = OTHER_FOLDERS[other](run)
    with pytest.raises(RunFolderError) as err:
        train(cfg, run)
    assert str(run) in str(err.value) and "\n" not in str(err.value), str(err.value)
    assert _files(run) == kept and sorted(p.name for p in run.iterdir()) == sorted({p.relative_to(run).parts[0]
                                                                                      for p in kept})


def test_train_from_python_into_a_folder_another_run_holds_is_refused(tmp_path):
    """A folder another training run holds (its ``.train.lock``): ``FolderBusy`` naming it, nothing written."""
    from cicfw.core.locks import FolderBusy
    from cicfw.train.app import train

    cfg = _tiny_train_cfg(write_tiny_dataset(tmp_path / "data", n_files=4, n=16))
    run = tmp_path / "run"
    run.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom cicfw.core.run_folder import "
                               "TrainFolderLock\nTrainFolderLock(sys.argv[1]).acquire()\nprint('held', flush=True)\n"
                               "time.sleep(120)", str(run)], stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        assert holder.stdout.readline().strip() == "held"
        kept = _files(run)
        with pytest.raises(FolderBusy) as err:
            train(cfg, run)
        assert str(run) in str(err.value), str(err.value)
        assert _files(run) == kept and not (run / "checkpoints").exists() and not (run / "data.json").exists()
    finally:
        holder.kill()
        holder.wait()


def test_train_from_python_resumes_its_own_run_and_a_refused_call_leaves_nothing(tmp_path):
    """A call refused once its folder is held (a batch larger than the split) leaves no data record there, so
    the same call with the value fixed trains there; resuming that run in process (``ckpt_path`` inside it)
    goes on from its checkpoint."""
    from cicfw.core.errors import ConfigError
    from cicfw.train.app import train

    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    run = tmp_path / "run"
    with pytest.raises(ConfigError) as err:
        train(_tiny_train_cfg(data, "data.balanced=false", "data.batch_size=400"), run)
    assert err.value.key == "data.batch_size"
    assert not run.exists() or not list(run.iterdir())  # no data.json, no lock left behind
    train(_tiny_train_cfg(data), run)
    last = run / "checkpoints" / "last.ckpt"
    assert torch.load(last, map_location="cpu", weights_only=True)["epoch"] == 0
    train(_tiny_train_cfg(data, f"ckpt_path={last}", "trainer.max_epochs=2"), run)
    assert torch.load(last, map_location="cpu", weights_only=True)["epoch"] == 1
    assert (run / "data.json").is_file()


EVAL_OTHER_FOLDERS = {
    **OTHER_FOLDERS,
    "user's table and summary": lambda run: users_files(run, "table.md", "summary.json"),
}


@pytest.mark.parametrize("other", list(EVAL_OTHER_FOLDERS))
def test_evaluate_from_python_into_another_runs_or_a_users_folder_is_refused(tmp_path, other):
    """``evaluate(cfg, run_dir)`` claims its folder as the app does: a training run's folder or a user's own
    files (a ``table.md`` and ``summary.json`` it would write over) are refused, left byte for byte."""
    from cicfw.benchmark.app import compose_config, evaluate
    from cicfw.core.run_folder import RunFolderError

    run = tmp_path / "run"
    kept = EVAL_OTHER_FOLDERS[other](run)
    with pytest.raises(RunFolderError) as err:
        evaluate(compose_config(ONE_EPISODE), run)
    assert err.value.key == "run_dir" and str(run) in str(err.value), str(err.value)
    assert _files(run) == kept


def test_evaluate_checkpoint_into_a_users_table_and_summary_is_refused(tmp_path):
    from cicfw.benchmark.app import evaluate_checkpoint
    from cicfw.core.run_folder import RunFolderError

    ckpt = save_checkpoint(tmp_path / "model" / "best.ckpt")
    run = tmp_path / "run"
    kept = users_files(run, "table.md", "summary.json")
    with pytest.raises(RunFolderError) as err:
        evaluate_checkpoint(ckpt, run, ONE_EPISODE[1:])
    assert err.value.key == "run_dir" and str(run) in str(err.value), str(err.value)
    assert _files(run) == kept


# ---- a folder inside another app's run ---------------------------------------------------------------


def _paths(folder: Path) -> list[Path]:
    return sorted(folder.rglob("*"))


@pytest.mark.parametrize("run_dir", [".", "../csv"])
def test_evaluate_checkpoint_inside_a_training_run_is_refused_as_inside_it(tmp_path, monkeypatch, run_dir):
    """An evaluation into a training run's ``checkpoints`` (the working folder) or ``csv``: that run's files,
    refused as a folder inside it, not as files no cicfw app wrote; the run left byte for byte."""
    from cicfw.benchmark.app import evaluate_checkpoint
    from cicfw.core.run_folder import RunFolderError

    run = tmp_path / "run"
    kept = hydra_run(run, "train", "checkpoints/epoch001-mae0.1364.ckpt", "checkpoints/last.ckpt",
                     "csv/hparams.yaml", "csv/metrics.csv")
    paths = _paths(run)
    monkeypatch.chdir(run / "checkpoints")
    with pytest.raises(RunFolderError) as err:
        evaluate_checkpoint("last.ckpt", Path(run_dir), ONE_EPISODE[1:])
    line = str(err.value)
    assert err.value.key == "run_dir" and err.value.value == run_dir, line
    assert "inside" in line and "cicfw train" in line and str(run.resolve()) in line and "no cicfw app" not in line
    assert _files(run) == kept and _paths(run) == paths


@pytest.mark.parametrize("inside", ["ev/again", "results/cells/cil/seed0/mine"])
def test_train_from_python_inside_another_apps_run_is_refused(tmp_path, inside):
    """``train(cfg, run_dir)`` claims as the app does: a folder inside an evaluation's run or a reproduction's
    results is refused naming ``run_dir``, before anything is written there."""
    from cicfw.core.run_folder import RunFolderError
    from cicfw.train.app import train

    hydra_run(tmp_path / "ev", "evaluate", "episodes.jsonl")
    results_folder(tmp_path / "results")
    kept, paths = _files(tmp_path), _paths(tmp_path)
    with pytest.raises(RunFolderError) as err:
        train(compose_train(*TINY_TRAIN, f"data.path={tmp_path / 'data'}"), tmp_path / inside)
    assert err.value.key == "run_dir" and err.value.value == str(tmp_path / inside), str(err.value)
    assert "inside" in str(err.value)
    assert _files(tmp_path) == kept and _paths(tmp_path) == paths


def test_the_folders_cicfw_nests_in_a_run_stay_claimable(tmp_path):
    """The evaluation after training's ``<run>/evaluate`` (its resume: cicfw evaluate there), a sweep's job
    folder for the sweeping app and a run of the app's own kind are no folder inside another's run; the
    same folders for another app are."""
    from cicfw.core.run_folder import RunFolderError, claim_folder

    run = tmp_path / "run"
    hydra_run(run, "train", "checkpoints/last.ckpt")
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text("hydra:\n  job:\n    name: evaluate\n")
    for folder, app in [(run / "evaluate", "diagnose"), (run / "checkpoints", "diagnose"), (sweep / "3", "train")]:
        with pytest.raises(RunFolderError) as err:
            claim_folder(folder, app, "hydra.run.dir")
        assert err.value.key == "hydra.run.dir" and err.value.value == str(folder) and "inside" in str(err.value)
    claim_folder(run / "evaluate", "evaluate", "hydra.run.dir")  # missing
    (run / "evaluate").mkdir()
    claim_folder(run / "evaluate", "evaluate", "hydra.run.dir")  # empty
    (run / "evaluate" / "episodes.jsonl").write_text(EPISODE_LOG_HEADER)
    claim_folder(run / "evaluate", "evaluate", "hydra.run.dir")  # the evaluation's
    claim_folder(run / "more", "train", "run_dir")  # the same app's run around it
    claim_folder(sweep / "3", "evaluate", "hydra.run.dir")


# ---- a run's records copied beside a user's files do not make them the run's ------------------------------
def test_an_evaluation_s_hydra_copied_beside_a_user_s_tables_does_not_make_them_its_own(tmp_path):
    """A real evaluation's ``.hydra`` (cicfw's callbacks, job evaluate) copied into a folder of the user's own
    ``table.md`` and ``summary.json``: without an episode log they are the user's, and the evaluation is refused
    before it writes anything."""
    mine = tmp_path / "mine"
    hydra_run(mine, "evaluate")
    (mine / "table.md").write_text("# my table\n")
    (mine / "summary.json").write_text('{"mine": 1}')
    kept = _files(mine)
    res = run_app_in_process("cicfw.evaluate", *ONE_EPISODE, f"hydra.run.dir={mine}", env=IN_PROCESS)
    assert_refused(res, "hydra.run.dir", str(mine))
    assert "summary.json" in res.stderr and "table.md" in res.stderr
    assert _files(mine) == kept


def test_a_training_run_s_hydra_copied_beside_a_user_s_manifest_does_not_make_it_a_record(tmp_path):
    from cicfw.core.run_folder import RunFolderError, claim_folder

    mine = tmp_path / "mine"
    hydra_run(mine, "train")
    (mine / "data.json").write_text('{"mine": "manifest v1", "files": []}')
    kept = _files(mine)
    with pytest.raises(RunFolderError) as err:
        claim_folder(mine, "train", "hydra.run.dir")
    assert err.value.key == "hydra.run.dir" and "data.json" in str(err.value)
    (mine / "data.json").write_text(json.dumps(data_record("/data")))  # its own record: its run, resumed
    claim_folder(mine, "train", "hydra.run.dir")
    assert _files(mine) != kept


def test_a_reproduction_s_cell_is_no_run_to_train_or_evaluate_into(tmp_path):
    """A cell's ``train`` and ``evaluate`` folders are its own kind of run, but the reproduction's: training
    there replaced the weights its table drove, evaluating there rewrote its report."""
    from cicfw.core.run_folder import RunFolderError, claim_folder

    results = tmp_path / "results"
    cell = results / "cells" / "cil" / "seed0"
    (results / "reproduce.json").parent.mkdir(parents=True)
    (results / "reproduce.json").write_text("{}")
    api_train_run(cell / "train")
    (cell / "evaluate").mkdir(parents=True)
    (cell / "evaluate" / "episodes.jsonl").write_text(json.dumps({"format": "cicfw-episode-log/1"}) + "\n")
    kept = _files(results)
    for app in ("train", "evaluate"):
        with pytest.raises(RunFolderError) as err:
            claim_folder(cell / app, app, "hydra.run.dir")
        assert err.value.value == str(cell / app) and str(results) in str(err.value)
    assert _files(results) == kept


def _hard_linked_copy(src: Path, dst: Path) -> None:
    """``cp -al src dst``: the folders, with every file linked, not copied."""
    for p in sorted(src.rglob("*")):
        if p.is_dir():
            (dst / p.relative_to(src)).mkdir(parents=True, exist_ok=True)
        else:
            (dst / p.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
            os.link(p, dst / p.relative_to(src))


def test_an_evaluation_resumed_in_a_hard_linked_copy_leaves_the_original_as_it_was(one_episode_eval, tmp_path):
    """A ``cp -al`` copy shares its files' inodes: Hydra rewrote the original's .hydra records and appended to
    its evaluate.log through the copy's run."""
    original = tmp_path / "original"
    _hard_linked_copy(one_episode_eval, original)  # a private original first: the shared fixture stays apart
    from cicfw.core.files import unshare_links

    unshare_links(original)
    kept = _files(original)
    _hard_linked_copy(original, tmp_path / "copy")
    res = _evaluate(tmp_path / "copy", "name=Copy")
    assert res.returncode == 0, res.stderr[-3000:]
    assert _files(original) == kept
    assert b"Copy" in (tmp_path / "copy" / ".hydra" / "overrides.yaml").read_bytes()
