"""``cicfw report`` pools only the cells of its folder's reproduction: a cell whose dataset, epochs, weather
family or pinned recipe differs from reproduce.json's pin, or whose recorded training overrides differ from
another seed's of its row, is refused in one line (the check a run makes before it skips a finished cell), and
nothing is written."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from cicfw.core.errors import CicfwError
from cicfw.reproduction.cells import (DELETED, NOT_SET, CellPin, cell_mismatch, check_rows_agree, load_cells,
                                      override_values, pinned_epochs, pinned_recipe)
from cicfw.reproduction.report import folder_pin
from conftest import assert_refused, run_app_in_process

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"
PUBLISHED = sorted(p.parent for p in RESULTS.glob("**/reproduce.json"))


def snapshot(folder: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under ``folder``: its bytes and its modification time."""
    return {str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def refused(folder: Path, key: str, cell: Path, *values: object) -> None:
    """``cicfw report folder`` exits 2 with one line naming ``cell``, ``key`` and ``values``, and writes nothing."""
    before = snapshot(folder)
    line = assert_refused(run_app_in_process("cicfw.reproduction.report", str(folder)), key)
    assert str(cell) in line, line
    for v in values:
        assert f"{key}={v}" in line, (v, line)
    assert snapshot(folder) == before


def test_a_cell_of_another_budget_and_recipe_is_refused(tmp_path):
    folder = tmp_path / "c6e"
    shutil.copytree(RESULTS / "converged6_carla", folder)
    cell = folder / "cells" / "cil" / "seed0" / "cell.json"
    shutil.copy(RESULTS / "converged6_half" / "cells" / "cil" / "seed0" / "cell.json", cell)
    refused(folder, "epochs", cell, 3, 6)  # converged6_half trains 3 epochs, converged6 pins 6


def test_a_cell_of_another_dataset_is_refused(tmp_path):
    folder = tmp_path / "c6e"
    shutil.copytree(RESULTS / "converged6_carla", folder)
    cell = folder / "cells" / "gtu" / "seed1" / "cell.json"
    d = json.loads(cell.read_text())
    d.update(dataset="0000000000000000", epochs=2)
    cell.write_text(json.dumps(d))
    refused(folder, "dataset", cell, "0000000000000000", "fb489a765fcd8c91")


def test_a_recipe_value_the_pin_sets_otherwise_is_refused(tmp_path):
    folder = tmp_path / "half"
    shutil.copytree(RESULTS / "converged6_half", folder)
    cell = folder / "cells" / "cil" / "seed1" / "cell.json"
    d = json.loads(cell.read_text())
    d["recipe"]["model"]["lr"] = 0.0002  # converged6's; converged6_half pins model.lr=6e-4
    cell.write_text(json.dumps(d))
    refused(folder, "recipe.model.lr", cell, 0.0002, 0.0006)


def test_a_recorded_weather_family_other_than_the_pin_is_refused(tmp_path):
    folder = tmp_path / "half"
    shutil.copytree(RESULTS / "converged6_half", folder)
    cell = folder / "cells" / "cil" / "seed2" / "cell.json"
    d = json.loads(cell.read_text())
    d["weather_family"] = "carla"  # converged6_half pins sim.weather_family=harsh
    cell.write_text(json.dumps(d))
    before = snapshot(folder)
    assert_refused(run_app_in_process("cicfw.reproduction.report", str(folder)), "weather_family", "carla")
    assert snapshot(folder) == before


def test_the_pin_is_read_from_the_training_overrides():
    train = ["data=sim_default", "trainer.max_epochs=6", "model.lr=6e-4", "data.batch_size=60",
             "data.path=${oc.env:CICFW_CACHE,/tmp}/x", "data.num_workers=4", "~model.ema_decay",
             "trainer.max_epochs=3", "speed.compile=true"]
    assert pinned_epochs(train) == 3  # the last one wins, as Hydra's
    assert pinned_recipe(train) == {"model.lr": 0.0006, "data.batch_size": 60}
    assert pinned_epochs(["data=sim_default"]) is None


def test_only_what_both_sides_know_is_compared():
    pin = CellPin(dataset="a", weather_family="harsh", family_known=True, epochs=6, recipe={"model.lr": 0.0002})
    assert cell_mismatch({"epochs": 6, "recipe": {"model": {"lr": 0.0002, "ema_decay": 0.0}}}, pin) is None
    assert cell_mismatch({"dataset": None, "recipe": {"model": {"betas": [0.7, 0.85]}}}, pin) is None
    assert cell_mismatch({"recipe": {"model": {"lr": 0.0006}}}, pin) == ("recipe.model.lr", 0.0006, 0.0002)
    assert cell_mismatch({"weather_family": "carla"}, CellPin()) is None  # no pinned suite: not known


@pytest.mark.parametrize("folder", PUBLISHED, ids=lambda p: p.name)
def test_every_published_cell_belongs_to_its_folders_pin(folder: Path):
    pin = folder_pin(json.loads((folder / "reproduce.json").read_text()))
    cells, _ = load_cells(folder)
    assert cells and pin.dataset and pin.epochs
    assert [(c.row, c.seed, cell_mismatch(c.meta, pin)) for c in cells if cell_mismatch(c.meta, pin)] == []


def test_the_paired_switch_refuses_a_cell_its_folder_s_pin_did_not_make(tmp_path):
    """The paired switch reads a row's cells itself: a cell of another reproduction copied into a results
    folder would be paired seed by seed. The same check, one line naming the cell, the key and both values;
    the two folders as published pair as before."""
    a, b = tmp_path / "converged6", tmp_path / "half"
    shutil.copytree(RESULTS / "converged6", a)
    shutil.copytree(RESULTS / "converged6_half", b)
    rows = [str(a / "cells" / "cil"), str(b / "cells" / "cil"), "--margin", "5"]
    assert run_app_in_process("cicfw.reproduction.paired_switch", *rows).returncode == 0
    cell = a / "cells" / "cil" / "seed0" / "cell.json"
    shutil.copy(RESULTS / "converged6_half" / "cells" / "cil" / "seed0" / "cell.json", cell)
    line = assert_refused(run_app_in_process("cicfw.reproduction.paired_switch", *rows), "epochs")
    assert str(cell) in line and "epochs=3" in line and "epochs=6" in line, line


@pytest.mark.parametrize("retouch", [None, "finished_s", "wall_s.train"])
def test_a_seed_that_is_a_copy_of_another_is_refused(tmp_path, retouch):
    """seed0's cell.json copied as seed1 with its seed renamed counted one model as two independent seeds (a
    narrower interval); a retouched field its training does not decide (its wall time) leaves it a copy."""
    folder = tmp_path / "c6e"
    shutil.copytree(RESULTS / "converged6_carla", folder)
    first, copy = (folder / "cells" / "cil" / f"seed{s}" / "cell.json" for s in (0, 1))
    d = json.loads(first.read_text())
    d["seed"] = 1
    if retouch == "wall_s.train":
        d["wall_s"]["train"] += 7
    elif retouch is not None:
        d[retouch] += 1
    copy.write_text(json.dumps(d))
    before = snapshot(folder)
    line = assert_refused(run_app_in_process("cicfw.reproduction.report", str(folder)), copy)
    assert str(first) in line, line
    assert snapshot(folder) == before


def test_the_copy_signature_is_the_validation_error_curve_and_episodes(tmp_path):
    """Another validation error is another trained model, pooled; a cell that records none is a copy only when
    identical but for its seed, as before (a retouched field then makes it another cell)."""
    folder = tmp_path / "c6e"
    shutil.copytree(RESULTS / "converged6_carla", folder)
    first, copy = (folder / "cells" / "cil" / f"seed{s}" / "cell.json" for s in (0, 1))
    d = json.loads(first.read_text())
    d.update(seed=1, val_steer_mae=d["val_steer_mae"] + 1e-9)
    copy.write_text(json.dumps(d))
    n = len(list(folder.glob("cells/*/seed*/cell.json")))
    assert len(load_cells(folder)[0]) == n
    for path in (first, copy):  # neither records its validation error: the whole cell.json decides
        d = json.loads(path.read_text())
        d.pop("val_steer_mae")
        d["finished_s"] = 1.0 if path == first else 2.0
        path.write_text(json.dumps(d))
    assert len(load_cells(folder)[0]) == n
    d["finished_s"] = 1.0
    copy.write_text(json.dumps(d))
    with pytest.raises(CicfwError) as err:
        load_cells(folder)
    assert err.value.value == str(copy)


def test_a_cell_copied_into_another_row_is_refused_naming_both_files(tmp_path):
    """CIL's seed 2 copied in as GTU's seed 2, its row, recipe and overrides edited to GTU's: every check of a
    row passes, and one model would count in both rows. The copy signature holds whatever the row: refused in
    one line naming both files, nothing written; another validation error is another model, pooled."""
    folder = tmp_path / "c6x"
    shutil.copytree(RESULTS / "converged6_xeon", folder)
    original, copy = folder / "cells" / "cil" / "seed2" / "cell.json", folder / "cells" / "gtu" / "seed2" / "cell.json"
    gtu = json.loads(copy.read_text())
    d = json.loads(original.read_text())
    d.update({k: gtu[k] for k in ("row", "recipe", "overrides", "mixer", "head") if k in gtu})
    copy.write_text(json.dumps(d))
    before = snapshot(folder)
    line = assert_refused(run_app_in_process("cicfw.reproduction.report", str(folder)), original)
    assert str(copy) in line, line
    assert snapshot(folder) == before
    with pytest.raises(CicfwError) as err:
        load_cells(folder)
    assert (err.value.key, err.value.value) == ("cell", str(copy))
    d["val_steer_mae"] += 1e-9
    copy.write_text(json.dumps(d))
    assert ("gtu", 2) in [(c.row, c.seed) for c in load_cells(folder)[0]]


def gtu_as_cil(folder: Path, seed: int, recipe: bool = True) -> Path:
    """The same seed's GTU cell.json written as ``folder``'s CIL cell (its ``row`` edited): another model."""
    cell = folder / f"seed{seed}" / "cell.json"
    d = json.loads((RESULTS / "converged6_xeon" / "cells" / "gtu" / f"seed{seed}" / "cell.json").read_text())
    d["row"] = "cil"
    if not recipe:  # a cell written before it recorded its recipe: its own mixer and head fields
        d.pop("recipe")
    cell.write_text(json.dumps(d))
    return cell


@pytest.mark.parametrize("recipe", [True, False])
def test_the_report_refuses_a_row_whose_cells_record_another_model(tmp_path, recipe):
    folder = tmp_path / "c6x"
    shutil.copytree(RESULTS / "converged6_xeon", folder)
    cell = gtu_as_cil(folder / "cells" / "cil", 3, recipe)
    before = snapshot(folder)
    line = assert_refused(run_app_in_process("cicfw.reproduction.report", str(folder)), "recipe.mixer.name=gtu")
    assert str(cell) in line and "mixer.name=independent" in line, line
    assert snapshot(folder) == before


def copy_row(src: Path, dst: Path) -> Path:
    """A row's cells copied with ``cp -a``: outside any results folder (no pin read)."""
    shutil.copytree(src, dst)
    return dst


@pytest.mark.parametrize("side", [0, 1])
def test_the_paired_switch_refuses_a_side_whose_cells_record_another_model(tmp_path, side):
    rows = [copy_row(RESULTS / "converged6_xeon" / "cells" / "cil", tmp_path / "a"),
            copy_row(RESULTS / "converged6" / "cells" / "cil", tmp_path / "b")]
    cell = gtu_as_cil(rows[side], 2)
    line = assert_refused(run_app_in_process("cicfw.reproduction.paired_switch", *map(str, rows)),
                          "recipe.mixer.name=gtu")
    assert str(cell) in line, line


@pytest.mark.parametrize("retouch", [False, True])
def test_the_paired_switch_refuses_any_seed_whose_two_cells_are_copies(tmp_path, retouch):
    """B is A's cells (cp -a) but for one seed from another reproduction: four of five seeds compared with
    themselves. The first copied seed is named; a retouched wall time leaves a copy a copy."""
    a = copy_row(RESULTS / "converged6_xeon" / "cells" / "cil", tmp_path / "a")
    b = copy_row(a, tmp_path / "b")
    shutil.copy(RESULTS / "converged" / "cells" / "cil" / "seed0" / "cell.json", b / "seed0" / "cell.json")
    if retouch:
        d = json.loads((b / "seed1" / "cell.json").read_text())
        d["wall_s"]["train"] += 7
        (b / "seed1" / "cell.json").write_text(json.dumps(d))
    assert_refused(run_app_in_process("cicfw.reproduction.paired_switch", str(a), str(b)), f"{b}/seed1")


def test_the_overrides_a_row_trained_with_are_compared_key_by_key():
    """A cell records its row's training overrides; a ``trainer.*`` key (no recipe, no epochs) set on one side
    alone or otherwise is a mismatch, spellings of one setting are not, and a cell that records none is not
    compared."""
    pin = CellPin(overrides=override_values(["experiment=paper_gtu", "trainer.max_epochs=2"]))
    cell = {"overrides": ["experiment=paper_gtu", "+trainer.accumulate_grad_batches=2", "trainer.max_epochs=2"]}
    assert cell_mismatch(cell, pin) == ("overrides.trainer.accumulate_grad_batches", "2", NOT_SET)
    assert cell_mismatch({"overrides": ["experiment=paper_gtu", "trainer.max_epochs=3"]}, pin) == (
        "overrides.trainer.max_epochs", "3", "2")
    assert cell_mismatch({"overrides": ["experiment=paper_gtu", "+trainer.max_epochs=1", "trainer.max_epochs=2"]},
                         pin) is None  # the last one wins, as Hydra's
    assert cell_mismatch({"recipe": {}}, pin) is None  # written before cells recorded their overrides
    assert override_values(["~model.ema_decay", "trainer.compile=true"]) == {"model.ema_decay": DELETED,
                                                                            "speed.compile": "true"}


def with_overrides(cell: Path, overrides: list[str]) -> None:
    d = json.loads(cell.read_text())
    d["overrides"] = overrides
    cell.write_text(json.dumps(d))


def test_cells_of_one_row_trained_with_other_overrides_are_refused(tmp_path):
    """Two seeds of a row made under two definitions of it (a trainer key changed between runs) are not
    pooled: the report names the cell, the key and both values, and writes nothing. A cell that records no
    overrides (written before cells did) is not compared."""
    folder = tmp_path / "half"
    shutil.copytree(RESULTS / "converged6_half", folder)
    cells = folder / "cells" / "cil"
    with_overrides(cells / "seed0" / "cell.json", ["experiment=paper_cil", "trainer.max_epochs=3"])
    with_overrides(cells / "seed2" / "cell.json", ["experiment=paper_cil", "trainer.max_epochs=3",
                                                   "+trainer.gradient_clip_val=0.0001"])
    refused(folder, "overrides.trainer.gradient_clip_val", cells / "seed2" / "cell.json", "0.0001", NOT_SET)
    with_overrides(cells / "seed2" / "cell.json", ["experiment=paper_cil", "trainer.max_epochs=3"])
    check_rows_agree(folder, load_cells(folder)[0])  # seed1 records none: not compared
