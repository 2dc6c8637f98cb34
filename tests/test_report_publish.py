"""``cicfw report RESULTS --publish DEST`` writes into DEST only what ``publish_dir`` may: a published folder
holding a finished cell RESULTS lacks, another run's results folder or files of no reproduction are refused in
one line naming ``--publish``, and neither folder changes."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from cicfw.reproduction.cells import COLUMNS
from conftest import assert_refused, run_app_in_process


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` and its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def results(folder: Path, cells: dict[str, int]) -> Path:
    """A results folder made by hand: ``row/seedK`` -> successes of 4 in each column; each cell its own model
    (its validation error, curve and episodes differ from every other's)."""
    (folder / "cells").mkdir(parents=True)
    (folder / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    for i, (name, wins) in enumerate(cells.items()):
        row, seed = name.split("/")
        eps = {f"{col}/{k}": {"success": k < wins, "column": col, "command": "left"}
               for col in COLUMNS for k in range(4)}
        path = folder / "cells" / row / seed / "cell.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"row": row, "seed": int(seed[4:]), "status": "ok", "val_steer_mae": 0.1 + i / 100,
                                    "curve": [{"epoch": 1, "samples": 16, "overall": 25.0 * i}], "episodes": eps}))
    return folder


def report(*args: object):
    return run_app_in_process("cicfw.reproduction.report", *map(str, args))


def test_a_published_folder_holding_cells_the_results_lack_is_refused(tmp_path):
    """RESULTS without GTU published over the folder an earlier --publish of RESULTS with GTU wrote: its table
    would lose GTU's rows while GTU's cells stay beside it. Refused naming --publish and the cells; both
    folders unchanged; the full RESULTS publishes there again."""
    full = results(tmp_path / "full", {"cil/seed0": 1, "cil/seed1": 2, "gtu/seed0": 3, "gtu/seed1": 4})
    pub = tmp_path / "pub"
    assert report(full, "--publish", pub).returncode == 0
    part = tmp_path / "part"
    shutil.copytree(full, part)
    shutil.rmtree(part / "cells" / "gtu")
    before = snapshot(pub), snapshot(part)
    line = assert_refused(report(part, "--publish", pub), "--publish", repr(str(pub)))
    assert "gtu/seed0" in line and "gtu/seed1" in line, line
    assert (snapshot(pub), snapshot(part)) == before
    assert report(full, "--publish", pub).returncode == 0


def test_publishing_over_another_runs_results_folder_is_refused(tmp_path):
    """A results folder (its cells hold their runs) given as --publish: its reproduce.json, report and
    cell.json files would be replaced beside its checkpoints."""
    mine = results(tmp_path / "mine", {"cil/seed0": 1, "cil/seed1": 2})
    other = results(tmp_path / "other", {"cil/seed0": 3, "cil/seed1": 0})
    (other / "cells" / "cil" / "seed0" / "train").mkdir()
    before = snapshot(other)
    line = assert_refused(report(mine, "--publish", other), "--publish", repr(str(other)))
    assert "cells/cil/seed0/train" in line, line
    assert snapshot(other) == before
