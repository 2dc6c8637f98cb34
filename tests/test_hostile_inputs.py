"""Bad input that was a traceback, a misleading line or nothing at all: a folder name longer than the
filesystem takes (evaluate, reproduce, report), a hand-edited learning curve in a cell.json, the bench
scripts' arguments and a full file-size limit, Hydra's config options given to reproduce, relation_choice's
candidates and folder; and the joined report's note when its rows drove different routes."""
from __future__ import annotations

import errno
import json
import shutil
import sys
from pathlib import Path

import pytest

from cicfw.benchmark.evaluation_report import Run, markdown_table, write_run
from cicfw.core.errors import CicfwError
from cicfw.core.run_folder import name_max
from cicfw.reproduction import app as reproduce
from cicfw.reproduction import relation_choice
from cicfw.reproduction.cells import load_cell
from conftest import assert_refused, load_bench_script, run_app_in_process

REPO = Path(__file__).resolve().parents[1]
#: a published folder whose cells hold learning curves
PUBLISHED = REPO / "docs" / "results" / "laptop"


def _long(tmp_path: Path) -> Path:
    """A folder whose last name is one byte longer than the filesystem takes."""
    return tmp_path / ("x" * (name_max(tmp_path) + 1))


def _rows(town: str, pairs: list[int]) -> list[dict]:
    """Episode rows of ``pairs`` in ``town`` (training town), one per pair and weather, each a success."""
    return [{"episode": k, "key": f"{town}/{w}/{p:03d}", "town": town, "weather": w, "town_set": "training",
             "weather_set": ws, "pair": p, "route": f"{town}/r{p}", "command": "left", "success": True,
             "reason": "success"} for k, (p, (w, ws)) in
            enumerate((p, w) for p in pairs for w in (("ClearNoon", "training"), ("MidRainyNoon", "new")))]


# ---- names longer than the filesystem takes: one line naming the key, nothing made


@pytest.mark.slow
def test_evaluate_refuses_a_run_folder_name_too_long(tmp_path):
    res = run_app_in_process("cicfw.evaluate", "policy=expert", f"hydra.run.dir={_long(tmp_path)}")
    assert_refused(res, "hydra.run.dir", f"{name_max(tmp_path) + 1} bytes")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_reproduce_refuses_a_results_dir_name_too_long(tmp_path):
    res = run_app_in_process("cicfw.reproduce", f"results_dir={_long(tmp_path)}")
    assert_refused(res, "results_dir", f"{name_max(tmp_path) + 1} bytes")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_report_refuses_an_out_or_a_folder_name_too_long(tmp_path):
    run = tmp_path / "run"
    write_run(run, Run("Expert", _rows("town_a", [1])))
    res = run_app_in_process("cicfw.cli", "report", str(run), "--out", str(_long(tmp_path)), "--no-plots")
    assert_refused(res, "--out", f"{name_max(tmp_path) + 1} bytes")
    res = run_app_in_process("cicfw.cli", "report", str(_long(tmp_path)))
    assert_refused(res, "dirs", f"{name_max(tmp_path) + 1} bytes")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


# ---- a cell.json's learning curve, edited by hand


@pytest.mark.parametrize("edit, key", [
    ({"samples": None}, "curve.0.samples"), ({"samples": 1e30}, "curve.0.samples"),
    ({"samples": "x"}, "curve.0.samples"), ({"samples": -5}, "curve.0.samples"),
    ({"overall": "abc"}, "curve.0.overall"), ({"overall": float("nan")}, "curve.0.overall"),
    ({"overall": 100.5}, "curve.0.overall"), ("oops", "curve"), ([1], "curve.0"),
])
def test_a_bad_curve_is_refused_naming_the_file_and_the_key(tmp_path, edit, key):
    cell = json.loads((PUBLISHED / "cells" / "cil" / "seed0" / "cell.json").read_text())
    assert cell["curve"] and load_cell(PUBLISHED / "cells" / "cil" / "seed0" / "cell.json")  # as shipped: read
    if isinstance(edit, dict):
        cell["curve"][0].update(edit)
    else:
        cell["curve"] = edit
    path = tmp_path / "cell.json"
    path.write_text(json.dumps(cell))
    with pytest.raises(CicfwError) as err:
        load_cell(path)
    assert err.value.key == key and str(path) in str(err.value)


def test_curve_none_or_empty_is_no_curve(tmp_path):
    cell = json.loads((PUBLISHED / "cells" / "cil" / "seed0" / "cell.json").read_text())
    for curve in (None, [], [{"samples": 0, "overall": None}]):
        (tmp_path / "cell.json").write_text(json.dumps({**cell, "curve": curve}))
        assert load_cell(tmp_path / "cell.json").meta["curve"] == curve


@pytest.mark.slow
def test_the_report_of_a_folder_with_a_bad_curve_is_one_line(tmp_path):
    folder = tmp_path / "laptop"
    shutil.copytree(PUBLISHED, folder)
    path = folder / "cells" / "cil" / "seed0" / "cell.json"
    cell = json.loads(path.read_text())
    cell["curve"][0]["samples"] = None  # was a traceback in the report's learning curve
    path.write_text(json.dumps(cell))
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    res = run_app_in_process("cicfw.cli", "report", str(folder))
    assert_refused(res, "curve[0].samples", str(path))
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before


# ---- bench scripts


@pytest.fixture(scope="module")
def row_cost():
    return load_bench_script("row_cost")


@pytest.mark.parametrize("argv, named", [(["--rows", "cil,gtuu"], "gtuu"), (["--rounds", "0"], "--rounds"),
                                         (["--steps", "0"], "--steps")])
def test_row_cost_refuses_bad_arguments_before_compiling(row_cost, monkeypatch, capsys, argv, named):
    monkeypatch.setattr(row_cost, "build", lambda *a, **k: pytest.fail("built a model for refused arguments"))
    monkeypatch.setattr(sys, "argv", ["row_cost.py", *argv])
    with pytest.raises(SystemExit) as stop:
        row_cost.main()
    err = capsys.readouterr().err
    assert stop.value.code == 2 and named in err and "Traceback" not in err


def test_data_scale_write_at_a_file_size_limit_is_one_line(tmp_path, monkeypatch):
    import cicfw.data.cil_hdf5

    bench = load_bench_script("data_scale")
    monkeypatch.setattr(bench, "FRAMES_PER_FILE", 4)

    def too_large(path, data):
        raise OSError(errno.EFBIG, "File too large", str(path))

    monkeypatch.setattr(cicfw.data.cil_hdf5, "atomic_write", too_large)
    with pytest.raises(CicfwError) as err:
        bench.write(tmp_path / "data", 2, 0)
    assert (err.value.key, err.value.value) == ("folder", str(tmp_path / "data"))
    assert "data_00000.h5" in str(err.value) and list((tmp_path / "data").iterdir()) == []


# ---- reproduce takes no --config-dir


@pytest.mark.parametrize("argv", [["--config-dir", "/tmp/x"], ["--config-dir=/tmp/x"], ["-cn", "mine"]])
def test_reproduce_refuses_hydras_config_options(capsys, argv):
    assert reproduce.main(argv) == 2
    err = capsys.readouterr().err
    assert argv[0].split("=")[0] in err and "+catalogue" in err and "quote" not in err, err


# ---- relation_choice


def _cell(folder: Path, row: str, seed: int, mae: float) -> None:
    d = folder / "cells" / row / f"seed{seed}"
    d.mkdir(parents=True)
    (d / "cell.json").write_text(json.dumps({"row": row, "seed": seed, "status": "ok", "val_steer_mae": mae}))


def test_relation_choice_refuses_an_unknown_candidate(tmp_path, capsys):
    _cell(tmp_path, "re_all", 0, 0.05)
    _cell(tmp_path, "mine", 0, 0.04)  # a row of the folder's own: known
    assert relation_choice.main([str(tmp_path), "--candidates", "re_alll", "re_none"]) == 2
    out = capsys.readouterr()
    assert "re_alll" in out.err and "re_all," in out.err and out.out == ""  # no command repeating the typo
    assert relation_choice.main([str(tmp_path), "--candidates", "mine", "re_all"]) == 0


def test_relation_choice_refuses_a_rows_folder(tmp_path, capsys):
    _cell(tmp_path, "re_all", 0, 0.05)
    for folder in (tmp_path / "cells" / "re_all", tmp_path / "cells" / "re_all" / "seed0"):
        assert relation_choice.main([str(folder)]) == 2
        out = capsys.readouterr()
        assert str(folder) in out.err and out.out == "" and "continue_from" not in out.err


# ---- the joined report says when its rows drove different routes


def test_the_joined_table_notes_rows_of_different_routes():
    a, b = Run("A", _rows("town_a", [1, 2])), Run("B", _rows("town_a", [3, 4]))
    md = markdown_table([a, b]).splitlines()
    assert "Episodes per column: 2, 2, –, –." in md  # the same counts: no note of those
    note = [line for line in md if line.startswith("Routes differ")]
    assert len(note) == 1 and "A: town_a pairs 1, 2" in note[0] and "B: town_a pairs 3, 4" in note[0], md
    same = markdown_table([a, Run("C", _rows("town_a", [1, 2]))])
    assert "Routes differ" not in same
