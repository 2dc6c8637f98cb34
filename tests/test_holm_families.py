"""Holm adjusts within each family of claims fixed in advance: a separate question (the loss weights of
Tables 2 and 3) neither weakens the main comparison's verdicts nor is weakened by them."""
from __future__ import annotations

import math

import pytest

from cicfw.reproduction.analysis import analyse
from cicfw.reproduction.claims import Claim, Part, default_claims, holm_families, judge, load_claims
from conftest import p_two_sided_2df, pinned as at


def test_each_family_is_adjusted_on_its_own_by_hand():
    """Paired differences a - b = 4, 5, 6 (t = 5 / (1 / sqrt 3)) and c - b = 1, 5, 9 (t = 5 / (4 / sqrt 3)).
    Main family {a > b, an untested part}: Holm multiplies the smaller p by 2. Family 'w' {c > b}: by 1.
    Pooled into one family of 3, a's p would be multiplied by 3."""
    cells = ([at("b", s, 50) for s in range(3)] + [at("a", s, 50 + d) for s, d in zip(range(3), (4, 5, 6))]
             + [at("c", s, 50 + d) for s, d in zip(range(3), (1, 5, 9))])
    claims = [Claim("m", "a beats b", (Part("a", "b"), Part("a", "missing"))),
              Claim("w", "c beats b", (Part("c", "b"),), family="w")]
    out = judge(analyse(cells, n_boot=100), claims, {}, {}, margin=5.0)
    p_a, p_c = p_two_sided_2df(5 * math.sqrt(3)), p_two_sided_2df(5 * math.sqrt(3) / 4)
    assert out[0]["parts"][0]["p"] == pytest.approx(p_a, abs=1e-9)
    assert out[0]["parts"][0]["p_holm"] == pytest.approx(2 * p_a, abs=1e-9)
    assert out[1]["parts"][0]["p_holm"] == pytest.approx(p_c, abs=1e-9)
    assert holm_families(out) == {"main": 2, "w": 1}
    assert "family" not in out[0] and out[1]["family"] == "w"


def test_the_shipped_weight_claims_are_their_own_family():
    families = {c.id: c.family for c in default_claims()}
    assert families["hybrid_w"] == families["coexistence_w"] == "weights"
    assert families["headline"] == "main"
    assert load_claims([{"id": "x", "claim": "x", "parts": [{"a": "a", "b": "b"}]}])[0].family == "main"
