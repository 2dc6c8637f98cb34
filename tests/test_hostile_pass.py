"""Inputs a new user gets wrong that once gave a silently wrong result: each is now refused or honoured."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cicfw.benchmark.suite import build_suite, make_backend
from cicfw.core.errors import ConfigError

TOWN = Path(__file__).parent / "data" / "bench_town.yaml"


@pytest.mark.parametrize("second", ["copy", "builtin"])
def test_two_towns_of_one_name_are_refused(tmp_path: Path, second: str) -> None:
    """Episodes are keyed <town>/<weather>/<pair> by the town's name (a file's stem): two towns of one name
    would share keys, so one episode's trajectory and map would be the other's."""
    first = tmp_path / "a" / "town_b.yaml"
    first.parent.mkdir()
    shutil.copy(TOWN, first)
    other = str(shutil.copy(TOWN, tmp_path / "town_b.yaml")) if second == "copy" else "town_b"
    with pytest.raises(ConfigError) as err:
        build_suite(make_backend(None), [str(first), other], ["ClearNoon"], training_towns=["town_a"], limit=1)
    assert err.value.key == "suite.towns" and err.value.value == other


def test_towns_of_distinct_names_are_driven(tmp_path: Path) -> None:
    first = Path(shutil.copy(TOWN, tmp_path / "mine.yaml"))
    eps = build_suite(make_backend(None), [str(first), "town_b"], ["ClearNoon"], training_towns=["mine"], limit=1)
    assert len({e.key for e in eps}) == len(eps) == 2


def _ckpt(folder: Path, *names: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"x")


def test_a_run_folder_means_its_own_checkpoint_not_a_nested_run(tmp_path: Path) -> None:
    """A run trained in a folder inside another run's: ``checkpoint=<outer run>`` is the outer run's
    ``last.ckpt``, never the nested run's best checkpoint."""
    from cicfw.model.checkpoint import resolve_checkpoint

    run = tmp_path / "run"
    _ckpt(run / "checkpoints", "last.ckpt")
    _ckpt(run / "nested" / "checkpoints", "epoch000-mae0.2771.ckpt", "last.ckpt")
    assert resolve_checkpoint(run) == (run / "checkpoints" / "last.ckpt").resolve()
    _ckpt(run / "checkpoints", "epoch001-mae0.2000.ckpt")
    assert resolve_checkpoint(run) == (run / "checkpoints" / "epoch001-mae0.2000.ckpt").resolve()


def test_a_run_folder_never_means_a_kept_epoch_checkpoint(tmp_path: Path) -> None:
    """keep_epoch_checkpoints' epochNNN.ckpt is no best checkpoint: a run that never validated (or with a
    best beside kept epochs) means its last.ckpt (or that best), not the weights after an earlier epoch."""
    from cicfw.model.checkpoint import resolve_checkpoint

    run = tmp_path / "run"
    _ckpt(run / "checkpoints", "epoch001.ckpt", "last.ckpt")  # two epochs, no validation: epoch 1 kept
    assert resolve_checkpoint(run) == (run / "checkpoints" / "last.ckpt").resolve()
    _ckpt(run / "checkpoints", "epoch002.ckpt", "epoch001-mae0.2000.ckpt")
    assert resolve_checkpoint(run) == (run / "checkpoints" / "epoch001-mae0.2000.ckpt").resolve()


def test_a_reproduction_cell_means_the_weights_its_table_drove(tmp_path: Path) -> None:
    """A cell drives its last epoch's weights; its folder resolved to the best validation checkpoint instead."""
    from cicfw.model.checkpoint import resolve_checkpoint

    cell = tmp_path / "cells" / "gtu" / "seed0"
    _ckpt(cell / "train" / "checkpoints", "epoch000-mae0.2000.ckpt", "epoch001.ckpt", "epoch002.ckpt", "last.ckpt")
    (cell / "cell.json").write_text('{"row": "gtu", "seed": 0, "epochs": 2}')
    assert resolve_checkpoint(cell) == (cell / "train" / "checkpoints" / "epoch002.ckpt").resolve()
    assert resolve_checkpoint(cell / "train").name == "epoch000-mae0.2000.ckpt"  # a run folder: its best


def _cell(tmp_path: Path, last: dict | None, **recorded) -> Path:
    """A finished cell of two epochs whose final epoch002.ckpt is gone; ``last``: its last.ckpt's dict."""
    import json

    import torch

    cell = tmp_path / "cells" / "gtu" / "seed0"
    _ckpt(cell / "train" / "checkpoints", "epoch001-mae0.2000.ckpt", "epoch001.ckpt")
    if last is not None:
        torch.save(last, cell / "train" / "checkpoints" / "last.ckpt")
    (cell / "cell.json").write_text(json.dumps({"row": "gtu", "seed": 0, "status": "ok", "epochs": 2, **recorded}))
    return cell


def test_a_cell_without_its_final_epoch_file_means_its_last_checkpoint_of_that_epoch(tmp_path: Path) -> None:
    """The final epochNNN.ckpt deleted, last.ckpt kept: the cell's folder means last.ckpt (Lightning's 0-based
    epoch 1 is the second), never the best validation checkpoint."""
    from cicfw.model.checkpoint import resolve_checkpoint

    cell = _cell(tmp_path, {"epoch": 1, "global_step": 8}, samples_seen=8 * 4, recipe={"data": {"batch_size": 4}})
    assert resolve_checkpoint(cell) == (cell / "train" / "checkpoints" / "last.ckpt").resolve()


@pytest.mark.parametrize("last, recorded", [
    (None, {}),  # no last.ckpt
    ({"epoch": 0, "global_step": 4}, {}),  # an earlier epoch's
    ({"epoch": 2, "global_step": 12}, {}),  # trained on after the cell
    ({"epoch": 1, "global_step": 7}, {"samples_seen": 32, "recipe": {"data": {"batch_size": 4}}}),  # other steps
    (None, {"epochs": None, "status": "failed"}),  # a cell that never finished
])
def test_a_cell_without_its_final_weights_is_refused(tmp_path: Path, last, recorded) -> None:
    from cicfw.model.checkpoint import CheckpointError, resolve_checkpoint

    cell = _cell(tmp_path, last, **recorded)
    with pytest.raises(CheckpointError) as err:
        resolve_checkpoint(cell)
    assert err.value.key == "checkpoint" and err.value.value == str(cell)
    if "epochs" not in recorded:
        assert "epoch002.ckpt" in str(err.value)


def test_a_cell_s_last_checkpoint_written_by_lightning_is_its_final_epoch_s(tmp_path: Path) -> None:
    """Real checkpoints: train's last.ckpt and its kept epoch002.ckpt after two epochs record the same epoch
    and step, so a cell that lost epoch002.ckpt resolves to that last.ckpt; after a third epoch it is refused."""
    import json

    import lightning as L
    import torch
    from torch.utils.data import DataLoader

    from cicfw.model.checkpoint import CheckpointError, resolve_checkpoint
    from cicfw.model.module import CICModule
    from cicfw.train.app import EpochCheckpoints, last_checkpoint

    frames = [{"image": torch.full((3, 88, 200), i * 20, dtype=torch.uint8), "speed": torch.tensor(10.0),
               "command": torch.tensor(i % 4), "steer": torch.tensor(0.0)} for i in range(4)]
    cell = tmp_path / "cell"
    ckpts = cell / "train" / "checkpoints"

    def fit(epochs: int, ckpt_path: str | None = None) -> None:
        L.seed_everything(0)
        trainer = L.Trainer(max_epochs=epochs, limit_val_batches=0, logger=False, enable_progress_bar=False,
                            enable_model_summary=False, accelerator="cpu", default_root_dir=tmp_path,
                            callbacks=[last_checkpoint(ckpts), EpochCheckpoints(ckpts, [epochs], epochs)])
        trainer.fit(CICModule(), DataLoader(frames, batch_size=2), ckpt_path=ckpt_path)

    fit(2)
    final = torch.load(ckpts / "epoch002.ckpt", weights_only=True)
    (cell / "cell.json").write_text(json.dumps({"status": "ok", "epochs": final["epoch"] + 1,
                                                "samples_seen": final["global_step"] * 2,
                                                "recipe": {"data": {"batch_size": 2}}}))
    (ckpts / "epoch002.ckpt").unlink()
    assert resolve_checkpoint(cell) == (ckpts / "last.ckpt").resolve()
    fit(3, str(ckpts / "last.ckpt"))  # trained on: last.ckpt is no longer the cell's final weights
    (ckpts / "epoch003.ckpt").unlink()
    with pytest.raises(CheckpointError) as err:
        resolve_checkpoint(cell)
    assert err.value.key == "checkpoint" and "epoch002.ckpt" in str(err.value)


def test_a_folder_above_several_runs_is_refused(tmp_path: Path) -> None:
    from cicfw.model.checkpoint import CheckpointError, resolve_checkpoint

    _ckpt(tmp_path / "day" / "a" / "checkpoints", "epoch000-mae0.3000.ckpt", "last.ckpt")
    _ckpt(tmp_path / "day" / "b" / "checkpoints", "last.ckpt")
    with pytest.raises(CheckpointError) as err:
        resolve_checkpoint(tmp_path / "day")
    assert err.value.key == "checkpoint" and err.value.value == tmp_path / "day"
    assert resolve_checkpoint(tmp_path / "day" / "b") == (tmp_path / "day" / "b" / "checkpoints" / "last.ckpt").resolve()
    assert resolve_checkpoint(tmp_path / "day" / "a" / "checkpoints").name == "epoch000-mae0.3000.ckpt"


@pytest.mark.parametrize("threads", [-1, 0, 1.5, True, "2"])
def test_agent_threads_must_be_a_count(tmp_path: Path, threads: object) -> None:
    """threads=-1 reached torch.set_num_threads as a RuntimeError traceback (a checkpoint), or onnxruntime
    as its default (an exported model): refused as one line before the model is read."""
    from cicfw.core.errors import CicfwError
    from cicfw.export.agent import Agent

    with pytest.raises(CicfwError) as err:
        Agent.load(tmp_path / "not-read.ckpt", threads=threads)
    assert err.value.key == "threads" and err.value.value == threads


def test_an_onnx_model_is_known_by_any_case_or_through_a_link(tmp_path: Path, monkeypatch) -> None:
    """'M.ONNX', or a link 'model' to 'm.onnx', was read as a PyTorch checkpoint and refused as one."""
    from cicfw.export.agent import Agent

    monkeypatch.setattr(Agent, "_load_onnx", classmethod(lambda cls, p, threads: ("onnx", p.name)))
    (tmp_path / "M.ONNX").write_bytes(b"\x08\x07")
    (tmp_path / "m.onnx").write_bytes(b"\x08\x07")
    (tmp_path / "model").symlink_to(tmp_path / "m.onnx")
    assert Agent.load(tmp_path / "M.ONNX") == ("onnx", "M.ONNX")
    assert Agent.load(tmp_path / "model") == ("onnx", "model")


@pytest.mark.parametrize("device", ["cuda", "cuda:0"])
def test_an_onnx_model_asked_to_run_on_a_gpu_is_refused(tmp_path: Path, monkeypatch, device) -> None:
    """onnxruntime runs the model on the CPU here: device='cuda' ran it there without a word."""
    from cicfw.core.errors import CicfwError
    from cicfw.export.agent import Agent

    monkeypatch.setattr(Agent, "_load_onnx", classmethod(lambda cls, p, threads: ("onnx", p.name)))
    (tmp_path / "m.onnx").write_bytes(b"\x08\x07")
    with pytest.raises(CicfwError) as err:
        Agent.load(tmp_path / "m.onnx", device=device)
    assert (err.value.key, err.value.value) == ("device", device)
    assert Agent.load(tmp_path / "m.onnx", device="auto") == ("onnx", "m.onnx")


def test_an_edited_town_file_is_another_evaluation(tmp_path: Path) -> None:
    """A town file edited between two runs into one folder kept its route names, so the rerun resumed
    (or, finished, reported) the episodes driven in the old town: the fingerprint holds its contents."""
    from cicfw.benchmark.app import run_fingerprint
    from cicfw.benchmark.runner import RunnerConfig

    town = Path(shutil.copy(TOWN, tmp_path / "mine.yaml"))
    suite = {"towns": [str(town)], "weathers": ["ClearNoon"], "limit": 1}

    def fingerprint() -> dict:
        eps = build_suite(make_backend(None), [str(town)], ["ClearNoon"], training_towns=["mine"], limit=1)
        return run_fingerprint({"name": "expert"}, suite, {"name": "embedded"}, RunnerConfig(), eps)[0]

    before = fingerprint()
    assert fingerprint() == before
    town.write_text(town.read_text().replace("lane_width:", "lane_width: 3.5 #", 1))
    assert fingerprint() != before
    builtin = build_suite(make_backend(None), ["town_b"], ["ClearNoon"], training_towns=["town_a"], limit=1)
    assert "town_files" not in run_fingerprint({"name": "expert"}, {"towns": ["town_b"]}, {"name": "embedded"},
                                               RunnerConfig(), builtin)[0]


def test_checkpoint_and_policy_checkpoint_naming_two_models_are_refused() -> None:
    """policy.checkpoint= replaces the ${checkpoint} it defaults to, so checkpoint=b was silently ignored
    and a drove (the report named a as well)."""
    from omegaconf import OmegaConf

    from cicfw.benchmark.app import policy_spec
    from cicfw.core.errors import CicfwError

    def cfg(top: str | None, own: str | None):
        c = OmegaConf.create({"checkpoint": top, "name": None,
                              "policy": {"name": "checkpoint", "checkpoint": "${checkpoint}"}})
        if own is not None:
            c.policy.checkpoint = own
        return c

    with pytest.raises(CicfwError) as err:
        policy_spec(cfg("b.ckpt", "a.ckpt"))
    assert err.value.key == "policy.checkpoint" and err.value.value == "a.ckpt"
    assert policy_spec(cfg("b.ckpt", None))["checkpoint"] == "b.ckpt"
    assert policy_spec(cfg(None, "a.ckpt"))["checkpoint"] == "a.ckpt"
    assert policy_spec(cfg("a.ckpt", "a.ckpt"))["checkpoint"] == "a.ckpt"


def _run_with_config(run: Path, mixer: str) -> None:
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(
        f"seed: 7\nencoder: {{name: cil}}\nmixer: {{name: {mixer}}}\nhead: {{name: regression}}\n"
        f"data: {{path: /data, seed: 7, val_fraction: 0.3}}\n")


def _checkpoint(path: Path, mixer: str) -> Path:
    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": {}, "hyper_parameters": {"encoder": "cil", "mixer": mixer, "head": "regression"}}, path)
    return path


def test_a_checkpoint_in_another_runs_folder_does_not_borrow_its_config(tmp_path: Path) -> None:
    """A gtu checkpoint copied into an independent run's checkpoints/ took that run's config: the export
    sidecar's row_config named the other model, and diagnose drew the other run's split."""
    from cicfw.diagnose.app import training_data
    from cicfw.model.checkpoint import config_parts_differ

    run = tmp_path / "run"
    _run_with_config(run, "independent")
    own = _checkpoint(run / "checkpoints" / "last.ckpt", "independent")
    foreign = _checkpoint(run / "checkpoints" / "copied.ckpt", "gtu")
    assert training_data(own) is not None and training_data(own)[0]["seed"] == 7
    assert training_data(foreign) is None
    cfg = {"encoder": {"name": "cil"}, "mixer": {"name": "independent"}, "head": {"name": "regression"}}
    assert config_parts_differ(cfg, {"encoder": "cil", "mixer": "independent", "head": "regression"}) is None
    assert "gtu" in config_parts_differ(cfg, {"encoder": "cil", "mixer": "gtu", "head": "regression"})
    assert config_parts_differ({"cell": {"row": "cil"}}, {"mixer": "gtu"}) is None


def test_a_pair_listed_twice_is_refused() -> None:
    """suite.pairs=[0,0] drove pair 0 twice under one key and counted it twice in the table."""
    with pytest.raises(ConfigError) as err:
        build_suite(make_backend(None), ["town_a"], ["ClearNoon"], training_towns=["town_a"], pairs=[0, 3, 0])
    assert (err.value.key, err.value.value) == ("suite.pairs", 0)
    assert len(build_suite(make_backend(None), ["town_a"], ["ClearNoon"], training_towns=["town_a"], pairs=[0, 3])) == 2


def test_a_collection_inside_another_collected_dataset_is_refused(tmp_path: Path) -> None:
    """Data folders are read recursively: episodes collected into a folder inside another collection's joined
    that dataset for everyone training on it (10 files where its metadata listed 8)."""
    from cicfw.collect.dataset import collect_dataset
    from cicfw.collect.errors import CollectConfigError
    from cicfw.collect.metadata import META_NAME

    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / META_NAME).write_text("{}")
    with pytest.raises(CollectConfigError) as err:
        collect_dataset({"episodes": 1, "seconds": 0.1, "workers": 0}, tmp_path / "ds" / "more", progress=False)
    assert err.value.key == "out_dir" and err.value.value == tmp_path / "ds" / "more"
    assert not (tmp_path / "ds" / "more").exists()


def _report_run(folder: Path, sim: dict, runner: dict | None = None) -> Path:
    from cicfw.benchmark.evaluation_report import Run, write_run

    row = {"episode": 0, "key": "town_a/ClearNoon/000", "town": "town_a", "weather": "ClearNoon",
           "town_set": "training", "weather_set": "training", "pair": 0, "route": "town_a/j/a>b/left",
           "command": "left", "success": True, "reason": "success", "time_s": 1.0, "timeout_s": 30.0,
           "distance_m": 50.0, "route_length_m": 50.0, "goal_distance_m": 1.0, "progress": 1.0,
           "offroad_fraction": 0.0, "opposite_lane_fraction": 0.0, "steps": 10}
    suite = {"name": "junctions", "training_towns": ["town_a"], "training_weathers": ["ClearNoon"]}
    runner = runner or {"off_road_s": 3.0, "off_road_level": 0.5, "target_speed_kmh": None}
    write_run(folder, Run("Expert", [row], {"suite": suite, "fingerprint": {"sim": sim, "runner": runner}}))
    return folder


@pytest.mark.parametrize("key, other", [("sim.success_radius", 8.0), ("sim.weather_family", "harsh"),
                                        ("runner.off_road_s", 1.0)])
def test_report_refuses_runs_of_other_episode_rules(tmp_path: Path, key: str, other) -> None:
    """A run with an 8 m success radius (or another weather family, other off-road rules) joined beside one
    with 2 m made one table whose rows measured different things, exit 0 and no mark."""
    from cicfw.benchmark.evaluation_report import find_runs
    from cicfw.core.errors import CicfwError

    sim = {"name": "embedded", "success_radius": 2.0, "weather_family": "carla"}
    runner = {"off_road_s": 3.0, "off_road_level": 0.5, "target_speed_kmh": None}
    part, name = key.split(".")
    changed = {"sim": dict(sim), "runner": dict(runner)}
    changed[part][name] = other
    a = _report_run(tmp_path / "a", sim, runner)
    b = _report_run(tmp_path / "b", changed["sim"], changed["runner"])
    with pytest.raises(CicfwError) as err:
        find_runs([a, b])
    assert err.value.key == key and err.value.value == other
    # the same rules join; a key only one run records (an older cicfw's) is not compared
    c = _report_run(tmp_path / "c", {**sim, "route_after": 25.0}, runner)
    assert len(find_runs([a, c])) == 2


@pytest.mark.parametrize("job", ["train", "evaluate"])
def test_collect_into_another_apps_run_folder_is_refused(tmp_path: Path, job: str, monkeypatch, capsys) -> None:
    """Collecting into a training or evaluation run's folder wrote the episodes beside the run's files, exit 0;
    the folder then read as a dataset (a training resume there was refused as writing over a dataset)."""
    from hydra import compose, initialize_config_module

    import cicfw.collect.app as collect_app
    import cicfw.collect.dataset as dataset_mod

    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "hydra.yaml").write_text(f"hydra:\n  callbacks:\n    run_folder:\n      _target_: "
                                               f"cicfw.core.run_folder.RunFolderCheck\n  job:\n    name: {job}\n")
    (run / f"{job}.log").write_text("a line\n")
    before = sorted(p.name for p in run.rglob("*"))
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("collected into a run folder"))
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("collect", overrides=[f"out_dir={run}", "episodes=1", "seconds=1", "workers=0"])
    with pytest.raises(SystemExit) as exc:
        collect_app.run(cfg)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "out_dir" in err and str(run) in err
    assert sorted(p.name for p in run.rglob("*")) == before


def test_evaluate_sweep_into_a_folder_of_another_sweep_leaves_its_records(tmp_path: Path) -> None:
    """A second evaluate sweep (other values) into a sweep folder wrote over multirun.yaml and job 0's
    .hydra before job 0 refused the other episodes: the folder's records then named settings its episodes
    were not driven with. The same sweep's command still resumes there."""
    from conftest import run_app_in_process

    sweep = tmp_path / "sweep"
    base = ["-m", "policy=expert", "suite.towns=[town_a]", "suite.weathers=[ClearNoon]", "suite.limit=1",
            "progress_bar=false", "maps=false", f"hydra.sweep.dir={sweep}"]
    first = run_app_in_process("cicfw.evaluate", *base, "sim.success_radius=2,6")
    assert first.returncode == 0, first.stderr[-2000:]
    before = {p: p.read_bytes() for p in sweep.rglob("*") if p.is_file()}
    other = run_app_in_process("cicfw.evaluate", *base, "sim.success_radius=3,4")
    assert other.returncode == 2 and "hydra.sweep.dir" in other.stderr and "success_radius=3,4" in other.stderr
    assert {p: p.read_bytes() for p in sweep.rglob("*") if p.is_file()} == before
    again = run_app_in_process("cicfw.evaluate", *base, "sim.success_radius=2,6")
    assert again.returncode == 0, again.stderr[-2000:]


def test_fast_dev_run_keeps_a_users_data_folder(tmp_path: Path) -> None:
    """fast_dev_run(<a project folder>) wrote its random tiny dataset over <folder>/data/data_00000.h5 ..."""
    from cicfw.core.errors import CicfwError
    from cicfw.testing import fast_dev_run

    mine = tmp_path / "data" / "data_00000.h5"
    mine.parent.mkdir()
    mine.write_bytes(b"the user's episode")
    with pytest.raises(CicfwError) as err:
        fast_dev_run(tmp_path)
    assert err.value.key == "tmp_path" and err.value.value == str(tmp_path)
    assert mine.read_bytes() == b"the user's episode"


def test_diagnose_on_another_dataset_counts_the_files_that_folder_holds(tmp_path: Path) -> None:
    """data.path=<a collected dataset of 4 episodes> for a checkpoint trained on 6 other files was refused
    as '(0 files, hash ...)': the count of the recorded files found there, read as what the folder holds."""
    import re

    import torch

    from cicfw.data.provenance import CHECKPOINT_KEY, record_data
    from cicfw.model.module import CICModule
    from conftest import assert_refused, run_app_in_process, write_tiny_dataset
    from test_diagnose import write_episodes

    trained_on = write_tiny_dataset(tmp_path / "trained_on")  # 6 files
    other = write_episodes(tmp_path / "collected", n_files=4)
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True)
    model = CICModule()
    torch.save({"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams),
                CHECKPOINT_KEY: record_data(trained_on)}, ckpt)
    res = run_app_in_process("cicfw.diagnose", f"checkpoint={ckpt}", f"data.path={other}", "data.seed=0",
                             f"hydra.run.dir={tmp_path / 'out'}", "threads=1")
    line = assert_refused(res, "data.path", other)
    assert not re.search(r"\b0 files?\b", line) and re.search(r"\b4 HDF5 file", line), line
    assert re.search(r"\b6 files\b", line), line  # the recorded data, counted as files too


@pytest.mark.parametrize("suffix", [".pt", ".onnx"])
def test_an_exported_model_given_as_checkpoint_says_what_it_is(tmp_path: Path, suffix: str) -> None:
    """checkpoint=<a model export wrote> to export or diagnose was 'not a PyTorch checkpoint, or it is
    truncated': it is an exported model, and the checkpoint it came from (its sidecar names it) is wanted."""
    import json

    import torch

    from cicfw.model.checkpoint import CheckpointError, read_checkpoint
    from conftest import assert_refused, run_app_in_process

    model = tmp_path / f"cil{suffix}"
    if suffix == ".pt":  # a TorchScript archive, as torch.jit.save writes it (export's is one too)
        torch.jit.save(torch.jit.script(torch.nn.Linear(2, 1)), str(model))
    else:
        model.write_bytes(b"\x08\x07")
    source = tmp_path / "run" / "checkpoints" / "epoch003.ckpt"
    model.with_name(model.name + ".json").write_text(json.dumps({"checkpoint": {"path": str(source)}}))
    res = run_app_in_process("cicfw.export", f"checkpoint={model}", "format=torchscript",
                             f"out={tmp_path / 'again.pt'}")
    line = assert_refused(res, f"checkpoint={str(model)!r}")
    assert str(source) in line and not (tmp_path / "again.pt").exists(), line
    with pytest.raises(CheckpointError) as err:  # diagnose reads it so
        read_checkpoint(model)
    assert err.value.key == "checkpoint" and err.value.value == str(model) and str(source) in str(err.value)


@pytest.mark.parametrize("speed, command", [(np.full((2, 2), 10.0), [2, 3, 4, 5]),
                                            ([10.0] * 4, np.full((2, 2), 2)), (np.full((4, 1), 10.0), [2] * 4)])
def test_the_agent_refuses_a_speed_or_command_not_shaped_as_the_batch(tmp_path: Path, speed, command) -> None:
    """Agent.act(4 images, speed of shape (2, 2), ...) flattened the speeds and drove: refused, naming the
    argument and the shape seen, before the model runs. One value per image, (B,), still drives."""
    from cicfw.export.agent import Agent, AgentInputError

    agent = Agent(lambda img, s, c: pytest.fail("the model ran"), {}, "test")
    images = np.zeros((4, 88, 200, 3), np.uint8)
    with pytest.raises(AgentInputError) as err:
        agent.act(images, speed, command)
    bad = np.asarray(speed if np.ndim(speed) > 1 else command)
    assert err.value.key == ("speed_kmh" if np.ndim(speed) > 1 else "command")
    assert err.value.value == str(bad.shape).replace(",)", ")") and "\n" not in str(err.value)
    with pytest.raises(AgentInputError) as err:
        agent.act(images[0], np.full((1, 1), 10.0), 2)
    assert err.value.key == "speed_kmh" and err.value.value == "(1, 1)"
    driven = Agent(lambda img, s, c: s / 10.0, {}, "test")
    assert driven.act(images, [10.0, 20.0, 30.0, 40.0], [2, 3, 4, 5]).tolist() == [1.0, 2.0, 3.0, 4.0]
    assert driven.act(images[0], 10.0, 2) == 1.0


@pytest.mark.parametrize("override, key, value", [("mixer=nosuch", "mixer", "nosuch"),
                                                  ("model.lr=abc", "model.lr", None),
                                                  ("+evaluate_aftr=true", "evaluate_aftr", None),
                                                  ("+data.nosuch=1", "data.nosuch", None)])
def test_fast_dev_run_refuses_a_bad_override_as_the_cli_does(tmp_path: Path, override: str, key: str, value) -> None:
    """fast_dev_run(folder, "mixer=nosuch") raised Hydra's MissingConfigException with its traceback (after
    writing the tiny dataset), and a +key that composes but train refuses came only after the dataset was
    written: now the one-line cicfw error the CLI prints, before anything is written."""
    from cicfw.core.errors import CicfwError
    from cicfw.testing import fast_dev_run
    from conftest import assert_refused, run_app_in_process

    with pytest.raises(CicfwError) as err:
        fast_dev_run(tmp_path / "fresh", override)
    assert err.value.key == key and (value is None or err.value.value == value)
    assert err.value.__suppress_context__ and "\n" not in str(err.value)
    assert not (tmp_path / "fresh").exists()
    cli = run_app_in_process("cicfw.train", override, f"hydra.run.dir={tmp_path / 'run'}")
    assert assert_refused(cli, key, value) == f"cicfw: error: {err.value}"


def test_a_run_folder_without_hydra_records_is_still_its_apps_own(tmp_path: Path) -> None:
    """hydra.output_subdir=null leaves no .hydra: a training run's folder was then 'files that no cicfw app
    wrote', so resuming it was refused. Its job log beside the app's own outputs names the app; either one
    alone does not."""
    from cicfw.core.run_folder import RunFolderError, claim_folder, folder_owner

    run = tmp_path / "train_run"
    _ckpt(run / "checkpoints", "last.ckpt")
    (run / "train.log").write_text("a line\n")
    (run / "data.json").write_text(json.dumps({"path": "/data", "root": "/data", "files": [], "hash": "0" * 64,
                                               "hash_of": "names, sizes and SHA-256", "n_files": 0}))
    assert folder_owner(run) == "train"
    claim_folder(run, "train", "hydra.run.dir")
    with pytest.raises(RunFolderError) as err:
        claim_folder(run, "evaluate", "hydra.run.dir")
    assert err.value.key == "hydra.run.dir" and err.value.value == str(run) and "train" in str(err.value)
    diag = tmp_path / "diagnosis"
    diag.mkdir()
    (diag / "diagnose.log").write_text("")
    (diag / "steer_diagnostic.json").write_text("{}")
    assert folder_owner(diag) == "diagnose"
    for name in ("train.log", "data.json"):  # the log alone, or an output alone: no app's run
        alone = tmp_path / f"only_{name}"
        alone.mkdir()
        (alone / name).write_text("")
        assert folder_owner(alone) is None
        with pytest.raises(RunFolderError):
            claim_folder(alone, "train", "hydra.run.dir")


def test_a_results_folder_holding_only_its_reproduce_log_is_claimed_by_reproduce_alone(tmp_path: Path) -> None:
    """reproduce's own log (or a shell's redirect of its output there) makes no folder the reproduction's, but
    reproduce itself may go on in a folder holding only it (appending); another app finds a file of no app."""
    from cicfw.core.run_folder import RunFolderError, claim_folder, folder_owner

    out = tmp_path / "results"
    out.mkdir()
    (out / "reproduce.log").write_text("[12:00:00][cicfw.reproduce] 4 cells in 60 s; report: RESULTS.md\n")
    assert folder_owner(out) is None
    claim_folder(out, "reproduce", "results_dir")
    with pytest.raises(RunFolderError) as err:
        claim_folder(out, "train", "hydra.run.dir")
    assert err.value.key == "hydra.run.dir" and err.value.value == str(out)


def _user_folder(folder: Path, files: dict[str, str]) -> dict[str, bytes]:
    for name, text in files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


_RESULTS = {"RESULTS.md": "# my study\n", "results.csv": "a,b\n1,2\n", "results.json": '{"mine": 1}'}
USER_FOLDERS = {
    "reproduce.log": ("reproduce", "results_dir", {"reproduce.log": "my redirect of reproduce's output\n", **_RESULTS}),
    "cells": ("reproduce", "results_dir", {"cells/counts.csv": "cell,n\nA,3\n", "RESULTS.md": "# cells\n"}),
    "episodes-empty": ("evaluate", "hydra.run.dir",
                       {"episodes.jsonl": "", "table.md": "| mine |\n", "summary.json": '{"n": 1}'}),
    "episodes-other": ("evaluate", "hydra.run.dir", {"episodes.jsonl": '{"format": "other-tool/2"}\n{"ep": 1}\n',
                                                     "table.md": "| mine |\n", "summary.json": '{"n": 1}'}),
    "data.json": ("train", "hydra.run.dir", {"data.json": '{"path": "/data/set", "files": ["a.h5"]}',
                                             "notes.md": "my manifest\n"}),
    "hydra-evaluate": ("evaluate", "hydra.run.dir", {
        ".hydra/hydra.yaml": "hydra:\n  job:\n    name: evaluate\n", ".hydra/config.yaml": "model: mine\n",
        "evaluate.log": "my script's log\n", "table.md": "| mine |\n", "summary.json": '{"n": 1}'}),
}


@pytest.mark.parametrize("case", sorted(USER_FOLDERS))
def test_a_users_folder_with_a_file_of_a_records_name_is_not_an_apps(tmp_path: Path, case: str) -> None:
    """A folder is an app's run only by a record whose content is cicfw's: a user's file that merely bears
    a record's name (a redirected log, a cells/ folder, an episodes.jsonl or data.json of another shape, a
    Hydra script of their own named evaluate) leaves the folder the user's, refused before a byte changes."""
    from cicfw.core.run_folder import RunFolderError, claim_folder, folder_owner

    app, key, files = USER_FOLDERS[case]
    folder = tmp_path / "study"
    before = _user_folder(folder, files)
    assert folder_owner(folder) is None
    with pytest.raises(RunFolderError) as err:
        claim_folder(folder, app, key)
    assert (err.value.key, err.value.value) == (key, str(folder))
    assert _user_folder(folder, {}) == before


def test_cicfw_records_by_content_still_name_their_app(tmp_path: Path) -> None:
    """The same names holding cicfw's content keep the folder the app's: an interrupted evaluation (its log's
    header only), a cicfw evaluate run's hydra.yaml (its callbacks), a training run stopped before its first
    checkpoint (its whole data record), a reproduction stopped before its manifest (cells/<row>/seed<k>)."""
    import json

    from cicfw.core.run_folder import claim_folder, folder_owner

    cases = {
        "ev": ("evaluate", {"episodes.jsonl": json.dumps({"format": "cicfw-episode-log/1", "fingerprint": {}}) + "\n"}),
        "hy": ("evaluate", {".hydra/hydra.yaml": "hydra:\n  callbacks:\n    run_folder:\n      _target_: "
                                                "cicfw.core.run_folder.LockedRunFolderCheck\n  job:\n    name: evaluate\n",
                            "evaluate.log": ""}),
        "tr": ("train", {"data.json": json.dumps({"path": "/d", "root": "/d", "hash": "0" * 16, "hash_of": "names",
                                                  "n_files": 0, "bytes": 0, "files": []})}),
        "re": ("reproduce", {"cells/cil/seed0/train/notes.txt": ""}),
    }
    for name, (app, files) in cases.items():
        _user_folder(tmp_path / name, files)
        assert folder_owner(tmp_path / name) == app, name
        claim_folder(tmp_path / name, app, "hydra.run.dir")


def test_evaluate_into_a_training_run_of_the_python_api_names_train(tmp_path: Path) -> None:
    """A run folder trained through the Python API (no .hydra, no train.log: a reproduction's cell, a notebook)
    given to evaluate as its run folder was refused as holding 'files that no cicfw app wrote'; cicfw train
    wrote them. A data.json that is no data record is still no proof."""
    from conftest import compose_train, run_app_in_process, write_tiny_dataset

    from cicfw.core.run_folder import folder_owner
    from cicfw.train.app import train

    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    run = tmp_path / "run"
    train(compose_train("data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "data.val_batch_size=8",
                        "trainer.max_epochs=1", "trainer.limit_train_batches=1", "trainer.limit_val_batches=1",
                        "trainer.num_sanity_val_steps=0", "progress_bar=false", "speed.compile=false"), run)
    assert not (run / ".hydra").exists() and not (run / "train.log").exists()
    before = sorted(str(p.relative_to(run)) for p in run.rglob("*"))
    res = run_app_in_process("cicfw.evaluate", "policy=expert", f"suite.towns=[{TOWN}]", "suite.weathers=[ClearNoon]",
                             "suite.limit=1", "runner.workers=1", "maps=false", f"hydra.run.dir={run}")
    assert res.returncode == 2, (res.returncode, res.stderr)
    assert "hydra.run.dir" in res.stderr and "cicfw train" in res.stderr, res.stderr
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*")) == before
    (run / "data.json").write_text('{"notes": "mine"}')  # any file of that name: no training run's record
    assert folder_owner(run) is None


def test_a_training_run_without_hydra_records_resumes(tmp_path: Path) -> None:
    from conftest import run_app_in_process, write_tiny_dataset

    data = write_tiny_dataset(tmp_path / "data")
    args = ["data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false",
            "trainer.limit_train_batches=1", "trainer.limit_val_batches=1", "trainer.num_sanity_val_steps=0",
            "trainer.enable_model_summary=false", "speed.compile=false", f"hydra.run.dir={tmp_path / 'run'}",
            "hydra.output_subdir=null"]
    first = run_app_in_process("cicfw.train", *args, "trainer.max_epochs=1")
    assert first.returncode == 0 and not (tmp_path / "run" / ".hydra").exists(), first.stderr[-2000:]
    again = run_app_in_process("cicfw.train", *args, "trainer.max_epochs=2", "ckpt_path=last")
    assert again.returncode == 0, again.stderr[-2000:]


def test_an_evaluate_sweep_that_is_not_joined_keeps_no_sweep_table(tmp_path: Path) -> None:
    """An evaluate multirun over settings one table cannot compare left job 0's one-row table.md (.tex, .csv,
    bars) in the sweep folder, naming one job of several: no sweep table now, and the log says where each
    job's table is."""
    from cicfw.benchmark.evaluation_report import REPORT_FILES
    from conftest import run_app_in_process

    sweep = tmp_path / "sweep"
    res = run_app_in_process("cicfw.evaluate", "-m", "policy=expert", "suite.towns=[town_a]",
                             "suite.weathers=[ClearNoon]", "suite.limit=1", "progress_bar=false", "maps=false",
                             f"hydra.sweep.dir={sweep}", "sim.success_radius=2,6")
    assert res.returncode == 0, res.stderr[-2000:]
    assert [n for n in REPORT_FILES if (sweep / n).exists()] == []
    for job in ("0", "1"):
        assert (sweep / job / "table.md").is_file() and str(sweep / job / "table.md") in res.stdout + res.stderr


@pytest.mark.parametrize("through", ["CICFW_CACHE", "data.path"])
def test_a_collect_folder_train_cannot_make_names_what_train_s_user_changes(tmp_path: Path, through: str) -> None:
    """data=sim_default under a CICFW_CACHE that is a file said "give a writable out_dir", collect's key, which
    a user of train has no way to give: the refusal names CICFW_CACHE (or data.path when that was given)."""
    from conftest import assert_refused, run_app_in_process

    blocker = tmp_path / "a_file"
    blocker.write_text("")
    args = ["trainer.fast_dev_run=true", "progress_bar=false", "speed.compile=false", f"hydra.run.dir={tmp_path / 'run'}"]
    if through == "data.path":
        args.append(f"data.path={blocker / 'sim'}")
    res = run_app_in_process("cicfw.train", *args, env={"CICFW_CACHE": str(blocker)})
    line = assert_refused(res, through, blocker if through == "CICFW_CACHE" else blocker / "sim")
    assert "out_dir" not in line
    assert not (tmp_path / "run").exists()  # refused before training: the run folder as it was


@pytest.mark.parametrize("under", [False, True])
def test_evaluate_policy_into_a_file_is_one_line_naming_out_dir(tmp_path: Path, under: bool) -> None:
    """evaluate_policy(out_dir=<an existing file>) raised a bare FileExistsError from the episode log."""
    from cicfw.benchmark.app import evaluate_policy
    from cicfw.core.errors import CicfwError

    blocker = tmp_path / "a_file"
    blocker.write_text("kept")
    out = blocker / "run" if under else blocker
    suite = {"towns": [str(TOWN)], "weathers": ["ClearNoon"], "training_towns": [], "limit": 1}
    with pytest.raises(CicfwError) as err:
        evaluate_policy({"name": "expert"}, suite, {"workers": 1}, out, maps=False)
    assert (err.value.key, err.value.value) == ("out_dir", str(out)) and "\n" not in str(err.value)
    assert blocker.read_text() == "kept"


def test_evaluate_policy_into_a_folder_of_other_files_is_refused(tmp_path: Path) -> None:
    """evaluate_policy wrote its table.md, summary.json ... over files no cicfw app wrote (or a training
    run's folder); an earlier call's folder still resumes."""
    from cicfw.benchmark.app import evaluate_policy
    from cicfw.core.run_folder import RunFolderError

    out = tmp_path / "notes"
    out.mkdir()
    (out / "table.md").write_text("mine")
    suite = {"towns": [str(TOWN)], "weathers": ["ClearNoon"], "training_towns": [], "limit": 1}
    with pytest.raises(RunFolderError) as err:
        evaluate_policy({"name": "expert"}, suite, {"workers": 1}, out, maps=False)
    assert (err.value.key, err.value.value) == ("out_dir", str(out))
    assert sorted(p.name for p in out.iterdir()) == ["table.md"] and (out / "table.md").read_text() == "mine"
    for _ in range(2):  # a fresh folder, then the same folder again
        assert evaluate_policy({"name": "expert"}, suite, {"workers": 1}, tmp_path / "own", maps=False).success == 100.0


@pytest.mark.parametrize("override, key, value", [("seed=-1", "seed", -1), ("runner.threads=0", "runner.threads", 0),
                                                  ("runner.threads=-2", "runner.threads", -2)])
def test_evaluate_refuses_a_negative_seed_and_no_threads(tmp_path: Path, override: str, key: str, value) -> None:
    """evaluate took seed=-1, which train refuses, and runner.threads=0 silently meant null (cores / workers):
    both are one line naming the key, before anything is driven or left in the run folder."""
    from conftest import assert_refused, run_app_in_process

    run = tmp_path / "run"
    res = run_app_in_process("cicfw.evaluate", "policy=expert", f"suite.towns=[{TOWN}]", "suite.weathers=[ClearNoon]",
                             "suite.limit=1", "runner.workers=1", "maps=false", override, f"hydra.run.dir={run}")
    assert_refused(res, key, value)
    assert not run.exists()


def test_a_copy_among_a_run_of_the_same_parts_does_not_borrow_its_config(tmp_path: Path) -> None:
    """A checkpoint of the same parts, trained on other data, copied into a run's folder: the export sidecar's
    row_config (its seed, its experiment) would be that run's; its own data record tells them apart."""
    import json

    import torch

    from cicfw.data.provenance import CHECKPOINT_KEY
    from cicfw.export.app import other_run

    run = tmp_path / "run"
    _run_with_config(run, "independent")
    (run / "checkpoints").mkdir()
    (run / "data.json").write_text(json.dumps({"path": "/data/a", "files": []}))
    cfg = {"mixer": {"name": "independent"}}
    hp = {"encoder": "cil", "mixer": "independent", "head": "regression"}
    for name, data in (("own.ckpt", "/data/a"), ("copied.ckpt", "/data/b")):
        torch.save({"state_dict": {}, "hyper_parameters": hp, CHECKPOINT_KEY: {"path": data, "files": []}},
                   run / "checkpoints" / name)
    config = run / ".hydra" / "config.yaml"
    assert other_run(cfg, config, hp, run / "checkpoints" / "own.ckpt") is None
    assert "/data/b" in other_run(cfg, config, hp, run / "checkpoints" / "copied.ckpt")
