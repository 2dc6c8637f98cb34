"""The claims' tests as the claims state them: a direction ("A beats B") is the two-sided t-test against 0
read on the claim's side, "A failed to improve on B" is tested against the equivalence margin (non-superiority:
supported only when the 95% interval lies below +margin), and an interval that holds the margin reads
*not shown*. Each formula against a hand computation and statsmodels' TOST, its size by simulation."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from cicfw.reproduction.analysis import analyse
from cicfw.reproduction.cells import CellResult
from cicfw.reproduction.claims import (CONTRADICTED, INCONCLUSIVE, NOT_SHOWN, SUPPORTED, Claim, Part, check_margin,
                                       combine, default_claims, default_margin, judge, load_claims, part_verdict)
from cicfw.reproduction.report import markdown, report_data
from cicfw.reproduction.seed_stats import difference
from conftest import p_two_sided_2df, pinned as at

T_975_2 = 4.303  # t_{0.975, 2} from a printed table


def one_part(cells: list[CellResult], part: Part, margin: float = 5.0) -> dict:
    return judge(analyse(cells, n_boot=100), [Claim("x", "x", (part,))], {}, {}, margin=margin)[0]["parts"][0]


def test_not_better_than_is_tested_against_the_margin_by_hand():
    """Paired differences A - B = -2, +1, +4 (mean 1, sd 3, se sqrt 3): the 95% interval 1 +- 4.303 sqrt 3 =
    [-6.45, +8.45] holds +5, so "A not better than B" is not shown; its test against +5: t = (1 - 5) / sqrt 3
    = -2.309, p = 1 - 2.309 / sqrt(2 + 5.333) = 0.147. Tested against 0 (as before) it read supported."""
    cells = [at("b", s, 50) for s in range(3)] + [at("a", s, 50 + d) for s, d in zip(range(3), (-2, 1, 4))]
    rec = one_part(cells, Part("a", "b", test="not_greater"))
    half = T_975_2 * 3 / math.sqrt(3)
    assert rec["measured"] == pytest.approx({"mean": 1.0, "lo": 1 - half, "hi": 1 + half}, abs=5e-3)
    assert rec["p"] == pytest.approx(p_two_sided_2df((1 - 5) / math.sqrt(3)), abs=1e-9)
    assert rec["p"] == pytest.approx(0.1472, abs=1e-4)
    assert (rec["claim"], rec["test"], rec["null"], rec["verdict"]) == ("not_greater", "two-sided", 5.0, NOT_SHOWN)
    assert rec["comparison"] == "a not better than b by 5 points or more (overall)"


def test_not_better_than_supported_below_the_margin_and_contradicted_above_it():
    """-4, -3, -2 (mean -3, sd 1): [-5.48, -0.52] lies below +5, t = -8 / (1 / sqrt 3) = -13.86, p 0.0052:
    supported. +9, +10, +11: [+7.52, +12.48] lies above +5: contradicted (A better by more than the margin).
    +6, +9, +12 (mean 9, sd 3): [+1.55, +16.45] is above 0 but holds +5: not shown, not contradicted."""
    def part(diffs: tuple[int, int, int]) -> dict:
        cells = [at("b", s, 50) for s in range(3)] + [at("a", s, 50 + d) for s, d in zip(range(3), diffs)]
        return one_part(cells, Part("a", "b", test="not_greater"))

    below, above, between = part((-4, -3, -2)), part((9, 10, 11)), part((6, 9, 12))
    assert below["p"] == pytest.approx(p_two_sided_2df(-8 * math.sqrt(3)), abs=1e-9) and below["verdict"] == SUPPORTED
    assert above["verdict"] == CONTRADICTED
    assert between["measured"]["lo"] > 0 and between["measured"]["hi"] > 5 and between["verdict"] == NOT_SHOWN


def test_the_paired_margin_test_is_statsmodels_tost_upper_half():
    """The non-superiority test is the upper of TOST's two one-sided tests (statsmodels ``ttost_paired``):
    its one-sided p, doubled toward the nearer side, is the part's two-sided p against +margin."""
    from statsmodels.stats.weightstats import ttost_paired

    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b = rng.normal(60, 6, 4), rng.normal(60, 6, 4)
        _, _, (_, p_upper, _) = ttost_paired(a, b, -5.0, 5.0)
        d = difference(dict(enumerate(a)), dict(enumerate(b)), null=5.0)
        assert d.p == pytest.approx(2 * min(p_upper, 1 - p_upper), rel=1e-9)


def test_the_welch_margin_test_by_hand_and_against_statsmodels():
    """3 vs 5 seeds: Welch's t = (mean_a - mean_b - 5) / sqrt(s_a^2/3 + s_b^2/5) with Welch-Satterthwaite df,
    written out here; statsmodels' ``ttost_ind(usevar="unequal")`` upper test agrees."""
    from statsmodels.stats.weightstats import ttost_ind

    a, b = np.array([61.5, 55.5, 69.7]), np.array([61.1, 60.0, 57.7, 60.2, 72.4])
    va, vb = a.var(ddof=1) / 3, b.var(ddof=1) / 5
    t = (a.mean() - b.mean() - 5.0) / math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va ** 2 / 2 + vb ** 2 / 4)
    d = difference(dict(zip(range(3), a)), dict(zip(range(10, 15), b)), null=5.0)
    assert d.p == pytest.approx(2 * stats.t.sf(abs(t), df), rel=1e-9)
    _, _, (_, p_upper, _) = ttost_ind(a, b, -5.0, 5.0, usevar="unequal")
    assert d.p == pytest.approx(2 * min(p_upper, 1 - p_upper), rel=1e-9)
    assert d.estimate.lo < 5.0 < d.estimate.hi  # so "classification failed to improve on CIL" is not shown


@pytest.mark.slow  # simulates thousands of experiments
@pytest.mark.parametrize("paired", [True, False])
def test_the_margin_test_has_its_size_at_the_margin(paired: bool):
    """At a true A - B of exactly +5 (the margin), "not better than" must read supported in 2.5% of
    experiments (one side of a two-sided 95% test) and contradicted in 2.5%: simulated, 5 seeds each (paired:
    a shared split half of the seed variance), 2,000 experiments; 2.5% +- 1.15 (3.3 standard errors) holds for
    both with probability > 0.998, and a test of twice the size (5%) is 2.5 points off."""
    rng = np.random.default_rng(11 if paired else 12)
    supported = contradicted = 0
    n_exp = 2000
    for _ in range(n_exp):
        shared = rng.normal(0, 4.2, 5) if paired else 0.0
        a = 65 + shared + rng.normal(0, 4.2, 5)
        b = 60 + shared + rng.normal(0, 4.2, 5)
        seeds_b = range(5) if paired else range(5, 10)
        d = difference(dict(enumerate(a)), dict(zip(seeds_b, b)), null=5.0)
        verdict = part_verdict("not_greater", d.estimate.mean - 5.0, d.p < 0.05)
        supported += verdict == SUPPORTED
        contradicted += verdict == CONTRADICTED
    assert abs(supported / n_exp - 0.025) < 0.0115, supported / n_exp
    assert abs(contradicted / n_exp - 0.025) < 0.0115, contradicted / n_exp


def test_verdicts_read_each_side_of_each_null():
    assert [part_verdict("greater", x, True) for x in (1, -1)] == [SUPPORTED, CONTRADICTED]
    assert [part_verdict("less", x, True) for x in (1, -1)] == [CONTRADICTED, SUPPORTED]
    assert [part_verdict("not_greater", x, True) for x in (1, -1)] == [CONTRADICTED, SUPPORTED]
    assert [part_verdict("not_less", x, True) for x in (1, -1)] == [SUPPORTED, CONTRADICTED]
    assert part_verdict("greater", 3, False) == INCONCLUSIVE and part_verdict("not_greater", -3, False) == NOT_SHOWN
    assert combine([SUPPORTED, NOT_SHOWN]) == NOT_SHOWN and combine([NOT_SHOWN, INCONCLUSIVE]) == INCONCLUSIVE


def test_not_worse_than_mirrors_it_at_minus_the_margin():
    """-2, -1, 0 (mean -1, sd 1): [-3.48, +1.48] lies above -5: "A not worse than B" supported; tested against
    -5: t = 4 sqrt 3 = 6.93, p = 1 - 6.93 / sqrt(2 + 48) = 0.0202."""
    cells = [at("b", s, 50) for s in range(3)] + [at("a", s, 50 + d) for s, d in zip(range(3), (-2, -1, 0))]
    rec = one_part(cells, Part("a", "b", test="not_less"))
    assert rec["null"] == -5.0 and rec["verdict"] == SUPPORTED and "widened" not in rec["method"]
    assert rec["p"] == pytest.approx(p_two_sided_2df(4 * math.sqrt(3)), abs=1e-9)
    assert rec["comparison"] == "a not worse than b by 5 points or more (overall)"


def test_holm_reads_the_margin_tests_p_value():
    """The family holds each part's p against its own null: two parts, -4/-3/-2 not better than (p 0.0052
    against +5) and a directional +1/+2/+3 (t = 2 sqrt 3, p = 1 - 3.464 / sqrt 14 = 0.0742); Holm: 0.0104
    (supported) and 0.0742."""
    cells = [at("b", s, 50) for s in range(3)]
    cells += [at("a", s, 50 + d) for s, d in zip(range(3), (-4, -3, -2))]
    cells += [at("c", s, 50 + d) for s, d in zip(range(3), (1, 2, 3))]
    got = judge(analyse(cells, n_boot=100), [Claim("x", "x", (Part("a", "b", test="not_greater"), Part("c", "b")))],
                {}, {}, margin=5.0)[0]["parts"]
    p1, p2 = p_two_sided_2df(-8 * math.sqrt(3)), p_two_sided_2df(2 * math.sqrt(3))
    assert [g["p_holm"] for g in got] == pytest.approx([2 * p1, p2], abs=1e-9)
    assert [g["verdict_holm"] for g in got] == [SUPPORTED, INCONCLUSIVE]


def test_the_margin_comes_from_the_config_and_bad_ones_are_refused():
    assert default_margin() == 5.0
    for bad in (0, -5, "5", True, float("nan"), None):
        with pytest.raises(ValueError, match="equivalence_margin"):
            check_margin(bad)
    assert {p.test for c in default_claims() for p in c.parts} <= {"greater", "less", "not_greater", "not_less"}
    with pytest.raises(ValueError, match="not_less"):
        load_claims([{"id": "x", "claim": "x", "parts": [{"a": "a", "b": "b", "test": "equal"}]}])


def test_the_report_says_which_test_each_part_had():
    """results.json's part names the claim's direction, the two-sided test and its null; RESULTS.md names
    the margin in the comparison and explains *not shown*."""
    cells = [at("cil", s, 50) for s in range(3)]
    cells += [at("classification", s, 50 + d) for s, d in zip(range(3), (-2, 1, 4))]
    claims = [Claim("c", "Classification failed to improve on CIL",
                    (Part("classification", "cil", test="not_greater"),)),
              Claim("g", "Classification beats CIL", (Part("classification", "cil"),))]
    data = report_data(cells, [], {"cil": {"label": "CIL"}, "classification": {"label": "Classification"}},
                       {"budget": "smoke"}, n_boot=50, claims=claims, margin=5.0)
    parts = [c["parts"][0] for c in data["claims"]]
    assert [(p["claim"], p["test"], p["null"]) for p in parts] == [("not_greater", "two-sided", 5.0),
                                                                    ("greater", "two-sided", 0.0)]
    assert data["equivalence_margin"] == 5.0
    md = markdown(data)
    row = next(line for line in md.splitlines() if line.startswith("| Classification failed to improve"))
    assert "not better than CIL by 5 points or more" in row and "**not shown**" in row
    assert "*not shown* when it holds +5" in md
