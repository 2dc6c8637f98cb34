"""A run knows its data: it records the absolute data path and its files (names, sizes, SHA-256) in its folder
and its checkpoints; a resume on other data is refused unless asked for, diagnose reads the recorded folder and
file list (not a relative path read from another directory, nor files added since), and export's sidecar
names the files the model trained on."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from cicfw.core.errors import USER_ERRORS
from cicfw.data.cil_hdf5 import check_file
from cicfw.data.provenance import OtherData
from test_diagnose import write_episodes

pytestmark = pytest.mark.slow  # trains, or runs an app

#: one batch of one epoch: a checkpoint to resume from, in seconds
SHORT = ["data=cil_hdf5", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false", "speed.compile=false",
         "trainer.max_epochs=1", "trainer.limit_train_batches=1", "trainer.limit_val_batches=1",
         "trainer.num_sanity_val_steps=0", "trainer.enable_model_summary=false", "seed=3"]


def compose_train(*overrides: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("train", overrides=list(overrides))


def train_run(cfg, run: Path) -> None:
    """``train`` into ``run`` with the config Hydra would save there (unresolved, ``data.path`` as typed)."""
    from cicfw.train.app import train

    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")
    train(cfg, run, refuse_finished=True, claim=False)  # as the app, which claimed it before .hydra was written


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A run trained from ``work/`` on ``data.path=data/good`` (relative): its folder, data and checkpoint."""
    base = tmp_path_factory.mktemp("provenance")
    data = write_episodes(base / "work" / "data" / "good", n_files=8)
    run = base / "run"
    here = os.getcwd()
    os.chdir(base / "work")
    try:
        train_run(compose_train(*SHORT, "data.path=data/good"), run)
    finally:
        os.chdir(here)
    return {"base": base, "data": data, "run": run, "last": run / "checkpoints" / "last.ckpt"}


def _refusal(err: pytest.ExceptionInfo) -> str:
    assert isinstance(err.value, USER_ERRORS), repr(err.value)
    text = str(err.value)
    assert "\n" not in text, text
    return text


def test_a_run_records_the_absolute_data_path_and_its_files(trained):
    data = trained["data"]
    record = json.loads((trained["run"] / "data.json").read_text())
    assert record["path"] == str(data) and Path(record["path"]).is_absolute()
    names = sorted(p.name for p in data.glob("*.h5"))
    assert [f["name"] for f in record["files"]] == names
    assert all(f["bytes"] == (data / f["name"]).stat().st_size for f in record["files"])
    assert record["files"][0]["sha256"] == hashlib.sha256((data / names[0]).read_bytes()).hexdigest()
    ckpt = torch.load(trained["last"], map_location="cpu", weights_only=True)
    assert ckpt["cicfw_data"]["path"] == str(data) and ckpt["cicfw_data"]["hash"] == record["hash"]


def test_resuming_on_another_folder_is_refused_naming_both(trained, tmp_path):
    from cicfw.train.app import train

    other = write_episodes(tmp_path / "other", n_files=8, seed=5)
    cfg = compose_train(*SHORT, f"data.path={other}", f"ckpt_path={trained['last']}", "trainer.max_epochs=2")
    with pytest.raises(Exception) as err:
        train(cfg, tmp_path / "run", refuse_finished=True)
    text = _refusal(err)
    assert getattr(err.value, "key", None) == "data.path" and str(other) in text and str(trained["data"]) in text
    assert not (tmp_path / "run" / "checkpoints").exists()  # refused before training


def test_resuming_on_a_changed_file_set_is_refused(trained, tmp_path):
    from cicfw.train.app import train

    data = tmp_path / "grown"
    shutil.copytree(trained["data"], data)
    write_episodes(tmp_path / "extra", n_files=2, seed=9)
    shutil.copy(tmp_path / "extra" / "ep000.h5", data / "ep100.h5")  # one file more
    cfg = compose_train(*SHORT, f"data.path={data}", f"ckpt_path={trained['last']}", "trainer.max_epochs=2")
    with pytest.raises(Exception) as err:
        train(cfg, tmp_path / "run", refuse_finished=True)
    text = _refusal(err)
    assert getattr(err.value, "key", None) == "data.path" and "ep100.h5" in text


def _copy_over(src: Path, dst: Path) -> None:
    """``src``'s HDF5 files over ``dst``'s of the same names and sizes (other bytes), their times kept, as
    ``cp -p``, ``rsync -a`` or ``tar x`` leave them: older than ``dst``'s metadata."""
    for f in sorted(src.glob("*.h5")):
        assert f.stat().st_size == (dst / f.name).stat().st_size and f.read_bytes() != (dst / f.name).read_bytes()
        shutil.copy2(f, dst / f.name)
        assert (dst / f.name).stat().st_mtime_ns < (dst / "dataset_metadata.json").stat().st_mtime_ns


def _sha256s(folder: Path) -> dict[str, str]:
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(folder.glob("*.h5"))}


def test_a_collection_s_files_replaced_with_their_times_kept_are_hashed(tmp_path, monkeypatch):
    """The collection's SHA-256s are reused only for files of the size and mtime it recorded with them: another
    collection's files copied over with their times kept are hashed, and so get another hash; untouched files
    (also in a copy that keeps times) are not read; metadata that records no mtimes vouches for nothing."""
    from cicfw.collect import collect_dataset
    from cicfw.data import provenance

    tiny = {"episodes": 1, "seconds": 2, "weathers": ["ClearNoon"], "cameras": ["centre"], "workers": 0}
    other, ours = tmp_path / "other", tmp_path / "ours"
    collect_dataset({**tiny, "seed": 8}, other, progress=False)  # first: its files are the older
    collect_dataset({**tiny, "seed": 7}, ours, progress=False)
    swapped = tmp_path / "swapped"
    shutil.copytree(ours, swapped)
    _copy_over(other, swapped)
    record = provenance.record_data(swapped)
    assert {f["name"]: f["sha256"] for f in record["files"]} == _sha256s(other)
    assert record["hash"] != provenance.record_data(ours)["hash"]

    read: list[str] = []
    monkeypatch.setattr(provenance, "file_sha256", lambda f: read.append(Path(f).name) or "0" * 64)
    kept = tmp_path / "kept"
    shutil.copytree(ours, kept)  # times kept, bytes the same: the collection's SHA-256s still hold
    for folder in (ours, kept):
        assert {f["name"]: f["sha256"] for f in provenance.record_data(folder)["files"]} == _sha256s(ours)
    assert read == []
    meta = json.loads((kept / "dataset_metadata.json").read_text())
    for entry in meta["files"].values():  # as cicfw wrote it before it recorded sizes and mtimes
        del entry["bytes"], entry["mtime_ns"]
    (kept / "dataset_metadata.json").write_text(json.dumps(meta))
    provenance.record_data(kept)
    assert read == sorted(_sha256s(ours))


def test_resuming_on_files_copied_over_with_their_times_kept_is_refused(trained, tmp_path):
    """A folder whose metadata gives the checkpoint's files' SHA-256s (with their sizes and mtimes) but that
    holds other files of the same names and sizes, copied in with older times: refused, naming a changed file."""
    from cicfw.train.app import train

    other = write_episodes(tmp_path / "other", n_files=8, seed=5)  # first: its files are the older
    data = tmp_path / "swapped"
    shutil.copytree(trained["data"], data)
    recorded = json.loads((trained["run"] / "data.json").read_text())["files"]
    meta = {"files": {f["name"]: {"episode": Path(f["name"]).stem, "samples": check_file(data / f["name"]).n,
                                  "sha256": f["sha256"], "bytes": f["bytes"],
                                  "mtime_ns": (data / f["name"]).stat().st_mtime_ns} for f in recorded}}
    (data / "dataset_metadata.json").write_text(json.dumps(meta))  # as a collection of these files writes it
    _copy_over(other, data)
    cfg = compose_train(*SHORT, f"data.path={data}", f"ckpt_path={trained['last']}", "trainer.max_epochs=2")
    with pytest.raises(Exception) as err:
        train(cfg, tmp_path / "run", refuse_finished=True)
    text = _refusal(err)
    assert isinstance(err.value, OtherData) and (err.value.key, err.value.value) == ("data.path", str(data))
    assert "changed" in text and "ep000.h5" in text
    assert not (tmp_path / "run" / "checkpoints").exists()  # refused before training


def test_resuming_on_other_data_on_purpose_records_both(trained, tmp_path):
    from cicfw.train.app import train

    other = write_episodes(tmp_path / "other", n_files=8, seed=5)
    run = tmp_path / "run"
    cfg = compose_train(*SHORT, f"data.path={other}", f"ckpt_path={trained['last']}", "trainer.max_epochs=2",
                        "resume_on_other_data=true")
    train(cfg, run, refuse_finished=True)
    record = json.loads((run / "data.json").read_text())
    assert record["path"] == str(other) and [b["path"] for b in record["before"]] == [str(trained["data"])]
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["cicfw_data"]["path"] == str(other) and ckpt["cicfw_data"]["before"][0]["path"] == str(trained["data"])


@pytest.mark.parametrize("override, key, value", [("seed=4", "data.seed", 4),
                                                 ("data.val_fraction=0.5", "data.val_fraction", 0.5),
                                                 ("data.val_cameras=[0,1]", "data.val_cameras", [0, 1]),
                                                 ("data.cameras=[0,1]", "data.cameras", [0, 1]),
                                                 ("data.max_abs_steer=0.7", "data.max_abs_steer", 0.7),
                                                 ("data.side_camera_correction=0.2", "data.side_camera_correction",
                                                  0.2)])
def test_resuming_with_another_split_is_refused(trained, tmp_path, override, key, value):
    """Another seed or validation share would validate on episodes the checkpoint trained on; other cameras,
    steering filter or side-camera correction would train and validate on other samples or labels."""
    from cicfw.train.app import train

    ckpt = torch.load(trained["last"], map_location="cpu", weights_only=True)
    assert ckpt["cicfw_split"] == {"seed": 3, "val_fraction": 0.3, "cameras": [0, 1, 2], "val_cameras": [0],
                                   "max_abs_steer": 0.8, "side_camera_correction": 0.15}
    cfg = compose_train(*SHORT, f"data.path={trained['data']}", f"ckpt_path={trained['last']}",
                        "trainer.max_epochs=2", override)
    with pytest.raises(Exception) as err:
        train(cfg, tmp_path / "run", refuse_finished=True)
    _refusal(err)
    assert (err.value.key, err.value.value) == (key, value)
    assert not (tmp_path / "run").exists()  # refused before anything was written


@pytest.mark.parametrize("recorded, override, key, value", [
    (None, "seed=4", "data.seed", 4),  # written before checkpoints recorded their split
    ({"seed": 3, "val_fraction": 0.3}, "data.max_abs_steer=0.7", "data.max_abs_steer", 0.7),  # the split only
])
def test_an_older_checkpoint_s_data_settings_are_read_from_its_run_config(trained, tmp_path, recorded, override,
                                                                           key, value):
    """A checkpoint that recorded no split, or data.seed and data.val_fraction only: the settings it does not
    record are read from its run's .hydra/config.yaml and compared as the recorded ones are."""
    from cicfw.train.app import train

    run = tmp_path / "older"
    shutil.copytree(trained["run"], run)
    last = run / "checkpoints" / "last.ckpt"
    ckpt = torch.load(last, map_location="cpu", weights_only=True)
    if recorded is None:
        del ckpt["cicfw_split"]
    else:
        ckpt["cicfw_split"] = recorded
    torch.save(ckpt, last)
    cfg = compose_train(*SHORT, f"data.path={trained['data']}", f"ckpt_path={last}", "trainer.max_epochs=2",
                        override)
    with pytest.raises(Exception) as err:
        train(cfg, tmp_path / "run", refuse_finished=True)
    _refusal(err)
    assert (err.value.key, err.value.value) == (key, value)


def _diagnose(checkpoint: Path, out: Path, *overrides: str) -> dict:
    from cicfw.diagnose.app import diagnose

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("diagnose", overrides=[f"checkpoint={checkpoint}", "phases.approach_m=3", "threads=1",
                                             "plot=false", *overrides])
    diagnose(cfg, out)
    return json.loads((out / "steer_diagnostic.json").read_text())


def test_diagnose_from_another_directory_reads_the_recorded_data(trained, tmp_path, monkeypatch):
    """The run's config says ``data.path: data/good``; from a directory holding its own ``data/good``,
    diagnose still measures the run's own validation episodes."""
    from cicfw.data.frames import load_frames, split_by_episode

    elsewhere = tmp_path / "elsewhere"
    write_episodes(elsewhere / "data" / "good", n_files=12, seed=7)
    monkeypatch.chdir(elsewhere)
    doc = _diagnose(trained["last"], tmp_path / "out")
    assert doc["data"]["path"] == str(trained["data"])
    _, val = split_by_episode(load_frames(str(trained["data"])), 0.3, 3)
    assert doc["data"]["frames"] == int((val.camera == 0).sum())


def test_diagnose_keeps_the_split_of_the_files_the_run_trained_on(trained, tmp_path):
    """Files added to the run's data folder after training: diagnose draws its validation episodes from
    the recorded files only (a split over the grown folder would put training episodes under val)."""
    from cicfw.data.frames import load_frames, split_by_episode

    data = trained["data"]
    added = [data / f"ep{i:03d}.h5" for i in (100, 101, 102, 103)]
    write_episodes(tmp_path / "extra", n_files=4, seed=11)
    try:
        for i, f in enumerate(added):
            shutil.copy(tmp_path / "extra" / f"ep{i:03d}.h5", f)
        doc = _diagnose(trained["last"], tmp_path / "out")
    finally:
        for f in added:
            f.unlink(missing_ok=True)
    recorded = sorted(data.glob("ep00*.h5"))
    _, val = split_by_episode(load_frames([str(f) for f in recorded]), 0.3, 3)
    frames = np.load(tmp_path / "out" / "steer_frames.npz")
    assert doc["data"]["frames"] == int((val.camera == 0).sum()) == len(frames["row"])
    assert doc["data"]["files"] == len(recorded)


def test_diagnose_refuses_a_recorded_file_that_changed(trained, tmp_path):
    data = tmp_path / "copy"
    shutil.copytree(trained["data"], data)
    run = tmp_path / "run"
    shutil.copytree(trained["run"], run)
    record = json.loads((run / "data.json").read_text())
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    for rec in (record, ckpt["cicfw_data"]):  # the same run, trained on the copy
        rec["path"] = rec["root"] = str(data)
    (run / "data.json").write_text(json.dumps(record))
    torch.save(ckpt, run / "checkpoints" / "last.ckpt")
    victim = data / "ep002.h5"
    victim.write_bytes(victim.read_bytes()[:-100] + b"\0" * 100)  # same size, other bytes
    os.utime(victim, ns=(1, 1))
    with pytest.raises(Exception) as err:
        _diagnose(run / "checkpoints" / "last.ckpt", tmp_path / "out")
    text = _refusal(err)
    assert getattr(err.value, "key", None) == "data.path" and "ep002.h5" in text and str(data) in text


def test_export_sidecar_names_the_files_the_model_trained_on(trained, tmp_path, monkeypatch):
    """From a directory whose ``data/good`` holds other files, the sidecar still gives the run's own data:
    its absolute path, its number of files and the recorded hash."""
    from cicfw.export.app import export_model

    elsewhere = tmp_path / "elsewhere"
    write_episodes(elsewhere / "data" / "good", n_files=12, seed=7)
    monkeypatch.chdir(elsewhere)
    info = export_model(trained["last"], "torchscript", tmp_path / "m.pt", n_frames=2)
    record = json.loads((trained["run"] / "data.json").read_text())
    side = info["training_dataset"]
    assert side["path"] == str(trained["data"]) and side["files"] == 8 and side["hash"] == record["hash"]


def test_export_of_an_older_run_resolves_a_relative_data_path_where_it_trained(trained, tmp_path, monkeypatch):
    """A checkpoint without a record (trained before runs recorded their data): the relative data.path is
    read against the run's working directory (Hydra's ``hydra.runtime.cwd``), not export's."""
    from cicfw.export.app import export_model

    run = tmp_path / "old"
    shutil.copytree(trained["run"], run)
    (run / "data.json").unlink(missing_ok=True)
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    ckpt.pop("cicfw_data", None)
    torch.save(ckpt, run / "checkpoints" / "last.ckpt")
    OmegaConf.save(OmegaConf.create({"hydra": {"runtime": {"cwd": str(trained["base"] / "work")}}}),
                   run / ".hydra" / "hydra.yaml")
    elsewhere = tmp_path / "elsewhere"
    write_episodes(elsewhere / "data" / "good", n_files=12, seed=7)
    monkeypatch.chdir(elsewhere)
    info = export_model(run / "checkpoints" / "last.ckpt", "torchscript", tmp_path / "m.pt", n_frames=2)
    assert info["training_dataset"]["path"] == str(trained["data"]) and info["training_dataset"]["files"] == 8


def test_a_file_that_is_not_hdf5_is_named_before_any_file_is_hashed(tmp_path, monkeypatch):
    """A large file named ``*.h5`` that is not HDF5 (here 4 GB, sparse) is refused in the loader's one line
    before the data record reads any file whole: hashing it would take seconds a GB first."""
    from cicfw.data import provenance
    from cicfw.data.cil_hdf5 import CILFormatError

    folder = write_episodes(tmp_path / "data", n_files=2)
    junk = folder / "ep999.h5"
    with open(junk, "wb") as f:
        f.truncate(4 << 30)
    read: list[str] = []
    monkeypatch.setattr(provenance, "file_sha256", lambda f: read.append(Path(f).name) or "0" * 64)
    with pytest.raises(CILFormatError) as err:
        provenance.record_data(folder)
    assert str(junk) in str(err.value) and read == []
    junk.unlink()
    assert sorted(f["name"] for f in provenance.record_data(folder)["files"]) == sorted(read) == ["ep000.h5",
                                                                                                   "ep001.h5"]
