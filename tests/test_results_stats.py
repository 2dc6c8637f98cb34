"""The reproduction's statistics on synthetic cell results with known answers: t-intervals over seeds
(paired and Welch) against hand computations with t quantiles written from a table, the too-few-seeds
rule, Holm's adjustment on a case solved by hand, Fieller's ratio interval, the verdicts, the claims as
data, and the secondary two-level bootstrap against hand computations."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from cicfw.core.errors import CicfwError
from cicfw.reproduction import report as results
from cicfw.reproduction import seed_stats
from cicfw.reproduction.cells import COLUMNS, CellResult
from cicfw.reproduction.analysis import analyse, row_estimate
from cicfw.reproduction.claims import (CONTRADICTED, INCONCLUSIVE, NOT_RUN, NOT_SHOWN, SUPPORTED, TOO_FEW, Claim,
                                       Part, _boot_part, combine, default_claims, judge, load_claims)
from cicfw.reproduction.report import markdown, report_data
from cicfw.reproduction.seed_stats import (Difference, Estimate, difference, holm, mover_ratio, ratio_interval,
                                          t_interval, with_episode_floor, with_ratio_floor)

from conftest import mover, wilson

# Student's t quantiles t_{0.975, df} from a printed table
T_975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776}


def cell(row: str, seed: int, successes: dict[str, list[int]]) -> CellResult:
    """A cell whose column c drove len(successes[c]) episodes with those outcomes (1 = success)."""
    eps = {}
    for c, outs in successes.items():
        for k, ok in enumerate(outs):
            eps[f"{c}/{k:03d}"] = {"success": bool(ok), "column": c, "command": "left" if k % 2 else "right"}
    return CellResult(row=row, seed=seed, episodes=eps, meta={"decoder": None, "wall_s": {"train": 1.0}})


def same_in_every_column(row: str, seed: int, outs: list[int]) -> CellResult:
    return cell(row, seed, {c: outs for c in COLUMNS})


def at(row: str, seed: int, pct: int | list[int], n: int = 100) -> CellResult:
    """A cell with ``pct`` successes of ``n`` episodes in every column (or pct[i] in column i)."""
    pcts = pct if isinstance(pct, list) else [pct] * 4
    return cell(row, seed, {c: [1] * p + [0] * (n - p) for c, p in zip(COLUMNS, pcts)})


def binomial_quantile(n: int, p: float, q: float) -> float:
    """The q-quantile of Binomial(n, p) / n, by summing the probabilities by hand."""
    acc = 0.0
    for k in range(n + 1):
        acc += math.comb(n, k) * p ** k * (1 - p) ** (n - k)
        if acc >= q:
            return k / n
    return 1.0


# ------------------------------------------------------------------------------------------------
# t-intervals over seeds (primary)


def test_t_interval_by_hand():
    """60, 70, 80: mean 70, sd 10, half-width t_{0.975,2} 10 / sqrt(3) = 4.303 x 5.7735 = 24.84.
    50..70 by 5: mean 60, sd sqrt(62.5) = 7.9057, half-width 2.776 x 7.9057 / sqrt(5) = 9.815."""
    mean, lo, hi = t_interval(np.array([60.0, 70.0, 80.0]))
    assert float(mean) == 70.0
    assert (float(lo), float(hi)) == pytest.approx((70 - 24.844, 70 + 24.844), abs=0.01)
    mean, lo, hi = t_interval(np.array([50.0, 55.0, 60.0, 65.0, 70.0]))
    assert (float(lo), float(hi)) == pytest.approx((60 - 9.815, 60 + 9.815), abs=0.01)
    # vectorised over leading axes, and no interval from one value
    m, lo, hi = t_interval(np.array([[60.0, 70.0, 80.0], [1.0, 1.0, 1.0]]))
    assert list(np.round(lo, 2)) == [45.16, 1.0]
    _, lo1, hi1 = t_interval(np.array([42.0]))
    assert math.isnan(float(lo1)) and math.isnan(float(hi1))


def test_row_interval_is_t_over_seeds_with_the_episodes_floor():
    """Per-seed overall 60 / 70 / 80 (same in every column): the overall interval is the hand t-interval;
    three seeds that all drove 100% of 96 episodes get, instead of a zero-width interval, the Clopper-Pearson
    interval of 288 of 288, whose lower end is (0.025)^(1/288) = 0.98727 by hand."""
    cells = [at("cil", s, p) for s, p in zip(range(3), (60, 70, 80))]
    e = row_estimate(cells, "overall")
    assert (e.mean, e.lo, e.hi) == pytest.approx((70.0, 70 - 24.844, 70 + 24.844), abs=0.01)
    full = [at("hybrid", s, 96, n=96) for s in range(3)]
    e = row_estimate(full, COLUMNS[0])
    assert (e.mean, e.hi) == (100.0, 100.0)
    assert e.lo == pytest.approx(100 * 0.025 ** (1 / 288), abs=0.005) and e.lo == pytest.approx(98.727, abs=0.005)
    assert row_estimate(full[:1], COLUMNS[0]).lo is None  # one seed: no interval at all


def test_paired_difference_by_hand():
    """A = 50, 62, 71 and B = 40, 50, 55 on seeds 0..2: differences 10, 12, 16, mean 12.667, sd 3.0551,
    half-width 4.303 x 3.0551 / sqrt(3) = 7.590; t = 12.667 / (3.0551 / sqrt 3) = 7.181, and with 2 df
    P(|T| > t) = 1 - t / sqrt(2 + t^2) = 0.0189. Unpaired, the same numbers would give a far wider interval."""
    a = {0: 50.0, 1: 62.0, 2: 71.0}
    b = {0: 40.0, 1: 50.0, 2: 55.0}
    d = difference(a, b)
    assert d.paired and d.method == "paired t, 3 seeds"
    assert (d.estimate.mean, d.estimate.lo, d.estimate.hi) == pytest.approx((12.667, 5.077, 20.256), abs=0.01)
    t = 12.6667 / (3.05505 / math.sqrt(3))
    assert d.p == pytest.approx(1 - t / math.sqrt(2 + t * t), abs=2e-4)
    assert d.p == pytest.approx(0.0189, abs=2e-4)


def newcombe(a: tuple[int, int], b: tuple[int, int], z: float) -> tuple[float, float]:
    """Newcombe's hybrid score interval (his method 10) for a[0]/a[1] - b[0]/b[1], in points, by hand."""
    (p1, (l1, u1)), (p2, (l2, u2)) = ((k / n, wilson(k, n, z)) for k, n in (a, b))
    d = p1 - p2
    return 100 * (d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2)), 100 * (d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2))


def test_episode_interval_is_newcombes_and_its_p_value_is_dual_to_it():
    """29 of 192 against 50 of 192 (GTU and CCE+MSE in the new town under new weathers on the Xeon): the
    interval is Newcombe's from Wilson's closed form with z = 1.959964; at the p-value's level
    (z = the normal quantile 1 - p/2) its upper bound is 0. Both rows at 100%: width, p = 1."""
    lo, hi, p = seed_stats.episode_interval([(1.0, 29, 192), (-1.0, 50, 192)])
    assert (lo, hi) == pytest.approx(newcombe((29, 192), (50, 192), 1.959964), abs=1e-3)
    assert lo == pytest.approx(-18.85, abs=0.05) and hi < 0
    z = float(stats.norm.ppf(1 - p / 2))
    assert newcombe((29, 192), (50, 192), z)[1] == pytest.approx(0.0, abs=1e-6)
    # the chi-square test of the 2x2 table (uncorrected), a close relative, lands near it
    chi = stats.chi2_contingency([[29, 163], [50, 142]], correction=False).pvalue
    assert 0.5 * chi < p < 2 * chi
    lo, hi, p = seed_stats.episode_interval([(1.0, 96, 96), (-1.0, 96, 96)])
    assert p == 1.0 and (lo, hi) == pytest.approx(newcombe((96, 96), (96, 96), 1.959964), abs=1e-3) and hi > 3.0


def test_seeds_whose_differences_agree_still_get_the_episodes_interval():
    """Three paired seeds each exactly 7 of 64 episodes apart in one column (a t-interval of zero width,
    p = 0, a verdict Holm cannot touch) get the pooled episodes' interval and its p-value instead."""
    a = [cell("gtu", s, {c: [1] * (10 + s) + [0] * (54 - s) for c in COLUMNS}) for s in range(3)]
    b = [cell("hybrid", s, {c: [1] * (17 + s) + [0] * (47 - s) for c in COLUMNS}) for s in range(3)]
    assert difference({c.seed: c.rate(COLUMNS[3]) for c in a}, {c.seed: c.rate(COLUMNS[3]) for c in b}).p == 0.0
    an = analyse(a + b, n_boot=200)
    part = judge(an, [Claim("x", "GTU beats CCE+MSE there", (Part("gtu", "hybrid", on=COLUMNS[3]),))], {}, {})[0]["parts"][0]
    lo, hi = newcombe((33, 192), (54, 192), 1.959964)
    assert part["measured"]["mean"] == pytest.approx(-10.94, abs=0.01)
    assert (part["measured"]["lo"], part["measured"]["hi"]) == pytest.approx((lo, hi), abs=0.01)
    assert part["method"] == "paired t, 3 seeds, widened to the episodes' interval"
    assert 0.005 < part["p"] < 0.05 and part["verdict"] == CONTRADICTED


def test_an_overall_claim_on_seeds_that_agree_gets_the_episodes_interval():
    """GTU 3 of 12 episodes in every column on each of three seeds, CIL 0 of 12: every seed's overall
    difference is +25, so the t-interval had no width ("supported, +25.0 [+25.0, +25.0]"). Overall is the
    mean of the four columns, so its floor is the MOVER interval of 1/4 x (9 of 36) per column against
    1/4 x (0 of 36), by hand from Wilson's closed form; the p-value is dual to it: at z = the normal quantile
    of 1 - p / 2 its lower bound touches 0."""
    a = [cell("gtu", s, {c: [1] * 3 + [0] * 9 for c in COLUMNS}) for s in range(3)]
    b = [cell("cil", s, {c: [0] * 12 for c in COLUMNS}) for s in range(3)]
    got = judge(analyse(a + b, n_boot=200), [Claim("x", "GTU beats CIL", (Part("gtu", "cil"),))], {}, {})[0]["parts"][0]
    terms = [(0.25, 9, 36)] * 4 + [(-0.25, 0, 36)] * 4
    lo, hi = mover(terms, 1.959964)
    # by hand once more: each side's four equal terms sum to 4 (d / 4)^2 = (d / 2)^2
    assert lo == pytest.approx(100 * (0.25 - math.hypot((0.25 - wilson(9, 36, 1.959964)[0]) / 2,
                                                        (wilson(0, 36, 1.959964)[1] - 0) / 2)))
    assert got["measured"] == pytest.approx({"mean": 25.0, "lo": lo, "hi": hi}, abs=1e-6)
    assert got["method"] == "paired t, 3 seeds, widened to the episodes' interval"
    assert 0 < lo < 25 < hi and got["verdict"] == SUPPORTED
    z = float(stats.norm.ppf(1 - got["p"] / 2))
    assert mover(terms, z)[0] == pytest.approx(0.0, abs=1e-5) and 0 < got["p"] < 0.05
    one = judge(analyse([c for c in a + b if c.seed == 0] + [cell("cil", 9, {c: [0] * 12 for c in COLUMNS})],
                        n_boot=50), [Claim("x", "x", (Part("gtu", "cil"),))], {}, {})[0]["parts"][0]
    assert one["measured"]["lo"] is None  # one paired seed: no interval to widen


def test_a_town_gap_sums_a_column_counted_twice():
    """A gap on means of columns, the new weathers (columns 1 and 3) minus the new town (2 and 3): column 3
    enters both with opposite signs and drops out, so the floor is the MOVER interval of the four remaining
    terms (+1/2 on column 1, -1/2 on column 2, each for A and, negated, for B), never a column counted as two
    independent proportions."""
    per = {COLUMNS[0]: 10, COLUMNS[1]: 8, COLUMNS[2]: 4, COLUMNS[3]: 6}
    a = [cell("gtu", s, {c: [1] * k + [0] * (16 - k) for c, k in per.items()}) for s in range(3)]
    b = [cell("cil", s, {c: [1] * (k - 2) + [0] * (18 - k) for c, k in per.items()}) for s in range(3)]
    part = Part("gtu", "cil", on="gap", hard="new_weathers", easy="new_town")
    got = judge(analyse(a + b, n_boot=50), [Claim("g", "g", (part,))], {}, {})[0]["parts"][0]
    terms = [(0.5, 24, 48), (-0.5, 18, 48), (-0.5, 12, 48), (0.5, 6, 48)]  # A col 1, B col 1, A col 2, B col 2
    lo, hi = mover(terms, 1.959964)
    assert got["measured"]["mean"] == pytest.approx(0.0, abs=1e-9)
    assert (got["measured"]["lo"], got["measured"]["hi"]) == pytest.approx((lo, hi), abs=1e-6)


def test_a_rows_overall_on_agreeing_seeds_gets_the_episodes_interval():
    """Three seeds each at 3 of 12 in every column: the overall t-interval has no width; the floor is the
    MOVER interval of the four columns' mean, 1/4 x (9 of 36) each: 25 less half of Wilson's distance down."""
    e = row_estimate([cell("gtu", s, {c: [1] * 3 + [0] * 9 for c in COLUMNS}) for s in range(3)], "overall")
    lo, hi = wilson(9, 36, 1.959964)
    assert (e.mean, e.lo, e.hi) == pytest.approx((25.0, 25 - 100 * (0.25 - lo) / 2, 25 + 100 * (hi - 0.25) / 2))
    town = row_estimate([cell("gtu", s, {c: [1] * 3 + [0] * 9 for c in COLUMNS}) for s in range(3)], "new_town")
    assert town.lo == pytest.approx(25 - 100 * (0.25 - lo) / math.sqrt(2))  # two columns: sqrt(2 (d / 2)^2)


def test_the_method_says_widened_only_where_a_bound_moved():
    """A floor that raises the p-value but lies inside the seeds' interval (equal pooled episodes, 50 of 100
    against 50 of 100: Newcombe's interval is about ±13.7, the seeds' ±20) takes the larger p-value and
    leaves the interval and the method alone."""
    d = Difference(Estimate(0.0, -20.0, 20.0), 0.5, "paired t, 3 seeds", True, (3, 3))
    f = with_episode_floor(d, [(1.0, 50, 100), (-1.0, 50, 100)])
    assert (f.estimate.lo, f.estimate.hi, f.p, f.method) == (-20.0, 20.0, 1.0, "paired t, 3 seeds")
    lo, hi = newcombe((50, 100), (50, 100), 1.959964)
    assert -20 < lo < -13 and 13 < hi < 20  # inside, as the docstring says


def test_a_scaled_part_gets_the_floor_of_its_scaled_contrast():
    """Cross-stitch below a quarter of CIL: every seed's A - 0.25 x B is 30 - 0.25 x 80 = +10 points in
    every column (a t-interval of no width); the floor is MOVER's on A's 90 of 300 against -0.25 x B's 240 of
    300 per column, a quarter each, by hand."""
    a = [at("cross_stitch", s, 30) for s in range(3)]
    b = [at("cil", s, 80) for s in range(3)]
    part = Part("cross_stitch", "cil", test="less", b_scale=0.25)
    got = judge(analyse(a + b, n_boot=50), [Claim("x", "x", (part,))], {}, {})[0]["parts"][0]
    lo, hi = mover([(0.25, 90, 300)] * 4 + [(-0.0625, 240, 300)] * 4, 1.959964)
    assert got["measured"] == pytest.approx({"mean": 10.0, "lo": lo, "hi": hi}, abs=1e-6)
    assert got["method"] == "paired t, 3 seeds, widened to the episodes' interval" and got["verdict"] == CONTRADICTED


def test_paired_over_the_seeds_both_ran():
    """Rows that share seeds share their splits: A on seeds 0-2 and B on seeds 0-3 are paired over seeds 0-2
    (B's seed 3 left out): A - B = 20, 20, 35, mean 25, sd 8.660, 25 +- 4.303 x 8.660 / sqrt 3 by hand, where
    Welch over all seeds would treat the shared splits as independent."""
    a = {0: 60.0, 1: 70.0, 2: 80.0}
    b = {0: 40.0, 1: 50.0, 2: 45.0, 3: 55.0}
    d = difference(a, b)
    assert d.paired and d.n == (3, 3)
    assert d.method == "paired t, 3 seeds (the seeds both ran; 0 of A's and 1 of B's left out)"
    half = 4.303 * math.sqrt(75.0) / math.sqrt(3)
    assert (d.estimate.mean, d.estimate.lo, d.estimate.hi) == pytest.approx((25.0, 25 - half, 25 + half), abs=0.01)


def test_welch_when_no_seed_is_shared():
    """Rows that share no seed are not paired: Welch's interval, recomputed here from its formula
    (se^2 = sa^2/na + sb^2/nb, Welch-Satterthwaite df)."""
    from scipy import stats

    a = {0: 60.0, 1: 70.0, 2: 80.0}  # var 100
    b = {10: 40.0, 11: 50.0, 12: 45.0, 13: 55.0}  # mean 47.5, var 41.667
    d = difference(a, b)
    assert not d.paired and d.method == "Welch t, 3 vs 4 seeds, none shared"
    va, vb = 100 / 3, (41.6667) / 4
    se = math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va ** 2 / 2 + vb ** 2 / 3)
    q = stats.t.ppf(0.975, df)
    assert (d.estimate.mean, d.estimate.lo, d.estimate.hi) == pytest.approx((22.5, 22.5 - q * se, 22.5 + q * se), abs=0.01)
    assert d.p == pytest.approx(2 * stats.t.sf(22.5 / se, df), abs=1e-4)


def test_ratio_interval_by_hand():
    """Fieller with a constant B (40 on every seed) is the t-interval of A divided by 40:
    [45.156, 94.844] / 40 = [1.1289, 2.3711]; B indistinguishable from 0 makes it unbounded."""
    r, lo, hi = ratio_interval([60.0, 70.0, 80.0], [40.0, 40.0, 40.0], paired=True)
    assert (r, lo, hi) == pytest.approx((1.75, 45.156 / 40, 94.844 / 40), abs=5e-4)
    r, lo, hi = ratio_interval([60.0, 70.0, 80.0], [0.0, 3.0, 0.0], paired=True)
    assert r == pytest.approx(70.0) and lo is None and hi is None


def mover_r(a: float, a_lim: tuple[float, float], b: float, b_lim: tuple[float, float]) -> tuple[float, float]:
    """Donner & Zou's MOVER-R limits of a / b, written out from the paper's closed form."""
    (l1, u1), (l2, u2) = a_lim, b_lim
    lower = (a * b - math.sqrt((a * b) ** 2 - l1 * u2 * (2 * a - l1) * (2 * b - u2))) / (u2 * (2 * b - u2))
    upper = (a * b + math.sqrt((a * b) ** 2 - u1 * l2 * (2 * a - u1) * (2 * b - l2))) / (l2 * (2 * b - l2))
    return lower, upper


def test_mover_ratio_by_hand():
    """MOVER-R of two estimates with asymmetric limits, against the closed form; the same limits given in
    points or as fractions give the same ratio interval."""
    got = mover_ratio(30.0, (20.0, 45.0), 60.0, (50.0, 68.0))
    assert got == pytest.approx(mover_r(30.0, (20.0, 45.0), 60.0, (50.0, 68.0)), rel=1e-12)
    assert got == pytest.approx(mover_ratio(0.3, (0.2, 0.45), 0.6, (0.5, 0.68)), rel=1e-12)
    assert 20 / 68 < got[0] < 0.5 < got[1] < 45 / 50  # inside the crude bounds of the limits' ratios


def test_a_relative_change_on_seeds_that_agree_gets_the_episodes_ratio_interval():
    """GTU built as CIL's cells with exactly 2 more successes of 64 in each column (CIL 48, 50 and 52 on
    seeds 0-2): the difference's t-interval has no width and is floored to Newcombe's, which holds 0, but
    Fieller's ratio interval of +4% is about a point wide and excluded 0. Floored, it contains MOVER-R of
    the pooled 156 of 192 against 150 of 192, each Wilson's interval, by hand, and the record says so."""
    b = [cell("cil", s, {c: [1] * k + [0] * (64 - k) for c in COLUMNS}) for s, k in enumerate((48, 50, 52))]
    a = [cell("gtu", s, {c: [1] * (k + 2) + [0] * (62 - k) for c in COLUMNS}) for s, k in enumerate((48, 50, 52))]
    part = Part("gtu", "cil", on=COLUMNS[3], relative=True)
    got = judge(analyse(a + b, n_boot=50), [Claim("h", "h", (part,))], {}, {})[0]["parts"][0]
    _, f_lo, f_hi = ratio_interval([50.0, 52.0, 54.0], [48.0, 50.0, 52.0], paired=True)
    assert 1.0 < f_lo < f_hi < 1.06  # Fieller alone: +4% [+4, +5], 0 excluded
    z = 1.959964
    lo, hi = mover_r(156 / 192, wilson(156, 192, z), 150 / 192, wilson(150, 192, z))
    assert got["measured"]["lo"] < 0 < got["measured"]["hi"] and got["verdict"] == INCONCLUSIVE
    assert got["relative"]["mean"] == pytest.approx(4.0, abs=0.05)
    assert (got["relative"]["lo"], got["relative"]["hi"]) == pytest.approx((100 * (lo - 1), 100 * (hi - 1)), abs=0.051)
    assert got["relative"]["lo"] < 0 < got["relative"]["hi"]
    assert got["relative"]["method"] == "Fieller, widened to the episodes' interval"
    assert results._relative(got["relative"]).endswith("widened to the episodes' interval")


def test_a_wider_fieller_interval_is_left_alone():
    """A at 60, 70 and 80 of 100 over seeds against B at 40 on each: Fieller's [1.129, 2.371] (the
    t-interval of A over 40) holds MOVER-R of the pooled 210 of 300 against 120 of 300, so nothing moves."""
    r, f_lo, f_hi = ratio_interval([60.0, 70.0, 80.0], [40.0, 40.0, 40.0], paired=True)
    z = 1.959964
    lo, hi = mover_r(0.7, wilson(210, 300, z), 0.4, wilson(120, 300, z))
    assert f_lo < lo < 1.75 < hi < f_hi
    assert with_ratio_floor(f_lo, f_hi, [(1.0, 210, 300)], [(1.0, 120, 300)]) == (f_lo, f_hi, False)
    a = [at("gtu", s, p) for s, p in enumerate((60, 70, 80))]
    b = [at("cil", s, 40) for s in range(3)]
    got = judge(analyse(a + b, n_boot=50), [Claim("h", "h", (Part("gtu", "cil", on=COLUMNS[3], relative=True),))],
                {}, {})[0]["parts"][0]
    assert got["relative"] == pytest.approx({"paper": None, "mean": 75.0, "lo": round(100 * (f_lo - 1), 1),
                                             "hi": round(100 * (f_hi - 1), 1), "method": "Fieller"})


def test_a_floor_unbounded_where_b_may_be_zero():
    """B's lower limit at or below 0: MOVER-R has no bound, as Fieller's then; a pooled B of 0 of 64
    (Wilson's lower limit 0) makes a bounded Fieller interval unbounded, and says the floor moved it; an
    unbounded Fieller interval stays so."""
    assert mover_ratio(50.0, (40.0, 60.0), 2.0, (-1.0, 5.0)) == (None, None)
    assert mover_ratio(50.0, (40.0, 60.0), 2.0, (0.0, 5.0)) == (None, None)
    assert with_ratio_floor(1.0, 1.2, [(1.0, 30, 64)], [(1.0, 0, 64)]) == (None, None, True)
    assert with_ratio_floor(None, None, [(1.0, 30, 64)], [(1.0, 20, 64)]) == (None, None, False)


# ------------------------------------------------------------------------------------------------
# verdicts, Holm, too few seeds


def test_holm_by_hand():
    """p = .01, .04, .03, .005: sorted .005 x 4 = .02, .01 x 3 = .03, .03 x 2 = .06, .04 x 1 -> max(.04, .06) = .06."""
    adj, reject = holm([0.01, 0.04, 0.03, 0.005])
    assert adj == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert reject == [True, False, False, True]
    assert holm([]) == ([], [])


def test_holm_over_a_family_fixed_in_advance():
    """Two of a family of four tested, .01 and .04; the two untested count as p = 1: sorted .01 x 4 = .04,
    .04 x 3 = .12 (the family of the two tested alone would give .02 and .04, both rejected)."""
    adj, reject = holm([0.04, 0.01], family_size=4)
    assert adj == pytest.approx([0.12, 0.04])
    assert reject == [False, True]
    assert holm([0.04, 0.01]) == (pytest.approx([0.04, 0.02]), [True, True])
    with pytest.raises(ValueError, match="family of 1"):
        holm([0.04, 0.01], family_size=1)


def test_a_fixed_family_only_grows_more_lenient_as_it_fills_in(monkeypatch):
    """Holm is monotone: replacing an untested member's p = 1 by any tested p never raises another member's
    adjusted p-value, so a verdict reached over the fixed family survives the rows still to come."""
    import gc

    # statsmodels' Holm calls gc.collect() on every call: 0.25 s each in a test process holding torch, 294 s
    # of the suite for these 600 calls; collecting garbage changes no p-value
    monkeypatch.setattr(gc, "collect", lambda *args: 0)
    rng = np.random.default_rng(7)
    for _ in range(300):
        m = int(rng.integers(2, 12))
        ps = list(rng.uniform(0, 0.2, size=m) ** 2)
        k = int(rng.integers(1, m))
        before, _ = holm(ps[:k], family_size=m)
        after, _ = holm(ps[:k + 1], family_size=m)
        assert all(a <= b + 1e-12 for a, b in zip(after[:k], before))


def test_holm_turns_a_marginal_claim_inconclusive():
    """Three claims on 3 paired seeds against a row at 50%: differences (10, 8, 12), (8, 5, 11), (4, 1, 7).
    With 2 df, p = 1 - t / sqrt(2 + t^2): t = 8.660 -> .0131, t = 4.619 -> .0437, t = 2.309 -> .1472.
    Uncorrected the first two are supported; Holm multiplies by 3, 2, 1: .0392 (kept), .0874 (not), .1472."""
    cells = [at("cil", s, 50) for s in range(3)]
    cells += [at("x", s, p) for s, p in zip(range(3), (60, 58, 62))]
    cells += [at("w", s, p) for s, p in zip(range(3), (58, 55, 61))]
    cells += [at("y", s, p) for s, p in zip(range(3), (54, 51, 57))]
    claims = [Claim(r, f"{r} beats cil", (Part(r, "cil"),)) for r in ("x", "w", "y")]
    got = {c["id"]: c for c in judge(analyse(cells, n_boot=200), claims, {}, {})}

    def p2(t: float) -> float:
        return 1 - t / math.sqrt(2 + t * t)

    ps = {"x": p2(10 / (2 / math.sqrt(3))), "w": p2(8 / (3 / math.sqrt(3))), "y": p2(4 / (3 / math.sqrt(3)))}
    assert ps == pytest.approx({"x": 0.0131, "w": 0.0437, "y": 0.1472}, abs=2e-4)
    for r in ps:
        assert got[r]["parts"][0]["p"] == pytest.approx(ps[r], abs=1e-6)
    assert got["x"]["parts"][0]["p_holm"] == pytest.approx(3 * ps["x"], abs=1e-6)
    assert got["w"]["parts"][0]["p_holm"] == pytest.approx(2 * ps["w"], abs=1e-6)
    assert got["y"]["parts"][0]["p_holm"] == pytest.approx(ps["y"], abs=1e-6)
    assert [got[r]["verdict"] for r in "xwy"] == [SUPPORTED, SUPPORTED, INCONCLUSIVE]
    assert [got[r]["verdict_holm"] for r in "xwy"] == [SUPPORTED, INCONCLUSIVE, INCONCLUSIVE]


def test_a_claim_not_run_still_counts_in_holms_family():
    """The three claims of the test above plus one on a row never run: the family is 4, so Holm multiplies
    the sorted p-values .0131, .0437, .1472 by 4, 3, 2: .0524 (x is no longer supported after Holm)."""
    cells = [at("cil", s, 50) for s in range(3)]
    cells += [at("x", s, p) for s, p in zip(range(3), (60, 58, 62))]
    cells += [at("w", s, p) for s, p in zip(range(3), (58, 55, 61))]
    cells += [at("y", s, p) for s, p in zip(range(3), (54, 51, 57))]
    claims = [Claim(r, f"{r} beats cil", (Part(r, "cil"),)) for r in ("x", "w", "y", "never")]
    got = {c["id"]: c for c in judge(analyse(cells, n_boot=200), claims, {}, {})}
    p_x = 1 - 8.660254 / math.sqrt(2 + 75.0)  # t = 10 / (2 / sqrt 3), 2 df (as above)
    p_w = 1 - 4.618802 / math.sqrt(2 + 4.618802 ** 2)
    p_y = 1 - 2.309401 / math.sqrt(2 + 2.309401 ** 2)
    assert got["x"]["parts"][0]["p_holm"] == pytest.approx(4 * p_x, abs=1e-5)
    assert got["w"]["parts"][0]["p_holm"] == pytest.approx(3 * p_w, abs=1e-5)
    assert got["y"]["parts"][0]["p_holm"] == pytest.approx(2 * p_y, abs=1e-5)
    assert [got[r]["verdict_holm"] for r in "xwy"] == [INCONCLUSIVE] * 3
    assert got["never"]["verdict_holm"] == NOT_RUN and "p_holm" not in got["never"]["parts"][0]


def test_a_row_with_fewer_than_three_seeds_gets_no_verdict():
    """Two seeds: the mean is reported (and its wide 2-seed interval), the verdict is 'too few seeds' and
    the part stays out of Holm's family; one seed: no interval at all."""
    cells = [at("cil", s, 30) for s in range(3)] + [at("gtu", s, 90) for s in range(2)] + [at("sine", 0, 95)]
    claims = [Claim("g", "GTU beats CIL", (Part("gtu", "cil"),)),
              Claim("s", "sine beats CIL", (Part("sine", "cil"),)),
              Claim("m", "MoE beats CIL", (Part("moe", "cil"),))]
    an = analyse(cells, n_boot=200)
    got = {c["id"]: c for c in judge(an, claims, {}, {})}
    g = got["g"]["parts"][0]
    assert g["measured"]["mean"] == 60.0 and g["verdict"] == TOO_FEW and got["g"]["verdict"] == TOO_FEW
    assert g["verdict_holm"] == TOO_FEW and "p_holm" not in g
    # the seeds agree exactly (90 - 30 on both), so the interval is the pooled episodes' (widened)
    assert g["method"] == ("paired t, 2 seeds, widened to the episodes' interval, on the seeds both ran "
                           "(0 of A's and 1 of B's cells left out)")
    assert got["s"]["verdict"] == TOO_FEW and got["s"]["parts"][0]["measured"]["lo"] is None
    assert got["m"]["verdict"] == NOT_RUN
    assert an.estimates["sine"][4].lo is None and an.estimates["gtu"][4].lo is not None
    data = report_data(cells, [], {"cil": {"label": "CIL"}, "gtu": {"label": "GTU"}, "sine": {"label": "Sine"}},
                       {"budget": "smoke"}, n_boot=200, claims=claims)
    md = markdown(data)
    assert "fewer than 3 seeds: *too few seeds*" in md and "{" not in md  # no unformatted placeholder
    assert "| GTU | – | 2 † |" in md and "| Sine | – | 1 † |" in md and "| CIL | – | 3 |" in md
    assert "too few seeds" in next(line for line in md.splitlines() if line.startswith("| GTU beats CIL"))


def test_verdicts_on_known_differences():
    strong = [same_in_every_column("gtu", s, [1] * (36 - s) + [0] * (4 + s)) for s in range(3)]  # 90, 87.5, 85
    weak = [same_in_every_column("cil", s, [1] * (20 + s) + [0] * (20 - s)) for s in range(3)]  # 50, 52.5, 55
    close = [same_in_every_column("sine", s, [1] * (20 + 2 * (s % 2)) + [0] * (20 - 2 * (s % 2))) for s in range(3)]
    an = analyse(strong + weak + close, n_boot=500)
    claims = [Claim("a", "GTU beats CIL", (Part("gtu", "cil"),)), Claim("b", "CIL beats GTU", (Part("cil", "gtu"),)),
              Claim("c", "sine beats CIL", (Part("sine", "cil"),)),
              Claim("d", "GTU below CIL", (Part("gtu", "cil", test="less"),)),
              Claim("e", "GTU not better than CIL", (Part("gtu", "cil", test="not_greater"),)),
              Claim("f", "CIL not better than GTU", (Part("cil", "gtu", test="not_greater"),)),
              Claim("g", "sine not better than CIL", (Part("sine", "cil", test="not_greater"),)),
              Claim("h", "between", (Part("gtu", "cil"), Part("moe", "cil")))]
    got = {c["id"]: c["verdict"] for c in judge(an, claims, {}, {}, margin=5.0)}
    # g: sine - CIL per seed 0, +2.5, -5, whose interval [-10.3, +8.7] holds the +5 margin: nothing is
    # significant, and "not better than" is not shown by that (it read supported when tested against 0)
    assert got == {"a": SUPPORTED, "b": CONTRADICTED, "c": INCONCLUSIVE, "d": CONTRADICTED,
                   "e": CONTRADICTED, "f": SUPPORTED, "g": NOT_SHOWN, "h": NOT_RUN}


def test_gap_claim_supported_when_the_advantage_grows_in_the_hard_column():
    easy, hard = COLUMNS[0], COLUMNS[3]
    gtu = [cell("gtu", s, {easy: [1] * 40, COLUMNS[1]: [1] * 40, COLUMNS[2]: [1] * 40, hard: [1] * (36 - s) + [0] * (4 + s)})
           for s in range(3)]
    cil = [cell("cil", s, {easy: [1] * 40, COLUMNS[1]: [1] * 40, COLUMNS[2]: [1] * 40, hard: [1] * (12 + 2 * s) + [0] * (28 - 2 * s)})
           for s in range(3)]
    an = analyse(gtu + cil, n_boot=500)
    part = Part("gtu", "cil", on="gap", hard=hard, easy=easy)
    got = judge(an, [Claim("gap", "gap", (part,))], {}, {})[0]["parts"][0]
    # per seed (90 - 30) - 0, (87.5 - 35), (85 - 40): 60, 52.5, 45
    assert got["measured"]["mean"] == pytest.approx(52.5) and got["verdict"] == SUPPORTED
    assert got["measured"]["lo"] == pytest.approx(52.5 - 4.303 * 7.5 / math.sqrt(3), abs=0.01)


def test_the_contrast_interval_of_one_difference_is_statsmodels_newcombe():
    """The MOVER interval of A - B is Newcombe's hybrid score interval: statsmodels' own implementation
    (``method="newcomb"``) agrees, at 0%, 100% and in between, at 95% and 90%."""
    from statsmodels.stats.proportion import confint_proportions_2indep

    for a, b in [((29, 192), (50, 192)), ((96, 96), (90, 96)), ((0, 64), (5, 64)), ((40, 64), (40, 64))]:
        for level in (0.95, 0.90):
            lo, hi = confint_proportions_2indep(a[0], a[1], b[0], b[1], method="newcomb", compare="diff",
                                                alpha=1 - level)
            got = seed_stats.contrast_interval([(1.0, *a), (-1.0, *b)], level)
            assert got == pytest.approx((100 * lo, 100 * hi), abs=1e-6)


def test_a_gaps_episode_interval_by_hand():
    """(A - B) in one column minus (A - B) in another, four independent proportions: the lower bound
    subtracts the root of the summed squared distances to the side each term pulls down (the lower Wilson
    distance for +, the upper for -), the upper bound the mirror (Zou & Donner's MOVER), Wilson by hand."""
    z = 1.959964
    terms = [(1.0, 160, 192), (-1.0, 100, 192), (-1.0, 190, 192), (1.0, 185, 192)]
    value, below, above = 0.0, 0.0, 0.0
    for c, k, n in terms:
        p, (lo, hi) = k / n, wilson(k, n, z)
        value += c * p
        below += (p - lo) ** 2 if c > 0 else (hi - p) ** 2
        above += (hi - p) ** 2 if c > 0 else (p - lo) ** 2
    want = (100 * (value - math.sqrt(below)), 100 * (value + math.sqrt(above)))
    lo, hi, p = seed_stats.episode_interval(terms)
    assert (lo, hi) == pytest.approx(want, abs=1e-3)
    assert lo > 0 and 0 < p < 0.05
    assert seed_stats.contrast_interval(terms, 1 - p)[0] == pytest.approx(0.0, abs=1e-6)  # p is dual to it


def test_a_gap_whose_easy_column_is_full_still_gets_the_episodes_interval():
    """Every seed at 100% in the easy column and exactly 7 of 64 episodes apart in the hard one: the
    per-seed gaps agree (a t-interval of zero width, p = 0) until the four columns' pooled episodes
    widen it to their interval."""
    easy, hard = COLUMNS[0], COLUMNS[3]
    rest = {c: [1] * 64 for c in COLUMNS[1:3]}
    a = [cell("gtu", s, {easy: [1] * 96, hard: [1] * (17 + s) + [0] * (47 - s), **rest}) for s in range(3)]
    b = [cell("cil", s, {easy: [1] * 96, hard: [1] * (10 + s) + [0] * (54 - s), **rest}) for s in range(3)]
    part = Part("gtu", "cil", on="gap", hard=hard, easy=easy)
    got = judge(analyse(a + b, n_boot=200), [Claim("gap", "gap", (part,))], {}, {})[0]["parts"][0]
    z = 1.959964
    (la, ua), (lb, ub), (lf, uf) = wilson(54, 192, z), wilson(33, 192, z), wilson(288, 288, z)
    d = 54 / 192 - 33 / 192
    # at 100% only the distance down to Wilson's lower bound is left: B's full column pulls the gap
    # down (its coefficient is +1), A's pulls it up (-1); each enters one side once
    want = (100 * (d - math.sqrt((54 / 192 - la) ** 2 + (ub - 33 / 192) ** 2 + (1 - lf) ** 2)),
            100 * (d + math.sqrt((ua - 54 / 192) ** 2 + (33 / 192 - lb) ** 2 + (1 - lf) ** 2)))
    assert uf == pytest.approx(1.0)
    assert got["measured"]["mean"] == pytest.approx(100 * 7 / 64, abs=0.01)
    assert (got["measured"]["lo"], got["measured"]["hi"]) == pytest.approx(want, abs=0.01)
    assert got["method"] == "paired t, 3 seeds, widened to the episodes' interval"
    assert 0.001 < got["p"] < 0.05 and got["verdict"] == SUPPORTED


def test_combine_and_paper_differences():
    assert combine([SUPPORTED, SUPPORTED]) == SUPPORTED
    assert combine([SUPPORTED, INCONCLUSIVE]) == INCONCLUSIVE
    assert combine([SUPPORTED, CONTRADICTED]) == CONTRADICTED
    assert combine([SUPPORTED, NOT_RUN]) == NOT_RUN
    assert combine([TOO_FEW, SUPPORTED]) == TOO_FEW
    assert combine([TOO_FEW, CONTRADICTED]) == CONTRADICTED
    paper = {"gtu": [100.0, 93.42, 81.25, 75.0], "cil": [94.74, 86.84, 52.5, 46.25], "hybrid": [97.37, 85.53, 64.25, 56.25]}
    assert Part("gtu", "cil").paper(paper) == pytest.approx(
        np.mean([100 - 94.74, 93.42 - 86.84, 81.25 - 52.5, 75 - 46.25]))
    gap = Part("gtu", "cil", on="gap", hard=COLUMNS[3], easy=COLUMNS[0])
    assert gap.paper(paper) == pytest.approx((75 - 46.25) - (100 - 94.74))
    head = Part("gtu", "cil", on=COLUMNS[3], relative=True)
    assert head.paper(paper) == pytest.approx(28.75) and head.paper_relative(paper) == pytest.approx(75 / 46.25 - 1)
    assert round(100 * Part("hybrid", "cil", on=COLUMNS[3], relative=True).paper_relative(paper)) == 22  # "21%"


def test_the_paper_claims_come_from_the_config_with_their_sentences():
    """conf/reproduce.yaml holds the claims: the headline (GTU vs CIL in the new town under new weathers,
    relative), GTU vs CCE+MSE there, 'failed to improve' as not-better-than; each quote is the paper's
    own sentence (checked against the LaTeX source where the shared folder is present)."""
    claims = {c.id: c for c in default_claims()}
    head = claims["headline"].parts[0]
    assert (head.a, head.b, head.on, head.test, head.relative) == ("gtu", "cil", COLUMNS[3], "greater", True)
    assert "by 62\\%" in claims["headline"].quote
    hyb = claims["gtu_vs_hybrid"].parts[0]
    assert (hyb.a, hyb.b, hyb.on, hyb.test) == ("gtu", "hybrid", COLUMNS[3], "greater")
    assert claims["classification_vs_cil"].parts[0].test == "not_greater"
    assert [p.test for p in claims["coexistence"].parts] == ["greater", "not_greater"]
    assert all(c.quote and c.source for c in claims.values())
    paper = sorted(Path(__file__).resolve().parents[2].joinpath("shared", "paper").glob("*.txt"))
    if paper:
        text = re.sub(r"\s+", " ", paper[0].read_text())
        for c in claims.values():
            assert re.sub(r"\s+", " ", c.quote) in text, c.id


@pytest.mark.parametrize("spec, named", [  # named: the key or value the error names
    ([{"id": "x", "claim": "x", "parts": [{"a": "gtu", "b": "cil", "column": "nowhere"}]}], "'nowhere'"),
    ([{"id": "x", "claim": "x", "parts": [{"a": "gtu", "b": "cil", "test": "beats"}]}], "'beats'"),
    ([{"id": "x", "claim": "x", "parts": [{"a": "gtu", "b": "cil", "on": "overall"}]}], "on"),
    ([{"id": "x", "parts": [{"a": "gtu", "b": "cil"}]}], "'claim'"),
])
def test_bad_claims_are_one_clear_error(spec, named):
    with pytest.raises(ValueError) as err:
        load_claims(spec)
    assert named in str(err.value) and "\n" not in str(err.value), err.value


# ------------------------------------------------------------------------------------------------
# the secondary two-level episode bootstrap


def test_one_seed_column_bootstrap_is_the_binomial_bootstrap():
    """With one seed, resampling a column's n episodes makes the rate Binomial(n, k/n)/n: the bootstrap's
    95% interval is its 2.5% and 97.5% quantiles (hand-summed), within one episode."""
    n, k = 40, 30
    outs = [1] * k + [0] * (n - k)
    an = analyse([same_in_every_column("cil", 0, outs)], n_boot=20000, seed=1)
    est = an.bootstrap["cil"][0]
    assert est.mean == pytest.approx(75.0)
    assert est.lo == pytest.approx(100 * binomial_quantile(n, 0.75, 0.025), abs=100 / n)
    assert est.hi == pytest.approx(100 * binomial_quantile(n, 0.75, 0.975), abs=100 / n)
    # hand values: P(X<=23)=0.0116, P(X<=24)=0.0262, P(X<=34)=0.9567, P(X<=35)=0.9840 for X~Binomial(40, .75)
    assert (binomial_quantile(n, 0.75, 0.025), binomial_quantile(n, 0.75, 0.975)) == (24 / 40, 35 / 40)


def test_bootstrap_seed_level_resampling_by_hand():
    """Two seeds, one always succeeding and one always failing: a replicate's mean is 0, 50 or 100 % with
    probabilities 1/4, 1/2, 1/4 (episode resampling changes nothing), so the 95% interval is [0, 100]."""
    an = analyse([same_in_every_column("gtu", 0, [1] * 10), same_in_every_column("gtu", 1, [0] * 10)],
                 n_boot=8000, seed=2)
    reps = an.replicates["gtu"][:, 4]
    assert set(np.unique(reps)) == {0.0, 50.0, 100.0}
    assert np.mean(reps == 50.0) == pytest.approx(0.5, abs=0.02)
    assert np.mean(reps == 0.0) == pytest.approx(0.25, abs=0.02)
    e = an.bootstrap["gtu"][4]
    assert (e.mean, e.lo, e.hi) == (50.0, 0.0, 100.0)


def test_overall_is_the_mean_of_the_four_columns():
    c = cell("cil", 0, {COLUMNS[0]: [1, 1, 1, 1], COLUMNS[1]: [1, 1, 0, 0], COLUMNS[2]: [1, 0, 0, 0],
                        COLUMNS[3]: [0, 0, 0, 0, 0, 0, 0, 0]})
    assert c.rate() == pytest.approx((100 + 50 + 25 + 0) / 4)
    an = analyse([c], n_boot=500)
    assert an.estimates["cil"][4].mean == pytest.approx(43.75)


def test_bootstrap_paired_difference_of_identical_rows_is_exactly_zero():
    """Rows that drove the same episodes with the same outcomes differ by 0 in every replicate:
    the episode draw is shared (paired), so the bootstrap interval is [0, 0]."""
    outs = [1, 0, 1, 1, 0, 1, 0, 1]
    an = analyse([same_in_every_column("a", 0, outs), same_in_every_column("b", 0, outs)], n_boot=2000)
    d = _boot_part(an, Part("a", "b"), an.rows)
    assert (d.mean, d.lo, d.hi) == (0.0, 0.0, 0.0)


def test_cells_on_other_episodes_are_refused():
    a = same_in_every_column("a", 0, [1, 0])
    b = same_in_every_column("b", 0, [1, 0, 1])
    with pytest.raises(ValueError, match="drove other episodes") as err:
        analyse([a, b])
    assert "(12 episodes against 8" in str(err.value)


def _folder(tmp_path: Path, suite: list[str], families: dict[str, str | None]) -> Path:
    """A results folder pinned to ``suite``, a cell per row recording ``families[row]`` (None: no record)."""
    folder = tmp_path / "results"
    (folder / "cells").mkdir(parents=True)
    (folder / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"suite": suite}}))
    for seed in range(3):
        for row, family in families.items():
            c = at(row, seed, [6 + seed, 5, 4, 3], n=10)
            path = folder / "cells" / row / f"seed{seed}" / "cell.json"
            path.parent.mkdir(parents=True)
            path.write_text(json.dumps({"status": "ok", "row": row, "seed": seed, "episodes": c.episodes,
                                        **({"weather_family": family} if family is not None else {})}))
    return folder


def test_the_report_refuses_a_cell_driven_under_another_weather_family(tmp_path):
    """A folder pinned before the families (harsh) holding a cell that records carla: the same episode keys,
    other weathers; refused naming the cell and both families. A cell without the record is the folder's."""
    folder = _folder(tmp_path, ["suite=single_turn"], {"cil": None, "gtu": "carla"})
    with pytest.raises(CicfwError) as err:
        results.write_report(folder, {"cil": {}, "gtu": {}}, n_boot=20, claims=[], margin=5.0)
    assert (err.value.key, err.value.value) == ("weather_family", "carla")
    assert "gtu/seed0" in str(err.value) and "'harsh'" in str(err.value), err.value
    assert not (folder / "results.json").exists()
    blank = _folder(tmp_path / "blank", ["suite=single_turn"], {"cil": None, "gtu": ""})  # edited to nothing
    with pytest.raises(CicfwError) as err:
        results.write_report(blank, {"cil": {}, "gtu": {}}, n_boot=20, claims=[], margin=5.0)
    assert (err.value.key, err.value.value) == ("weather_family", "")
    ok = _folder(tmp_path / "ok", ["suite=single_turn", "sim.weather_family=carla"], {"cil": None, "gtu": "carla"})
    assert [r["row"] for r in results.write_report(ok, {"cil": {}, "gtu": {}}, n_boot=20, claims=[],
                                                   margin=5.0)["rows"]] == ["cil", "gtu"]


# ------------------------------------------------------------------------------------------------
# the report


def test_report_table_shows_mean_interval_paper_value_and_each_verdict_method():
    cells = [at("cil", s, p, n=40) for s, p in zip(range(3), (28, 30, 32))]  # 70, 75, 80 %
    cells += [at("gtu", s, p, n=40) for s, p in zip(range(3), (36, 37, 38))]  # 90, 92.5, 95 %
    catalogue = {"cil": {"label": "Regression (CIL)", "paper": [94.74, 86.84, 52.5, 46.25]},
                 "gtu": {"label": "Co-learning (GTU)", "paper": [100.0, 93.42, 81.25, 75.0]}}
    data = report_data(cells, [{"row": "hybrid", "seed": 1, "error": "RuntimeError: boom"}], catalogue,
                       {"budget": "smoke", "suite": {"name": "single_turn"}}, n_boot=500)
    md = markdown(data)
    row = next(line for line in md.splitlines() if line.startswith("| Regression (CIL)"))
    # overall 75 +- 4.303 x 5 / sqrt(3) = 12.42 (the hand t-interval), the paper's overall 70.1
    assert "| 3 | 75.0 [" in row and "*94.7*" in row and "75.0 [62.6, 87.4]<br>*70.1*" in row
    assert "- hybrid seed 1: RuntimeError: boom" in md
    assert data["rows"][0]["per_seed"]["2"]["overall"] == 80.0
    head = next(line for line in md.splitlines() if line.startswith("| Co-learning (GTU) improves the new town"))
    assert "paired t, 3 seeds" in head and "+62%" in head and "+28.8" in head
    assert "Bootstrap (secondary)" in md and "## Secondary: the two-level episode bootstrap" in md
    assert "Holm" in md and "“On the other hand, our proposed CIC model tackled this issue" in md
    # the generated summary quotes the same numbers as the table
    assert "- **Regression (CIL)**: 75.0 [62.6, 87.4]% overall over 3 seed(s); per seed 70.0 / 75.0 / 80.0." in md


def test_wall_time_table_names_the_cicfw_that_made_each_cell():
    """Cells of one folder come from several commits (``continue_from``): the wall-time table says which,
    ``–`` for a cell made before cells recorded it."""
    cells = [at("cil", s, 30, n=40) for s in range(3)]
    cells[0].meta["code"] = {"version": "0.2.0", "commit": "1cee6eb8fb7487929ba588f58be21eba1a40473c", "modified": False}
    cells[1].meta["code"] = {"version": "0.2.0", "commit": "0743064aaaabbbbccccddddeeeeffff000011112", "modified": True}
    md = markdown(report_data(cells, [], {"cil": {"label": "CIL"}}, {"budget": "smoke"}, n_boot=50))
    table = md.split("## Wall time per cell")[1].splitlines()
    assert "| cicfw |" in table[2]
    assert [line.rsplit("|", 2)[1].strip() for line in table[4:7]] == [
        "0.2.0 @ 1cee6eb", "0.2.0 @ 0743064 + changes", "–"]
    # a folder none of whose cells records its code (made before cells did) keeps the table it was published with
    old = markdown(report_data([at("cil", s, 30, n=40) for s in range(3)], [], {"cil": {"label": "CIL"}},
                               {"budget": "smoke"}, n_boot=50)).split("## Wall time per cell")[1].splitlines()
    assert old[2] == "| Row | Seed | Train | Evaluate | Curve evaluations |" and old[4] == "| CIL | 0 | 1.0 | – | – |"


def test_wall_time_table_names_each_cells_machine_where_they_differ():
    """A folder continued on another machine mixes machines: its wall times are not one machine's, so the
    table says whose each is; a folder made on one machine keeps the table it was published with."""
    amd, intel = "2 cores (AMD EPYC), no GPU", "2 cores (Intel(R) Xeon(R) Processor), no GPU"
    cells = [at("cil", s, 30, n=40) for s in range(3)]
    for c, m in zip(cells, (amd, amd, intel)):
        c.meta["machine"] = m
    data = report_data(cells, [], {"cil": {"label": "CIL"}}, {"budget": "smoke"}, n_boot=50)
    table = markdown(data).split("## Wall time per cell")[1].splitlines()
    assert table[0] == " (s, on each cell's machine)" and table[2].endswith("| Curve evaluations | Machine |")
    assert [line.rsplit("|", 2)[1].strip() for line in table[4:7]] == [amd, amd, intel]
    assert data["rows"][0]["machine"] == {"0": amd, "1": amd, "2": intel}
    for c in cells:
        c.meta["machine"] = amd
    same = report_data(cells, [], {"cil": {"label": "CIL"}}, {"budget": "smoke"}, n_boot=50)
    table = markdown(same).split("## Wall time per cell")[1].splitlines()
    assert same["rows"][0]["machine"] == {} and table[0] == " (s, on the machine above)"
    assert table[2] == "| Row | Seed | Train | Evaluate | Curve evaluations |"


def test_a_row_keeps_its_colour_whichever_rows_the_folder_holds(tmp_path, monkeypatch):
    """Two folders' pictures are compared by colour: CIL's points are drawn in the same colour with GTU
    present or absent (its place in the catalogue fixes it), and two rows never share one."""
    drawn = []
    monkeypatch.setattr(results, "_save", lambda fig, path: drawn.append(fig) or path)  # plots', as the report imported it
    catalogue = {"cil": {"label": "CIL"}, "gtu": {"label": "GTU"}, "moe": {"label": "MoE"}}

    def colour_of(rows: list[str]) -> dict[str, tuple]:
        cells = [at(r, s, 30, n=40) for r in rows for s in range(3)]
        data = report_data(cells, [], catalogue, {"budget": "smoke"}, n_boot=50)
        drawn.clear()
        results.plot_results(data, tmp_path / "results.png", order=list(catalogue))
        ax = drawn[0].axes[0]
        return {bars.get_label(): tuple(bars.lines[0].get_color()) for bars in ax.containers}

    both, without_gtu = colour_of(["cil", "gtu", "moe"]), colour_of(["cil", "moe"])
    assert len(set(both.values())) == 3
    assert without_gtu == {"CIL": both["CIL"], "MoE": both["MoE"]}
    # a row outside the catalogue follows it; the catalogue's rows keep their places
    assert results.row_colours(["x", "moe", "cil"], list(catalogue)) == {"x": 3, "moe": 2, "cil": 0}


def test_a_learning_curve_of_one_seed_shows_its_value_not_a_range():
    """One seed's curve point is a value ("60.9", not "60.9 [60.9, 60.9]", which reads like an interval
    of no width); several seeds' is their mean with [min, max] and the count, recomputed here by hand."""
    data = {"rows": [
        {"label": "CIL", "curve": {"0": [{"samples": 120, "overall": 60.94}, {"samples": 240, "overall": 59.1}]}},
        {"label": "GTU", "curve": {"0": [{"samples": 120, "overall": 50.0}],
                                   "1": [{"samples": 120, "overall": 70.0}], "2": [{"samples": 120, "overall": 66.0}]}},
    ]}
    lines = results.curve_table(data)
    assert lines[0] == "| Row | 120 samples | 240 samples |"
    assert lines[2] == "| CIL | 60.9 | 59.1 |"
    assert lines[3] == f"| GTU | {(50 + 70 + 66) / 3:.1f} [50.0, 70.0] (3 seeds) | – |"


def test_the_results_plot_says_its_column_bars_are_the_widened_intervals(tmp_path, monkeypatch):
    """Seeds that all drove 100% have a t-interval of no width; the plot draws the episodes' floor, as the
    table does (a column's Clopper-Pearson interval, overall the MOVER interval of the four columns' mean),
    and its title must say so rather than call the bar a t-interval alone."""
    drawn = []
    monkeypatch.setattr(results, "_save", lambda fig, path: drawn.append(fig) or path)
    cells = [at("cil", s, 40, n=40) for s in range(3)]  # 40 of 40 in every column, each seed
    data = report_data(cells, [], {"cil": {"label": "CIL"}}, {"budget": "smoke"}, n_boot=50)
    results.plot_results(data, tmp_path / "results.png")
    ax = drawn[0].axes[0]
    lo = 100 * stats.beta.ppf(0.025, 120, 1)  # Clopper-Pearson's lower bound for 120 of 120
    below = ax.containers[0].lines[2][0].get_segments()[0][:, 1]  # the first column's bar, (x, y) ends
    assert min(below) == pytest.approx(lo, abs=1e-6) and max(below) == pytest.approx(100.0)
    overall = ax.containers[0].lines[2][0].get_segments()[4][:, 1]
    z = stats.norm.ppf(0.975)
    # each column 120 of 120 at weight 1/4: 100 - sqrt(4 (d / 4)^2) = 100 - d / 2, d Wilson's distance down
    assert min(overall) == pytest.approx(100 - (100 - 100 * wilson(120, 120, z)[0]) / 2, abs=1e-6)
    assert "never narrower than the interval of the episodes pooled over the seeds" in ax.get_title()


def test_the_learning_curve_names_the_suite_it_was_driven_on(tmp_path, monkeypatch):
    """The curve's title named the single-turn suite whatever suite the budget drove."""
    drawn = []
    monkeypatch.setattr(results, "_save", lambda fig, path: drawn.append(fig) or path)
    data = {"manifest": {"budget": "mine", "suite": {"name": "junctions"}},
            "rows": [{"label": "CIL", "row": "cil", "curve": {"0": [{"samples": 120, "overall": 60.0}]}}]}
    results.plot_curve(data, tmp_path / "learning_curve.png")
    title = drawn[0].axes[0].get_title()
    assert "junctions" in title and "single-turn" not in title
