"""Offline vs closed loop: Spearman's rho and its Fisher-z (Bonett-Wright) interval against a hand
computation and, by simulation, its coverage; the within-row pooling and the pick-by-validation gain
by hand; the cells read once each from a results tree; the report written."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from cicfw.reproduction.cells import COLUMNS
from cicfw.reproduction.offline_vs_closed_loop import (Corr, Point, collect_points, pooled_within, selection_gain,
                                                spearman_ci, write_report)


def test_the_interval_matches_a_hand_computation():
    x = list(range(1, 11))
    y = [1, 2, 3, 4, 9, 10, 7, 8, 6, 5]  # sum of squared rank differences: 0+0+0+0+25+16+0+0+9+25 = 66
    c = spearman_ci(x, y)
    assert c.rho == pytest.approx(1 - 6 * 66 / (10 * 99))  # = 0.6, no ties
    # atanh(0.6) = 0.693147; se = sqrt((1 + 0.36/2) / 7) = 0.410575; 1.959964 se = 0.804714
    assert (c.lo, c.hi) == (pytest.approx(math.tanh(0.693147 - 0.804714), abs=1e-5),
                            pytest.approx(math.tanh(0.693147 + 0.804714), abs=1e-5))
    assert (c.lo, c.hi) == (pytest.approx(-0.11110, abs=1e-4), pytest.approx(0.90476, abs=1e-4))


def test_the_interval_covers_the_true_rank_correlation_about_95_percent_of_the_time():
    rng = np.random.default_rng(20261205)
    r, n, reps = 0.6, 25, 400
    true = 6 / math.pi * math.asin(r / 2)  # Spearman's rho of a bivariate normal with Pearson r
    cov = [[1, r], [r, 1]]
    hits = 0
    for _ in range(reps):
        xy = rng.multivariate_normal([0, 0], cov, size=n)
        c = spearman_ci(xy[:, 0], xy[:, 1])
        hits += c.lo <= true <= c.hi
    assert 0.91 <= hits / reps <= 0.985, hits / reps


def test_no_interval_where_it_is_undefined():
    assert spearman_ci([1, 2, 3], [3, 1, 2]).lo is None  # n - 3 = 0
    assert spearman_ci([1, 2, 3, 4], [1, 2, 3, 4]).lo is None  # |rho| = 1
    flat = spearman_ci([1, 2, 3, 4, 5], [7, 7, 7, 7, 7])
    assert math.isnan(flat.rho) and flat.lo is None


def test_within_row_pooling_by_hand():
    a, b = Corr(0.5, -0.2, 0.8, 10), Corr(-0.2, -0.6, 0.2, 20)
    wa, wb = 7 / (1 + 0.5 ** 2 / 2), 17 / (1 + 0.2 ** 2 / 2)  # inverse Bonett-Wright variances
    z = (wa * math.atanh(0.5) + wb * math.atanh(-0.2)) / (wa + wb)
    se = 1 / math.sqrt(wa + wb)
    got = pooled_within([a, b, Corr(1.0, None, None, 3)])  # a group without an interval is left out
    assert got.rho == pytest.approx(math.tanh(z))
    assert (got.lo, got.hi) == (pytest.approx(math.tanh(z - 1.959964 * se)),
                                pytest.approx(math.tanh(z + 1.959964 * se)))
    assert got.n == 30


def point(val, success, row="cil", cpu="AMD EPYC"):
    return Point(row, 0, cpu, "converged", val, {"overall": success})


def test_the_gain_of_picking_the_lowest_validation_error_by_hand():
    pts = [point(0.03, 60.0), point(0.04, 70.0), point(0.05, 80.0)]
    assert selection_gain(pts) == pytest.approx(60.0 - 70.0)


def write_cell(folder: Path, row: str, seed: int, val: float, wins: dict[str, int], machine: str) -> None:
    """A finished cell.json: per column, ``wins[column]`` successes out of 4 episodes."""
    eps = {f"{col}/{k}": {"success": k < wins[col], "column": col, "command": "left"}
           for col in COLUMNS for k in range(4)}
    path = folder / "cells" / row / f"seed{seed}" / "cell.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"row": row, "seed": seed, "status": "ok", "val_steer_mae": val,
                                "machine": machine, "episodes": eps}))


EPYC = "2 cores (AMD EPYC), no GPU, Python 3.11.7"
XEON = "2 cores (Intel(R) Xeon(R) Processor), no GPU, Python 3.11.7"


def results_tree(root: Path) -> Path:
    wins = dict(zip(COLUMNS, (4, 2, 3, 1)))
    for name, budget in (("study", "converged"), ("continued", "converged")):
        (root / name).mkdir(parents=True)
        (root / name / "reproduce.json").write_text(json.dumps({"budget": budget}))
        write_cell(root / name, "cil", 0, 0.05, wins, EPYC)  # the same cell, copied into the continued folder
    for seed in range(1, 6):
        write_cell(root / "study", "cil", seed, 0.04 + 0.001 * seed, {c: (seed + i) % 5 for i, c in enumerate(COLUMNS)},
                   XEON)
    return root


def test_each_cell_is_read_once_with_its_kind_budget_and_success(tmp_path):
    pts = collect_points(results_tree(tmp_path / "results"))
    assert len(pts) == 6
    first = next(p for p in pts if p.seed == 0)
    assert sorted(first.folders) == ["continued", "study"] and first.cpu == "AMD EPYC" and first.budget == "converged"
    assert first.success["overall"] == pytest.approx(100 * (4 + 2 + 3 + 1) / 16)  # the mean of the 4 columns
    assert first.success[COLUMNS[1]] == 50.0
    assert {p.cpu for p in pts if p.seed} == {"Intel Xeon"}


def test_the_report_is_written(tmp_path):
    root = results_tree(tmp_path / "results")
    out = root / "offline_vs_closed_loop"
    res = write_report(root, out)
    assert res["cells"] == 6 and set(res["scopes"]) == {"both kinds (pooled)", "Intel Xeon", "AMD EPYC"}
    text = (out / "README.md").read_text()
    for heading in ("**Question.**", "**Data.**", "**Method.**", "## Answer"):
        assert heading in text
    assert (out / "offline_vs_closed_loop.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((out / "results.json").read_text())["cells"] == 6


def test_a_folder_holding_files_the_study_did_not_write_is_refused(tmp_path, capsys):
    """``--out .`` in a clone wrote the study's README.md over the repository's own."""
    from cicfw.reproduction import offline_vs_closed_loop as study

    root = results_tree(tmp_path / "results")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "README.md").write_text("my notes\n")
    with pytest.raises(SystemExit) as exc:
        study.main(["--results", str(root), "--out", str(mine)])
    assert exc.value.code == 2 and "--out" in capsys.readouterr().err
    assert (mine / "README.md").read_text() == "my notes\n" and not (mine / "results.json").exists()
    out = root / "offline_vs_closed_loop"
    write_report(root, out)
    write_report(root, out)  # its own earlier report: rewritten


def test_another_weather_family_is_analysed_on_its_own(tmp_path):
    root = results_tree(tmp_path / "results")
    calibrated = root / "calibrated"
    calibrated.mkdir()
    pinned = {"suite": ["suite=single_turn", "sim.weather_family=carla"]}
    (calibrated / "reproduce.json").write_text(json.dumps({"budget": "converged", "pinned": pinned}))
    for seed in range(4):  # the same models as the study's Xeon cells, other new-weather outcomes
        write_cell(calibrated, "cil", seed + 1, 0.04 + 0.001 * (seed + 1), dict(zip(COLUMNS, (4, 4, 3, 3 - seed))), XEON)
    pts = collect_points(root)
    assert {p.family for p in pts if "calibrated" in p.folders} == {"carla"}
    assert {p.family for p in pts if "study" in p.folders} == {"harsh"}  # no family pinned: the harsh presets
    out = root / "offline_vs_closed_loop"
    res = write_report(root, out)
    assert res["cells"] == 6  # the main analysis holds the harsh family's cells only
    carla = res["families"]["carla"]
    assert carla["cells"] == 4
    # by hand: validation errors 0.041..0.044 against new-town/new-weather wins 3, 2, 1, 0: rho = -1
    assert carla["scopes"]["both kinds (pooled)"]["pooled"][COLUMNS[3]]["rho"] == pytest.approx(-1.0)
    text = (out / "README.md").read_text()
    assert "## Under the `carla` weathers" in text and "`calibrated`" in text.split("## Under")[-1]
    assert "`calibrated`" not in text.split("**Data.**")[1].split("**Method.**")[0]


def test_a_cell_whose_validation_error_is_nan_has_no_point(tmp_path):
    """A diverged run records NaN (json writes it, read_json reads it back): as a cell without a value, it is no
    point, rather than one that blanks every pooled correlation while the report counts it."""
    root = results_tree(tmp_path / "results")
    cell = root / "study" / "cells" / "cil" / "seed3" / "cell.json"
    cell.write_text(json.dumps({**json.loads(cell.read_text()), "val_steer_mae": float("nan")}))
    assert "NaN" in cell.read_text()
    pts = collect_points(root)
    assert len(pts) == 5 and 3 not in {p.seed for p in pts}
    assert all(math.isfinite(p.val_mae) for p in pts)
