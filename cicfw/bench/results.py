"""The paper's comparison as results: per-cell outcomes -> Table 4 with 95% intervals -> a verdict per claim.

A *cell* is one (row, seed) of a reproduction: a model trained with that seed and driven on the suite;
``cell.json`` keeps every episode's outcome. Everything here is numpy/scipy/statsmodels over those
outcomes, so ``cicfw report`` and the tests use it without training anything. *Overall* is always the
mean of the four table columns (each column weighs the same, as in reading the paper's table), never the
success pooled over all episodes; a seed's overall is the mean of its four column rates.

**Intervals (primary): the seed is the unit of replication.** A row's value in a column is the mean over
its seeds of each seed's success rate there; its 95% interval is Student's t-interval over those per-seed
rates, ``mean ± t_{0.975, n-1} · sd / sqrt(n)`` (``scipy.stats.t``; ``sd`` with ``n - 1``), widened, in a
table column, to contain the Clopper-Pearson interval of the episodes pooled over the seeds
(``statsmodels ... proportion_confint(method="beta")``), so that seeds that all drove 100% (or 0%) do not
get a zero-width interval. A row with one seed has no interval. A difference between two rows (A - B) is
computed on per-seed values: when both rows ran the same seeds (the same seed trains on the same
train/validation split, so the cells are paired), the t-interval over the per-seed differences
``A_s - B_s`` with ``n - 1`` degrees of freedom; when their seeds differ, Welch's t-interval
(``scipy.stats.ttest_ind(equal_var=False)``, Welch-Satterthwaite degrees of freedom) over all seeds of
each; on one table column (or a gap between two table columns) it too is widened, to contain the interval
of the same contrast of the two rows' success on their pooled episodes (Zou & Donner's MOVER from each
proportion's Wilson interval, ``statsmodels ... proportion_confint(method="wilson")``; on one column this is
Newcombe's hybrid score interval), and its p-value is then the larger of the t-test's and the one dual to
that interval, so seeds whose differences happen to agree (a column's rates come in steps of 1/64 or 1/96,
an easy column often sits at 100%) do not get a zero-width interval and p = 0; the method column says
"widened to the episodes' interval" where it moved a bound. Overall and a town's or weather's mean of two
columns keep their t-interval, as a row's overall does. A relative change (``A / B - 1``) gets Fieller's
interval for a ratio of means, with the same variances, covariance (paired) and degrees of freedom; it is
unbounded when B is not clearly above 0.
Simulated experiments with a known truth (``tests/test_results_coverage.py``) check that these intervals
cover the truth in at least 93% of experiments at 3 and at 5 seeds.

Whether a row's seeds differ beyond the episodes' luck (the premise of the seed as the unit) is tested per
row and column by ``cicfw.bench.seed_spread`` and shown as a table of its own.

**Secondary: the episode bootstrap.** Beside it, for comparison with earlier reports, a two-level
percentile bootstrap (``n_boot`` replicates): each replicate draws the row's seeds with replacement and,
within each table column, the suite's episodes with replacement (one episode draw shared by every row:
rows drove the same episodes); the statistic is the mean over the drawn seeds of the success on the drawn
episodes; the interval is its 2.5th..97.5th percentile. With few seeds it is too narrow (3 seeds have only
10 distinct seed draws; in the coverage simulation it covers the true difference in about 90% of
experiments at 3 seeds and 93% at 5, where the paired t-interval covers 95%): it is not used for a
verdict.

**Verdicts.** Each claim of the paper (``claims:`` in ``conf/reproduce.yaml``, with its sentence quoted)
is one or more tested parts, each a difference A - B of per-seed values on a column, the mean of some
columns, or a change of the gap between two columns. Each part's test is the two-sided t-test of that
difference against 0 (paired t-test on the per-seed differences, or Welch's), so the uncorrected verdict
and the 95% interval agree: *significant* means the interval excludes 0. A part ``greater`` (A beats B)
is *supported* when A - B is significantly above 0, *contradicted* when significantly below,
*inconclusive* otherwise; ``less`` is its mirror; ``not_greater`` ("A failed to improve on B") is
*contradicted* only when A is significantly better than B and *supported* otherwise. A part whose rows
have fewer than 3 seeds (either row) gets no verdict: *too few seeds* (its difference is still shown).
**Family-wise control:** the family is fixed in advance, every part of every claim in the list (a part
without a verdict, its rows not run or short of seeds, counts as p = 1), adjusted by Holm's step-down
method (``statsmodels.stats.multitest.multipletests(method="holm")``, family-wise error 5%), so a Holm
verdict does not weaken when another row's cells arrive; the Holm verdict uses the adjusted p-value in place of the interval and is shown beside the
uncorrected one. A claim of several parts is *contradicted* when any part is, *not run* when a part's rows
were not run, *too few seeds* when a part lacks seeds, *supported* when every part is, *inconclusive*
otherwise.

**Resumed cells.** A cell whose training was stopped and resumed from an epoch checkpoint records it in
``cell.json`` (``resumed``); the report marks its row and seed (‡) with a footnote: a resumed training does
not restore the data pipeline's and augmentation's random state, so its numbers can differ from an
uninterrupted run's (``RESUME_EXAMPLE``). Every file written here is readable by others as the umask allows
(0644 under umask 022), like any file the user writes, not owner-only as a bare temporary file would be.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import stats

from cicfw.bench.runs import cell_key, cell_name
from cicfw.bench.seed_spread import seed_spread
from cicfw.files import atomic_write
from cicfw.bench.suite import CELLS

COLUMNS = tuple(cell_key(*c) for c in CELLS)  # training_town/training_weathers ... new_town/new_weathers
COLUMN_NAMES = tuple(cell_name(*c) for c in CELLS)
SUPPORTED, CONTRADICTED, INCONCLUSIVE, NOT_RUN = "supported", "contradicted", "inconclusive", "not run"
TOO_FEW = "too few seeds"
LEVEL = 0.95
ALPHA = 1.0 - LEVEL
#: a row needs this many seeds for a verdict (fewer: reported, "too few seeds")
MIN_SEEDS = 3
#: what a part of a claim compares: one table column, or the mean of several (overall: all four)
SELECTORS: dict[str, tuple[int, ...]] = {
    **{c: (i,) for i, c in enumerate(COLUMNS)},
    "overall": (0, 1, 2, 3),
    "training_town": (0, 1), "new_town": (2, 3), "training_weathers": (0, 2), "new_weathers": (1, 3),
}
SELECTOR_NAMES = {**dict(zip(COLUMNS, COLUMN_NAMES)), "overall": "overall", "training_town": "training town",
                  "new_town": "new town", "training_weathers": "training weathers", "new_weathers": "new weathers"}
TESTS = ("greater", "less", "not_greater")
#: what resuming a killed training changed, measured (issue 17): the report's footnote on resumed cells
RESUME_EXAMPLE = ("measured once: GTU's validation steering error after its last epoch was 0.12519 uninterrupted "
                  "and 0.12743 when the run was killed after epoch 1 and resumed")
RESUMED_MARK = "‡"


@dataclass
class CellResult:
    """One finished (row, seed) cell: every episode's success, keyed by episode key."""

    row: str
    seed: int
    episodes: dict[str, dict[str, Any]]  # key -> {"success": bool, "column": str, "command": str}
    meta: dict[str, Any] = field(default_factory=dict)

    def rate(self, column: str | None = None) -> float:
        """Success (%) on one table column, or the mean of the four columns (``None``)."""
        if column is None:
            return float(np.mean([self.rate(c) for c in COLUMNS]))
        v = [e["success"] for e in self.episodes.values() if e["column"] == column]
        return 100.0 * float(np.mean(v)) if v else float("nan")

    def value(self, on: str) -> float:
        """Success (%) on a selector of ``SELECTORS``: the mean of its columns' rates."""
        return float(np.mean([self.rate(COLUMNS[i]) for i in SELECTORS[on]]))

    def counts(self, column: str, command: str | None = None) -> tuple[int, int]:
        """(successes, episodes) in one table column, or in its episodes of one command."""
        v = [bool(e["success"]) for e in self.episodes.values()
             if e["column"] == column and (command is None or e.get("command") == command)]
        return sum(v), len(v)


def load_cell(path: Path) -> CellResult | dict[str, Any]:
    """One ``cell.json``: its CellResult when it finished (status ok), else the file's dict as it is."""
    d = json.loads(Path(path).read_text())
    if d.get("status") == "ok":
        return CellResult(row=d["row"], seed=int(d["seed"]), episodes=d["episodes"], meta=d)
    return d


def load_cells(results_dir: Path) -> tuple[list[CellResult], list[dict[str, Any]]]:
    """The finished cells (status ok) and the failed ones (their cell.json) under ``results_dir``."""
    ok, failed = [], []
    for p in sorted(Path(results_dir).glob("cells/*/seed*/cell.json")):
        c = load_cell(p)
        (ok if isinstance(c, CellResult) else failed).append(c)
    return ok, failed


# ------------------------------------------------------------------------------------------------
# intervals over seeds (primary)


def t_quantile(n: int | np.ndarray, level: float = LEVEL) -> np.ndarray:
    """Student's t quantile ``t_{(1+level)/2, n-1}`` for ``n`` seeds (scipy.stats.t)."""
    return stats.t.ppf(0.5 + level / 2.0, np.asarray(n) - 1)


def t_interval(values: np.ndarray, level: float = LEVEL, axis: int = -1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, lo, hi) of the t-interval over ``values`` along ``axis`` (the seeds):
    ``mean ± t_{(1+level)/2, n-1} · sd / sqrt(n)``, sd with n - 1 (vectorised over the other axes).
    With one value the bounds are NaN."""
    v = np.asarray(values, dtype=float)
    n = v.shape[axis]
    mean = v.mean(axis=axis)
    if n < 2:
        nan = np.full_like(mean, np.nan)
        return mean, nan, nan
    half = t_quantile(n, level) * v.std(axis=axis, ddof=1) / math.sqrt(n)
    return mean, mean - half, mean + half


def paired_t_interval(a: np.ndarray, b: np.ndarray, level: float = LEVEL,
                      axis: int = -1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A - B paired by seed: the t-interval over the per-seed differences ``a_s - b_s`` (n - 1 df)."""
    return t_interval(np.asarray(a, dtype=float) - np.asarray(b, dtype=float), level, axis)


def welch_t_interval(a: np.ndarray, b: np.ndarray, level: float = LEVEL,
                     axis: int = -1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A - B over unpaired seeds: Welch's t-interval (``scipy.stats.ttest_ind(equal_var=False)``,
    Welch-Satterthwaite degrees of freedom), vectorised over the other axes."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ci = stats.ttest_ind(a, b, equal_var=False, axis=axis).confidence_interval(level)
    return a.mean(axis=axis) - b.mean(axis=axis), np.asarray(ci.low), np.asarray(ci.high)


def pooled_clopper_pearson(successes: int, episodes: int, level: float = LEVEL) -> tuple[float, float]:
    """The Clopper-Pearson interval (%) of ``successes`` of ``episodes`` (statsmodels, method "beta")."""
    from statsmodels.stats.proportion import proportion_confint

    lo, hi = proportion_confint(successes, episodes, alpha=1.0 - level, method="beta")
    return 100.0 * float(lo), 100.0 * float(hi)


def ratio_interval(a: Sequence[float], b: Sequence[float], paired: bool,
                   level: float = LEVEL) -> tuple[float, float | None, float | None]:
    """(ratio, lo, hi) of mean(A) / mean(B) by Fieller's theorem: the set of R with
    ``(mean_a - R mean_b)^2 <= t^2 · (v_a - 2 R c + R^2 v_b)``, where v_a, v_b are the variances of the two
    means (sd^2 / n), c their covariance (paired seeds; 0 otherwise) and t the quantile with n - 1 df
    (paired) or Welch-Satterthwaite df at the estimated ratio (unpaired). Bounds are None when the set is
    not a bounded interval (B not clearly above 0)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ma, mb = float(a.mean()), float(b.mean())
    ratio = ma / mb if mb != 0 else float("nan")
    if len(a) < 2 or len(b) < 2 or mb == 0:
        return ratio, None, None
    va, vb = float(a.var(ddof=1)) / len(a), float(b.var(ddof=1)) / len(b)
    if paired:
        c = float(np.cov(a, b, ddof=1)[0, 1]) / len(a)
        df = len(a) - 1
    else:
        c = 0.0
        r2vb = ratio ** 2 * vb
        den = va ** 2 / (len(a) - 1) + r2vb ** 2 / (len(b) - 1)
        df = (va + r2vb) ** 2 / den if den > 0 else float(min(len(a), len(b)) - 1)
    q2 = float(stats.t.ppf(0.5 + level / 2.0, df)) ** 2
    qa, qb, qc = mb * mb - q2 * vb, ma * mb - q2 * c, ma * ma - q2 * va  # qa R^2 - 2 qb R + qc <= 0
    disc = qb * qb - qa * qc
    if qa <= 0 or disc < 0:
        return ratio, None, None
    root = math.sqrt(disc)
    return ratio, (qb - root) / qa, (qb + root) / qa


@dataclass
class Estimate:
    mean: float
    lo: float | None
    hi: float | None

    def as_dict(self) -> dict[str, float | None]:
        r = lambda v: None if v is None or (isinstance(v, float) and math.isnan(v)) else round(float(v), 2)  # noqa: E731
        return {"mean": r(self.mean), "lo": r(self.lo), "hi": r(self.hi)}

    def fmt(self, sign: str = "") -> str:
        d = self.as_dict()
        if d["lo"] is None or d["hi"] is None:
            return f"{self.mean:{sign}.1f}"
        return f"{self.mean:{sign}.1f} [{self.lo:{sign}.1f}, {self.hi:{sign}.1f}]"


def pooled_counts(cells: Sequence[CellResult], column: str) -> tuple[int, int]:
    """(successes, episodes) in one table column, pooled over ``cells``: the episodes' floor's input."""
    k, n = (sum(x) for x in zip(*(c.counts(column) for c in cells)))
    return k, n


def row_estimate(cells: Sequence[CellResult], on: str, level: float = LEVEL) -> Estimate:
    """A row's mean over seeds on ``on`` with its t-interval over seeds; on a single table column the
    interval is widened to contain the pooled episodes' Clopper-Pearson interval. No interval for one seed."""
    v = np.array([c.value(on) for c in cells])
    mean, lo, hi = (float(x) for x in t_interval(v, level))
    if len(v) < 2:
        return Estimate(mean, None, None)
    if len(SELECTORS[on]) == 1:
        col = COLUMNS[SELECTORS[on][0]]
        cp_lo, cp_hi = pooled_clopper_pearson(*pooled_counts(cells, col), level)
        lo, hi = min(lo, cp_lo), max(hi, cp_hi)
    return Estimate(mean, max(lo, 0.0), min(hi, 100.0))  # a rate lies in [0, 100]


@dataclass
class Difference:
    """One tested difference A - (scale) B on per-seed values: its estimate, two-sided p-value and method."""

    estimate: Estimate
    p: float | None
    method: str
    paired: bool
    n: tuple[int, int]

    @property
    def enough_seeds(self) -> bool:
        return min(self.n) >= MIN_SEEDS


def difference(a: Mapping[int, float], b: Mapping[int, float], level: float = LEVEL) -> Difference:
    """A - B from per-seed values (seed -> value): paired t when both have the same seeds, else Welch's t.
    The p-value is the two-sided t-test's (``scipy.stats.ttest_1samp`` on the differences, or
    ``ttest_ind(equal_var=False)``); with no spread at all it is 0 (a difference) or 1 (none)."""
    na, nb = len(a), len(b)
    if sorted(a) == sorted(b):
        d = np.array([a[s] - b[s] for s in sorted(a)])
        mean, lo, hi = (float(x) for x in t_interval(d, level))
        if na < 2:
            return Difference(Estimate(mean, None, None), None, "1 seed", True, (na, nb))
        if np.ptp(d) == 0:
            p = 1.0 if mean == 0 else 0.0
        else:
            p = float(stats.ttest_1samp(d, 0.0).pvalue)
        return Difference(Estimate(mean, lo, hi), p, f"paired t, {na} seeds", True, (na, nb))
    va, vb = np.array(list(a.values()), dtype=float), np.array(list(b.values()), dtype=float)
    mean = float(va.mean() - vb.mean())
    method = f"Welch t, {na} vs {nb} seeds"
    if na < 2 or nb < 2:
        return Difference(Estimate(mean, None, None), None, method, False, (na, nb))
    if np.ptp(va) == 0 and np.ptp(vb) == 0:
        return Difference(Estimate(mean, mean, mean), 1.0 if mean == 0 else 0.0, method, False, (na, nb))
    _, lo, hi = welch_t_interval(va, vb, level)
    p = float(stats.ttest_ind(va, vb, equal_var=False).pvalue)
    return Difference(Estimate(mean, float(lo), float(hi)), p, method, False, (na, nb))


def episode_interval(terms: Sequence[tuple[float, int, int]], level: float = LEVEL) -> tuple[float, float, float]:
    """A contrast of table columns on the episodes pooled over each row's seeds, ``sum c * k / n`` over
    ``terms`` of ``(c, successes, episodes)``, in points: its interval (``contrast_interval``; A - B is
    Newcombe's) and the two-sided p-value dual to it, the level at which the bound nearer 0 reaches 0 (1
    when the contrast is 0). The rows drove the same episodes, and treating them as independent ignores
    that pairing, which widens the interval: it is a floor for the episodes' luck, not an estimate of its own."""
    lo, hi = contrast_interval(terms, level)
    value = sum(c * k / n for c, k, n in terms)
    if abs(value) < 1e-12:
        return lo, hi, 1.0
    return lo, hi, contrast_level(terms, "lo" if value > 0 else "hi", 0.0)


def contrast_level(terms: Sequence[tuple[float, int, int]], bound: str, target: float) -> float:
    """The alpha at which the two-sided (1 - alpha) ``contrast_interval``'s ``bound`` ("lo" or "hi")
    reaches ``target`` (points) as the interval narrows toward the contrast itself: the p-value dual to
    the interval (root-found). 0 when even the (1 - 1e-12) interval's bound lies beyond ``target``, 1 when
    the contrast itself does not."""
    from scipy.optimize import brentq

    i, sign = (0, 1.0) if bound == "lo" else (1, -1.0)

    def past(alpha: float) -> float:  # > 0 once the bound has moved past target, toward the contrast
        return sign * (contrast_interval(terms, 1.0 - alpha)[i] - target)

    tiny, near_one = 1e-12, 1.0 - 1e-9  # at alpha -> 1 the interval shrinks to the contrast itself
    if past(near_one) <= 0:
        return 1.0
    return 0.0 if past(tiny) > 0 else float(brentq(past, tiny, near_one, xtol=1e-12))


def contrast_interval(terms: Sequence[tuple[float, int, int]], level: float = LEVEL) -> tuple[float, float]:
    """``sum c * k / n`` of independent proportions, in points: the MOVER interval (Zou & Donner 2008),
    which recovers each side's variance from the proportions' Wilson score intervals (statsmodels), so it
    keeps a width at 0% and 100%; for one difference, ``[(1, A), (-1, B)]``, it is Newcombe's hybrid score
    interval, and for a gap, ``(A - B)`` in one column minus ``(A - B)`` in another, its four-term form."""
    from statsmodels.stats.proportion import proportion_confint

    value, below, above = 0.0, 0.0, 0.0
    for c, k, n in terms:
        p = k / n
        lo, hi = (float(x) for x in proportion_confint(k, n, alpha=1.0 - level, method="wilson"))
        down, up = (p - lo, hi - p) if c > 0 else (hi - p, p - lo)  # a negative coefficient swaps the sides
        value, below, above = value + c * p, below + (c * down) ** 2, above + (c * up) ** 2
    return 100.0 * (value - math.sqrt(below)), 100.0 * (value + math.sqrt(above))


def difference_terms(a: tuple[int, int], b: tuple[int, int]) -> list[tuple[float, int, int]]:
    """A - B, each ``(successes, episodes)``, as the terms of a contrast (``contrast_interval``)."""
    return [(1.0, *a), (-1.0, *b)]


def with_episode_floor(d: Difference, terms: Sequence[tuple[float, int, int]], level: float = LEVEL) -> Difference:
    """``d`` (a contrast of table columns between rows A and B, its ``terms`` the pooled episodes)
    widened to contain the episodes' interval (``episode_interval``), its p-value the larger of the two:
    seeds whose differences happen to agree (rates come in steps of 1/64, and an easy column often sits at
    100% for every seed) leave the t-interval no width, but never remove the episodes' luck. The method
    says so where the floor moved a bound."""
    e = d.estimate
    if e.lo is None or e.hi is None or d.p is None:
        return d
    lo, hi, p = episode_interval(terms, level)
    if lo >= e.lo and hi <= e.hi and p <= d.p:
        return d
    return Difference(Estimate(e.mean, min(e.lo, lo), max(e.hi, hi)), max(d.p, p),
                      d.method + ", widened to the episodes' interval", d.paired, d.n)


def holm_family_size(claims: Sequence[Mapping[str, Any]]) -> int:
    """Holm's family, fixed in advance: every part of every claim, whether it could be tested or not."""
    return sum(len(c["parts"]) for c in claims)


def holm(pvalues: Sequence[float], alpha: float = ALPHA,
         family_size: int | None = None) -> tuple[list[float], list[bool]]:
    """Holm's step-down adjustment of a family of p-values (statsmodels ``multipletests``, method "holm"):
    the adjusted p-values and which are rejected at family-wise error ``alpha``.

    ``family_size``: the family fixed in advance, of which ``pvalues`` are the members tested so far; the
    untested ones count as p = 1 (they can reject nothing), so a verdict reached here can only stay
    reached as they are filled in (Holm's procedure is monotone in every p-value)."""
    if not len(pvalues):
        return [], []
    from statsmodels.stats.multitest import multipletests

    n = len(pvalues)
    if family_size is not None and family_size < n:
        raise ValueError(f"a family of {family_size} cannot hold {n} p-values")
    padded = list(pvalues) + [1.0] * ((family_size or n) - n)
    reject, adj, _, _ = multipletests(padded, alpha=alpha, method="holm")
    return [float(x) for x in adj[:n]], [bool(x) for x in reject[:n]]


# ------------------------------------------------------------------------------------------------
# the two-level episode bootstrap (secondary)


def _matrix(cells: Sequence[CellResult], keys: Sequence[str]) -> np.ndarray:
    """(seeds, episodes) success matrix of one row's cells, episodes in ``keys`` order."""
    return np.array([[float(c.episodes[k]["success"]) for k in keys] for c in cells])


def bootstrap_replicates(m: np.ndarray, ep_draws: Mapping[str, np.ndarray], rng: np.random.Generator,
                         n_boot: int) -> np.ndarray:
    """(n_boot, 5) two-level bootstrap replicates of [column rates..., overall] (in %) of one row whose
    (seeds, episodes) success matrix is ``m``: the seeds drawn with replacement, the episodes of each
    column drawn by ``ep_draws`` (shared across rows)."""
    s = m.shape[0]
    seeds = rng.integers(0, s, size=(n_boot, s))  # seed draw, per replicate
    cols = []
    for c in COLUMNS:
        per_seed_rates = m[:, ep_draws[c]].mean(axis=2).T  # (n_boot, S): each seed on the drawn episodes
        cols.append(np.take_along_axis(per_seed_rates, seeds, axis=1).mean(axis=1))
    out = 100.0 * np.stack(cols, axis=1)
    return np.concatenate([out, out.mean(axis=1, keepdims=True)], axis=1)


def episode_draws(keys: Sequence[str], columns: Sequence[str], rng: np.random.Generator,
                  n_boot: int) -> dict[str, np.ndarray]:
    """Per table column, ``n_boot`` draws (with replacement) of that column's episode positions."""
    cols = np.asarray(columns)
    out = {}
    for c in COLUMNS:
        pos = np.flatnonzero(cols == c)
        if len(pos) == 0:
            raise ValueError(f"the suite has no episode in column {c!r}: the table needs all four columns")
        out[c] = pos[rng.integers(0, len(pos), size=(n_boot, len(pos)))]
    return out


def percentile_interval(samples: np.ndarray, level: float = LEVEL) -> tuple[float, float]:
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(samples, [a, 1.0 - a])
    return float(lo), float(hi)


def _boot_value(rep: np.ndarray, on: str) -> np.ndarray:
    return rep[:, list(SELECTORS[on])].mean(axis=1)


# ------------------------------------------------------------------------------------------------
# the analysis of one results folder


@dataclass
class Analysis:
    """Every row's estimates (per column + overall): t-intervals over seeds (primary) and the two-level
    episode bootstrap (secondary, with its replicates, all on one episode draw)."""

    rows: dict[str, list[CellResult]]
    estimates: dict[str, list[Estimate]]  # row -> 5 estimates (4 columns + overall), t over seeds
    bootstrap: dict[str, list[Estimate]]  # row -> 5 estimates, the episode bootstrap
    replicates: dict[str, np.ndarray]  # row -> (n_boot, 5)
    n_boot: int

    def per_seed(self, row: str, on: str) -> dict[int, float]:
        return {c.seed: c.value(on) for c in self.rows[row]}


def analyse(cells: Sequence[CellResult], n_boot: int = 4000, seed: int = 0) -> Analysis:
    """Group cells by row, check they drove the same episodes, estimate every row (t over seeds) and
    bootstrap it (secondary)."""
    rows: dict[str, list[CellResult]] = {}
    for c in sorted(cells, key=lambda c: (c.row, c.seed)):
        rows.setdefault(c.row, []).append(c)
    if not rows:
        raise ValueError("no finished cell to analyse")
    first = next(iter(rows.values()))[0]
    keys = sorted(first.episodes)
    for row, cs in rows.items():
        for c in cs:
            if sorted(c.episodes) != keys:
                raise ValueError(f"cell {row}/seed{c.seed} drove other episodes than {first.row}/seed{first.seed}: "
                                 f"cells of one results folder must share the suite")
    columns = [first.episodes[k]["column"] for k in keys]
    rng = np.random.default_rng(seed)
    draws = episode_draws(keys, columns, rng, n_boot)
    reps, est, boot = {}, {}, {}
    for row, cs in rows.items():
        reps[row] = bootstrap_replicates(_matrix(cs, keys), draws, rng, n_boot)
        est[row] = [row_estimate(cs, on) for on in [*COLUMNS, "overall"]]
        boot[row] = [Estimate(e.mean, *percentile_interval(reps[row][:, i])) for i, e in enumerate(est[row])]
    return Analysis(rows=rows, estimates=est, bootstrap=boot, replicates=reps, n_boot=n_boot)


# ------------------------------------------------------------------------------------------------
# the paper's claims (data: ``claims:`` in conf/reproduce.yaml)


@dataclass(frozen=True)
class Part:
    """One tested part of a claim: A - b_scale x B on ``on`` (a selector), or, with ``on="gap"``, A's
    advantage over B on ``hard`` minus that on ``easy``; ``test`` says which way the claim goes
    (``greater``, ``less``, ``not_greater``); ``relative`` also reports A / B - 1."""

    a: str
    b: str
    on: str = "overall"
    test: str = "greater"
    relative: bool = False
    hard: str | None = None
    easy: str | None = None
    b_scale: float = 1.0

    def text(self, labels: Mapping[str, str]) -> str:
        la, lb = labels.get(self.a, self.a), labels.get(self.b, self.b)
        lb = lb if self.b_scale == 1.0 else f"{self.b_scale:g} x {lb}"
        if self.on == "gap":
            return (f"{la} − {lb} larger in {SELECTOR_NAMES[self.hard]} than in {SELECTOR_NAMES[self.easy]}"
                    if self.test != "less" else
                    f"{la} − {lb} smaller in {SELECTOR_NAMES[self.hard]} than in {SELECTOR_NAMES[self.easy]}")
        op = {"greater": ">", "less": "<", "not_greater": "not better than"}[self.test]
        return f"{la} {op} {lb} ({SELECTOR_NAMES[self.on]})"

    def values(self, per_seed: Any, row: str) -> dict[int, float]:
        """The per-seed statistic of ``row`` this part compares (``per_seed(row, on)`` gives a selector's)."""
        if self.on == "gap":
            hard, easy = per_seed(row, self.hard), per_seed(row, self.easy)
            return {s: hard[s] - easy[s] for s in hard}
        return per_seed(row, self.on)

    def paper(self, paper: Mapping[str, Sequence[float]]) -> float | None:
        """The paper's value of this difference (from its Table 4), None when a row has no paper values."""
        if not paper.get(self.a) or not paper.get(self.b):
            return None
        val = lambda row, on: float(np.mean([paper[row][i] for i in SELECTORS[on]]))  # noqa: E731
        if self.on == "gap":
            return ((val(self.a, self.hard) - self.b_scale * val(self.b, self.hard))
                    - (val(self.a, self.easy) - self.b_scale * val(self.b, self.easy)))
        return val(self.a, self.on) - self.b_scale * val(self.b, self.on)

    def paper_relative(self, paper: Mapping[str, Sequence[float]]) -> float | None:
        if not self.relative or not paper.get(self.a) or not paper.get(self.b) or self.on == "gap":
            return None
        va, vb = (float(np.mean([paper[r][i] for i in SELECTORS[self.on]])) for r in (self.a, self.b))
        return va / vb - 1.0 if vb else None


@dataclass(frozen=True)
class Claim:
    id: str
    text: str
    parts: tuple[Part, ...]
    quote: str = ""
    source: str = ""


def load_claims(spec: Sequence[Mapping[str, Any]]) -> list[Claim]:
    """Claims from their data (``claims:`` in conf/reproduce.yaml), checked: one clear error per bad entry."""
    out = []
    for k, c in enumerate(spec or []):
        where = f"claims[{k}] ({c.get('id', '?')})"
        for key in ("id", "claim", "parts"):
            if not c.get(key):
                raise ValueError(f"{where} has no {key!r}; a claim needs id, claim, quote, source and parts")
        parts = []
        for j, p in enumerate(c["parts"]):
            p = dict(p)
            unknown = {str(k) for k in p} - {"a", "b", "column", "test", "relative", "hard", "easy", "b_scale"}
            if unknown or "a" not in p or "b" not in p:
                raise ValueError(f"{where} part {j}: needs a and b; accepted keys: a, b, column, test, relative, hard, "
                                 f"easy, b_scale" + (f" (unknown: {', '.join(sorted(unknown))})" if unknown else ""))
            on = p.get("column", "overall")
            sels = [p.get("hard"), p.get("easy")] if on == "gap" else [on]
            for s in sels:
                if s not in SELECTORS:
                    raise ValueError(f"{where} part {j}: unknown column {s!r}; accepted: {', '.join(SELECTORS)}"
                                     + (" (a gap needs hard and easy)" if on == "gap" else ", gap"))
            if p.get("test", "greater") not in TESTS:
                raise ValueError(f"{where} part {j}: unknown test {p.get('test')!r}; accepted: {', '.join(TESTS)}")
            parts.append(Part(a=str(p["a"]), b=str(p["b"]), on=on, test=p.get("test", "greater"),
                              relative=bool(p.get("relative", False)), hard=p.get("hard"), easy=p.get("easy"),
                              b_scale=float(p.get("b_scale", 1.0))))
        out.append(Claim(id=str(c["id"]), text=str(c["claim"]), parts=tuple(parts), quote=str(c.get("quote") or ""),
                         source=str(c.get("source") or "")))
    return out


def default_claims() -> list[Claim]:
    """The paper's claims as shipped in ``conf/reproduce.yaml`` (``claims:``), read as plain YAML (no Hydra
    state is touched, so this works inside a running app too)."""
    from importlib.resources import files

    import yaml

    return load_claims(yaml.safe_load(files("cicfw.conf").joinpath("reproduce.yaml").read_text())["claims"])


def part_verdict(test: str, mean: float, significant: bool) -> str:
    """A part's verdict from its direction and whether the difference is significant."""
    if test == "not_greater":
        return CONTRADICTED if significant and mean > 0 else SUPPORTED
    if not significant or mean == 0:
        return INCONCLUSIVE
    up = mean > 0
    return SUPPORTED if up == (test == "greater") else CONTRADICTED


def combine(verdicts: Sequence[str]) -> str:
    """A claim's verdict from its parts': contradicted > not run > too few seeds > inconclusive > supported."""
    if not verdicts:
        return NOT_RUN
    for v in (CONTRADICTED, NOT_RUN, TOO_FEW, INCONCLUSIVE):
        if v in verdicts:
            return v
    return SUPPORTED


def _excludes_zero(e: Estimate) -> bool:
    return e.lo is not None and e.hi is not None and (e.lo > 0 or e.hi < 0)


def _pct_change(r: float | None) -> float | None:
    return None if r is None or (isinstance(r, float) and math.isnan(r)) else round(100.0 * (r - 1.0), 1)


def judge(an: Analysis, claims: Sequence[Claim], paper: Mapping[str, Sequence[float]],
          labels: Mapping[str, str]) -> list[dict[str, Any]]:
    """Every claim with each part's measured difference (t-interval over seeds), its two-sided p-value,
    the Holm-adjusted p-value over the family of every claim's parts (fixed in advance: a part without a
    verdict counts as p = 1), the paper's difference, the episode
    bootstrap's interval (secondary) and the verdicts, uncorrected and Holm."""
    out, family = [], []
    for claim in claims:
        parts = []
        for p in claim.parts:
            rec: dict[str, Any] = {"comparison": p.text(labels), "test": p.test, "on": p.on, "paper": p.paper(paper)}
            if p.relative:
                rec["relative"] = {"paper": _pct_change(None if p.paper_relative(paper) is None
                                                        else 1.0 + p.paper_relative(paper))}
            if p.a not in an.rows or p.b not in an.rows:
                rec.update(verdict=NOT_RUN, verdict_holm=NOT_RUN, method="–")
                parts.append(rec)
                continue
            va, vb = p.values(an.per_seed, p.a), p.values(an.per_seed, p.b)
            d = difference(va, {s: p.b_scale * v for s, v in vb.items()})
            terms = episode_terms(an, p)
            if terms:  # on single table columns: the episodes' floor, as for a row
                d = with_episode_floor(d, terms)
            rec.update(measured=d.estimate.as_dict(), p=d.p, method=d.method, seeds=list(d.n),
                       means=[round(float(np.mean(list(va.values()))), 2), round(p.b_scale * float(np.mean(list(vb.values()))), 2)])
            rec["bootstrap"] = _boot_part(an, p).as_dict()
            if p.relative:
                r, lo, hi = ratio_interval([va[s] for s in sorted(va)], [vb[s] for s in sorted(vb)], d.paired)
                rec["relative"].update(mean=_pct_change(r), lo=_pct_change(lo), hi=_pct_change(hi))
            if not d.enough_seeds:
                rec.update(verdict=TOO_FEW, verdict_holm=TOO_FEW)
            else:
                rec["verdict"] = part_verdict(p.test, d.estimate.mean, _excludes_zero(d.estimate))
                family.append(rec)
            parts.append(rec)
        out.append({"id": claim.id, "claim": claim.text, "quote": claim.quote, "source": claim.source,
                    "parts": parts})
    # the family is fixed in advance: every part of every claim, tested or not (``holm``'s family_size)
    adjusted, reject = holm([r["p"] for r in family], family_size=holm_family_size(out))
    for rec, padj, rej in zip(family, adjusted, reject):
        rec["p_holm"] = padj
        rec["verdict_holm"] = part_verdict(rec["test"], rec["measured"]["mean"], rej)
    for c in out:
        c["verdict"] = combine([p["verdict"] for p in c["parts"]])
        c["verdict_holm"] = combine([p["verdict_holm"] for p in c["parts"]])
    return out


def episode_terms(an: Analysis, p: Part) -> list[tuple[float, int, int]] | None:
    """A part as a contrast of its rows' pooled episodes, ``(coefficient, successes, episodes)`` per
    row and column, for the episodes' floor; None where it is not made of single table columns (overall,
    a town or weather's mean of two columns: a mean of column rates, whose t-interval keeps its width) or
    B is scaled."""
    if p.b_scale != 1.0:
        return None
    sides = [(p.hard, 1.0), (p.easy, -1.0)] if p.on == "gap" else [(p.on, 1.0)]
    if any(col not in COLUMNS for col, _ in sides):
        return None
    return [(sign * side, *pooled_counts(an.rows[row], col))
            for col, sign in sides for row, side in ((p.a, 1.0), (p.b, -1.0))]


def _boot_part(an: Analysis, p: Part) -> Estimate:
    """A part's difference in the episode bootstrap's replicates (secondary): the same statistic on
    every replicate of A and B (paired by episode draw, seeds drawn per row)."""
    ra, rb = an.replicates[p.a], an.replicates[p.b]
    if p.on == "gap":
        d = ((_boot_value(ra, p.hard) - p.b_scale * _boot_value(rb, p.hard))
             - (_boot_value(ra, p.easy) - p.b_scale * _boot_value(rb, p.easy)))
        va, vb = p.values(an.per_seed, p.a), p.values(an.per_seed, p.b)
    else:
        d = _boot_value(ra, p.on) - p.b_scale * _boot_value(rb, p.on)
        va, vb = an.per_seed(p.a, p.on), an.per_seed(p.b, p.on)
    mean = float(np.mean(list(va.values())) - p.b_scale * np.mean(list(vb.values())))
    return Estimate(mean, *percentile_interval(d))


# ------------------------------------------------------------------------------------------------
# the report


def _row_order(rows: Sequence[str], catalogue: Mapping[str, Mapping[str, Any]]) -> list[str]:
    order = list(catalogue)
    return sorted(rows, key=lambda r: (order.index(r) if r in order else len(order), r))


def _method_text() -> str:
    doc = __doc__ or ""
    return doc.split("**Intervals (primary):")[1].split("**Verdicts.**")[0].strip() if "**Intervals (primary):" in doc else ""


def spread_data(cs: Sequence[CellResult]) -> dict[str, dict[str, Any]]:
    """Per column (and per command in the bar's column, training town / training weathers): do the row's seeds
    differ beyond the episodes' luck (``cicfw.bench.seed_spread``)? Empty with fewer than two seeds."""
    if len(cs) < 2:
        return {}

    def test(column: str, command: str | None) -> dict[str, Any] | None:
        successes, episodes = zip(*(c.counts(column, command) for c in cs))
        t = seed_spread(successes, episodes)
        return None if t is None else {"p": round(t.pvalue, 4), "chi2": round(t.statistic, 3),
                                       "failures": list(t.failures), "episodes": list(t.episodes)}

    out: dict[str, dict[str, Any]] = {col: {"all": test(col, None)} for col in COLUMNS}
    for m in ("left", "right", "straight"):
        if any(e.get("command") == m and e["column"] == COLUMNS[0] for c in cs for e in c.episodes.values()):
            out[COLUMNS[0]][m] = test(COLUMNS[0], m)
    return out


def report_data(cells: Sequence[CellResult], failed: Sequence[Mapping[str, Any]],
                catalogue: Mapping[str, Mapping[str, Any]], manifest: Mapping[str, Any],
                n_boot: int = 4000, claims: Sequence[Claim] | None = None) -> dict[str, Any]:
    """Everything RESULTS.md shows, as JSON-ready data (``claims``: the paper's, from conf/reproduce.yaml,
    when not given)."""
    an = analyse(cells, n_boot=n_boot)
    claims = default_claims() if claims is None else list(claims)
    labels = {r: str((catalogue.get(r) or {}).get("label", r)) for r in {*catalogue, *an.rows}}
    paper = {r: list(catalogue[r]["paper"]) for r in catalogue if (catalogue[r] or {}).get("paper")}
    machines = {c.meta.get("machine") for cs in an.rows.values() for c in cs}
    rows = []
    for r in _row_order(list(an.rows), catalogue):
        cs = an.rows[r]
        man: dict[str, list[float]] = {}
        for c in cs:
            for m in ("left", "right", "straight"):
                v = [e["success"] for e in c.episodes.values() if e["command"] == m]
                if v:
                    man.setdefault(m, []).append(100.0 * float(np.mean(v)))
        rows.append({
            "row": r, "label": labels[r], "decoder": cs[0].meta.get("decoder"),
            "seeds": [c.seed for c in cs], "enough_seeds": len(cs) >= MIN_SEEDS,
            "columns": {col: est.as_dict() for col, est in zip([*COLUMNS, "overall"], an.estimates[r])},
            "bootstrap": {col: est.as_dict() for col, est in zip([*COLUMNS, "overall"], an.bootstrap[r])},
            "per_seed": {str(c.seed): {**{col: round(c.rate(col), 2) for col in COLUMNS}, "overall": round(c.rate(), 2)}
                         for c in cs},
            "manoeuvres": {m: round(float(np.mean(v)), 2) for m, v in man.items()},
            "spread": spread_data(cs),
            "paper": paper.get(r),
            "wall_s": {str(c.seed): c.meta.get("wall_s") for c in cs},
            "code": {str(c.seed): c.meta["code"] for c in cs if c.meta.get("code")},
            # each cell's machine, only where the folder's cells come from more than one (``continue_from``)
            "machine": {str(c.seed): c.meta.get("machine") for c in cs} if len(machines) > 1 else {},
            "resumed": {str(c.seed): c.meta["resumed"] for c in cs if c.meta.get("resumed")},
            "curve": {str(c.seed): c.meta.get("curve", []) for c in cs if c.meta.get("curve")},
        })
    return {"manifest": dict(manifest), "method": _method_text(), "n_boot": n_boot, "level": LEVEL,
            "min_seeds": MIN_SEEDS, "overall": "mean of the four table columns (not pooled episodes)",
            "rows": rows, "claims": judge(an, claims, paper, labels),
            "failed": [{"row": f.get("row"), "seed": f.get("seed"), "error": f.get("error")} for f in failed]}


def results_csv(data: Mapping[str, Any]) -> str:
    """One line per (row, column): the mean over seeds, the t-interval, the bootstrap's (secondary), the
    paper's value and the per-seed values."""
    lines = ["row,label,decoder,column,seeds,mean,lo,hi,boot_lo,boot_hi,paper,per_seed"]
    nz = lambda v: "" if v is None else v  # noqa: E731
    for r in data["rows"]:
        for i, col in enumerate([*COLUMNS, "overall"]):
            e, b = r["columns"][col], r["bootstrap"][col]
            paper = r["paper"]
            pv = "" if not paper else f"{(paper[i] if i < 4 else float(np.mean(paper))):.2f}"
            per_seed = ";".join(f"{s}:{v[col]}" for s, v in r["per_seed"].items())
            lines.append(f"{r['row']},\"{r['label']}\",{r['decoder'] or ''},{col},{len(r['seeds'])},{e['mean']},"
                         f"{nz(e['lo'])},{nz(e['hi'])},{nz(b['lo'])},{nz(b['hi'])},{pv},{per_seed}")
    return "\n".join(lines) + "\n"


def _pct(v: float | None) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.1f}"


def _est(e: Mapping[str, Any], sign: str = "") -> str:
    if e.get("lo") is None or e.get("hi") is None:
        return f"{e['mean']:{sign}.1f}"
    return f"{e['mean']:{sign}.1f} [{e['lo']:{sign}.1f}, {e['hi']:{sign}.1f}]"


def _code(c: Mapping[str, Any] | None) -> str:
    """Which cicfw made a cell (its ``code``): ``0.2.0 @ 1cee6eb``, ``+ changes`` when its files differed from
    the commit; ``–`` for cells made before cells recorded it."""
    if not c:
        return "–"
    at = f" @ {c['commit'][:7]}" if c.get("commit") else ""
    return f"{c.get('version', '?')}{at}" + (" + changes" if c.get("modified") else "")


def _p(v: float | None) -> str:
    if v is None:
        return "–"
    return "<0.001" if v < 0.001 else f"{v:.3f}"


def _relative(rel: Mapping[str, Any] | None) -> str:
    if not rel or rel.get("mean") is None:
        return ""
    if rel.get("lo") is None or rel.get("hi") is None:
        return f"; relative {rel['mean']:+.0f}% (interval unbounded)"
    return f"; relative {rel['mean']:+.0f}% [{rel['lo']:+.0f}, {rel['hi']:+.0f}]"


def summary_lines(data: Mapping[str, Any]) -> list[str]:
    """Sentences generated from the same numbers as the tables (for quoting in prose: no hand-written figure)."""
    out = []
    for r in data["rows"]:
        o = r["columns"]["overall"]
        seeds = " / ".join(f"{v['overall']:.1f}" for v in r["per_seed"].values())
        few = "" if r["enough_seeds"] else f" (fewer than {data.get('min_seeds', MIN_SEEDS)} seeds: no verdict)"
        out.append(f"- **{r['label']}**: {_est(o)}% overall over {len(r['seeds'])} seed(s){few}; per seed {seeds}.")
    for c in data["claims"]:
        bits = []
        for p in c["parts"]:
            if "measured" not in p:
                bits.append(f"{p['comparison']}: {p['verdict']}")
                continue
            rel = p.get("relative") or {}
            ab = f" ({p['means'][0]:.1f} vs {p['means'][1]:.1f})" if p["on"] != "gap" and p.get("means") else ""
            paper = "" if p.get("paper") is None else f"; the paper {p['paper']:+.1f}"
            if rel.get("paper") is not None:
                paper += f" ({rel['paper']:+.0f}%)"
            bits.append(f"{p['comparison']}{ab}: {_est(p['measured'], '+')} points{_relative(rel)} "
                        f"({p['method']}{paper})")
        out.append(f"- *{c['claim']}*: **{c['verdict']}** (Holm: **{c['verdict_holm']}**). " + "; ".join(bits) + ".")
    return out


def resumed_text(data: Mapping[str, Any]) -> str:
    """The footnote on resumed cells (‡), or "" when every cell ran uninterrupted."""
    which = []
    for r in data["rows"]:
        for s, how in (r.get("resumed") or {}).items():
            epoch = ((how or {}).get("training") or {}).get("from_epoch") if isinstance(how, Mapping) else None
            which.append(f"{r['label']} seed {s} (training resumed"
                         + (f" after epoch {epoch})" if epoch is not None else ")"))
    if not which:
        return ""
    return (f"{RESUMED_MARK} {', '.join(which)}: resumed from an epoch checkpoint after its run was stopped. A "
            "resumed cell's numbers can differ from an uninterrupted run's, since resuming restores the weights, "
            "the optimizer and the epoch but not the random state of the batch order and augmentation "
            f"({RESUME_EXAMPLE}); its evaluation, when resumed, is the uninterrupted one's.")


def markdown(data: Mapping[str, Any]) -> str:
    """RESULTS.md: the machine and budget, Table 4 with t-intervals over seeds and the paper's values, the
    claims (uncorrected and Holm verdicts, each with its method, the episode bootstrap beside as a secondary
    figure, the paper's sentences), a generated summary, per-seed values, success by manoeuvre, the
    learning curve and each cell's wall time."""
    m = data["manifest"]
    min_seeds = data.get("min_seeds", MIN_SEEDS)
    lines = ["# Reproduction of the paper's Table 4", ""]
    lines += [f"- **Budget:** `{m.get('budget')}`; suite: `{m.get('suite', {}).get('name')}` "
              f"({m.get('episodes', '?')} episodes per cell); dataset: {m.get('dataset_summary', '?')}.",
              f"- **Machine:** {m.get('machine', '?')}.",
              *[f"- **Continued from:** `{c.get('from')}` ({len(c.get('cells') or [])} finished cells copied"
                + (f", only those made on a machine with {c['only_machine']!r}" if c.get("only_machine") else
                   f", made on {c['machine']}" if c.get("machine") else "") + f", {c.get('date', '?')})."
                for c in m.get("continued_from") or []],
              f"- **Cells:** {sum(len(r['seeds']) for r in data['rows'])} finished"
              + (f", {len(data['failed'])} failed" if data["failed"] else "") + ".",
              "- **Intervals:** 95% t-intervals over seeds (the seed is the unit of replication: "
              "`mean ± t(0.975, n−1) · sd / √n` over the per-seed success rates; in a table column never narrower "
              "than the pooled episodes' Clopper-Pearson interval). Success in %; each cell "
              "`mean over seeds [95% interval]`, the paper's value in *italics* below. *Overall* is the mean of "
              "the four columns (per seed, then over seeds), not the success pooled over episodes. "
              f"A row with fewer than {min_seeds} seeds is shown but gets no verdict (†).", ""]
    lines += ["| Row | Decoder | Seeds | " + " | ".join(COLUMN_NAMES) + " | Overall |",
              "|---|---|---:|" + "---:|" * 5]
    for r in data["rows"]:
        cells = []
        for i, col in enumerate([*COLUMNS, "overall"]):
            paper = r["paper"]
            pv = None if not paper else (paper[i] if i < 4 else float(np.mean(paper)))
            cells.append(f"{_est(r['columns'][col])}<br>*{_pct(pv)}*")
        seeds = (f"{len(r['seeds'])}" + ("" if r["enough_seeds"] else " †")
                 + (f" {RESUMED_MARK}" if r.get("resumed") else ""))
        lines.append(f"| {r['label']} | {r['decoder'] or '–'} | {seeds} | " + " | ".join(cells) + " |")
    if any(not r["enough_seeds"] for r in data["rows"]):
        lines += ["", f"† fewer than {min_seeds} seeds: too few seeds for a verdict (with 2 seeds the t-interval "
                      "uses t(0.975, 1) = 12.7; with 1 seed there is none)."]
    resumed = resumed_text(data)
    if resumed:
        lines += ["", resumed]
    lines += ["", "## The paper's claims", "",
              "Each part of a claim is a difference of per-seed values (A − B, points), tested two-sided: "
              "**paired t** over the per-seed differences when both rows ran the same seeds (the same seed trains "
              "on the same split), **Welch t** otherwise. *Verdict*: uncorrected, from the 95% t-interval "
              "(*supported* when it lies on the claim's side of 0, *contradicted* on the other side, "
              "*inconclusive* when it contains 0; a *not better than* part is contradicted only when A is "
              "significantly better than B). *Holm*: the same with Holm-adjusted p-values over a family fixed in "
              f"advance, the {holm_family_size(data['claims'])} parts of the claims below, a part "
              f"without a verdict counting as p = 1 (family-wise error 5%). A part whose rows have fewer than {min_seeds} "
              "seeds: *too few seeds*. *Bootstrap* is the two-level episode bootstrap's 95% interval, a secondary "
              "figure (too narrow with few seeds), not used for a verdict.", "",
              "| Claim | Comparison | Method | Measured (points) [95% t] | Paper | p | Holm p | Verdict | "
              "Holm verdict | Bootstrap (secondary) |",
              "|---|---|---|---:|---:|---:|---:|---|---|---:|"]
    for c in data["claims"]:
        for k, p in enumerate(c["parts"]):
            meas = p.get("measured")
            rel = p.get("relative")
            ms = (_est(meas, "+") + _relative(rel)) if meas else "–"
            pp = "–" if p.get("paper") is None else f"{p['paper']:+.1f}"
            if rel and rel.get("paper") is not None:
                pp += f"; {rel['paper']:+.0f}%"
            boot = _est(p["bootstrap"], "+") if p.get("bootstrap") else "–"
            head = (f"{c['claim']} (**{c['verdict']}**; Holm **{c['verdict_holm']}**)" if k == 0 else "")
            lines.append(f"| {head} | {p['comparison']} | {p.get('method', '–')} | {ms} | {pp} | {_p(p.get('p'))} | "
                         f"{_p(p.get('p_holm'))} | {p['verdict']} | {p.get('verdict_holm', '–')} | {boot} |")
    quoted = [c for c in data["claims"] if c.get("quote")]
    if quoted:
        lines += ["", "### The claims in the paper's words", ""]
        lines += [f"- **{c['claim']}** — “{c['quote']}” ({c['source']})" for c in quoted]
    lines += ["", "## Summary (generated from the numbers above)", "", *summary_lines(data)]
    lines += ["", "## Per seed (success %, overall = mean of the four columns)", "",
              "| Row | Seed | " + " | ".join(COLUMN_NAMES) + " | Overall |", "|---|---:|" + "---:|" * 5]
    for r in data["rows"]:
        for s, v in r["per_seed"].items():
            mark = f" {RESUMED_MARK}" if s in (r.get("resumed") or {}) else ""
            lines.append(f"| {r['label']} | {s}{mark} | "
                         + " | ".join(f"{v[c]:.1f}" for c in [*COLUMNS, "overall"]) + " |")
    lines += ["", f"## Secondary: the two-level episode bootstrap ({data['n_boot']} replicates)", "",
              "Seeds, then episodes within each column, drawn with replacement (paired by episode between rows). "
              "Kept for comparison with earlier reports; with few seeds its intervals are too narrow "
              "(docs/reproduce.md gives its simulated coverage).", "",
              "| Row | Seeds | " + " | ".join(COLUMN_NAMES) + " | Overall |", "|---|---:|" + "---:|" * 5]
    for r in data["rows"]:
        lines.append(f"| {r['label']} | {len(r['seeds'])} | "
                     + " | ".join(_est(r["bootstrap"][c]) for c in [*COLUMNS, "overall"]) + " |")
    if any(r["manoeuvres"] for r in data["rows"]):
        names = [n for n in ("left", "right", "straight") if any(n in r["manoeuvres"] for r in data["rows"])]
        lines += ["", "## Success by manoeuvre (mean over seeds, %)", "",
                  "| Row | " + " | ".join(n.capitalize() for n in names) + " |", "|---|" + "---:|" * len(names)]
        for r in data["rows"]:
            lines.append(f"| {r['label']} | " + " | ".join(_pct(r["manoeuvres"].get(n)) for n in names) + " |")
    lines += spread_lines(data)
    curve = curve_table(data)
    if curve:
        heading = "## Learning curve (overall success: a seed's value; of several seeds, their mean [min, max])"
        lines += ["", heading, "", *curve]
    # optional columns: cicfw only once some cell records it, the machine only where the cells come from several
    optional = [(name, value) for name, key, value in [
        ("cicfw", "code", lambda r, s: _code((r.get("code") or {}).get(s))),
        ("Machine", "machine", lambda r, s: (r.get("machine") or {}).get(s) or "–"),
    ] if any(r.get(key) for r in data["rows"])]
    where = "on each cell's machine" if any(n == "Machine" for n, _ in optional) else "on the machine above"
    lines += ["", f"## Wall time per cell (s, {where})", "",
              "| Row | Seed | Train | Evaluate | Curve evaluations |" + "".join(f" {n} |" for n, _ in optional),
              "|---|---:|---:|---:|---:|" + "---|" * len(optional)]
    for r in data["rows"]:
        for s, w in r["wall_s"].items():
            w = w or {}
            lines.append(f"| {r['label']} | {s} | {_pct(w.get('train'))} | {_pct(w.get('evaluate'))} | "
                         f"{_pct(w.get('curve'))} |" + "".join(f" {value(r, s)} |" for _, value in optional))
    if data["failed"]:
        lines += ["", "## Failed cells", ""] + [f"- {f['row']} seed {f['seed']}: {f['error']}" for f in data["failed"]]
    return "\n".join(lines) + "\n"


def _spread(t: Mapping[str, Any] | None) -> str:
    if not t:
        return "–"
    n = set(t["episodes"])
    of = f" of {n.pop()}" if len(n) == 1 else ""
    return f"{_p(t['p'])} ({', '.join(map(str, t['failures']))}{of})"


def spread_lines(data: Mapping[str, Any]) -> list[str]:
    """RESULTS.md's section on the seeds' spread: a p-value per row and column, failures per seed beside it."""
    rows = [r for r in data["rows"] if r.get("spread")]
    if not rows:
        return []
    commands = [m for m in ("left", "right", "straight") if any(m in r["spread"][COLUMNS[0]] for r in rows)]
    lines = ["", "## Do the seeds differ beyond the episodes' luck?", "",
             "Each entry: the p-value of the test that every seed of the row has the same success rate there "
             "(Pearson's chi-square of the seeds' successes and failures, p by Monte Carlo over tables with the "
             "same margins, `cicfw.bench.seed_spread`), then each seed's failures in seed order. A small p: the "
             "seeds trained models of different quality, beyond what the episodes' luck gives.", "",
             "| Row | Seeds | " + " | ".join(COLUMN_NAMES) + " | "
             + " | ".join(f"{COLUMN_NAMES[0]}: {m} turns" if m != "straight" else f"{COLUMN_NAMES[0]}: straight"
                          for m in commands) + " |",
             "|---|---:|" + "---:|" * (len(COLUMNS) + len(commands))]
    for r in rows:
        sp = r["spread"]
        lines.append(f"| {r['label']} | {len(r['seeds'])} | " + " | ".join(_spread(sp[c]["all"]) for c in COLUMNS)
                     + " | " + " | ".join(_spread(sp[COLUMNS[0]].get(m)) for m in commands) + " |")
    return lines


def curve_points(data: Mapping[str, Any]) -> dict[str, list[tuple[int, float, float, float, int]]]:
    """row -> [(samples seen, mean, min, max of overall success over seeds, number of seeds)] for rows
    with a curve."""
    out = {}
    for r in data["rows"]:
        by_samples: dict[int, list[float]] = {}
        for pts in r["curve"].values():
            for p in pts:
                by_samples.setdefault(int(p["samples"]), []).append(float(p["overall"]))
        if by_samples:
            out[r["label"]] = [(s, float(np.mean(v)), float(np.min(v)), float(np.max(v)), len(v))
                               for s, v in sorted(by_samples.items())]
    return out


def curve_table(data: Mapping[str, Any]) -> list[str]:
    pts = curve_points(data)
    if not pts:
        return []
    samples = sorted({s for v in pts.values() for s, *_ in v})
    lines = ["| Row | " + " | ".join(f"{s:,} samples" for s in samples) + " |", "|---|" + "---:|" * len(samples)]

    def point(m: float, lo: float, hi: float, n: int) -> str:  # one seed has a value, not a range
        return f"{m:.1f}" if n == 1 else f"{m:.1f} [{lo:.1f}, {hi:.1f}] ({n} seeds)"

    for label, v in pts.items():
        d = {s: rest for s, *rest in v}
        lines.append(f"| {label} | " + " | ".join(point(*d[s]) if s in d else "–" for s in samples) + " |")
    return lines


def row_colours(rows: Sequence[str], order: Sequence[str] = ()) -> dict[str, int]:
    """Each row's colour index: its place in ``order`` (the catalogue, the paper's Table-4 order), so a row
    keeps its colour in every folder's picture whichever rows are present; rows outside it follow it."""
    order = list(order)
    extras = [r for r in rows if r not in order]
    return {r: order.index(r) if r in order else len(order) + extras.index(r) for r in rows}


def _colour(plt: Any, k: int) -> Any:
    """Colour ``k``: tab10's ten, then their light shades (tab20's odd entries), then round again."""
    return plt.get_cmap("tab20")((2 * k) % 20 + (k // 10) % 2)


def plot_results(data: Mapping[str, Any], path: Path, order: Sequence[str] = ()) -> Path:
    """Success per column with 95% t-interval bars (over seeds) for each row; the paper's values as crosses
    in the row's colour. ``order``: the catalogue's rows, which fix each row's colour (``row_colours``)."""
    from cicfw.bench.plots import _plt, _save

    plt = _plt()
    rows = data["rows"]
    fig, ax = plt.subplots(figsize=(max(7.5, 1.2 * len(rows) + 4), 4.4))
    colour = row_colours([r["row"] for r in rows], order)
    x = np.arange(5)
    width = 0.8 / max(len(rows), 1)
    for k, r in enumerate(rows):
        xs = x - 0.4 + width * (k + 0.5)
        est = [r["columns"][c] for c in [*COLUMNS, "overall"]]
        mean = np.array([e["mean"] for e in est])
        err = np.array([[e["mean"] - e["lo"] if e["lo"] is not None else 0.0 for e in est],
                        [e["hi"] - e["mean"] if e["hi"] is not None else 0.0 for e in est]])
        label = r["label"] + ("" if r.get("enough_seeds", True) else f" ({len(r['seeds'])} seed(s): too few)")
        c = _colour(plt, colour[r["row"]])
        ax.errorbar(xs, mean, yerr=err, fmt="o", color=c, capsize=3, label=label)
        if r["paper"]:
            pv = [*r["paper"], float(np.mean(r["paper"]))]
            ax.scatter(xs, pv, marker="x", color=c, s=36, zorder=3)
    ax.scatter([], [], marker="x", color="grey", label="the paper's value (row's colour)")
    ax.set_xticks(x, [n.replace(" / ", "\n") for n in COLUMN_NAMES] + ["Overall\n(mean of columns)"])
    ax.set_ylim(-3, 105)
    ax.set_ylabel("reach destination success (%)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.17), ncol=min(len(rows) + 1, 4), frameon=False)
    suite = (data["manifest"].get("suite") or {}).get("name", "?")
    ax.set_title(f"Suite {suite}, budget {data['manifest'].get('budget')}: mean over seeds, 95% t-interval over seeds")
    return _save(fig, Path(path))


def plot_curve(data: Mapping[str, Any], path: Path, order: Sequence[str] = ()) -> Path | None:
    """Overall success against training samples seen, per row (mean over seeds, band = min..max), each row
    in its colour of ``plot_results``."""
    pts = curve_points(data)
    if not pts:
        return None
    from cicfw.bench.plots import _plt, _save

    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.0))
    colour = row_colours([r["row"] for r in data["rows"]], order)
    row_of = {r["label"]: r["row"] for r in data["rows"]}
    for label, v in pts.items():
        s, m, lo, hi, _ = (np.array(a) for a in zip(*v))
        c = _colour(plt, colour[row_of[label]])
        ax.plot(s, m, "o-", label=label, color=c)
        ax.fill_between(s, lo, hi, alpha=0.2, color=c)
    ax.set_xlabel("training samples seen")
    ax.set_ylabel("overall success (%)")
    ax.set_ylim(-3, 105)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Learning curve on the single-turn suite (band: min..max over seeds)")
    return _save(fig, Path(path))


def _with_pictures(md: str, pics: Path | str, curve: bool) -> str:
    pics = str(pics).rstrip("/")
    prefix = "" if pics in ("", ".") else pics + "/"
    return (md + f"\n![success per column with 95% intervals]({prefix}results.png)\n"
            + (f"\n![learning curve]({prefix}learning_curve.png)\n" if curve else ""))


def write_report(results_dir: Path, catalogue: Mapping[str, Mapping[str, Any]], n_boot: int = 4000,
                 claims: Sequence[Claim] | None = None) -> dict[str, Any]:
    """results.json, results.csv, RESULTS.md and the two pictures in ``results_dir``; returns the data.
    ``claims``: the paper's (conf/reproduce.yaml) when not given."""
    results_dir = Path(results_dir)
    manifest = json.loads((results_dir / "reproduce.json").read_text()) if (results_dir / "reproduce.json").is_file() else {}
    cells, failed = load_cells(results_dir)
    if not cells:
        raise ValueError(f"no finished cell in {str(results_dir)!r} (cells/<row>/seed<k>/cell.json): nothing to report"
                         + (f"; {len(failed)} failed" if failed else ""))
    data = report_data(cells, failed, catalogue, manifest, n_boot=n_boot, claims=claims)
    atomic_write(results_dir / "results.json", json.dumps(data, indent=1))
    atomic_write(results_dir / "results.csv", results_csv(data))
    plot_results(data, results_dir / "results.png", order=list(catalogue))
    curve = plot_curve(data, results_dir / "learning_curve.png", order=list(catalogue))
    data["has_curve"] = curve is not None
    atomic_write(results_dir / "RESULTS.md", _with_pictures(markdown(data), ".", data["has_curve"]))
    return data


def write_markdown_copy(data: Mapping[str, Any], path: Path, pictures: Path) -> Path:
    """The report's Markdown at ``path`` (e.g. docs/RESULTS.md), its pictures linked from ``pictures``."""
    rel = os.path.relpath(Path(pictures), Path(path).parent)
    atomic_write(Path(path), _with_pictures(markdown(data), rel, bool(data.get("has_curve"))))
    return Path(path)


def publish(results_dir: Path, dest: Path) -> list[Path]:
    """Copy a reproduction's small results into ``dest`` (for committing): RESULTS.md, results.json/.csv,
    the pictures, the manifest and every cell's cell.json (never checkpoints or episode logs)."""
    results_dir, dest = Path(results_dir), Path(dest)
    names = ["RESULTS.md", "results.json", "results.csv", "results.png", "learning_curve.png", "reproduce.json"]
    files = [results_dir / n for n in names if (results_dir / n).is_file()]
    files += sorted(results_dir.glob("cells/*/seed*/cell.json"))
    out = []
    if dest.exists() and not dest.is_dir():
        raise ValueError(f"publish_dir {str(dest)!r} is a file, not a folder; give publish_dir=<a folder>")
    for f in files:
        target = dest / f.relative_to(results_dir)
        if target.resolve() != f.resolve():
            atomic_write(target, f.read_bytes())
        out.append(target)
    return out


def published_manifest(src: Path) -> dict[str, Any]:
    """The manifest (``reproduce.json``) of a published results folder, or one line saying what it is not."""
    src = Path(src)
    if not src.is_dir():
        raise ValueError(f"continue_from={str(src)!r} is not a folder; give a published results folder "
                         f"(reproduce.json and cells/<row>/seed<k>/cell.json, e.g. docs/results/<budget>)")
    try:
        return json.loads((src / "reproduce.json").read_text())
    except FileNotFoundError:
        raise ValueError(f"continue_from={str(src)!r} is not a published results folder (no reproduce.json); give "
                         f"the folder that holds reproduce.json and cells/<row>/seed<k>/cell.json") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"continue_from={str(src)!r}: reproduce.json is not JSON ({err})") from None


def finished_cells(folder: Path) -> dict[str, dict[str, Any]]:
    """``row/seedK`` -> cell.json of every finished (status ok) cell under ``folder``."""
    out = {}
    for f in sorted(Path(folder).glob("cells/*/seed*/cell.json")):
        d = json.loads(f.read_text())
        if d.get("status") == "ok":
            out[f"{f.parent.parent.name}/{f.parent.name}"] = d
    return out


def continue_published(src: Path, results_dir: Path, machine: str | None = None) -> dict[str, list[str]]:
    """Copy into ``results_dir`` every finished cell of the published results folder ``src`` (as ``publish``
    writes it, e.g. docs/results/<budget>) that ``results_dir`` lacks, so the launcher skips it and a fresh
    clone grows the same table. The caller has checked that ``src`` is pinned to the same budget, suite and
    dataset and that its cells were trained as this cicfw trains them (``cicfw.reproduce``). Never
    overwritten: a finished cell ``results_dir`` already has. Not copied: failed cells (they are retried)
    and, with ``machine``, cells whose ``machine`` does not contain that text (a table made within one kind
    of CPU: the same seed trains another model on another kind). Returns {"copied": [...], "kept": [...],
    "other_machine": [...]} (``row/seedK`` names)."""
    src, results_dir = Path(src), Path(results_dir)
    copied, kept, other = [], [], []
    have = finished_cells(results_dir)
    for name, cell in finished_cells(src).items():
        if machine is not None and machine not in str(cell.get("machine") or ""):
            other.append(name)
            continue
        if name in have:
            kept.append(name)
            continue
        rel = Path("cells", *name.split("/"), "cell.json")
        if (results_dir / rel).resolve() != (src / rel).resolve():
            atomic_write(results_dir / rel, (src / rel).read_bytes())
        copied.append(name)
    return {"copied": copied, "kept": kept, "other_machine": other}


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cicfw.bench.results RESULTS_DIR [--publish DEST]``: (re)write a reproduction's report."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="cicfw report", description=main.__doc__)
    ap.add_argument("results_dir")
    ap.add_argument("--publish", default=None, help="also copy the small results into this folder")
    ap.add_argument("--markdown", default=None, help="also write the Markdown here (e.g. docs/RESULTS.md)")
    a = ap.parse_args(argv)
    try:
        from hydra import compose, initialize_config_module
        from omegaconf import OmegaConf

        with initialize_config_module("cicfw.conf", version_base="1.3"):
            cfg = compose("reproduce")
            catalogue = OmegaConf.to_container(cfg.catalogue, resolve=True)
            claims = load_claims(OmegaConf.to_container(cfg.claims, resolve=True))
        data = write_report(Path(a.results_dir), catalogue, claims=claims)
        if a.publish:
            publish(Path(a.results_dir), Path(a.publish))
        if a.markdown:
            write_markdown_copy(data, Path(a.markdown), Path(a.publish) if a.publish else Path(a.results_dir))
    except (ValueError, FileNotFoundError) as err:
        print(f"cicfw: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a read-only folder, a full disk: one line
        print(f"cicfw: error: cannot write {err.filename!r}: {err.strerror}", file=sys.stderr)
        return 2
    print(f"{sum(len(r['seeds']) for r in data['rows'])} cells of {len(data['rows'])} rows; "
          f"report in {Path(a.results_dir) / 'RESULTS.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
