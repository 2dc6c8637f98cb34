"""The report answers first: which row drives best, the leader against every other row with the
interval that separates or ties them (by hand), the rows by overall success, and each row against CIL with
the paper's difference (the forest plot)."""
from __future__ import annotations

import json
import math

import pytest

from cicfw.reproduction.analysis import analyse
from cicfw.reproduction.cells import COLUMNS, CellResult
from cicfw.reproduction.ranking import SEPARATED, TIED, TOO_FEW, forest, leader, ranking
from cicfw.reproduction.report import markdown, report_data, write_report

T_975_2 = 4.303  # t_{0.975, 2} from a printed table
CATALOGUE = {"cil": {"label": "CIL", "paper": [94.74, 86.84, 52.5, 46.25]},
             "gtu": {"label": "GTU", "paper": [100.0, 93.42, 81.25, 75.0]},
             "hybrid": {"label": "CCE + MSE", "paper": [97.37, 85.53, 64.25, 56.25]},
             "sine": {"label": "Sine"}}


def at(row: str, seed: int, pct: int, n: int = 100) -> CellResult:
    eps = {f"{c}/{k:03d}": {"success": k < pct, "column": c, "command": "left"} for c in COLUMNS for k in range(n)}
    return CellResult(row=row, seed=seed, episodes=eps, meta={"decoder": None, "wall_s": {}})


def cells() -> list[CellResult]:
    """CIL 50, 52, 54; GTU 60, 61, 65; CCE+MSE 66, 70, 71; sine one seed at 90 (too few to lead)."""
    out = [at("cil", s, p) for s, p in zip(range(3), (50, 52, 54))]
    out += [at("gtu", s, p) for s, p in zip(range(3), (60, 61, 65))]
    out += [at("hybrid", s, p) for s, p in zip(range(3), (66, 70, 71))]
    return out + [at("sine", 0, 90)]


def test_rows_by_overall_success_and_the_leader_by_hand():
    """The ranking: sine (90, one seed), CCE+MSE (69), GTU (62), CIL (52). The leader is the best row with
    3 seeds, CCE+MSE. Its lead over GTU, paired: 6, 9, 6, mean 7, sd sqrt 3, [7 - 4.303, 7 + 4.303]: separated;
    over CIL: 16, 18, 17, [17 - 2.48, 17 + 2.48]: separated; over sine: one seed, too few."""
    an = analyse(cells(), n_boot=50)
    ranked = ranking(an, list(CATALOGUE))
    assert ranked == ["sine", "hybrid", "gtu", "cil"]
    lead = leader(an, ranked)
    assert lead["row"] == "hybrid"
    vs = {v["b"]: v for v in lead["versus"]}
    half = T_975_2 * math.sqrt(3) / math.sqrt(3)
    assert vs["gtu"]["measured"] == {"mean": 7.0, "lo": round(7 - half, 2), "hi": round(7 + half, 2)}
    assert vs["gtu"]["verdict"] == SEPARATED and vs["gtu"]["method"] == "paired t, 3 seeds"
    half = T_975_2 * 1 / math.sqrt(3)
    assert vs["cil"]["measured"] == {"mean": 17.0, "lo": round(17 - half, 2), "hi": round(17 + half, 2)}
    assert vs["sine"]["verdict"] == TOO_FEW


def test_a_lead_whose_interval_holds_zero_is_a_tie():
    """A at 60, 62, 70 and B at 61, 60, 65: A - B = -1, 2, 5, mean 2, sd 3, [2 - 7.45, 2 + 7.45]: tied."""
    an = analyse([at("a", s, p) for s, p in zip(range(3), (60, 62, 70))]
                 + [at("b", s, p) for s, p in zip(range(3), (61, 60, 65))], n_boot=50)
    lead = leader(an, ranking(an))
    half = T_975_2 * 3 / math.sqrt(3)
    assert lead["row"] == "a" and lead["versus"][0]["verdict"] == TIED
    assert lead["versus"][0]["measured"] == {"mean": 2.0, "lo": round(2 - half, 2), "hi": round(2 + half, 2)}
    assert leader(analyse([at("a", 0, 60)], n_boot=50), ["a"]) is None  # one row: nothing to compare


def test_the_forest_is_each_row_minus_cil_with_the_papers_difference():
    """The paper's difference is the mean of its Table-4 row minus CIL's: GTU (87.4175 - 70.0825) = 17.34,
    CCE + MSE (75.85 - 70.0825) = 5.77; sine has no paper values."""
    an = analyse(cells(), n_boot=50)
    rows = forest(an, ranking(an, list(CATALOGUE)), {r: v["paper"] for r, v in CATALOGUE.items() if "paper" in v})
    assert [r["a"] for r in rows] == ["sine", "hybrid", "gtu"]
    assert [r["paper"] for r in rows] == [None, 5.77, 17.34]
    assert rows[2]["measured"]["mean"] == pytest.approx(10.0)  # GTU 62 - CIL 52
    assert forest(analyse([at("gtu", s, 60) for s in range(3)], n_boot=50), ["gtu"], {}) == []  # no CIL


def test_the_report_opens_with_the_answer_and_draws_the_forest(tmp_path):
    """RESULTS.md states the leader and the rows in order before Table 4, links the forest plot, and
    write_report draws it (a PNG)."""
    data = report_data(cells(), [], CATALOGUE, {"budget": "smoke"}, n_boot=50, claims=[], margin=5.0)
    md = markdown(data)
    answer, table4 = md.index("**Which row drives best?** **CCE + MSE**"), md.index("| Row | Decoder |")
    assert answer < md.index("![each row's overall success minus CIL's") < table4
    listed = [line.split("**")[1] for line in md.splitlines() if line[:3] in ("1. ", "2. ", "3. ", "4. ")]
    assert listed == ["Sine", "CCE + MSE", "GTU", "CIL"]
    assert "Ahead of (its lead's interval above 0): GTU (+7.0 [+2.7, +11.3]); CIL (+17.0 [+14.5, +19.5])." in md
    assert "Too few seeds to tell against: Sine." in md
    folder = tmp_path / "results"
    for c in cells():
        path = folder / "cells" / c.row / f"seed{c.seed}" / "cell.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"status": "ok", "row": c.row, "seed": c.seed, "episodes": c.episodes}))
    write_report(folder, CATALOGUE, n_boot=50, claims=[], margin=5.0)
    assert (folder / "forest.png").read_bytes()[:4] == b"\x89PNG"
    assert "](forest.png)" in (folder / "RESULTS.md").read_text()
