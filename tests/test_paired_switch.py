"""The paired switch comparison (cicfw.reproduction.paired_switch): its TOST recomputed by hand from Student's t,
its verdicts on cells with a known answer, and its one-line errors."""
from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import pytest
from scipy import stats

from cicfw.benchmark.evaluation_report import episodes_csv
from cicfw.core.errors import CicfwError
from cicfw.reproduction import paired_switch as ps
from cicfw.reproduction.cells import COLUMNS
from cicfw.reproduction.seed_stats import difference

from conftest import mover, wilson

EPISODES = 20  # per column


def write_cell(folder: Path, row: str, seed: int, successes: list[int], train_s: float = 100.0) -> None:
    """A finished cell whose four columns hold ``successes[i]`` successes of ``EPISODES`` episodes."""
    eps = {}
    for col, k in zip(COLUMNS, successes):
        for i in range(EPISODES):
            eps[f"{col}/{i:02d}"] = {"success": i < k, "column": col, "command": "left"}
    d = folder / f"seed{seed}"
    d.mkdir(parents=True)
    (d / "cell.json").write_text(json.dumps({"row": row, "seed": seed, "status": "ok", "episodes": eps,
                                             "wall_s": {"train": train_s}}))


def tost_by_hand(d: list[float], margin: float) -> float:
    """max of the two one-sided p-values: H0 mean <= -margin (t = (m + margin) / se, upper tail) and
    H0 mean >= +margin (t = (m - margin) / se, lower tail), n - 1 df."""
    n = len(d)
    m = sum(d) / n
    se = math.sqrt(sum((x - m) ** 2 for x in d) / (n - 1)) / math.sqrt(n)
    p_low = 1 - stats.t.cdf((m + margin) / se, n - 1)
    p_high = stats.t.cdf((m - margin) / se, n - 1)
    return max(p_low, p_high)


def test_tost_against_a_hand_computation():
    a, b = [61.0, 58.0, 64.0, 60.0], [60.0, 59.0, 62.0, 61.0]  # differences 1, -1, 2, -1: mean 0.25
    assert ps.tost_paired(a, b, 5.0) == pytest.approx(tost_by_hand([1, -1, 2, -1], 5.0), rel=1e-9)
    assert ps.tost_paired(a, b, 5.0) < 0.01
    # a margin the differences straddle: not equivalent
    assert ps.tost_paired(a, b, 0.5) == pytest.approx(tost_by_hand([1, -1, 2, -1], 0.5), rel=1e-9)
    assert ps.tost_paired(a, b, 0.5) > 0.3
    # no spread at all: inside or outside the margin decides
    assert ps.tost_paired([60, 60, 60], [58, 58, 58], 5.0) == 0.0
    assert ps.tost_paired([60, 60, 60], [50, 50, 50], 5.0) == 1.0


def test_verdicts_on_cells_with_a_known_answer(tmp_path):
    """Equal cells (every seed, every column): equivalent, in each column and overall, only where the 60
    pooled episodes a column can resolve the margin (±25, not ±5: equal seeds are no evidence that the
    episodes' luck is small; overall, the mean of four columns, is no exception); a switch that costs 5 of 20 episodes (25 points) in every column: not shown; two
    paired seeds: too few."""
    for s in range(3):
        write_cell(tmp_path / "fp32", "cil", s, [18, 10, 12, 5 + s])
        write_cell(tmp_path / "same", "cil_x", s, [18, 10, 12, 5 + s])
        write_cell(tmp_path / "worse", "cil_y", s, [13, 5, 7, s])
    base = ps.load_row(tmp_path / "fp32")
    same = ps.compare(ps.load_row(tmp_path / "same"), base, 5.0)
    assert [e.on for e in same] == [*COLUMNS, "overall"]
    assert all(e.mean == 0 for e in same) and all(e.verdict == "not shown" for e in same)
    assert all(e.hi > 9 for e in same[:-1]) and same[-1].hi > 5
    assert all(e.verdict == "equivalent within ±25" for e in ps.compare(ps.load_row(tmp_path / "same"), base, 25.0))
    worse = ps.compare(ps.load_row(tmp_path / "worse"), base, 5.0)
    assert all(e.verdict == "not shown" and e.mean == pytest.approx(-25.0) for e in worse)
    two = {s: c for s, c in base.items() if s < 2}
    assert all(e.verdict.startswith("too few seeds") and e.p_tost is None for e in ps.compare(two, base, 5.0))


def test_overall_is_the_mean_of_the_columns_and_tost_matches_by_hand(tmp_path):
    a = [[18, 10, 12, 4], [19, 12, 11, 6], [17, 9, 14, 5]]
    b = [[18, 11, 12, 5], [18, 10, 12, 4], [18, 10, 13, 6]]
    for s in range(3):
        write_cell(tmp_path / "a", "x", s, a[s])
        write_cell(tmp_path / "b", "y", s, b[s])
    got = ps.compare(ps.load_row(tmp_path / "a"), ps.load_row(tmp_path / "b"), 5.0)[-1]
    d = [sum(x - y for x, y in zip(a[s], b[s])) * 100 / EPISODES / 4 for s in range(3)]  # overall, points
    assert got.on == "overall" and got.mean == pytest.approx(sum(d) / 3)
    # the pooled episodes: each column's 60 of A against B's, a quarter each (the mean of the four columns)
    terms = [(w, sum(x[s][c] for s in range(3)), 3 * EPISODES) for c in range(4) for w, x in ((0.25, a), (-0.25, b))]
    p_seeds = tost_by_hand(d, 5.0)
    assert got.p_tost > p_seeds  # here the episodes are the weaker evidence: TOST takes their p-value
    z = float(stats.norm.ppf(1 - got.p_tost))  # at the dual level the farther bound touches its margin
    lo, hi = mover(terms, z)
    assert max(-lo, hi) == pytest.approx(5.0, abs=1e-6) and min(-lo, hi) < 5.0
    lo95, hi95 = mover(terms, stats.norm.ppf(0.975))
    half = stats.t.ppf(0.975, 2) * stats.tstd(d) / math.sqrt(3)
    assert (got.lo, got.hi) == pytest.approx((min(lo95, sum(d) / 3 - half), max(hi95, sum(d) / 3 + half)))


def test_the_printed_interval_says_a_column_is_widened_to_the_episodes(tmp_path):
    """A column's interval, widened to Newcombe's, was headed '95% t' as if it were the seeds' t-interval."""
    for s, (k, j) in enumerate([(15, 11), (16, 11), (15, 12)]):  # differences 20, 25, 15 points: a narrow t
        write_cell(tmp_path / "a", "x", s, [k] * 4)
        write_cell(tmp_path / "b", "y", s, [j] * 4)
    a, b = ps.load_row(tmp_path / "a"), ps.load_row(tmp_path / "b")
    column, overall = ps.compare(a, b, 5.0)[0], ps.compare(a, b, 5.0)[-1]
    assert column.hi - column.lo > overall.hi - overall.lo  # the same seeds' differences, widened in a column
    out = ps.lines(a, b, 5.0)
    assert "95% t]" not in out[1] and any("widened" in line and "Newcombe" in line for line in out), out


def test_the_verdict_is_printed_with_the_90_percent_interval_it_is_read_on(tmp_path):
    """Near the margin the verdict (TOST at 5% each side) and the word (95% interval) can differ: the line
    shows the verdict's own interval. Columns of 100 episodes whose seeds differ by 2, 6, 1 points: the
    episodes' floor is wider than the seeds' t-interval, so the 90% interval is Newcombe's, by hand
    (Wilson with z = 1.645 on the pooled 300 episodes of each side), its verdict from where it lies."""
    per = [(60, 58), (66, 60), (61, 60)]
    for s, (k, j) in enumerate(per):
        for side, n in (("a", k), ("b", j)):
            eps = {f"{c}/{i:03d}": {"success": i < n, "column": c, "command": "left"} for c in COLUMNS for i in range(100)}
            (tmp_path / side / f"seed{s}").mkdir(parents=True)
            (tmp_path / side / f"seed{s}" / "cell.json").write_text(json.dumps(
                {"row": side, "seed": s, "status": "ok", "episodes": eps}))
    a, b = ps.load_row(tmp_path / "a"), ps.load_row(tmp_path / "b")
    ka, kb, z = sum(k for k, _ in per), sum(j for _, j in per), float(stats.norm.ppf(0.95))
    (l1, u1), (l2, u2) = wilson(ka, 300, z), wilson(kb, 300, z)
    d = ka / 300 - kb / 300
    lo = 100 * (d - math.sqrt((ka / 300 - l1) ** 2 + (u2 - kb / 300) ** 2))
    hi = 100 * (d + math.sqrt((u1 - ka / 300) ** 2 + (kb / 300 - l2) ** 2))
    diffs = [k - j for k, j in per]
    half = stats.t.ppf(0.95, 2) * stats.tstd(diffs) / math.sqrt(3)
    lo, hi = min(lo, sum(diffs) / 3 - half), max(hi, sum(diffs) / 3 + half)
    for margin in (5.0, 12.0):
        column = ps.compare(a, b, margin)[0]
        assert (column.tost_lo, column.tost_hi) == pytest.approx((lo, hi), abs=1e-6)
        assert (column.verdict == f"equivalent within ±{margin:g}") == (-margin < lo and hi < margin)
        line = next(x for x in ps.lines(a, b, margin) if x.startswith(COLUMNS[0]))
        assert f"[90%: {lo:+.1f}, {hi:+.1f}]" in line, line


def test_episode_tost_is_dual_to_newcombes_interval_by_hand():
    """192 of 192 against 180 of 192 (+6.25 points), margin 10: the p-value is the alpha at which Newcombe's
    (1 - 2 alpha) interval, from Wilson's closed form with z = the normal quantile 1 - alpha, reaches
    +10; a difference outside the margin gives 1, a margin far wider than the episodes' luck about 0."""
    p = ps.episode_tost([(1.0, 192, 192), (-1.0, 180, 192)], 10.0)
    z = float(stats.norm.ppf(1 - p))
    (l1, u1), (l2, u2) = wilson(192, 192, z), wilson(180, 192, z)
    upper = 100 * (1.0 - 180 / 192 + math.sqrt((u1 - 1.0) ** 2 + (180 / 192 - l2) ** 2))
    assert 0.01 < p < 0.05 and upper == pytest.approx(10.0, abs=1e-6)
    assert ps.episode_tost([(1.0, 192, 192), (-1.0, 150, 192)], 10.0) == 1.0
    assert ps.episode_tost([(1.0, 96, 192), (-1.0, 96, 192)], 60.0) < 1e-9


def test_bad_input_is_one_line(tmp_path, capsys):
    assert ps.main([str(tmp_path / "nowhere"), str(tmp_path)]) == 2
    assert str(tmp_path / "nowhere") in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    write_cell(tmp_path / "b", "cil", 0, [1, 1, 1, 1])
    assert ps.main([str(tmp_path / "empty"), str(tmp_path / "b")]) == 2
    assert str(tmp_path / "empty") in capsys.readouterr().err
    assert ps.main([str(tmp_path / "b"), str(tmp_path / "b"), "--margin", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--margin" in err, err
    # an infinite margin read every comparison "equivalent within ±inf", a 70-point gap among them
    for seed in range(3):
        write_cell(tmp_path / "x", "cil", seed, [1 + seed, 1, 1, 1])
        write_cell(tmp_path / "y", "cil", seed, [15 + seed, 2, 2, 2])
    assert ps.main([str(tmp_path / "x"), str(tmp_path / "y"), "--margin", "inf"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--margin" in err and "inf" in err, err


def test_a_results_folder_given_for_a_row_names_its_rows(tmp_path, capsys):
    """Two reproductions' results folders (``<name>/cells/<row>/seed<k>``) given instead of a row's cells: the
    line says which they are and names the rows to pick from, not that they hold no cell."""
    for name in ("c6", "ch"):
        for row in ("gtu", "cil"):
            write_cell(tmp_path / name / "cells" / row, row, 0, [1, 1, 1, 1])
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    with pytest.raises(CicfwError) as err:
        ps.load_row(tmp_path / "c6")
    assert err.value.value == str(tmp_path / "c6") and "rows: cil, gtu" in str(err.value)
    assert ps.main([str(tmp_path / "c6"), str(tmp_path / "ch")]) == 2
    line = capsys.readouterr().err
    assert line.count("\n") == 1 and "results folder" in line and str(tmp_path / "c6" / "cells") in line, line
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def exact_mcnemar_by_hand(lost: int, gained: int) -> float:
    """Two-sided exact McNemar: twice the binomial(n, 1/2) tail at the smaller count, at most 1."""
    n, k = lost + gained, min(lost, gained)
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n)


def test_episode_changes_between_a_cell_and_an_evaluation_folder(tmp_path):
    """Cell B drives episodes 0-13 of column 0; evaluation A drives 2-19 of them (gains 14-19, loses 0-1):
    18 vs 14, gained 6, lost 2, p = 2 * (1 + 8 + 28) / 256 = .289."""
    write_cell(tmp_path / "cells", "cil", 0, [14, 10, 0, 0])
    col = COLUMNS[0]
    lines = ["key,town_set,weather_set,success"]
    for i in range(EPISODES):
        lines.append(f"{col}/{i:02d},training,training,{i >= 2}")
    (tmp_path / "eval").mkdir()
    (tmp_path / "eval" / "episodes.csv").write_text("\n".join(lines) + "\n")
    a = ps.load_episodes(tmp_path / "eval")
    b = ps.load_episodes(tmp_path / "cells" / "seed0" / "cell.json")
    got = {r["column"]: r for r in ps.episode_changes(a, b)}
    r = got[col]
    assert (r["episodes"], r["a"], r["b"], r["gained"], r["lost"]) == (20, 18, 14, 6, 2)
    assert r["p"] == pytest.approx(exact_mcnemar_by_hand(2, 6)) and r["p"] == pytest.approx(74 / 256)
    assert got["all"]["episodes"] == 20 and got[COLUMNS[1]]["episodes"] == 0 and got[COLUMNS[1]]["p"] == 1.0
    assert ps.main(["--episodes", str(tmp_path / "eval"), str(tmp_path / "nothing.json")]) == 2


def test_the_same_folder_or_file_twice_is_refused(tmp_path, capsys):
    """A run against itself is +0.0 'equivalent' by construction: refused, also under another spelling."""
    write_cell(tmp_path / "a", "cil", 0, [1, 1, 1, 1])
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "x" / ".." / "a")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and str(tmp_path / "a") in err, err
    cell = tmp_path / "a" / "seed0" / "cell.json"
    assert ps.main(["--episodes", str(cell), str(tmp_path / "a" / "seed0" / "." / "cell.json")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and str(cell) in err, err


def test_rows_with_no_common_seed_are_refused_and_row_names_are_printed(tmp_path, capsys):
    """No paired seed: one line naming each side's seeds, no numpy warning, no +nan table; two rows that
    do share seeds are compared, their row names printed."""
    write_cell(tmp_path / "a", "cil_bf16", 5, [1, 1, 1, 1])
    write_cell(tmp_path / "b", "cil", 0, [1, 1, 1, 1])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert ps.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "[5]" in err and "[0]" in err, err  # each side's seeds
    write_cell(tmp_path / "b", "cil", 5, [1, 1, 1, 1])
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    assert "(row cil_bf16) vs B" in capsys.readouterr().out


def test_episodes_files_without_episodes_are_refused(tmp_path, capsys):
    """--episodes on a text file, an empty file, a header-only episodes.csv, or two runs with no episode
    in common: one line each, nothing printed on stdout."""
    write_cell(tmp_path / "cells", "cil", 0, [2, 2, 2, 2])
    cell = str(tmp_path / "cells" / "seed0" / "cell.json")
    (tmp_path / "text.h5").write_text("not a table\n")
    (tmp_path / "empty.csv").write_text("")
    (tmp_path / "header.csv").write_text("key,town_set,weather_set,success\n")
    (tmp_path / "other.csv").write_text("key,town_set,weather_set,success\nzz/00,training,training,True\n")
    for name in ("text.h5", "empty.csv", "header.csv", "other.csv"):
        assert ps.main(["--episodes", str(tmp_path / name), cell]) == 2, name
        out, err = capsys.readouterr()
        assert out == "" and err.count("\n") == 1 and str(tmp_path / name) in err, (name, err)


def results_folder(root: Path, suite: list[str] | None, rows: dict[str, str | None], seeds: int = 3) -> dict[str, Path]:
    """A results folder pinned to ``suite`` (None: no reproduce.json) with a row per ``rows`` entry, each cell
    recording that weather family (None: no record); row -> its cells' folder."""
    if suite is not None:
        root.mkdir(parents=True)
        (root / "reproduce.json").write_text(json.dumps({"pinned": {"suite": suite}}))
    out = {}
    for row, family in rows.items():
        for s in range(seeds):
            write_cell(root / "cells" / row, row, s, [10, 10, 10, 10])
            if family:
                p = root / "cells" / row / f"seed{s}" / "cell.json"
                p.write_text(json.dumps({**json.loads(p.read_text()), "weather_family": family}))
        out[row] = root / "cells" / row
    return out


def test_rows_driven_under_different_weather_families_are_refused(tmp_path, capsys):
    """The families share weather names, so episode keys match: a row of a carla folder against one of a
    folder pinned before the families (harsh) is refused naming both; so are cells recording the two families
    without a reproduce.json; one family on both sides is compared."""
    carla = results_folder(tmp_path / "carla", ["suite=single_turn", "sim.weather_family=carla"], {"cil": None})
    harsh = results_folder(tmp_path / "harsh", ["suite=single_turn"], {"cil": None})
    assert ps.main([str(carla["cil"]), str(harsh["cil"])]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "'carla'" in err and "'harsh'" in err, err
    bare = results_folder(tmp_path / "bare", None, {"a": "harsh", "b": "carla", "c": None})
    with pytest.raises(CicfwError) as got:
        ps.check_one_family(ps.load_row(bare["a"]), ps.load_row(bare["b"]), (bare["a"], bare["b"]))
    assert (got.value.key, got.value.value) == ("weather_family", "carla")
    # a carla cell copied into the harsh folder: refused on its own record, against its folder's pin
    mixed = results_folder(tmp_path / "mixed", ["suite=single_turn"], {"cil": None, "gtu": "carla"})
    assert ps.main([str(mixed["gtu"]), str(harsh["cil"])]) == 2
    err = capsys.readouterr().err
    assert "weather_family=carla" in err and "weather_family=harsh" in err, err
    assert ps.main([str(bare["c"]), str(harsh["cil"])]) == 0  # no record, no manifest: not known
    assert ps.main([str(carla["cil"]), str(bare["b"])]) == 0
    capsys.readouterr()


#: an evaluation's records as `python -m cicfw.evaluate` writes them (the suite it drove, the simulator and the
#: runner's episode rules, and its fingerprint of them)
EVAL_SUITE = {"towns": ["town_a", "town_b"], "weathers": ["ClearNoon", "ClearSunset", "MidRainyNoon", "WetCloudySunset"],
              "training_towns": ["town_a"], "training_weathers": ["ClearNoon", "ClearSunset"], "pairs": None,
              "limit": None, "name": "junctions"}
EVAL_SIM = {"name": "embedded", "command_distance": 12.0, "success_radius": 2.0, "max_deviation": 10.0,
            "route_before": 30.0, "route_after": 25.0}


def eval_folder(path: Path, family: str, successes: int = 10) -> Path:
    """An evaluation folder of column 0's episodes: episodes.json with the records an evaluation writes (its
    suite, sim, runner and fingerprint), episodes.csv as the evaluation writes it."""
    path.mkdir(parents=True)
    rows = [{"model": path.name, "episode": i, "key": f"{COLUMNS[0]}/{i:02d}", "town": "town_a", "weather": "ClearNoon",
             "town_set": "training", "weather_set": "training", "pair": i, "route": f"town_a/r{i}", "command": "left",
             "success": i < successes, "reason": "success" if i < successes else "timeout"} for i in range(EPISODES)]
    sim, runner = {**EVAL_SIM, "weather_family": family}, {"off_road_s": 3.0, "off_road_level": 0.5,
                                                          "target_speed_kmh": None}
    meta = {"policy": "expert", "checkpoint": None, "seed": 0, "suite": EVAL_SUITE, "runner": runner, "sim": sim,
            "fingerprint": {"policy": {"name": "expert"}, "suite": EVAL_SUITE, "episodes": "0" * 16, "seed": 0,
                            "sim": sim, "runner": runner},
            "complete": True, "episodes_total": EPISODES, "model": path.name}
    (path / "episodes.json").write_text(json.dumps({"episodes": rows, "meta": meta}))
    (path / "episodes.csv").write_text(episodes_csv(rows))
    return path


def test_episodes_under_different_sim_settings_are_refused(tmp_path, capsys):
    """--episodes on two evaluation folders refuses other sim settings as `cicfw report` does (naming the key
    and both values); a cell against a folder compares their weather families."""
    carla, harsh = eval_folder(tmp_path / "carla", "carla"), eval_folder(tmp_path / "harsh", "harsh")
    assert ps.main(["--episodes", str(harsh), str(carla)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "sim.weather_family" in err and "harsh" in err, err
    assert ps.main(["--episodes", str(carla), str(eval_folder(tmp_path / "carla2", "carla", successes=12))]) == 0
    capsys.readouterr()
    rows = results_folder(tmp_path / "old", ["suite=single_turn"], {"cil": None}, seeds=1)  # harsh, by its pin
    assert ps.main(["--episodes", str(carla), str(rows["cil"] / "seed0" / "cell.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "sim.weather_family" in err and "carla" in err and "harsh" in err, err
    assert ps.main(["--episodes", str(harsh), str(rows["cil"] / "seed0" / "cell.json")]) == 0


#: a suite of 8 episodes (one pair per town and weather), driven by the expert in well under a second
SMALL_SUITE = {**EVAL_SUITE, "limit": 1}


def drive(out: Path, sim: dict | None = None, **suite: object) -> Path:
    """A real evaluation of the expert on ``SMALL_SUITE`` (with ``suite``'s changes) into ``out``, under every
    sim setting `python -m cicfw.evaluate` passes (with ``sim``'s changes)."""
    from cicfw.benchmark.app import evaluate_policy

    evaluate_policy({"name": "expert"}, {**SMALL_SUITE, **suite}, {"workers": 1}, out,
                    sim={**EVAL_SIM, "weather_family": "carla", **(sim or {})}, maps=False)
    return out


def cell_of(evaluation: Path, cell_dir: Path) -> Path:
    """A finished cell whose evaluation is ``evaluation`` (moved to ``<cell>/evaluate``, where a reproduction
    drives it): its cell.json's episodes as the reproduction records them."""
    from cicfw.benchmark.finished_run import cell_key, load_run

    cell_dir.mkdir(parents=True)
    evaluation.rename(cell_dir / "evaluate")
    eps = {r["key"]: {"success": bool(r["success"]), "column": cell_key(r["town_set"], r["weather_set"]),
                      "command": r["command"], "reason": r["reason"]} for r in load_run(cell_dir / "evaluate").rows}
    (cell_dir / "cell.json").write_text(json.dumps({"row": "cil", "seed": 0, "status": "ok", "episodes": eps}))
    return cell_dir / "cell.json"


@pytest.mark.slow  # drives the suite (three evaluations of 8 episodes)
def test_episodes_of_evaluations_of_other_suites_or_sim_settings_are_refused(tmp_path, capsys):
    """Two evaluations of one suite but other training weathers put the same episodes in other table columns:
    refused in either order, naming the key and both values, as `cicfw report` refuses them. A cell holding its
    evaluation gets the same check as an evaluation folder: another success radius is refused, not only
    another weather family."""
    e1 = drive(tmp_path / "e1")
    e3 = drive(tmp_path / "e3", training_weathers=["ClearNoon"])
    for a, b in ((e1, e3), (e3, e1)):
        assert ps.main(["--episodes", str(a), str(b)]) == 2
        out, err = capsys.readouterr()
        assert out == "" and err.count("\n") == 1 and "suite.training_weathers" in err, err
    with pytest.raises(CicfwError) as got:
        ps.check_same_sim(e1, e3)
    assert (got.value.key, got.value.value) == ("suite.training_weathers", ["ClearNoon"])
    wide = drive(tmp_path / "wide", sim={"success_radius": 8.0})
    cell = cell_of(drive(tmp_path / "e1b"), tmp_path / "cells" / "cil" / "seed0")
    assert ps.main(["--episodes", str(cell), str(wide)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "sim.success_radius" in err and "8.0" in err, err
    with pytest.raises(CicfwError) as got:
        ps.check_same_sim(wide, cell)
    assert (got.value.key, got.value.value) == ("sim.success_radius", 2.0)


def test_shared_episodes_in_other_columns_are_refused(tmp_path, capsys):
    """Two cells that record nothing of their suite, one counting column 1's episodes in column 0 (another split
    of the weathers): per column they compare nothing, refused in one line naming an episode and both columns."""
    write_cell(tmp_path / "a", "cil", 0, [10, 10, 10, 10])
    write_cell(tmp_path / "b", "cil", 0, [12, 10, 10, 10])
    p = tmp_path / "b" / "seed0" / "cell.json"
    d = json.loads(p.read_text())
    for k, e in d["episodes"].items():
        if e["column"] == COLUMNS[1]:
            e["column"] = COLUMNS[0]
    p.write_text(json.dumps(d))
    for a, b in (("a", "b"), ("b", "a")):
        assert ps.main(["--episodes", str(tmp_path / a / "seed0" / "cell.json"),
                        str(tmp_path / b / "seed0" / "cell.json")]) == 2
        out, err = capsys.readouterr()
        assert out == "" and err.count("\n") == 1 and f"{COLUMNS[1]}/00" in err, err
        assert COLUMNS[0] in err and COLUMNS[1] in err.replace(f"{COLUMNS[1]}/00", ""), err
    ea, eb = (ps.load_episodes(tmp_path / x / "seed0" / "cell.json") for x in ("a", "b"))
    with pytest.raises(CicfwError) as got:
        ps.episode_changes(ea, eb)
    assert (got.value.key, got.value.value) == ("column", COLUMNS[0])


@pytest.mark.parametrize("given", [["--margin", "500"], ["--margin", "5"], ["--family", "3"]])
def test_options_episodes_does_not_read_are_refused(tmp_path, capsys, given):
    """--episodes prints McNemar's test per column: a margin or a family of comparisons it would not read is
    refused in one line naming the option and its value, before any file is read."""
    write_cell(tmp_path / "a", "cil", 0, [10, 10, 10, 10])
    write_cell(tmp_path / "b", "cil", 0, [12, 10, 10, 10])
    cells = [str(tmp_path / x / "seed0" / "cell.json") for x in ("a", "b")]
    assert ps.main(["--episodes", *cells]) == 0
    capsys.readouterr()
    assert ps.main(["--episodes", *cells, *given]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and given[0] in err and f"{float(given[1]):g}" in err, err
    assert ps.main(["--episodes", str(tmp_path / "nowhere.json"), cells[1], *given]) == 2  # before reading
    assert given[0] in capsys.readouterr().err


def test_seeds_that_drove_other_episodes_are_refused(tmp_path, capsys):
    """A side whose seed 1 lost a column's last 5 episodes (75 against 80) is refused naming the seed and the
    counts, not compared on other episodes."""
    for s in range(3):
        write_cell(tmp_path / "a", "cil", s, [10, 10, 10, 10])
        write_cell(tmp_path / "b", "cil", s, [10, 10, 10, 10])
    p = tmp_path / "a" / "seed1" / "cell.json"
    d = json.loads(p.read_text())
    d["episodes"] = {k: e for k, e in d["episodes"].items() if not (k.startswith(COLUMNS[3]) and int(k[-2:]) >= 15)}
    p.write_text(json.dumps(d))
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "seed1" in err and "75" in err and "80" in err, err


def test_the_header_names_each_sides_cpu_kinds_where_they_differ(tmp_path, capsys):
    for s in range(3):
        write_cell(tmp_path / "a", "cil", s, [10, 10, 10, 10])
        write_cell(tmp_path / "b", "cil", s, [10, 10, 10, 10])
    a, b = ps.load_row(tmp_path / "a"), ps.load_row(tmp_path / "b")
    for c in a.values():
        c.meta["machine"] = "2 cores (Intel(R) Xeon(R) CPU @ 2.20GHz), no GPU"
    for c in b.values():
        c.meta["machine"] = "2 cores (AMD EPYC 7B13), no GPU"
    line = ps.lines(a, b, 5.0)[1]
    assert "CPU kinds differ" in line and "Intel Xeon (3)" in line and "AMD EPYC 7B13 (3)" in line, line
    assert not any("CPU kinds" in x for x in ps.lines(a, a, 5.0))
    for c in b.values():  # the same processor with a GPU: another machine kind, and said so
        c.meta["machine"] = "2 cores (Intel(R) Xeon(R) CPU @ 2.20GHz), NVIDIA H100 80GB HBM3, torch 2.13.0+cu126"
    line = ps.lines(a, b, 5.0)[1]
    assert "Machine kinds differ" in line and "Intel Xeon + NVIDIA H100 (3)" in line, line


def test_a_copy_of_a_folder_is_refused_not_equivalent(tmp_path, capsys):
    """A byte-identical copy of a row's cells read "equivalent within ±5" in every column: no switch at all."""
    import shutil

    for s in range(3):
        write_cell(tmp_path / "a", "cil", s, [18, 10, 12, 5 + s])
    shutil.copytree(tmp_path / "a", tmp_path / "copy")
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "copy"), "--margin", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{tmp_path / 'copy'}/seed0" in err[0], err
    cell = tmp_path / "a" / "seed0" / "cell.json"
    assert ps.main([str(cell), str(tmp_path / "copy" / "seed0" / "cell.json"), "--episodes"]) == 2
    assert "same episodes file" in capsys.readouterr().err
    for s in range(3):  # the same cells trained again: another file, compared
        write_cell(tmp_path / "b", "cil", s, [18, 10, 12, 5 + s], train_s=200.0)
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b"), "--margin", "5"]) == 0


@pytest.mark.parametrize("margin", ["1e9", "100.5", "0", "-5", "nan", "inf"])
def test_a_margin_outside_the_success_scale_is_refused(tmp_path, capsys, margin):
    """A margin past 100 points reads every pair "equivalent" (no two rates are further apart): one line."""
    for s in range(3):
        write_cell(tmp_path / "a", "cil", s, [18, 10, 12, 5 + s])
        write_cell(tmp_path / "b", "cil", s, [17, 10, 12, 5], train_s=200.0)
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b"), "--margin", margin]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1 and "--margin" in err and str(float(margin)) in err, err
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b"), "--margin", "100"]) == 0


def _cells(row: str, per_seed: list[list[int]]) -> dict:
    """seed -> a CellResult whose columns hold per_seed[seed][i] successes of EPISODES."""
    from cicfw.reproduction.cells import CellResult

    out = {}
    for s, successes in enumerate(per_seed):
        eps = {f"{col}/{i:02d}": {"success": i < k, "column": col, "command": "left"}
               for col, k in zip(COLUMNS, successes) for i in range(EPISODES)}
        out[s] = CellResult(row, s, eps, {"row": row, "seed": s})
    return out


def test_intervals_are_clipped_to_the_scale_of_a_difference():
    """Seeds that swing from all to none: the t-interval over 3 seeds runs past ±100, which no difference of
    two rates can reach; it is shown clipped, the verdict read as before."""
    a = _cells("a", [[20] * 4, [0] * 4, [20] * 4])
    b = _cells("b", [[0] * 4, [20] * 4, [0] * 4])
    d = [100.0, -100.0, 100.0]  # per seed, by hand
    m = sum(d) / 3
    half = stats.t.ppf(0.975, 2) * math.sqrt(sum((x - m) ** 2 for x in d) / 2) / math.sqrt(3)
    assert m - half < -100 and m + half > 100  # the unclipped interval, by hand
    for e in ps.compare(a, b, 5.0):
        assert e.mean == pytest.approx(m)
        assert (e.lo, e.hi) == (-100.0, 100.0)
        assert (e.tost_lo, e.tost_hi) == (-100.0, 100.0) and e.verdict == "not shown"
        assert (e.word_lo, e.word_hi) == (-100.0, 100.0)


def test_differences_equal_up_to_rounding_are_exact_without_a_warning():
    """Per seed A - B is 40 points overall, one seed's 39.99999999999999 by float rounding of its column rates:
    scipy's t-test warned of precision loss (and gave an interval 1e-14 wide); it is one value, known exactly."""
    a = _cells("a", [[8, 8, 8, 8], [8, 19, 19, 19], [8, 8, 8, 8]])
    b = _cells("b", [[0, 0, 0, 0], [0, 11, 11, 11], [0, 0, 0, 0]])
    overall = [a[s].rate(None) - b[s].rate(None) for s in range(3)]
    assert len(set(overall)) == 2 and max(overall) - min(overall) < 1e-12  # the inputs are as said
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = {e.on: e for e in ps.compare(a, b, 5.0)}
    assert got["overall"].p_tost == 1.0  # 40 apart every seed: outside ±5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = difference({s: a[s].rate(None) for s in a}, {s: b[s].rate(None) for s in b})
    assert d.estimate.lo == d.estimate.hi == d.estimate.mean == pytest.approx(40.0) and d.p == 0.0


def with_meta(folder: Path, seeds: range, **meta: object) -> None:
    """Each of ``seeds``' cell.json under ``folder`` given ``meta``'s fields."""
    for s in seeds:
        p = folder / f"seed{s}" / "cell.json"
        p.write_text(json.dumps({**json.loads(p.read_text()), **meta}))


def test_sides_trained_on_other_datasets_are_refused_naming_both(tmp_path, capsys):
    """The seed pairs two cells through the split and batch order it draws from one dataset: a paired seed whose
    cells trained on two datasets is no pair. A cell without a record reads its results folder's pin."""
    for s in range(3):
        write_cell(tmp_path / "a", "cil", s, [18, 10, 12, 5 + s])
        write_cell(tmp_path / "b", "cil", s, [17, 10, 12, 5 + s])
    with_meta(tmp_path / "a", range(3), dataset="aaaa000000000000")
    with_meta(tmp_path / "b", range(3), dataset="aaaa000000000000")
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    capsys.readouterr()
    with_meta(tmp_path / "b", range(1, 2), dataset="bbbb000000000000")
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1, err
    assert "dataset=aaaa000000000000" in err and "dataset=bbbb000000000000" in err and f"{tmp_path / 'b'}/seed1" in err
    pinned = results_folder(tmp_path / "pinned", ["suite=single_turn"], {"cil": None})  # cells record no dataset
    manifest = tmp_path / "pinned" / "reproduce.json"
    manifest.write_text(json.dumps({"pinned": {"suite": ["suite=single_turn"], "dataset": "cccc000000000000"}}))
    with pytest.raises(CicfwError) as got:
        ps.check_one_dataset(ps.load_row(tmp_path / "a"), ps.load_row(pinned["cil"]), ("a", "pinned"),
                             (ps.side_pin(tmp_path / "a"), ps.side_pin(pinned["cil"])))
    assert (got.value.key, got.value.value) == ("dataset", "cccc000000000000")


def test_sides_trained_for_other_epochs_are_compared_and_said(tmp_path, capsys):
    """Longer training may be the switch itself: compared, with a header line naming each side's epochs; none
    where they agree or one side records none."""
    for s in range(3):
        write_cell(tmp_path / "a", "cil", s, [18, 10, 12, 5 + s])
        write_cell(tmp_path / "b", "cil", s, [17, 10, 12, 5 + s])
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    assert "poch" not in capsys.readouterr().out
    with_meta(tmp_path / "a", range(3), epochs=6)
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0  # B records none: not compared
    assert "poch" not in capsys.readouterr().out
    with_meta(tmp_path / "b", range(3), epochs=6)
    with_meta(tmp_path / "b", range(2), epochs=4)
    assert ps.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    header = capsys.readouterr().out.splitlines()[1]
    assert "Epochs differ" in header and "6 epochs (3 seeds)" in header, header
    assert "4 epochs (2 seeds), 6 epochs (1 seed)" in header, header
