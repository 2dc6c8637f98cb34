"""Which row drives best: the rows by overall success, the leader against every other row, and every row
against CIL (the forest plot's data); each difference within one CPU kind where it can be
(``analysis.pair_cells``), two-sided 95% t-intervals over seeds, uncorrected (descriptive, not a claim)."""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from cicfw.reproduction.analysis import Analysis
from cicfw.reproduction.seed_stats import MIN_SEEDS, difference

#: the row every other is drawn against in the forest plot: the paper's baseline
BASELINE = "cil"
SEPARATED, TIED, TOO_FEW = "separated", "tied", "too few seeds"


def overall_difference(an: Analysis, a: str, b: str) -> dict[str, Any]:
    """Row ``a`` minus row ``b`` in overall success (points): the paired t-interval where the cells pair by
    seed, else Welch's, on the cells of one CPU kind where both rows have enough seeds there, else on
    all of them, marked mixed (``method`` says which); ``verdict`` reads the interval against 0."""
    pair = an.pair(a, b)
    d = difference({c.seed: c.value("overall") for c in pair.a}, {c.seed: c.value("overall") for c in pair.b})
    note = pair.note()
    e = d.estimate
    if not d.enough_seeds or e.lo is None or e.hi is None:
        verdict = TOO_FEW
    else:
        verdict = SEPARATED if e.lo > 0 or e.hi < 0 else TIED
    return {"a": a, "b": b, "measured": e.as_dict(), "p": d.p, "method": d.method + (f", {note}" if note else ""),
            "cpu": "mixed" if pair.mixed else pair.cpu, "seeds": list(d.n), "verdict": verdict}


def ranking(an: Analysis, order: Sequence[str] = ()) -> list[str]:
    """The rows by overall success (mean over seeds), best first; equal means keep ``order`` (the
    catalogue's), then the name."""
    order = list(order)
    place = {r: (order.index(r) if r in order else len(order), r) for r in an.rows}
    return sorted(an.rows, key=lambda r: (-an.estimates[r][4].mean, place[r]))


def leader(an: Analysis, ranked: Sequence[str]) -> dict[str, Any] | None:
    """The best row with enough seeds for a verdict (of all rows when none has) and its lead over every
    other row (``overall_difference``, leader minus row); None with fewer than two rows."""
    if len(ranked) < 2:
        return None
    eligible = [r for r in ranked if len(an.rows[r]) >= MIN_SEEDS] or list(ranked)
    top = eligible[0]
    return {"row": top, "versus": [overall_difference(an, top, r) for r in ranked if r != top]}


def forest(an: Analysis, ranked: Sequence[str], paper: Mapping[str, Sequence[float]]) -> list[dict[str, Any]]:
    """Every row's overall success minus CIL's (``overall_difference``), in ``ranked`` order, with the
    paper's difference (its Table 4 means; None for a row it gives no values); empty without CIL."""
    if BASELINE not in an.rows:
        return []
    base = paper.get(BASELINE)
    out = []
    for r in ranked:
        if r == BASELINE:
            continue
        rec = overall_difference(an, r, BASELINE)
        rec["paper"] = (round(float(np.mean(paper[r])) - float(np.mean(base)), 2)
                        if paper.get(r) and base else None)
        out.append(rec)
    return out
