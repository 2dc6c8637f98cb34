"""The words a comparison reads with (ahead / behind / equivalent within ±m / not separated), from rules:
the rule by its cases, its equivalence reading against statsmodels' TOST, and a claim's word recomputed from
scipy's interval at the Bonferroni level of its family."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from cicfw.reproduction.analysis import analyse
from cicfw.reproduction.claims import Claim, Part, judge
from cicfw.reproduction.seed_stats import difference, family_level, word
from conftest import pinned as at


def test_the_rule_by_its_cases():
    assert word(0.1, 9.0, 5.0) == "ahead" and word(-9.0, -0.1, 5.0) == "behind"
    assert word(-4.9, 4.9, 5.0) == "equivalent within ±5"
    assert word(-5.0, 4.9, 5.0) == word(-1.0, 6.0, 5.0) == "not separated"  # a bound on the margin is not inside
    assert word(0.5, 4.0, 5.0) == "ahead"  # ahead and inside the margin: the direction is said first
    assert word(None, 3.0, 5.0) is None
    assert family_level(20) == pytest.approx(0.9975) and family_level(1) == pytest.approx(0.95)


def test_equivalent_is_tost_at_half_the_intervals_error():
    """*equivalent within ±5* on a (1 - a) interval is TOST (statsmodels ``ttost_paired``) with each one-sided
    test at a / 2: both one-sided p-values below a / 2."""
    from statsmodels.stats.weightstats import ttost_paired

    rng = np.random.default_rng(5)
    level = family_level(10)
    seen = set()
    for _ in range(60):
        a = rng.normal(60, 3, 5)
        b = a + rng.normal(rng.uniform(-3, 3), rng.uniform(0.3, 3), 5)
        d = difference(dict(enumerate(a)), dict(enumerate(b)), level=level)
        _, (_, p_low, _), (_, p_upp, _) = ttost_paired(a, b, -5.0, 5.0)
        w = word(d.estimate.lo, d.estimate.hi, 5.0)
        tost = max(p_low, p_upp) < (1 - level) / 2
        seen.add(w)
        assert (w == "equivalent within ±5") == (tost and w not in ("ahead", "behind")), (w, p_low, p_upp)
    assert "equivalent within ±5" in seen and "not separated" in seen


def test_a_claims_word_is_read_on_scipys_interval_at_its_familys_bonferroni_level():
    """A family of 4 parts: GTU - CIL paired over the 3 seeds both ran (CIL's seed 3 left out), 9, 10, 10 points
    apart: its word is read on the 98.75% interval (scipy's ``ttest_rel``), which excludes 0 (ahead); sine -
    CIL, 0, 4, 4, is not separated; MoE's 2 seeds get no word."""
    cells = [at("cil", s, p) for s, p in zip(range(4), (50, 52, 54, 70))]
    cells += [at("gtu", s, p) for s, p in zip(range(3), (59, 62, 64))]
    cells += [at("sine", s, p) for s, p in zip(range(3), (50, 56, 58))]
    cells += [at("moe", s, 60) for s in range(2)]
    parts = (Part("gtu", "cil"), Part("sine", "cil"), Part("moe", "cil"), Part("gtu", "sine"))
    got = judge(analyse(cells, n_boot=50), [Claim("x", "x", parts)], {}, {}, margin=5.0)[0]["parts"]
    for rec, (a, b) in zip(got[:2], [((59, 62, 64), (50, 52, 54)), ((50, 56, 58), (50, 52, 54))]):
        ci = stats.ttest_rel(a, b).confidence_interval(1 - 0.05 / 4)
        assert (rec["word"]["lo"], rec["word"]["hi"]) == pytest.approx((ci.low, ci.high))
        assert rec["word"]["word"] == word(ci.low, ci.high, 5.0)
        assert "widened" not in rec["method"]  # 3,000 episodes a column: the floor lies inside scipy's interval
        assert rec["word"]["correction"] == "Bonferroni over the 4 parts of its family"
    assert got[0]["word"]["word"] == "ahead" and got[0]["word_uncorrected"] == "ahead"
    assert got[1]["word"]["word"] == "not separated"
    assert got[2]["word"]["word"] is None and got[2]["verdict"] == "too few seeds"
