"""Which row drives best, by a procedure fixed before it is run: Hsu's multiple comparisons with the best
(MCB) over every row with at least ``MIN_SEEDS`` seeds (the others listed apart, never ranked), and every
row against CIL (the forest plot's data). docs/reproduce.md#which-row-drives-best states the procedure,
its bounds and its words; tests/test_ranking.py recomputes it by hand."""
from __future__ import annotations

import math
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from scipy import stats

from cicfw.reproduction.analysis import Analysis
from cicfw.reproduction.cells import CellResult, episode_terms
from cicfw.reproduction.seed_stats import (AHEAD, ALPHA, BEHIND, LEVEL, MIN_SEEDS, NOT_SEPARATED, Difference,
                                           compared_seeds, contrast_interval, difference, equivalent, family_level,
                                           no_spread, seeds_suffice, with_episode_floor, word, word_record)

#: the row every other is drawn against in the forest plot: the paper's baseline
BASELINE = "cil"
#: one ordered pair's (estimate, lower, upper) one-sided bounds of mu_i - mu_j
Bounds = tuple[float, float, float]


def overall_difference(an: Analysis, a: str, b: str, margin: float | None = None,
                       family_size: int = 1) -> dict[str, Any]:
    """Row ``a`` minus row ``b`` in overall success (points): paired over the seeds both ran, else Welch's,
    on the cells of one CPU kind where both rows have enough seeds there, else on all of them, marked mixed
    (``method`` says which), its 95% t-interval (``measured``); with a ``margin``, its ``word`` read on the
    Bonferroni interval over ``family_size`` comparisons and ``word_uncorrected`` on the 95% one."""
    pair = an.pair(a, b)
    va, vb = ({c.seed: c.value("overall") for c in cs} for cs in (pair.a, pair.b))
    terms = overall_terms(pair.a, pair.b)
    d = floored(difference(va, vb), terms)
    note = pair.note()
    rec = {"a": a, "b": b, "measured": d.estimate.as_dict(), "p": d.p,
           "method": d.method + (f", {note}" if note else ""), "paired": d.paired,
           "cpu": "mixed" if pair.mixed else pair.cpu, "seeds": list(d.n)}
    if margin is not None:
        level = family_level(family_size)
        rec["word"] = word_record(floored(difference(va, vb, level=level), terms, level), margin, level,
                                  f"Bonferroni over the {family_size} comparisons with {BASELINE}"
                                  if family_size > 1 else "none (one comparison)")
        rec["word_uncorrected"] = word(d.estimate.lo, d.estimate.hi, margin) if d.enough_seeds else None
    return rec


def overall_terms(a: Sequence[CellResult], b: Sequence[CellResult]) -> list[tuple[float, int, int]] | None:
    """A's overall minus B's on the episodes pooled over each side's ``cells``: the episodes' floor's terms."""
    return episode_terms({"a": a, "b": b}, [(1.0, "a", "overall"), (-1.0, "b", "overall")])


def floored(d: Difference, terms: list[tuple[float, int, int]] | None, level: float = LEVEL) -> Difference:
    """``d`` widened to the episodes' interval of the same contrast (``seed_stats.with_episode_floor``),
    as every difference in the report is: seeds that agree leave the t-interval no width."""
    return with_episode_floor(d, terms, level=level) if terms else d


def ranking(an: Analysis, order: Sequence[str] = ()) -> list[str]:
    """The rows with at least ``MIN_SEEDS`` seeds by overall success (mean over seeds), best first; equal
    means keep ``order`` (the catalogue's), then the name (the sort is stable)."""
    return sorted(in_catalogue_order((r for r in an.rows if len(an.rows[r]) >= MIN_SEEDS), order),
                  key=lambda r: -an.estimates[r][4].mean)


def apart(an: Analysis, order: Sequence[str] = ()) -> list[str]:
    """The rows with fewer than ``MIN_SEEDS`` seeds, in the catalogue's order (``order``), then by name:
    listed apart, never ranked."""
    return in_catalogue_order((r for r in an.rows if len(an.rows[r]) < MIN_SEEDS), order)


def in_catalogue_order(rows: Iterable[str], order: Sequence[str]) -> list[str]:
    """``rows`` in the catalogue's order (``order``), the rows outside it after, by name."""
    order = list(order)
    return sorted(rows, key=lambda r: (order.index(r) if r in order else len(order), r))


def one_sided_bounds(a: Mapping[int, float], b: Mapping[int, float], confidence: float,
                     terms: Sequence[tuple[float, int, int]] | None = None) -> tuple[float, float, float]:
    """(A - B, lower, upper): the one-sided ``confidence`` bounds of mu_A - mu_B (each a one-sided interval
    of its own), paired over the seeds both have (``scipy.stats.ttest_rel``), Welch's where they share none
    (``ttest_ind(equal_var=False)``); -inf / +inf where there is no spread to estimate (fewer than two paired
    seeds, or one seed on a side). With the pooled episodes' ``terms`` (``overall_terms``), each bound is
    pushed out to the same contrast's one-sided bound at ``confidence`` (the two-sided MOVER interval at
    2 x confidence - 1), as the episodes' floor widens every interval of the report."""
    est, lo, hi = _t_bounds(a, b, confidence)
    if terms and math.isfinite(lo) and math.isfinite(hi):
        ep_lo, ep_hi = contrast_interval(terms, 2.0 * confidence - 1.0)
        lo, hi = min(lo, ep_lo), max(hi, ep_hi)
    return est, lo, hi


def _t_bounds(a: Mapping[int, float], b: Mapping[int, float], confidence: float) -> tuple[float, float, float]:
    """``one_sided_bounds`` from the seeds alone."""
    shared = sorted(set(a) & set(b))
    if shared:
        x, y = np.array([a[s] for s in shared]), np.array([b[s] for s in shared])
        est = float(np.mean(x - y))
        if len(shared) < 2:
            return est, -math.inf, math.inf
        if no_spread(x - y):  # one difference up to float rounding: known exactly (scipy would warn)
            return est, est, est
        test = lambda alt: stats.ttest_rel(x, y, alternative=alt)  # noqa: E731
    else:
        x, y = np.array(list(a.values()), float), np.array(list(b.values()), float)
        est = float(x.mean() - y.mean())
        if len(x) < 2 or len(y) < 2:
            return est, -math.inf, math.inf
        if no_spread(x) and no_spread(y):
            return est, est, est
        test = lambda alt: stats.ttest_ind(x, y, equal_var=False, alternative=alt)  # noqa: E731
    lo = float(test("greater").confidence_interval(confidence).low)
    hi = float(test("less").confidence_interval(confidence).high)
    return est, lo, hi


def _mcb(pairs: Mapping[tuple[str, str], tuple[Mapping[int, float], Mapping[int, float]]], rows: Sequence[str],
         margin: float, alpha: float = ALPHA,
         terms: Mapping[tuple[str, str], Sequence[tuple[float, int, int]] | None] | None = None,
         ) -> tuple[dict[str, Any], dict[tuple[str, str], Bounds]]:
    """MCB from each unordered pair's per-seed values (A's, B's) and, where given, its pooled episodes'
    ``terms`` (the floor, ``one_sided_bounds``): the intervals, the words and G, and the one-sided
    (estimate, lower, upper) bounds of every ordered pair they were read from. A pair with too few seeds for a
    claim's verdict (``seed_stats.seeds_suffice``) gets no bounds (-inf, +inf): it bounds no row's interval."""
    k = len(rows)
    if k < 2:
        return {"rows": [], "best": list(rows), "confidence": None, "comparisons": 0}, {}
    q = 1.0 - alpha / (k - 1)
    bounds = {}
    for (i, j), (va, vb) in pairs.items():
        est, lo, hi = one_sided_bounds(va, vb, q, (terms or {}).get((i, j)))
        if not seeds_suffice(compared_seeds(va, vb)):
            lo, hi = -math.inf, math.inf
        bounds[i, j], bounds[j, i] = (est, lo, hi), (-est, -hi, -lo)
    # Hsu's U_i = max(0, min_j up_ij), G = {i : U_i > 0}, L_i = 0 if G = {i} else min(0, min_{j in G} lo_ij)
    upper = {i: max(0.0, min(bounds[i, j][2] for j in rows if j != i)) for i in rows}
    g = [i for i in rows if upper[i] > 0]
    out = []
    for i in rows:
        lower = 0.0 if g == [i] else min([0.0] + [bounds[i, j][1] for j in g if j != i])
        if g == [i]:
            w = AHEAD
        elif upper[i] <= 0:
            w = BEHIND
        elif -margin < lower and upper[i] < margin:
            w = equivalent(margin)
        else:
            w = NOT_SEPARATED
        out.append({"row": i, "estimate": min(bounds[i, j][0] for j in rows if j != i),
                    "lo": _finite(lower), "hi": _finite(upper[i]), "word": w})
    return {"rows": out, "best": g, "confidence": q, "comparisons": k - 1}, bounds


def best(an: Analysis, ranked: Sequence[str], margin: float) -> dict[str, Any] | None:
    """"Which row drives best" for the report: MCB over the ``ranked`` rows, each pair on the cells
    ``analysis.pair_cells`` gives it (one CPU kind where it can be, the seeds both ran), with each pair's
    difference, test and MCB's bounds; None with fewer than two ranked rows."""
    if len(ranked) < 2:
        return None
    cells = {(i, j): an.pair(i, j) for x, i in enumerate(ranked) for j in ranked[x + 1:]}
    values = {ij: tuple({c.seed: c.value("overall") for c in cs} for cs in (p.a, p.b)) for ij, p in cells.items()}
    terms = {ij: overall_terms(p.a, p.b) for ij, p in cells.items()}
    res, bounds = _mcb(values, ranked, margin, terms=terms)
    pairs = []
    level = family_level(len(values))  # a pair's own word: Bonferroni over every pair of ranked rows
    for (i, j), (va, vb) in values.items():
        d, note = floored(difference(va, vb), terms[i, j]), cells[i, j].note()
        pairs.append({"a": i, "b": j, "measured": d.estimate.as_dict(),
                      "method": d.method + (f", {note}" if note else ""),
                      "lower": _finite(bounds[i, j][1]), "upper": _finite(bounds[i, j][2]),
                      "word": word_record(floored(difference(va, vb, level=level), terms[i, j], level), margin, level,
                                          f"Bonferroni over the {len(values)} pairs of ranked rows")})
    k = len(ranked)
    return {**res, "pairs": pairs, "procedure": f"Hsu's MCB over the {k} rows with >= {MIN_SEEDS} seeds, Bonferroni "
                                                f"over each row's {k - 1} comparisons (one-sided "
                                                f"{100 * res['confidence']:.2f}% bounds), 95% jointly"}


def _finite(v: float) -> float | None:
    return None if math.isinf(v) else v


def forest(an: Analysis, ranked: Sequence[str], paper: Mapping[str, Sequence[float]], margin: float,
           few: Sequence[str] = ()) -> list[dict[str, Any]]:
    """Every ranked row's overall success minus CIL's (``overall_difference``), in ``ranked`` order, its word
    read on the Bonferroni interval over the ranked rows' comparisons with CIL, then the rows with too few
    seeds (``few``), marked ``apart``, with no word; each with the paper's difference (its Table 4 means; None
    for a row it gives no values). Empty without CIL."""
    if BASELINE not in an.rows:
        return []
    base = paper.get(BASELINE)
    size = sum(r != BASELINE for r in ranked)
    out = []
    for r in [*ranked, *few]:
        if r == BASELINE:
            continue
        rec = overall_difference(an, r, BASELINE, margin, size) if r in ranked else \
            {**overall_difference(an, r, BASELINE), "apart": True}
        rec["paper"] = (round(float(np.mean(paper[r])) - float(np.mean(base)), 2)
                        if paper.get(r) and base else None)
        out.append(rec)
    return out
