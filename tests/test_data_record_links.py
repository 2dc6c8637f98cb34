"""A run's data record counts each file once, as the loader reads it: a symlink or a hard link to a file is
listed under ``links``, not as another file; a record written before that (every path hashed) still reads as
the same data."""
from __future__ import annotations

import hashlib
import json
import os
import shutil

import pytest
from omegaconf import OmegaConf

from cicfw.data.provenance import OtherData, check_same_data, record_data, recorded_files
from cicfw.testing import write_tiny_dataset
from cicfw.train.app import data_record


def _linked_folder(tmp_path):
    """12 distinct files, a symlink to one and a hard link to another."""
    folder = write_tiny_dataset(tmp_path / "data", n_files=12, n=4)
    os.symlink(folder / "data_00003.h5", folder / "zz_soft.h5")
    os.link(folder / "data_00005.h5", folder / "zz_hard.h5")
    return folder


def _every_path_record(folder) -> dict:
    """A record as cicfw wrote it before links counted once: every path an entry, hashed by hand."""
    entries = []
    for path in sorted(p for p in folder.iterdir() if p.suffix == ".h5"):
        data = path.read_bytes()
        entries.append({"name": path.name, "bytes": len(data), "mtime_ns": path.stat().st_mtime_ns,
                        "sha256": hashlib.sha256(data).hexdigest()})
    lines = "".join(f"{e['name']}:{e['bytes']}:{e['sha256']}\n" for e in entries)
    return {"path": str(folder), "root": str(folder), "hash": hashlib.sha256(lines.encode()).hexdigest()[:16],
            "hash_of": "the files' names (relative to root), sizes and SHA-256", "n_files": len(entries),
            "bytes": sum(e["bytes"] for e in entries), "files": entries}


def test_a_linked_path_is_counted_once_as_the_loader_reads_it(tmp_path):
    folder = _linked_folder(tmp_path)
    record = record_data(folder)
    distinct = [f"data_{i:05d}.h5" for i in range(12)]
    assert record["n_files"] == 12
    assert record["bytes"] == sum(os.path.getsize(folder / name) for name in distinct)
    assert [f["name"] for f in record["files"]] == distinct
    assert sorted((link["name"], link["same_as"]) for link in record["links"]) == [
        ("zz_hard.h5", "data_00005.h5"), ("zz_soft.h5", "data_00003.h5")]


def test_the_fingerprint_still_changes_when_a_file_is_added_or_changed(tmp_path):
    folder = _linked_folder(tmp_path)
    before = record_data(folder)["hash"]
    write_tiny_dataset(tmp_path / "more", n_files=13, n=4)
    shutil.copy(tmp_path / "more" / "data_00012.h5", folder / "data_00012.h5")  # one file more
    added = record_data(folder)["hash"]
    (folder / "data_00012.h5").unlink()
    assert record_data(folder)["hash"] == before
    with open(folder / "data_00001.h5", "r+b") as fh:  # one byte of a file changed, its size kept
        fh.seek(-1, os.SEEK_END)
        last = fh.read(1)
        fh.seek(-1, os.SEEK_END)
        fh.write(bytes([last[0] ^ 1]))
    assert len({before, added, record_data(folder)["hash"]}) == 3


def test_a_record_that_hashed_every_path_is_still_the_same_data(tmp_path):
    folder = _linked_folder(tmp_path)
    old = _every_path_record(folder)
    assert old["n_files"] == 14
    now = record_data(folder)
    assert now["hash"] != old["hash"]
    check_same_data(old, now, "data.path", "the checkpoint", "resume on it")  # no error: compared as it was made
    os.unlink(folder / "zz_soft.h5")  # a path it recorded is gone: no longer the data it hashed
    with pytest.raises(OtherData) as err:
        check_same_data(old, record_data(folder), "data.path", "the checkpoint", "resume on it")
    assert err.value.key == "data.path"


def test_resuming_a_run_recorded_before_links_counted_once_is_the_same_data(tmp_path):
    folder = _linked_folder(tmp_path)
    run = tmp_path / "run"
    run.mkdir()
    (run / "data.json").write_text(json.dumps(_every_path_record(folder)))
    cfg = OmegaConf.create({"ckpt_path": "last", "data": {"path": str(folder)}})
    record, other_data = data_record(cfg, str(folder), run)
    assert other_data is False and "before" not in record
    assert record["n_files"] == 12


def test_a_link_is_no_file_added_since_the_run_recorded_its_data(tmp_path):
    folder = write_tiny_dataset(tmp_path / "data", n_files=12, n=4)
    record = record_data(folder)
    os.symlink(folder / "data_00003.h5", folder / "zz_soft.h5")  # after the run: the same files, read once
    files, added = recorded_files(record, None, "data.path", "the run", "put them back")
    assert len(files) == 12 and added == []
    write_tiny_dataset(tmp_path / "more", n_files=13, n=4)
    shutil.copy(tmp_path / "more" / "data_00012.h5", folder / "data_00012.h5")
    assert recorded_files(record, None, "data.path", "the run", "put them back")[1] == ["data_00012.h5"]
