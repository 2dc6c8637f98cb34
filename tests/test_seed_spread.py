"""The seeds' spread test (cicfw.reproduction.seed_spread) against hand computations: Pearson's statistic from its
formula, the p-value against an exact enumeration of every table with the same margins, its calibration
when the seeds truly share one rate, and its place in the generated RESULTS.md."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import stats

from cicfw.reproduction.cells import COLUMNS, CellResult
from cicfw.reproduction.report import markdown, report_data
from cicfw.reproduction.seed_spread import seed_spread


def pearson_by_hand(successes, episodes):
    """sum over the 2 x k cells of (observed - expected)^2 / expected, expected = row total * column total / N."""
    s, n = np.asarray(successes, float), np.asarray(episodes, float)
    obs = np.stack([s, n - s])
    exp = np.outer(obs.sum(axis=1), n) / n.sum()
    return float(((obs - exp) ** 2 / exp).sum())


def exact_p(successes, episodes):
    """P(chi-square >= observed) over every table with these margins: each way of spreading the total
    failures over the seeds, weighted by the multivariate hypergeometric probability."""
    n = list(episodes)
    fails = sum(e - s for s, e in zip(successes, episodes))
    observed = pearson_by_hand(successes, episodes)
    p = 0.0
    for f in itertools.product(*[range(min(k, fails) + 1) for k in n[:-1]]):
        last = fails - sum(f)
        if not 0 <= last <= n[-1]:
            continue
        f = [*f, last]
        if pearson_by_hand([k - x for k, x in zip(n, f)], n) >= observed - 1e-9:
            p += stats.multivariate_hypergeom.pmf(f, n, fails)
    return p


def test_statistic_is_pearsons_chi_square_by_hand():
    t = seed_spread([95, 88, 85, 92, 86], [96] * 5)
    # by hand: 446 successes and 34 failures of 480; expected per seed 89.2 / 6.8
    hand = sum((s - 89.2) ** 2 / 89.2 + ((96 - s) - 6.8) ** 2 / 6.8 for s in [95, 88, 85, 92, 86])
    assert t.statistic == pytest.approx(hand, rel=1e-9)
    assert t.statistic == pytest.approx(11.2055, abs=1e-3)
    assert t.failures == (1, 8, 11, 4, 10)


@pytest.mark.parametrize("s,n", [([9, 4], [10, 10]), ([48, 40], [48, 48]), ([20, 18], [30, 30]),
                                 ([47, 45, 44], [48, 48, 48]), ([47, 36, 48], [48, 48, 48])])
def test_p_value_matches_the_exact_enumeration(s, n):
    assert seed_spread(s, n).pvalue == pytest.approx(exact_p(s, n), abs=0.012)  # Monte Carlo SE <= 0.005


def test_with_large_counts_the_p_value_is_the_asymptotic_chi_square():
    s, n = [700, 640, 720], [1000, 1000, 1000]
    t = seed_spread(s, n)
    assert t.pvalue == pytest.approx(stats.chi2.sf(pearson_by_hand(s, n), df=2), abs=0.01)


def test_no_spread_possible_and_too_few_seeds():
    assert seed_spread([96, 96, 96], [96, 96, 96]).pvalue == 1.0
    assert seed_spread([0, 0], [48, 48]).pvalue == 1.0
    assert seed_spread([90], [96]) is None
    with pytest.raises(ValueError, match="0 <= successes <= episodes"):
        seed_spread([97, 90], [96, 96])


def test_calibrated_when_the_seeds_share_one_rate():
    """Seeds with one true rate (5 seeds x 96 episodes at 93%): p < 0.05 in about 5% of simulated rows."""
    rng = np.random.default_rng(1)
    ps = [seed_spread(rng.binomial(96, 0.93, size=5), [96] * 5, n_resamples=999, seed=k).pvalue for k in range(300)]
    assert 0.015 <= np.mean(np.array(ps) < 0.05) <= 0.09


def test_finds_seeds_that_learned_differently():
    assert seed_spread([96, 95, 84, 96, 85], [96] * 5).pvalue < 0.01


def _cell(seed: int, left_fail: int, right_fail: int) -> CellResult:
    eps = {}
    for c in COLUMNS:
        for k in range(48):
            for cmd, fails in (("left", left_fail), ("right", right_fail)):
                ok = not (c == COLUMNS[0] and k < fails)
                eps[f"{c}/{cmd}/{k:03d}"] = {"success": ok, "column": c, "command": cmd}
    return CellResult(row="cil", seed=seed, episodes=eps, meta={"decoder": None, "wall_s": {}})


def test_report_shows_the_spread_per_column_and_per_command():
    cells = [_cell(0, 1, 0), _cell(1, 12, 0), _cell(2, 0, 1)]
    data = report_data(cells, [], {"cil": {"label": "CIL"}}, {"budget": "test"}, n_boot=50, claims=[])
    sp = data["rows"][0]["spread"]
    assert sp[COLUMNS[0]]["all"]["failures"] == [1, 12, 1]
    assert sp[COLUMNS[0]]["left"]["failures"] == [1, 12, 0]
    assert sp[COLUMNS[0]]["right"]["failures"] == [0, 0, 1]
    assert sp[COLUMNS[1]]["all"]["p"] == 1.0  # every seed drove every episode there
    assert sp[COLUMNS[0]]["left"]["p"] == pytest.approx(exact_p([47, 36, 48], [48] * 3), abs=0.012)
    md = markdown(data)
    assert "## Do the seeds differ beyond the episodes' luck?" in md
    section = md.split("## Do the seeds differ beyond the episodes' luck?")[1]
    line = next(ln for ln in section.splitlines() if ln.startswith("| CIL | 3 |"))
    assert "(1, 12, 1 of 96)" in line and "(1, 12, 0 of 48)" in line and "1.000 (0, 0, 0 of 96)" in line


def test_a_row_with_one_seed_has_no_spread_section():
    data = report_data([_cell(0, 1, 0)], [], {"cil": {"label": "CIL"}}, {"budget": "test"}, n_boot=50, claims=[])
    assert data["rows"][0]["spread"] == {}
    assert "beyond the episodes' luck" not in markdown(data)
