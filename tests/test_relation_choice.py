"""Fine tuning's R chosen by validation error: the rule against hand arithmetic, and the command line."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from cicfw.reproduction.relation_choice import choose, choose_in, main, unusable_errors, val_errors


def test_the_lowest_mean_over_shared_seeds_wins():
    errors = {"re_all": {0: 0.050, 1: 0.070}, "re_pairs": {0: 0.040, 1: 0.090}, "re_none": {0: 0.060, 1: 0.055}}
    c = choose(errors, ["re_all", "re_pairs", "re_none"])
    # by hand: re_all (0.050 + 0.070) / 2 = 0.060, re_pairs 0.065, re_none 0.0575
    assert c.seeds == (0, 1)
    assert c.errors == pytest.approx({"re_all": 0.060, "re_pairs": 0.065, "re_none": 0.0575})
    assert c.chosen == "re_none"


def test_only_seeds_every_candidate_has_count():
    errors = {"a": {0: 0.05, 1: 0.01}, "b": {0: 0.04}}
    c = choose(errors, ["a", "b"])
    assert c.seeds == (0,)  # seed 1 of a alone would make a win
    assert c.chosen == "b"


def test_a_tie_keeps_the_earlier_candidate():
    assert choose({"x": {0: 0.05}, "y": {0: 0.05}}, ["y", "x"]).chosen == "y"


def test_no_shared_seed_chooses_nothing():
    assert choose({"a": {0: 0.05}, "b": {1: 0.04}}, ["a", "b"]).chosen is None
    with pytest.raises(ValueError, match="relation_candidates"):
        choose({}, [])


def test_cells_without_a_finite_error_are_left_out():
    cells = {"a/seed0": {"val_steer_mae": 0.05}, "a/seed1": {"val_steer_mae": None},
             "b/seed0": {"val_steer_mae": float("nan")}, "other/seed0": {"val_steer_mae": 0.01}}
    assert val_errors(cells, ["a", "b"]) == {"a": {0: 0.05}, "b": {}}


def _cell(folder: Path, row: str, seed: int, mae: float, status: str = "ok") -> None:
    d = folder / "cells" / row / f"seed{seed}"
    d.mkdir(parents=True)
    (d / "cell.json").write_text(json.dumps({"row": row, "seed": seed, "status": status, "val_steer_mae": mae}))


def test_a_results_folder_and_the_command_line(tmp_path, capsys):
    _cell(tmp_path, "re_all", 0, 0.048)
    _cell(tmp_path, "re_pairs", 0, 0.046)
    _cell(tmp_path, "re_none", 0, 0.044, status="failed")  # a failed cell is no candidate's evidence
    assert choose_in(tmp_path, ["re_all", "re_pairs"]).chosen == "re_pairs"
    assert main([str(tmp_path), "--candidates", "re_all", "re_pairs"]) == 0
    assert "re_pairs" in capsys.readouterr().out.split("<- chosen")[0].splitlines()[-1]
    assert main([str(tmp_path)]) == 1  # re_none has no finished cell
    assert main([str(tmp_path / "missing")]) == 2


def test_a_diverged_candidate_is_named_not_called_missing(tmp_path, capsys):
    """Seed 0 finished for every candidate but re_all's error is NaN: the command said no seed had a finished
    cell and advised running seed 0 again; it names the cell and its NaN and advises the other seeds."""
    _cell(tmp_path, "re_all", 0, float("nan"))
    _cell(tmp_path, "re_pairs", 0, 0.046)
    _cell(tmp_path, "re_pairs", 1, 0.045)
    assert main([str(tmp_path), "--candidates", "re_all", "re_pairs"]) == 1
    out = capsys.readouterr().out
    assert "re_all/seed0 (val_steer_mae NaN" in out and "'seeds=[1]'" in out, out
    _cell(tmp_path, "re_all", 1, 0.050)  # seed 1 is shared: chosen there, the NaN cell still named
    assert main([str(tmp_path), "--candidates", "re_all", "re_pairs"]) == 0
    out = capsys.readouterr().out
    assert "left out: re_all/seed0 (val_steer_mae NaN" in out and "over seeds [1]" in out, out


def test_unusable_errors_names_each_kind():
    cells = {"a/seed0": {"val_steer_mae": float("nan")}, "a/seed1": {}, "a/seed2": {"val_steer_mae": float("inf")},
             "a/seed3": {"val_steer_mae": "0.1"}, "a/seed4": {"val_steer_mae": 0.1}, "b/seed0": {}}
    assert unusable_errors(cells, ["a"]) == {"a/seed0": "NaN", "a/seed1": "missing", "a/seed2": "inf",
                                             "a/seed3": '"0.1"'}
    # a mean absolute error below 0 is an edited or broken record: never the smallest error, the chosen R
    assert unusable_errors({"a/seed0": {"val_steer_mae": -1.0}, "a/seed1": {"val_steer_mae": -2}}, ["a"]) == {
        "a/seed0": "-1.0", "a/seed1": "-2"}


def test_the_advice_names_the_folders_budget_and_the_folder(tmp_path, capsys):
    """Without them the advised command trained the default budget into another folder."""
    (tmp_path / "reproduce.json").write_text('{"budget": "smoke"}')
    _cell(tmp_path, "re_all", 0, 0.05)
    (tmp_path / "cells" / "re_all" / "seed0" / "train").mkdir()
    assert main([str(tmp_path), "--candidates", "re_all", "re_pairs"]) == 1
    out = capsys.readouterr().out
    assert f"budget=smoke 'rows=[re_all,re_pairs]' 'seeds=[0]' results_dir={tmp_path}" in out, out
    _cell(tmp_path, "re_pairs", 0, -1.0)  # below 0: left out, so still no seed for both
    assert main([str(tmp_path), "--candidates", "re_all", "re_pairs"]) == 1
    assert "re_pairs/seed0 (val_steer_mae -1.0: below 0)" in capsys.readouterr().out


# ---- the report's account of the choice
# ---- the report's account of the choice


def _result(row: str, seed: int, mae: float | None):
    from cicfw.reproduction.cells import COLUMNS, CellResult

    eps = {f"{c}/{k}": {"success": k < 3, "column": c, "command": "left"} for c in COLUMNS for k in range(4)}
    return CellResult(row=row, seed=seed, episodes=eps, meta={"decoder": None, "wall_s": {}, "val_steer_mae": mae})


CANDIDATES = ["re_all", "re_pairs", "re_none"]
LABELS = {"re_all": "R: every pair", "re_pairs": "R: pairs", "re_none": "R: none", "cil": "CIL"}


def test_the_report_shows_each_candidates_error_and_the_choice():
    """Seed 0 all three, seed 1 only re_all and re_none: the means are over seed 0 alone (by hand: 0.048,
    0.046, 0.050), so re_pairs is chosen although re_none's seed 1 is the lowest error of all."""
    from cicfw.reproduction.report import markdown, report_data

    cells = [_result("cil", 0, 0.040), _result("re_all", 0, 0.048), _result("re_pairs", 0, 0.046),
             _result("re_none", 0, 0.050), _result("re_all", 1, 0.047), _result("re_none", 1, 0.030)]
    catalogue = {r: {"label": LABELS[r]} for r in LABELS}
    data = report_data(cells, [], catalogue, {}, n_boot=20, claims=[], margin=5.0, relation_candidates=CANDIDATES)
    rel = data["relation"]
    assert rel["seeds"] == [0] and rel["chosen"] == "re_pairs"
    assert [c["mean"] for c in rel["candidates"]] == pytest.approx([0.048, 0.046, 0.050])
    assert rel["candidates"][2]["val_steer_mae"] == {"0": 0.050, "1": 0.030}
    md = markdown(json.loads(json.dumps(data)))
    section = md.split("## Fine tuning's R, chosen by validation error")[1].split("\n## ")[0]
    assert "| Candidate | Seed 0 | Seed 1 | Mean over shared seeds |" in section
    assert "| **R: pairs** | 0.04600 | – | 0.04600 (chosen) |" in section
    assert "| R: none | 0.05000 | 0.03000 | 0.05000 |" in section
    # without a candidate's cell there is no section; with a candidate short of a shared seed, no choice
    plain = report_data(cells[:1], [], catalogue, {}, n_boot=20, claims=[], margin=5.0, relation_candidates=CANDIDATES)
    assert plain["relation"] is None and "Fine tuning's R" not in markdown(plain)
    part = report_data(cells[:3], [], catalogue, {}, n_boot=20, claims=[], margin=5.0,
                       relation_candidates=CANDIDATES)["relation"]
    assert part["chosen"] is None and part["seeds"] == []


def test_the_report_names_a_diverged_candidate():
    """re_all's seed 0 NaN: the report said some candidate had no finished cell; it names the cell, shows NaN in
    the table and chooses over the seeds left (seed 1)."""
    from cicfw.reproduction.report import markdown, report_data

    cells = [_result("re_all", 0, float("nan")), _result("re_pairs", 0, 0.046), _result("re_none", 0, 0.050)]
    catalogue = {r: {"label": LABELS[r]} for r in LABELS}
    data = report_data(cells, [], catalogue, {}, n_boot=20, claims=[], margin=5.0, relation_candidates=CANDIDATES)
    assert data["relation"]["chosen"] is None and data["relation"]["unusable"] == {"re_all/seed0": "NaN"}
    section = markdown(json.loads(json.dumps(data))).split("## Fine tuning's R")[1].split("\n## ")[0]
    assert "| R: every pair | NaN | – |" in section
    assert "re_all/seed0 (val_steer_mae NaN" in section and "no finished cell" not in section
    cells += [_result(r, 1, mae) for r, mae in (("re_all", 0.040), ("re_pairs", 0.045), ("re_none", 0.050))]
    rel = report_data(cells, [], catalogue, {}, n_boot=20, claims=[], margin=5.0,
                      relation_candidates=CANDIDATES)["relation"]
    assert rel["seeds"] == [1] and rel["chosen"] == "re_all" and rel["unusable"] == {"re_all/seed0": "NaN"}


def test_the_shipped_candidates_are_catalogue_rows_and_the_commands_default():
    from cicfw.reproduction.relation_choice import shipped_candidates

    assert shipped_candidates() == CANDIDATES
    import yaml
    from importlib.resources import files

    catalogue = yaml.safe_load(files("cicfw.conf").joinpath("reproduce.yaml").read_text())["catalogue"]
    assert set(shipped_candidates()) <= set(catalogue)
