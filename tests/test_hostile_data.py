"""The data layer's hostile cases: nothing the reader drops is dropped without a word."""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import socket
import subprocess
import sys

import h5py
import numpy as np
import pytest
from hydra import compose, initialize_config_module

import cicfw.collect.app as collect_mod
import cicfw.collect.dataset as dataset_mod
from cicfw.collect import CollectError, collect_dataset, verify_dataset
from cicfw.data.cil_hdf5 import T
from cicfw.data.frames import load_frames
from cicfw.testing import write_tiny_dataset
from conftest import run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)


def _set_camera(path, ids) -> None:
    with h5py.File(path, "r+") as f:
        t = f["targets"][()]
        t[:, T.CAMERA_ID] = np.resize(np.asarray(ids, np.float32), len(t))
        t[:, T.CAMERA_YAW] = 0.0
        f["targets"][...] = t


def _camera_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING and "camera id" in r.getMessage()]


def test_a_file_with_an_unknown_camera_id_is_named_once_not_dropped_silently(tmp_path, caplog):
    """Item 5: 6 files x 24 samples; one file's camera id is 7 (none of 0 centre, 1 left, 2 right). Its
    24 samples used to vanish from training without a word (96 -> 72 training samples)."""
    folder = write_tiny_dataset(tmp_path / "data")
    odd = folder / "data_00003.h5"
    _set_camera(odd, [7])
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):
        frames = load_frames(str(folder), max_abs_steer=1.0, cameras=(0, 1, 2))
    assert not np.any(frames.camera == 7)  # still not trained on: data.cameras decides
    said = _camera_warnings(caplog)
    assert len(said) == 1, said  # once per file
    msg = said[0]
    assert str(odd) in msg and "[7]" in msg and "24 sample(s)" in msg
    assert "data.cameras [0, 1, 2]" in msg  # the accepted ids
    assert "\n" not in msg


def test_unknown_ids_are_listed_together_once_per_file_and_chosen_ids_are_kept(tmp_path, caplog):
    folder = write_tiny_dataset(tmp_path / "data")
    _set_camera(folder / "data_00001.h5", [3, 4])
    _set_camera(folder / "data_00002.h5", [4])
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):
        load_frames(str(folder), max_abs_steer=1.0, cameras=(0, 1, 2))
    said = _camera_warnings(caplog)
    assert len(said) == 2, said
    assert "data_00001.h5" in said[0] and "[3, 4]" in said[0]
    assert "data_00002.h5" in said[1] and "[4]" in said[1]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):  # the user chose them: kept, no warning
        frames = load_frames(str(folder), max_abs_steer=1.0, cameras=(0, 3, 4))
    assert np.count_nonzero(np.isin(frames.camera, [3, 4])) == 48
    assert _camera_warnings(caplog) == []


def test_known_cameras_left_out_on_purpose_raise_no_warning(tmp_path, caplog):
    folder = write_tiny_dataset(tmp_path / "data")
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):
        frames = load_frames(str(folder), max_abs_steer=1.0, cameras=(0,))
    assert set(frames.camera.tolist()) == {0}
    assert _camera_warnings(caplog) == []


# ------------------------------------------------------------------------------------------------
# a checksum per collected file, verified on resume and by `cicfw collect --verify`

TINY = {"episodes": 2, "seconds": 2, "weathers": ["ClearNoon"], "cameras": ["centre"], "workers": 0}
FIRST = "ep0000_town_a_ClearNoon_000.h5"


def _meta(out) -> dict:
    return json.loads((out / "dataset_metadata.json").read_text())


def _flip(path, at: float = 0.6, n: int = 16) -> bytes:
    """Flip ``n`` bytes inside the file (in the images, past the HDF5 header: it still opens, same size)."""
    data = bytearray(path.read_bytes())
    i = int(len(data) * at)
    data[i:i + n] = bytes(b ^ 0xFF for b in data[i:i + n])
    path.write_bytes(bytes(data))
    return bytes(data)


def _collect_cfg(out, *overrides: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("collect", overrides=[f"out_dir={out}", "episodes=2", "seconds=2", "weathers=[ClearNoon]",
                                             "cameras=[centre]", "workers=0", *overrides])


@pytest.fixture(scope="module")
def tiny_collection(tmp_path_factory):
    out = tmp_path_factory.mktemp("collected")
    collect_dataset(TINY, out, progress=False)
    return out, {p.name: p.read_bytes() for p in sorted(out.glob("*.h5"))}


@pytest.fixture
def collected(tiny_collection, tmp_path):
    src, files = tiny_collection
    out = tmp_path / "collected"
    shutil.copytree(src, out)
    return out, files


def test_the_metadata_keeps_a_checksum_of_every_file(collected):
    out, files = collected
    meta = _meta(out)
    assert meta["complete"]
    for name, data in files.items():
        assert meta["files"][name]["sha256"] == hashlib.sha256(data).hexdigest(), name
    marker = json.loads((out / ".episodes" / "ep0000_town_a_ClearNoon.json").read_text())
    assert marker["files"][0]["sha256"] == hashlib.sha256(files[FIRST]).hexdigest()


def test_flipped_bytes_are_named_on_rerun_and_the_episode_collected_again(collected, caplog):
    """A finished file with bytes flipped (same size, still opens as HDF5): a rerun used to say complete=True."""
    out, files = collected
    _flip(out / FIRST)
    with caplog.at_level(logging.INFO, logger="cicfw.collect"):
        meta = json.loads(collect_dataset(TINY, out, progress=False).read_text())
    said = [r.getMessage() for r in caplog.records if FIRST in r.getMessage() and r.levelno >= logging.WARNING]
    assert len(said) == 1, said
    assert "checksum" in said[0] and "collected again" in said[0] and "\n" not in said[0]
    assert meta["complete"]
    assert (out / FIRST).read_bytes() == files[FIRST]  # re-collected, byte-identical
    assert meta["files"][FIRST]["sha256"] == hashlib.sha256(files[FIRST]).hexdigest()


def test_verify_says_ok_on_a_sound_dataset_and_changes_nothing(collected, capsys):
    out, files = collected
    before = (out / "dataset_metadata.json").read_bytes()
    line = collect_mod.run(_collect_cfg(out, "verify=true"))
    assert line.startswith(f"verified {out}: ") and "2 file(s)" in line and "match their checksums" in line, line
    assert (out / "dataset_metadata.json").read_bytes() == before


def test_verify_names_each_corrupt_file_in_one_line_and_exits_2(collected, capsys, monkeypatch):
    out, files = collected
    flipped = _flip(out / FIRST)
    (out / "ep0001_town_a_ClearNoon_000.h5").unlink()
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("verify must not collect"))
    with pytest.raises(SystemExit) as exc:
        collect_mod.run(_collect_cfg(out, "verify=true"))
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 3, lines
    assert lines[0].startswith(f"cicfw: corrupt: {out / FIRST}: ") and "sha256" in lines[0]
    assert lines[1].startswith(f"cicfw: missing: {out / 'ep0001_town_a_ClearNoon_000.h5'}")
    assert lines[2].startswith("cicfw: error: ") and str(out) in lines[2] and "2 of 2" in lines[2], lines
    assert (out / FIRST).read_bytes() == flipped  # verify changes nothing


def test_verify_calls_files_it_did_not_write_what_collect_does_and_its_advice_works(collected, capsys, tmp_path):
    out, _ = collected
    os.link(out / FIRST, out / "aa.h5")
    shutil.copy(out / FIRST, out / "notes_mine.h5")
    with pytest.raises(SystemExit) as exc:
        collect_mod.run(_collect_cfg(out, "verify=true"))
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert [line.split(": ")[1:3] for line in lines[:-1]] == [["foreign", str(out / "aa.h5")],
                                                              ["foreign", str(out / "notes_mine.h5")]]
    assert "did not write" in lines[-1] and "without verify" not in lines[-1], lines[-1]
    with pytest.raises(SystemExit):  # as verify says: collect refuses the folder while they are there
        collect_mod.run(_collect_cfg(out))
    (tmp_path / "aside").mkdir()
    for name in ("aa.h5", "notes_mine.h5"):  # what verify advises: move them out
        shutil.move(out / name, tmp_path / "aside" / name)
    assert collect_mod.run(_collect_cfg(out)).startswith(f"dataset: {out} ")
    assert collect_mod.run(_collect_cfg(out, "verify=true")).startswith(f"verified {out}: ")


def test_verify_on_the_real_command_line_with_the_flag(collected):
    out, _ = collected
    _flip(out / FIRST)
    r = run_app_in_process("cicfw.collect", f"out_dir={out}", "--verify")  # its command line, in this process
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert lines[0].startswith(f"cicfw: corrupt: {out / FIRST}: "), lines
    assert lines[-1].startswith("cicfw: error: 1 of 2 file(s) of "), lines


def test_verify_leaves_no_run_folder(collected, tmp_path):
    out, _ = collected
    r = run_app_in_process("cicfw.collect", f"out_dir={out}", "--verify", cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.startswith(f"verified {out}: "), r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["collected"]  # no outputs/<date>/<time>


def test_verify_in_its_dataset_folder_keeps_what_others_write_meanwhile(collected, monkeypatch):
    """With the dataset folder as its run folder, a verify takes back only Hydra's files: a file another
    process writes there while the check runs stays."""
    out, _ = collected
    before = sorted(p.name for p in out.iterdir())
    real = collect_mod.verify_dataset

    def verify_while_a_user_writes(*args, **kwargs):
        (out / "notes.txt").write_text("written while the check ran")
        return real(*args, **kwargs)

    monkeypatch.setattr(collect_mod, "verify_dataset", verify_while_a_user_writes)
    r = run_app_in_process("cicfw.collect", f"out_dir={out}", "--verify", f"hydra.run.dir={out}")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == sorted([*before, "notes.txt"])


def test_a_collector_meeting_a_verify_is_told_the_folder_is_verified_not_written(collected, monkeypatch, caplog):
    """A verify holds the collection lock while it reads; a collector starting then was told the folder 'is
    being collected into by another process'. It still waits (or, with lock_wait=0, stops), told a verify
    reads the folder."""
    from cicfw.collect import FolderLockedError, integrity

    out, _ = collected
    refused, real = [], integrity.marker_problems

    def collect_meanwhile(*args, **kwargs):
        if not refused:
            with pytest.raises(FolderLockedError) as err:
                collect_dataset({**TINY, "lock_wait": 0}, out, progress=False)
            refused.append(err.value)
            with caplog.at_level(logging.WARNING, logger="cicfw.collect"), pytest.raises(FolderLockedError):
                collect_dataset({**TINY, "lock_wait": 0.3}, out, progress=False)  # waits, then stops
        return real(*args, **kwargs)

    monkeypatch.setattr(integrity, "marker_problems", collect_meanwhile)
    assert verify_dataset(out).ok
    assert (refused[0].key, refused[0].value) == ("out_dir", out)
    assert "verif" in str(refused[0]) and "collected into" not in str(refused[0]), refused[0]
    waiting = [r.getMessage() for r in caplog.records if r.getMessage().startswith("waiting for")]
    assert len(waiting) == 1 and "verif" in waiting[0] and "collecting into" not in waiting[0], waiting
    assert not (out / ".collect.lock").exists()


def test_verify_reads_only_when_no_live_collector_holds_the_folder(collected, caplog):
    """A live collector's lock: verify stops (lock_wait=0) and reports nothing. A record a dead collector left
    lies under a free flock: verify takes it over with a warning, reads, and leaves no lock file."""
    from cicfw.collect import FolderLock, FolderLockedError

    out, _ = collected
    with FolderLock(out, 0, {"what": "cicfw collect, seed 0"}):
        with pytest.raises(FolderLockedError) as err:
            verify_dataset(out, 0)
    assert (err.value.key, err.value.value) == ("out_dir", out)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (out / ".collect.lock").write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname(),
                                                   "started": "2000-01-01 00:00:00"}))
    with caplog.at_level(logging.WARNING, logger="cicfw.collect"):
        assert verify_dataset(out, 0).ok
    assert any("stale lock" in r.getMessage() and str(dead.pid) in r.getMessage() for r in caplog.records)
    assert not (out / ".collect.lock").exists()


def test_verify_of_a_folder_without_a_dataset_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        collect_mod.run(_collect_cfg(tmp_path / "none", "verify=true"))
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cicfw: error: ") and str(tmp_path / "none") in lines[0], lines
    with pytest.raises(CollectError) as err:
        verify_dataset(tmp_path / "none")
    assert (err.value.key, err.value.value) == ("out_dir", tmp_path / "none")
    assert not (tmp_path / "none").exists()


def test_a_dataset_collected_before_checksums_gets_them_on_rerun(collected, caplog):
    out, files = collected
    for mp in (out / ".episodes").glob("*.json"):  # as cicfw wrote them before this change
        m = json.loads(mp.read_text())
        for f in m["files"]:
            for key in ("sha256", "mtime_ns"):
                f.pop(key, None)
        mp.write_text(json.dumps(m))
    meta = _meta(out)
    for f in meta["files"].values():
        for key in ("sha256", "bytes", "mtime_ns"):
            f.pop(key, None)
    (out / "dataset_metadata.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.INFO, logger="cicfw.collect"):
        meta = json.loads(collect_dataset(TINY, out, progress=False).read_text())
    assert meta["complete"]
    assert meta["files"][FIRST]["sha256"] == hashlib.sha256(files[FIRST]).hexdigest()
    st = (out / FIRST).stat()  # with the size and mtime hashed: a training run reuses the SHA-256 while they hold
    assert (meta["files"][FIRST]["bytes"], meta["files"][FIRST]["mtime_ns"]) == (st.st_size, st.st_mtime_ns)
    assert any("recorded the checksums of 2 file(s)" in r.getMessage() for r in caplog.records)
    assert {p.name: p.read_bytes() for p in out.glob("*.h5")} == files  # episode files untouched
