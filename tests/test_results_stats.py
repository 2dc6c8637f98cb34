"""The reproduction's statistics on synthetic cell results with known answers: the two-level bootstrap
against hand computations, the paired differences, the verdicts, and the report's table."""
from __future__ import annotations

import math

import numpy as np
import pytest

from cicfw.bench import results
from cicfw.bench.results import (COLUMNS, CONTRADICTED, INCONCLUSIVE, NOT_RUN, SUPPORTED, CellResult, Estimate,
                                 analyse, combine, judge, markdown, part_verdict, report_data)


def cell(row: str, seed: int, successes: dict[str, list[int]]) -> CellResult:
    """A cell whose column c drove len(successes[c]) episodes with those outcomes (1 = success)."""
    eps = {}
    for c, outs in successes.items():
        for k, ok in enumerate(outs):
            eps[f"{c}/{k:03d}"] = {"success": bool(ok), "column": c, "command": "left" if k % 2 else "right"}
    return CellResult(row=row, seed=seed, episodes=eps, meta={"decoder": None, "wall_s": {"train": 1.0}})


def same_in_every_column(row: str, seed: int, outs: list[int]) -> CellResult:
    return cell(row, seed, {c: outs for c in COLUMNS})


def binomial_quantile(n: int, p: float, q: float) -> float:
    """The q-quantile of Binomial(n, p) / n, by summing the probabilities by hand."""
    acc = 0.0
    for k in range(n + 1):
        acc += math.comb(n, k) * p ** k * (1 - p) ** (n - k)
        if acc >= q:
            return k / n
    return 1.0


def test_one_seed_column_interval_is_the_binomial_bootstrap():
    """With one seed, resampling a column's n episodes makes the rate Binomial(n, k/n)/n: the 95% interval
    is its 2.5% and 97.5% quantiles (hand-summed), within one episode."""
    n, k = 40, 30
    outs = [1] * k + [0] * (n - k)
    an = analyse([same_in_every_column("cil", 0, outs)], n_boot=20000, seed=1)
    est = an.estimates["cil"][0]
    assert est.mean == pytest.approx(75.0)
    assert est.lo == pytest.approx(100 * binomial_quantile(n, 0.75, 0.025), abs=100 / n)
    assert est.hi == pytest.approx(100 * binomial_quantile(n, 0.75, 0.975), abs=100 / n)
    # hand values: P(X<=23)=0.0116, P(X<=24)=0.0262, P(X<=34)=0.9567, P(X<=35)=0.9840 for X~Binomial(40, .75)
    assert (binomial_quantile(n, 0.75, 0.025), binomial_quantile(n, 0.75, 0.975)) == (24 / 40, 35 / 40)


def test_seed_level_resampling_by_hand():
    """Two seeds, one always succeeding and one always failing: a replicate's mean is 0, 50 or 100 % with
    probabilities 1/4, 1/2, 1/4 (episode resampling changes nothing), so the 95% interval is [0, 100]."""
    an = analyse([same_in_every_column("gtu", 0, [1] * 10), same_in_every_column("gtu", 1, [0] * 10)],
                 n_boot=8000, seed=2)
    reps = an.replicates["gtu"][:, 4]
    assert set(np.unique(reps)) == {0.0, 50.0, 100.0}
    assert np.mean(reps == 50.0) == pytest.approx(0.5, abs=0.02)
    assert np.mean(reps == 0.0) == pytest.approx(0.25, abs=0.02)
    e = an.estimates["gtu"][4]
    assert (e.mean, e.lo, e.hi) == (50.0, 0.0, 100.0)


def test_overall_is_the_mean_of_the_four_columns():
    c = cell("cil", 0, {COLUMNS[0]: [1, 1, 1, 1], COLUMNS[1]: [1, 1, 0, 0], COLUMNS[2]: [1, 0, 0, 0],
                        COLUMNS[3]: [0, 0, 0, 0, 0, 0, 0, 0]})
    assert c.rate() == pytest.approx((100 + 50 + 25 + 0) / 4)
    an = analyse([c], n_boot=500)
    assert an.estimates["cil"][4].mean == pytest.approx(43.75)


def test_paired_difference_of_identical_rows_is_exactly_zero():
    """Rows that drove the same episodes with the same outcomes differ by 0 in every replicate:
    the episode draw is shared (paired), so the interval is [0, 0]."""
    outs = [1, 0, 1, 1, 0, 1, 0, 1]
    an = analyse([same_in_every_column("a", 0, outs), same_in_every_column("b", 0, outs)], n_boot=2000)
    d = an.diff("a", "b")
    assert (d.mean, d.lo, d.hi) == (0.0, 0.0, 0.0)


def test_verdicts_on_known_differences():
    n = 40
    strong = [same_in_every_column("gtu", s, [1] * 36 + [0] * 4) for s in range(3)]  # 90%
    weak = [same_in_every_column("cil", s, [1] * 20 + [0] * 20) for s in range(3)]  # 50%
    close = [same_in_every_column("sine", s, [0] + [1] * 21 + [0] * 18) for s in range(3)]  # 52.5%: +2 -1 vs cil
    an = analyse(strong + weak + close, n_boot=4000)
    assert part_verdict(an.diff("gtu", "cil")) == SUPPORTED
    assert an.diff("gtu", "cil").mean == pytest.approx(40.0)
    assert part_verdict(an.diff("cil", "gtu")) == CONTRADICTED
    assert part_verdict(an.diff("sine", "cil")) == INCONCLUSIVE
    claims = {c["claim"]: c for c in judge(an, {}, {})}
    assert claims["GTU (co-learning) beats CIL"]["verdict"] == SUPPORTED
    assert claims["Sine encoding is (slightly) above CIL"]["verdict"] == INCONCLUSIVE
    assert claims["MoE lands between CIL and GTU"]["verdict"] == NOT_RUN
    # the gap claim: GTU's advantage is the same in every column here, so it is not larger anywhere
    assert claims["GTU's gain over CIL is largest in the new town under new weathers"]["verdict"] == INCONCLUSIVE
    assert n == 40


def test_gap_claim_supported_when_the_advantage_grows_in_the_hard_column():
    easy, hard = COLUMNS[0], COLUMNS[3]
    gtu = [cell("gtu", s, {easy: [1] * 40, COLUMNS[1]: [1] * 40, COLUMNS[2]: [1] * 40, hard: [1] * 36 + [0] * 4})
           for s in range(2)]
    cil = [cell("cil", s, {easy: [1] * 40, COLUMNS[1]: [1] * 40, COLUMNS[2]: [1] * 40, hard: [1] * 12 + [0] * 28})
           for s in range(2)]
    an = analyse(gtu + cil, n_boot=4000)
    gap = results.Comparison("gtu", "cil", kind="gap", hard=3, easy=0).estimate(an)
    assert gap.mean == pytest.approx(60.0)  # (90 - 30) - (100 - 100)
    assert part_verdict(gap) == SUPPORTED


def test_combine_and_paper_differences():
    assert combine([SUPPORTED, SUPPORTED]) == SUPPORTED
    assert combine([SUPPORTED, INCONCLUSIVE]) == INCONCLUSIVE
    assert combine([SUPPORTED, CONTRADICTED]) == CONTRADICTED
    assert combine([SUPPORTED, NOT_RUN]) == NOT_RUN
    paper = {"gtu": [100.0, 93.42, 81.25, 75.0], "cil": [94.74, 86.84, 52.5, 46.25]}
    assert results.Comparison("gtu", "cil").paper(paper) == pytest.approx(
        np.mean([100 - 94.74, 93.42 - 86.84, 81.25 - 52.5, 75 - 46.25]))
    assert results.Comparison("gtu", "cil", kind="gap").paper(paper) == pytest.approx((75 - 46.25) - (100 - 94.74))
    assert part_verdict(Estimate(1.0, 0.5, 2.0)) == SUPPORTED
    assert part_verdict(Estimate(-1.0, -2.0, 0.0)) == INCONCLUSIVE  # an interval touching 0 is not decisive


def test_cells_on_other_episodes_are_refused():
    a = same_in_every_column("a", 0, [1, 0])
    b = same_in_every_column("b", 0, [1, 0, 1])
    with pytest.raises(ValueError, match="drove other episodes"):
        analyse([a, b])


def test_report_table_shows_mean_interval_and_paper_value():
    cells = [same_in_every_column("cil", s, [1] * 30 + [0] * 10) for s in range(3)]
    catalogue = {"cil": {"label": "Regression (CIL)", "paper": [94.74, 86.84, 52.5, 46.25]}}
    data = report_data(cells, [{"row": "gtu", "seed": 1, "error": "RuntimeError: boom"}], catalogue,
                       {"budget": "smoke", "suite": {"name": "single_turn"}}, n_boot=1000)
    md = markdown(data)
    row = next(line for line in md.splitlines() if line.startswith("| Regression (CIL)"))
    assert "| 3 | 75.0 [" in row and "*94.7*" in row and "*70.1*" in row  # paper overall: mean of its 4 columns
    assert "- gtu seed 1: RuntimeError: boom" in md
    assert data["rows"][0]["per_seed"]["2"]["overall"] == 75.0
