"""Which row drives best, by the procedure fixed in ``cicfw.reproduction.ranking``: only rows with 3 seeds are
ranked (the others listed apart), Hsu's multiple comparisons with the best (MCB) with Bonferroni's constant,
each pair paired over the seeds both rows ran; recomputed here by hand from t quantiles (a printed table and
``scipy.stats.t``), its joint coverage and its error rate simulated; and each row against CIL (the forest)."""
from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
from scipy import stats

from cicfw.reproduction.analysis import analyse
from cicfw.reproduction.cells import COLUMNS, CellResult
from cicfw.reproduction.ranking import _mcb, apart, best, forest, one_sided_bounds, ranking
from cicfw.reproduction.report import markdown, report_data, write_report
from cicfw.reproduction.seed_stats import ALPHA, difference

from conftest import mover, wilson

T_975_2 = 4.303  # t_{0.975, 2} from a printed table
CATALOGUE = {"cil": {"label": "CIL", "paper": [94.74, 86.84, 52.5, 46.25]},
             "gtu": {"label": "GTU", "paper": [100.0, 93.42, 81.25, 75.0]},
             "hybrid": {"label": "CCE + MSE", "paper": [97.37, 85.53, 64.25, 56.25]},
             "sine": {"label": "Sine"}}


def mcb(values, margin: float, alpha: float = ALPHA) -> dict:
    """Hsu's MCB over ``values`` (row -> seed -> overall success), every pair on the same values (``best``
    gives each pair its own cells): each row's interval for mu_i - max_{j != i} mu_j, its word, and G."""
    rows = list(values)
    return _mcb({(i, j): (values[i], values[j]) for x, i in enumerate(rows) for j in rows[x + 1:]}, rows, margin,
                alpha)[0]


def at(row: str, seed: int, pct: int, n: int = 100) -> CellResult:
    eps = {f"{c}/{k:03d}": {"success": k < pct, "column": c, "command": "left"} for c in COLUMNS for k in range(n)}
    return CellResult(row=row, seed=seed, episodes=eps, meta={"decoder": None, "wall_s": {}})


def cells() -> list[CellResult]:
    """CIL 50, 52, 54 (and a seed 3 at 56); GTU 60, 61, 65; CCE+MSE 66, 70, 71; sine one seed at 90."""
    out = [at("cil", s, p) for s, p in zip(range(4), (50, 52, 54, 56))]
    out += [at("gtu", s, p) for s, p in zip(range(3), (60, 61, 65))]
    out += [at("hybrid", s, p) for s, p in zip(range(3), (66, 70, 71))]
    return out + [at("sine", 0, 90)]


def test_rows_with_too_few_seeds_are_listed_apart_never_ranked():
    an = analyse(cells(), n_boot=50)
    assert ranking(an, list(CATALOGUE)) == ["hybrid", "gtu", "cil"]  # sine (90%, one seed) is not first
    assert apart(an, list(CATALOGUE)) == ["sine"]


def test_mcb_by_hand_three_paired_rows():
    """Three rows, seeds 0-2 each: k = 3, so each row's two comparisons are one-sided at 0.05 / 2, whose t with
    2 df is the printed 4.303. Pairwise (paired) differences and their sd: CCE+MSE - GTU 6, 9, 6 (mean 7, sd
    sqrt 3); CCE+MSE - CIL 16, 18, 17 (17, sd 1); GTU - CIL 10, 9, 11 (10, sd 1). Half-widths 4.303 sd / sqrt 3:
    4.303, 2.484, 2.484. U_i = max(0, min_j (d_ij + h_ij)): CCE+MSE min(11.303, 19.484) > 0; GTU min(-7 + 4.303,
    12.484) < 0, so 0; CIL 0. G = {CCE+MSE} alone: it is *ahead* (L = 0); GTU's L = d - h against CCE+MSE,
    -11.303, CIL's -19.484; both *behind*."""
    values = {"hybrid": {0: 66.0, 1: 70.0, 2: 71.0}, "gtu": {0: 60.0, 1: 61.0, 2: 65.0}, "cil": {0: 50.0, 1: 52.0, 2: 54.0}}
    got = mcb(values, margin=5.0)
    assert got["confidence"] == pytest.approx(0.975) and got["best"] == ["hybrid"]
    rows = {r["row"]: r for r in got["rows"]}
    h_hg, h_1 = T_975_2 * math.sqrt(3) / math.sqrt(3), T_975_2 / math.sqrt(3)
    assert (rows["hybrid"]["lo"], rows["hybrid"]["word"]) == (0.0, "ahead")
    assert rows["hybrid"]["hi"] == pytest.approx(min(7 + h_hg, 17 + h_1), abs=2e-3)
    assert (rows["gtu"]["hi"], rows["gtu"]["word"]) == (0.0, "behind")
    assert rows["gtu"]["lo"] == pytest.approx(-7 - h_hg, abs=2e-3)
    assert rows["cil"]["lo"] == pytest.approx(-17 - h_1, abs=2e-3) and rows["cil"]["word"] == "behind"


def test_mcb_by_hand_when_the_best_is_not_separated():
    """A 60, 62, 70 and B 61, 60, 65 (A - B: -1, 2, 5, mean 2, sd 3), C one seed short of pairing nothing:
    seeds 5-7 at 40, 45, 50 (Welch against both). k = 3, one-sided 97.5%. A and B may both be best; their
    intervals by hand: A's upper min(2 + 4.303 sqrt 3, A - C's Welch upper), lower 2 - 4.303 sqrt 3; C behind."""
    values = {"a": {0: 60.0, 1: 62.0, 2: 70.0}, "b": {0: 61.0, 1: 60.0, 2: 65.0}, "c": {5: 40.0, 6: 45.0, 7: 50.0}}
    got = mcb(values, margin=5.0)
    rows = {r["row"]: r for r in got["rows"]}
    assert got["best"] == ["a", "b"]
    h = T_975_2 * 3 / math.sqrt(3)
    a, c = np.array([60.0, 62.0, 70.0]), np.array([40.0, 45.0, 50.0])
    se = math.sqrt(a.var(ddof=1) / 3 + c.var(ddof=1) / 3)
    df = se ** 4 / ((a.var(ddof=1) / 3) ** 2 / 2 + (c.var(ddof=1) / 3) ** 2 / 2)
    welch_upper = (a.mean() - c.mean()) + stats.t.ppf(0.975, df) * se
    assert rows["a"]["hi"] == pytest.approx(min(2 + h, welch_upper), abs=2e-3)
    assert rows["a"]["lo"] == pytest.approx(2 - h, abs=2e-3)
    assert rows["b"]["hi"] == pytest.approx(-2 + h, abs=2e-3) and rows["b"]["lo"] == pytest.approx(-2 - h, abs=2e-3)
    assert rows["a"]["word"] == rows["b"]["word"] == "not separated" and rows["c"]["word"] == "behind"


def test_pairs_share_seeds_or_go_welch():
    """Rows that share seeds are compared on those seeds, paired (CIL's seed 3 left out); rows that share none,
    by Welch's t; the one-sided bound is scipy's own."""
    est, lo, hi = one_sided_bounds({0: 66.0, 1: 70.0, 2: 71.0}, {0: 50.0, 1: 52.0, 2: 54.0, 3: 56.0}, 0.975)
    assert est == pytest.approx(17.0) and lo == pytest.approx(17 - T_975_2 / math.sqrt(3), abs=2e-3)
    an = analyse(cells(), n_boot=50)
    pairs = {(p["a"], p["b"]): p for p in best(an, ranking(an), 5.0)["pairs"]}
    # the seeds' differences (16, 18, 17) agree more closely than 300 episodes a column can tell: widened
    assert pairs["hybrid", "cil"]["method"].startswith("paired t, 3 seeds, widened to the episodes' interval, "
                                                       "on the seeds both ran (0 of A's and 1 of B's")
    assert pairs["hybrid", "cil"]["measured"]["mean"] == pytest.approx(17.0)


def test_a_bound_is_never_closer_than_the_pooled_episodes_allow():
    """Seeds whose overall differences agree exactly (every seed 60 of 100 against 50 of 100 in each column)
    leave the t-bounds no width; each one-sided 97.5% bound is pushed out to the pooled episodes' (the MOVER
    interval at 95% two-sided of the four columns' mean, 1/4 each, 180 of 300 against 150 of 300), and MCB
    reads its bounds on those."""
    a, b = {s: 60.0 for s in range(3)}, {s: 50.0 for s in range(3)}
    terms = [(0.25, 180, 300)] * 4 + [(-0.25, 150, 300)] * 4
    assert one_sided_bounds(a, b, 0.975) == (10.0, 10.0, 10.0)
    lo, hi = mover(terms, stats.norm.ppf(0.975))
    assert one_sided_bounds(a, b, 0.975, terms) == pytest.approx((10.0, lo, hi))
    assert lo == pytest.approx(10 - 100 * math.sqrt(sum((0.25 * (p - wilson(k, 300, 1.959964)[0])) ** 2
                                                           for p, k in [(0.6, 180)] * 4)
                                                       + sum((0.25 * (wilson(k, 300, 1.959964)[1] - p)) ** 2
                                                             for p, k in [(0.5, 150)] * 4)), abs=1e-4)
    an = analyse([at("a", s, 60) for s in range(3)] + [at("b", s, 50) for s in range(3)], n_boot=50)
    got = best(an, ranking(an), 5.0)
    rows = {r["row"]: r for r in got["rows"]}
    # two rows: MCB's one comparison each is one-sided at 95%, the 90% two-sided MOVER interval's bounds
    lo90, hi90 = mover(terms, stats.norm.ppf(0.95))
    assert got["confidence"] == pytest.approx(0.95) and got["best"] == ["a"] and rows["b"]["hi"] == 0.0
    assert rows["b"]["lo"] == pytest.approx(-hi90) and rows["a"]["hi"] == pytest.approx(hi90)
    assert rows["a"]["word"] == "ahead" and rows["b"]["word"] == "behind"
    assert got["pairs"][0]["measured"]["lo"] == pytest.approx(lo)  # the pair's own 95% interval


def simulate(n_exp: int, means: list[float], seed: int, alpha_scale: float = 1.0) -> tuple[float, float]:
    """(joint coverage of the k MCB intervals, how often the true best row is left out of G) over ``n_exp``
    experiments: 3 seeds a row (the first 5), each seed's split shared by every row (half the seed variance
    of 6 points), overall success per seed normal around the row's mean. ``alpha_scale`` breaks the
    procedure (e.g. k - 1: no Bonferroni) to show the simulation can fail."""
    rng = np.random.default_rng(seed)
    k, truth = len(means), np.asarray(means, float)
    target = {f"r{i}": truth[i] - max(np.delete(truth, i)) for i in range(k)}
    top = f"r{int(np.argmax(truth))}"
    covered = missed = 0
    for _ in range(n_exp):
        split = rng.normal(0.0, 6.0 / math.sqrt(2), 5)
        values = {f"r{i}": {s: truth[i] + split[s] + rng.normal(0.0, 6.0 / math.sqrt(2))
                            for s in range(5 if i == 0 else 3)} for i in range(k)}
        got = mcb(values, margin=5.0, alpha=0.05 * alpha_scale)
        covered += all(r["lo"] - 1e-9 <= target[r["row"]] <= r["hi"] + 1e-9 for r in got["rows"])
        missed += top not in got["best"]
    return covered / n_exp, missed / n_exp


def test_mcb_covers_jointly_and_keeps_the_best_in_its_set():
    """300 experiments, 4 rows: spread means (70, 66, 62, 55: the intervals' joint coverage, nominal >= 95%)
    and equal means (each row is a best: the designated best row r0 is left out of G at most 5% of the time,
    here 3 one-sided tests at 1.67% each). Binomial sd at 300 experiments: 1.3 points. Without Bonferroni's
    constant (alpha_scale 3) r0 is left out about three times as often, and the bound below fails: checked by
    hand once."""
    coverage, _ = simulate(300, [70.0, 66.0, 62.0, 55.0], seed=1)
    assert coverage >= 0.93, coverage
    _, missed = simulate(300, [60.0, 60.0, 60.0, 60.0], seed=2)
    assert missed <= 0.08, missed


def test_the_forest_is_each_row_minus_cil_with_the_papers_difference_and_a_word():
    """The paper's difference is the mean of its Table-4 row minus CIL's: GTU (87.4175 - 70.0825) = 17.34,
    CCE + MSE (75.85 - 70.0825) = 5.77; sine (one seed) is apart, with no word. GTU - CIL paired on seeds 0-2:
    10, 9, 11; its word is read on the Bonferroni interval over the two ranked comparisons with CIL (97.5%
    two-sided each: t_{0.9875, 2} from scipy)."""
    an = analyse(cells(), n_boot=50)
    ranked = ranking(an, list(CATALOGUE))
    rows = forest(an, ranked, {r: v["paper"] for r, v in CATALOGUE.items() if "paper" in v}, 5.0,
                  apart(an, list(CATALOGUE)))
    assert [r["a"] for r in rows] == ["hybrid", "gtu", "sine"]
    assert [r["paper"] for r in rows] == [5.77, 17.34, None]
    gtu = rows[1]
    assert gtu["measured"]["mean"] == pytest.approx(10.0) and gtu["method"].startswith("paired t, 3 seeds")
    half = stats.t.ppf(1 - 0.05 / 4, 2) * 1 / math.sqrt(3)
    # widened to the pooled episodes' interval at the same 97.5%: per column GTU 186 of 300, CIL 156 of 300
    lo, hi = mover([(0.25, 186, 300)] * 4 + [(-0.25, 156, 300)] * 4, stats.norm.ppf(1 - 0.05 / 4))
    assert lo < 10 - half and hi > 10 + half  # the floor is the wider here
    assert (gtu["word"]["lo"], gtu["word"]["hi"]) == pytest.approx((lo, hi))
    assert "widened to the episodes' interval" in gtu["method"]
    assert gtu["word"]["word"] == "ahead" and "Bonferroni over the 2" in gtu["word"]["correction"]
    assert rows[2].get("apart") and "word" not in rows[2]
    assert forest(analyse([at("gtu", s, 60) for s in range(3)], n_boot=50), ["gtu"], {}, 5.0) == []  # no CIL


def test_the_report_opens_with_the_answer_and_draws_the_forest(tmp_path):
    """RESULTS.md states the MCB answer and the ranked rows before Table 4, lists the one-seed row apart, links
    the forest plot, and write_report draws it (a PNG)."""
    data = report_data(cells(), [], CATALOGUE, {"budget": "smoke"}, n_boot=50, claims=[], margin=5.0)
    md = markdown(data)
    answer, table4 = md.index("**Which row drives best?** **CCE + MSE**"), md.index("| Row | Decoder |")
    assert answer < md.index("![each row's overall success minus CIL's") < table4
    listed = [line.split("**")[1] for line in md.splitlines() if line[:3] in ("1. ", "2. ", "3. ", "4. ")]
    assert listed == ["CCE + MSE", "GTU", "CIL"]
    assert "listed apart and not ranked: Sine (1 seed)." in md and "- Sine: 90.0%, 1 seed(s) †" in md
    folder = tmp_path / "results"
    for c in cells():
        path = folder / "cells" / c.row / f"seed{c.seed}" / "cell.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"status": "ok", "row": c.row, "seed": c.seed, "episodes": c.episodes}))
    write_report(folder, CATALOGUE, n_boot=50, claims=[], margin=5.0)
    assert (folder / "forest.png").read_bytes()[:4] == b"\x89PNG"
    assert "](forest.png)" in (folder / "RESULTS.md").read_text()


@pytest.mark.parametrize("b", [{0: 0.0, 1: 0.0, 2: 0.0}, {5: 0.0, 6: 0.0, 7: 0.0}])
def test_bounds_of_differences_equal_up_to_rounding_are_exact_without_a_warning(b):
    """Paired (the same seeds) or Welch (none shared): seeds at 40 points, one 39.99999999999999 by float
    rounding, against zeros have no spread; scipy's t-test warned of precision loss on them."""
    a = {0: 40.0, 1: 39.99999999999999, 2: 40.0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        est, lo, hi = one_sided_bounds(a, b, 0.95)
    assert est == pytest.approx(40.0) and lo == est and hi == est


def test_a_pair_with_too_few_shared_seeds_gets_no_mcb_bound_as_a_claim_gets_no_verdict():
    """C shares only seeds 0 and 2 with A and B (as a row whose third seed ran on another CPU kind): a claim
    on such a pair reads *too few seeds*, and so MCB gives it no bound. A - B is paired on 3 seeds (10, 11, 10:
    mean 31/3, sd 1/sqrt 3), its one-sided 97.5% bounds (k = 3) by scipy's t with 2 df. A's upper comes from B
    alone, B is behind; C is unbounded above, so it stays in G, and every lower bound, each needing a pair with
    C, is none."""
    values = {"a": {0: 70.0, 1: 72.0, 2: 75.0}, "b": {0: 60.0, 1: 61.0, 2: 65.0},
              "c": {0: 50.0, 2: 90.0, 3: 55.0, 4: 52.0}}
    for i, j in (("a", "c"), ("b", "c")):
        assert not difference(values[i], values[j]).enough_seeds  # the claims' rule: too few seeds
    got = mcb(values, margin=5.0)
    rows = {r["row"]: r for r in got["rows"]}
    half = stats.t.ppf(0.975, 2) * (1 / math.sqrt(3)) / math.sqrt(3)
    assert rows["a"]["hi"] == pytest.approx(31 / 3 + half) and rows["a"]["lo"] is None
    assert (rows["b"]["hi"], rows["b"]["word"]) == (0.0, "behind")
    assert -31 / 3 + half < 0 and rows["b"]["lo"] is None  # B - C, needed with C in G, has no bound either
    assert got["best"] == ["a", "c"] and rows["c"]["lo"] is None and rows["c"]["hi"] is None


def test_the_report_says_too_few_seeds_for_such_a_pair_and_clips_intervals_to_the_scale():
    """In RESULTS.md a ranked pair with too few shared seeds reads *too few seeds* where MCB's bounds go, and
    the rows it leaves unbounded say why. X and Y, three seeds of wild spread (X - Y: -90, +90, 0; sd 90): the
    pair's 95% t-interval, 0 -/+ t(0.975, 2) 90 / sqrt 3 = -/+223.6, and MCB's one-sided bounds reach past
    what a difference of two rates can be; each is printed clipped to [-100, +100]."""
    wild = [at(row, s, p) for row, pcts in (("x", (5, 95, 50)), ("y", (95, 5, 50))) for s, p in enumerate(pcts)]
    few = [at("z", s, 50) for s in (0, 3, 4)]  # shares only seed 0 with X and Y
    data = report_data(wild + few, [], {"x": {"label": "X"}, "y": {"label": "Y"}, "z": {"label": "Z"}},
                       {"budget": "smoke"}, n_boot=50, claims=[], margin=5.0)
    assert 0 - stats.t.ppf(0.975, 2) * 90 / math.sqrt(3) < -100
    pairs = {(p["a"], p["b"]): p for p in data["best"]["pairs"]}
    xy = pairs.get(("x", "y")) or pairs[("y", "x")]
    assert xy["measured"]["lo"] < -100 and xy["lower"] < -100 and xy["upper"] > 100  # kept whole in the data
    md = markdown(data)
    pair_table = md.split("## Each pair of ranked rows")[1].split("\n## ")[0].splitlines()
    xy_line = [line for line in pair_table if line.startswith(("| X | Y |", "| Y | X |"))]
    cols = xy_line[0].split(" | ")
    assert cols[2] == "+0.0 [-100.0, +100.0]" and cols[4] == "[-100.0, +100.0]"
    z_rows = [line for line in pair_table if line.startswith("|") and "Z |" in line]
    assert len(z_rows) == 2 and all(line.split(" | ")[4] == "too few seeds" for line in z_rows)
    assert "A bound shown as – rests on a pair with fewer than 3 seeds" in md
