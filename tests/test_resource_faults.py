"""Resource and file faults in one line: the address-space limit counted by ``data.in_memory=auto``, a corrupt
file named as corrupt, a filter that drops most rows saying so, the quoting hint only when a space is the
cause, every JSON read naming its file, every refusal naming its key."""
from __future__ import annotations

import json
import logging
import math
import resource
from pathlib import Path

import h5py
import numpy as np
import pytest

from cicfw.core.errors import CicfwError, ConfigError
from cicfw.testing import file_bytes, make_targets, write_tiny_dataset

# ---- the address-space limit (ulimit -v) ------------------------------------------------------------------


def _limited(monkeypatch, room: int) -> None:
    """RLIMIT_AS set ``room`` bytes above what this process maps now; the other limits as they are."""
    from cicfw.data import residency

    real = resource.getrlimit
    limit = residency._status_bytes("VmSize") + room  # what RLIMIT_AS counts

    def getrlimit(which: int):
        return (limit, limit) if which == resource.RLIMIT_AS else real(which)

    monkeypatch.setattr(residency.resource, "getrlimit", getrlimit)


def test_in_memory_auto_counts_the_address_space_limit(monkeypatch):
    from cicfw.data.residency import BYTES_PER_FRAME, decide

    frames = 1000  # 53 MB of images: nothing against the machine's memory, more than half of 60 MB of room
    assert decide(frames, "auto").in_memory  # unlimited: in RAM
    _limited(monkeypatch, 60 * 10**6)
    plan = decide(frames, "auto")
    assert not plan.in_memory and plan.available <= 60 * 10**6 < 2 * frames * BYTES_PER_FRAME
    assert "ulimit -v" in plan.reason()  # the log line says what bounds the memory
    with pytest.raises(CicfwError) as err:
        decide(2000, True)
    assert err.value.key == "data.in_memory"


@pytest.mark.skipif(not Path("/proc/meminfo").is_file(), reason="no /proc/meminfo (not Linux)")
def test_in_memory_auto_counts_no_more_than_the_kernel_says_is_available():
    from cicfw.data import residency

    kb = next(int(line.split()[1]) for line in Path("/proc/meminfo").read_text().splitlines()
              if line.startswith("MemAvailable:"))
    assert residency.available_bytes() <= kb * 1024 * 1.1  # it moves a little between the two reads


# ---- a corrupt file -----------------------------------------------------------------------------------------


def _corrupt_gzip_file(path: Path, n: int = 24, seed: int = 0, which: str = "rgb") -> Path:
    """A CIL file whose ``which`` dataset is gzip-compressed, with the bytes of one chunk overwritten."""
    rng = np.random.default_rng(seed)
    with h5py.File(path, "w") as f:
        f.create_dataset("rgb", data=rng.integers(0, 255, (n, 88, 200, 3), dtype=np.uint8),
                         chunks=(1, 88, 200, 3), compression="gzip")
        f.create_dataset("targets", data=make_targets(n, rng), chunks=(n // 2, 28), compression="gzip")
    with h5py.File(path, "r") as f:
        info = f[which].id.get_chunk_info(1)
    with open(path, "r+b") as fh:  # garbage in the middle of the second chunk: gzip's stream breaks
        fh.seek(info.byte_offset + info.size // 3)
        fh.write(b"\xff" * max(8, info.size // 3))
    return path


@pytest.fixture
def corrupt_data(tmp_path: Path) -> tuple[Path, Path]:
    data = write_tiny_dataset(tmp_path / "data")
    return data, _corrupt_gzip_file(data / "data_00000.h5")


def _setup(path: Path, in_memory: bool):
    from cicfw.data.datamodule import CILDataModule

    dm = CILDataModule(str(path), batch_size=8, val_batch_size=8, in_memory=in_memory, augment=False)
    dm.setup("fit")
    return dm


def test_a_corrupt_file_is_named_when_its_images_are_loaded_into_ram(corrupt_data):
    from cicfw.data.cil_hdf5 import CorruptFileError

    data, bad = corrupt_data
    with pytest.raises(CorruptFileError) as err:
        _setup(data, in_memory=True)
    assert err.value.path == bad and str(bad) in str(err.value)


def test_a_corrupt_file_streamed_is_corrupt_not_changed(corrupt_data):
    from cicfw.data.cil_hdf5 import CorruptFileError

    data, bad = corrupt_data
    dm = _setup(data, in_memory=False)
    for store in (dm.train_set.store, dm.val_set.store):
        rows = np.flatnonzero([store.frames.files[i] == bad for i in store.frames.file_idx])
        if len(rows):
            with pytest.raises(CorruptFileError) as err:
                store.get(rows)
            assert err.value.path == bad and "vanished" not in str(err.value)
            return
    pytest.fail("the corrupt file holds no sample")


@pytest.mark.slow  # a DataLoader worker process
def test_a_corrupt_file_read_by_a_worker_arrives_as_one_line(corrupt_data):
    from cicfw.data.cil_hdf5 import CorruptFileError
    from cicfw.data.datamodule import CILDataModule

    data, bad = corrupt_data
    dm = CILDataModule(str(data), batch_size=8, val_batch_size=8, in_memory=False, augment=False, num_workers=1)
    dm.setup("fit")
    with pytest.raises(CorruptFileError) as err:
        for loader in (dm.train_dataloader(), dm.val_dataloader()):
            for _ in loader:
                pass
    assert err.value.path == bad and "\n" not in str(err.value)


def test_corrupt_labels_are_named_before_training(tmp_path):
    from cicfw.data.cil_hdf5 import CorruptFileError

    data = write_tiny_dataset(tmp_path / "data")
    bad = _corrupt_gzip_file(data / "data_00000.h5", which="targets")
    with pytest.raises(CorruptFileError) as err:
        _setup(data, in_memory=False)
    assert err.value.path == bad


# ---- a filter that drops most rows --------------------------------------------------------------------------


def test_a_filter_dropping_most_rows_says_how_many_and_why(tmp_path, caplog):
    from cicfw.data.frames import load_frames

    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=40)
    for f in sorted(data.glob("*.h5")):  # steering in degrees: |steer| up to 27 rather than 0.6
        with h5py.File(f, "r+") as h:
            h["targets"][:, 0] = h["targets"][:, 0] * 45.0
    with caplog.at_level(logging.WARNING, logger="cicfw"):
        frames = load_frames(str(data), max_abs_steer=0.8)
    lines = [r.getMessage() for r in caplog.records if "data.max_abs_steer" in r.getMessage()]
    assert len(lines) == 1, [r.getMessage() for r in caplog.records]
    assert f"{160 - len(frames)} of 160" in lines[0] and "degrees" in lines[0]


def test_a_large_side_camera_correction_is_named_as_the_cause_not_the_units(tmp_path, caplog):
    from cicfw.data.frames import load_frames

    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=40)  # steer within 0.6, side cameras at +-30 deg
    with caplog.at_level(logging.WARNING, logger="cicfw"):
        load_frames(str(data), max_abs_steer=0.8, side_camera_correction=2.0)
    lines = [r.getMessage() for r in caplog.records if "data.max_abs_steer" in r.getMessage()]
    assert len(lines) == 1, [r.getMessage() for r in caplog.records]
    assert "data.side_camera_correction=2 " in lines[0] and "degrees" not in lines[0], lines[0]


def test_a_filter_tighter_than_cils_side_camera_offset_is_named_as_the_cause(tmp_path, caplog):
    """Mostly straight driving (|steer| <= 0.05) under data.max_abs_steer=0.1 and CIL's correction, 0.15: the
    warning advised setting the correction nearer 0.15."""
    from cicfw.data.frames import T, load_frames

    rng = np.random.default_rng(0)
    for i in range(4):
        t = make_targets(40, rng, (2, 3, 4, 5))
        t[:, T.STEER] *= 0.05 / np.abs(t[:, T.STEER]).max()
        (tmp_path / f"data_{i:05d}.h5").write_bytes(file_bytes(np.zeros((40, 88, 200, 3), np.uint8), t))
    with caplog.at_level(logging.WARNING, logger="cicfw"):
        load_frames(str(tmp_path), max_abs_steer=0.1, side_camera_correction=0.15)
    (line,) = [r.getMessage() for r in caplog.records if "data.max_abs_steer" in r.getMessage()]
    assert "raise data.max_abs_steer" in line and "nearer" not in line, line


def test_too_few_episodes_after_the_filters_names_episodes_and_files(tmp_path):
    from cicfw.data.frames import load_frames, split_by_episode

    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=24)
    for f in sorted(data.glob("*.h5"))[1:]:  # three files all beyond the filter
        with h5py.File(f, "r+") as h:
            h["targets"][:, 0] = 0.99  # beyond 0.8 after any side-camera correction
    frames = load_frames(str(data))
    with pytest.raises(CicfwError) as err:
        split_by_episode(frames, 0.3, 0)
    assert "1 episode" in str(err.value) and "4 file" in str(err.value) and "2 episodes" in str(err.value)


# ---- the quoting hint only when a space is the cause --------------------------------------------------------


def _line(args: list[str]) -> str:
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    from cicfw.core.override_hints import composition_error_line

    with pytest.raises(OverrideParseException) as err:
        OverridesParser.create().parse_overrides(args)
    return composition_error_line(err.value, args)


@pytest.mark.parametrize("args", [["data.cameras=[0,1"], ["evaluate_overrides=[suite.limit=0]"],
                                  ["mixer=gtu", "data.cameras=[0,1"]])
def test_no_quoting_hint_where_no_space_is_the_cause(args):
    line = _line(args)
    assert repr(args[-1]) in line and "space" not in line


@pytest.mark.parametrize("args", [["model.lr=1", "e-3"], ["data.augment={p_blur:", "0.2}"]])
def test_the_quoting_hint_where_the_shell_split_a_value(args):
    line = _line(args)
    assert "space" in line and f"'{' '.join(args)}'" in line


# ---- every JSON read names its file -------------------------------------------------------------------------


def test_a_truncated_cell_json_is_named(tmp_path):
    from cicfw.reproduction.cells import load_cells

    cell = tmp_path / "cells" / "cil" / "seed0" / "cell.json"
    cell.parent.mkdir(parents=True)
    cell.write_text(json.dumps({"status": "ok", "row": "cil", "seed": 0, "episodes": {}}, indent=1)[:-3])
    with pytest.raises(CicfwError) as err:
        load_cells(tmp_path)
    assert str(cell) in str(err.value)


@pytest.mark.parametrize("field, value", [("success", 2), ("success", "false"), ("success", None),
                                          ("column", "town_x/ClearNoon"), ("command", None), ("command", 3)])
def test_a_bad_episode_in_a_cell_json_is_named(tmp_path, field, value):
    """A hand-edited episode surfaced as matplotlib's "'yerr' must not contain negative values" or numpy's
    "could not convert string to float": now one error naming the file, the episode and the value."""
    from cicfw.reproduction.cells import COLUMNS, load_cells

    cell = tmp_path / "cells" / "cil" / "seed0" / "cell.json"
    cell.parent.mkdir(parents=True)
    episodes = {f"e{k}": {"success": k % 2 == 0, "column": c, "command": "left"} for k, c in enumerate(COLUMNS)}
    episodes["e1"][field] = value
    if value is None:
        del episodes["e1"][field]  # missing altogether (a KeyError traceback for the command)
    cell.write_text(json.dumps({"status": "ok", "row": "cil", "seed": 0, "episodes": episodes}))
    with pytest.raises(CicfwError) as err:
        load_cells(tmp_path)
    assert (err.value.key, err.value.value) == (f"episodes.e1.{field}", value)
    assert str(cell) in str(err.value) and "'e1'" in str(err.value) and json.dumps(value) in str(err.value)


@pytest.mark.parametrize("key, value", [("seed", "one"), ("seed", None), ("seed", True), ("row", None), ("row", 3)])
def test_a_cell_json_without_its_row_or_seed_is_named(tmp_path, key, value):
    """A finished cell's row and seed name its place: a text seed read as int("one") and a missing row as a
    KeyError traceback; now one error naming the file and the key."""
    from cicfw.reproduction.cells import COLUMNS, load_cells

    cell = tmp_path / "cells" / "cil" / "seed0" / "cell.json"
    cell.parent.mkdir(parents=True)
    d = {"status": "ok", "row": "cil", "seed": 0,
         "episodes": {f"e{k}": {"success": True, "column": c, "command": "left"} for k, c in enumerate(COLUMNS)}}
    if value is None:
        del d[key]
    else:
        d[key] = value
    cell.write_text(json.dumps(d))
    with pytest.raises(CicfwError) as err:
        load_cells(tmp_path)
    assert (err.value.key, err.value.value) == (key, value) and str(cell) in str(err.value)


def test_read_json_names_the_file(tmp_path):
    from cicfw.core.json_files import read_json

    bad = tmp_path / "x.json"
    bad.write_text('{"a": 1,\n')
    with pytest.raises(CicfwError) as err:
        read_json(bad)
    assert str(bad) in str(err.value) and "\n" not in str(err.value)
    assert read_json(tmp_path / "missing.json", default={}) == {}


def test_read_json_of_a_fifo_is_one_line_not_a_hang(tmp_path):
    """A FIFO where a cell.json belongs blocked cicfw report forever in its read."""
    from cicfw.core.json_files import read_json

    import os

    fifo = tmp_path / "cell.json"
    os.mkfifo(fifo)
    with pytest.raises(CicfwError) as err:
        read_json(fifo)
    assert str(fifo) in str(err.value)


# ---- every refusal names its key ----------------------------------------------------------------------------


@pytest.mark.parametrize("override, key, value", [("seed=-3", "seed", -3), ("seed=4294967296", "seed", 2**32),
                                                  ("model.lr=nan", "model.lr", math.nan),
                                                  ("model.lr=-1", "model.lr", -1.0),
                                                  ("model.speed_norm_kmh=nan", "model.speed_norm_kmh", math.nan)])
def test_a_refused_value_names_its_key(tmp_path, no_data, override, key, value):
    from conftest import compose_train

    from cicfw.train.app import train

    cfg = compose_train("data=cil_hdf5", f"data.path={tmp_path}/data", "debug=fast", "progress_bar=false", override)
    with pytest.raises(ConfigError) as err:
        train(cfg, tmp_path / "run")
    assert err.value.key == key
    assert err.value.value == value or (math.isnan(value) and math.isnan(err.value.value))
