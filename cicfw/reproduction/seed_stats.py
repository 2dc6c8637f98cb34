"""Intervals with the seed as the unit of replication, the episodes' floor under them and Holm's control
of a family of tests: plain numbers in, no cells (the method as the report states it is
``cicfw.reproduction.report``'s docstring)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy import stats
from scipy.optimize import brentq
from statsmodels.stats.multitest import multipletests
from statsmodels.stats.proportion import proportion_confint

LEVEL = 0.95
ALPHA = 1.0 - LEVEL
#: a row needs this many seeds for a verdict (fewer: reported, "too few seeds")
MIN_SEEDS = 3
#: what a comparison with fewer reads, in place of its verdict, word or bound
TOO_FEW = "too few seeds"
#: A - B of two success rates lies in [-100, 100] points: an interval is shown clipped to it
SCALE = 100.0
#: the words a comparison A - B is read with (``word``); the fourth is ``equivalent(margin)``
AHEAD, BEHIND, NOT_SEPARATED = "ahead", "behind", "not separated"


def equivalent(margin: float) -> str:
    """The word for an interval inside (-margin, +margin): ``equivalent within ±5``."""
    return f"equivalent within ±{margin:g}"


def word(lo: float | None, hi: float | None, margin: float) -> str | None:
    """How an interval for A - B reads (None where there is none): *ahead* when it lies above 0, *behind*
    below 0, *equivalent within ±margin* when it lies inside (-margin, +margin) (both one-sided tests of
    TOST pass, each at half the interval's error), else *not separated*. A family of comparisons is read on
    its corrected intervals (``family_level``), so every word of the family holds jointly."""
    if lo is None or hi is None or math.isnan(lo) or math.isnan(hi):
        return None
    if lo > 0:
        return AHEAD
    if hi < 0:
        return BEHIND
    if -margin < lo and hi < margin:
        return equivalent(margin)
    return NOT_SEPARATED


def word_record(d_corrected: Difference, margin: float, level: float, correction: str) -> dict:
    """A comparison's word (``word``) read on its corrected interval ``d_corrected`` (a ``Difference`` at
    ``level``), with that interval and the correction's name, as results.json keeps it."""
    e = d_corrected.estimate
    w = word(e.lo, e.hi, margin) if d_corrected.enough_seeds else None
    return {"word": w, "lo": e.lo if w else None, "hi": e.hi if w else None, "level": level,
            "correction": correction}


def compared_seeds(a: Mapping[int, float], b: Mapping[int, float]) -> tuple[int, int]:
    """The seeds a comparison of A and B rests on, each side's: the seeds both ran when they share any
    (paired, as ``difference`` compares them), else each side's own (Welch's)."""
    shared = len(set(a) & set(b))
    return (shared, shared) if shared else (len(a), len(b))


def seeds_suffice(n: tuple[int, int]) -> bool:
    """Whether a comparison on ``n`` seeds (``compared_seeds``) may get a verdict, a word or an MCB bound: at
    least MIN_SEEDS on each side; fewer read "too few seeds" wherever the report compares rows."""
    return min(n) >= MIN_SEEDS


def on_scale(lo: float | None, hi: float | None) -> tuple[float | None, float | None]:
    """An interval for A - B clipped to [-SCALE, SCALE]: a t-interval over few, spread seeds can reach past
    what a difference of two rates can be. The verdict and the word are read before clipping (with a margin
    of at most SCALE, clipping changes neither)."""
    return tuple(None if v is None else min(max(float(v), -SCALE), SCALE) for v in (lo, hi))  # type: ignore


def family_level(size: int, level: float = LEVEL) -> float:
    """Bonferroni: the level of each of ``size`` two-sided intervals that hold jointly with probability
    ``level`` (1 - (1 - level) / size); ``level`` itself for a family of one."""
    return 1.0 - (1.0 - level) / max(int(size), 1)


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


def welch_t_interval(a: np.ndarray, b: np.ndarray, level: float = LEVEL,
                     axis: int = -1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A - B over unpaired seeds: Welch's t-interval (``scipy.stats.ttest_ind(equal_var=False)``,
    Welch-Satterthwaite degrees of freedom), vectorised over the other axes."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ci = stats.ttest_ind(a, b, equal_var=False, axis=axis).confidence_interval(level)
    return a.mean(axis=axis) - b.mean(axis=axis), np.asarray(ci.low), np.asarray(ci.high)


def pooled_clopper_pearson(successes: int, episodes: int, level: float = LEVEL) -> tuple[float, float]:
    """The Clopper-Pearson interval (%) of ``successes`` of ``episodes`` (statsmodels, method "beta")."""
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


def mover_ratio(a: float, a_limits: tuple[float, float], b: float,
                b_limits: tuple[float, float]) -> tuple[float | None, float | None]:
    """The interval of a / b for two independent estimates from each one's limits (l, u) at the level
    wanted: MOVER-R (Donner & Zou 2012), Fieller's theorem with each variance recovered from its own
    limits. For a and its limits at or above 0 (a success rate; Newcombe 2013 treats either sign); (None,
    None) where b's lower limit is at or below 0, as Fieller's is then unbounded."""
    (l1, u1), (l2, u2) = a_limits, b_limits
    if l2 <= 0:
        return None, None
    ab = a * b

    def root(lim_a: float, lim_b: float, sign: float) -> float:  # lim_b (2b - lim_b) R^2 - 2ab R + ... = 0
        den, const = lim_b * (2 * b - lim_b), lim_a * (2 * a - lim_a)
        disc = math.sqrt(max(ab * ab - den * const, 0.0))
        if den == 0:  # u2 = 2b: the quadratic is linear (a = 0 leaves a bound of 0)
            return const / (2 * ab) if ab else 0.0
        return (ab + sign * disc) / den

    return root(l1, u2, -1.0), root(u1, l2, 1.0)


def with_ratio_floor(lo: float | None, hi: float | None,
                     a_terms: Sequence[tuple[float, int, int]], b_terms: Sequence[tuple[float, int, int]],
                     level: float = LEVEL) -> tuple[float | None, float | None, bool]:
    """Fieller's interval ``[lo, hi]`` of a ratio of rows' means over seeds widened to contain the
    ratio interval of the same two rows' success on their pooled episodes (``mover_ratio`` of A's and B's
    ``contrast_interval``, each on its own ``terms``): seeds whose values agree leave Fieller's no width
    but never remove the episodes' luck. Returns (lo, hi, whether a bound moved); an unbounded one (None)
    stays unbounded, and a floor unbounded (B's pooled lower limit at 0) makes it so."""
    if lo is None or hi is None:
        return lo, hi, False
    a = 100.0 * sum(c * k / n for c, k, n in a_terms)
    b = 100.0 * sum(c * k / n for c, k, n in b_terms)
    flo, fhi = mover_ratio(a, contrast_interval(a_terms, level), b, contrast_interval(b_terms, level))
    if flo is None or fhi is None:
        return None, None, True
    return min(lo, flo), max(hi, fhi), flo < lo or fhi > hi


@dataclass
class Estimate:
    """A mean (%, or points for a difference) with its interval; ``lo``/``hi`` are None where there is
    none (one seed, an unbounded Fieller set)."""

    mean: float
    lo: float | None
    hi: float | None

    def as_dict(self) -> dict[str, float | None]:
        """The JSON form (results.json): unrounded (the report rounds once, when it prints), NaN as None."""
        r = lambda v: None if v is None or (isinstance(v, float) and math.isnan(v)) else float(v)  # noqa: E731
        return {"mean": r(self.mean), "lo": r(self.lo), "hi": r(self.hi)}


@dataclass
class Difference:
    """One tested difference A - B on per-seed values (B already scaled by the caller where a claim's part
    has ``b_scale``): its estimate, two-sided p-value, method, whether paired, and each side's seeds."""

    estimate: Estimate
    p: float | None
    method: str
    paired: bool
    n: tuple[int, int]

    @property
    def enough_seeds(self) -> bool:
        """Both rows have at least MIN_SEEDS seeds (``seeds_suffice``): fewer get no verdict ("too few seeds")."""
        return seeds_suffice(self.n)


#: per-seed values closer than this (points) are one value: success rates are ratios of episode counts, so two
#: that differ by less are the same number apart only by float rounding (58.333... - 8.333... = 50.00000000000001)
ROUNDING = 1e-9


def no_spread(values: np.ndarray) -> bool:
    """Whether ``values`` are one value up to float rounding (``ROUNDING``): their interval is that value and
    a t-test's answer is known exactly (scipy's on such data warns of precision loss and is not)."""
    return bool(np.ptp(values) <= ROUNDING)


def difference(a: Mapping[int, float], b: Mapping[int, float], level: float = LEVEL, null: float = 0.0) -> Difference:
    """A - B from per-seed values (seed -> value). Rows that share seeds share their splits (a seed sets the
    train/validation split), so they are compared **paired over the seeds both have** (the t-interval over
    the per-seed differences, n - 1 df; the other seeds are left out, and the method says how many); only
    rows that share no seed get Welch's t. The p-value is the two-sided t-test's of A - B = ``null``
    (``scipy.stats.ttest_1samp`` on the differences, or ``ttest_ind(equal_var=False)`` with A shifted by
    ``null``), dual to the interval: p < 1 - level exactly when the interval excludes ``null``. With no
    spread at all it is 1 (the difference is ``null``) or 0."""
    na, nb = len(a), len(b)
    shared = sorted(set(a) & set(b))
    if shared:
        n = len(shared)
        d = np.array([a[s] - b[s] for s in shared])
        mean, lo, hi = (float(x) for x in t_interval(d, level))
        method = f"paired t, {n} seed{'s' if n != 1 else ''}"
        if n < na or n < nb:
            method += f" (the seeds both ran; {na - n} of A's and {nb - n} of B's left out)"
        if n < 2:
            return Difference(Estimate(mean, None, None), None, method, True, (n, n))
        if no_spread(d):  # known exactly: the one difference, and whether it is the null
            lo = hi = mean
            p = 1.0 if abs(mean - null) <= ROUNDING else 0.0
        else:
            p = float(stats.ttest_1samp(d, null).pvalue)
        return Difference(Estimate(mean, lo, hi), p, method, True, (n, n))
    va, vb = np.array(list(a.values()), dtype=float), np.array(list(b.values()), dtype=float)
    mean = float(va.mean() - vb.mean())
    method = f"Welch t, {na} vs {nb} seeds, none shared"
    if na < 2 or nb < 2:
        return Difference(Estimate(mean, None, None), None, method, False, (na, nb))
    if no_spread(va) and no_spread(vb):
        return Difference(Estimate(mean, mean, mean), 1.0 if abs(mean - null) <= ROUNDING else 0.0, method, False,
                          (na, nb))
    _, lo, hi = welch_t_interval(va, vb, level)
    p = float(stats.ttest_ind(va - null, vb, equal_var=False).pvalue)
    return Difference(Estimate(mean, float(lo), float(hi)), p, method, False, (na, nb))


def episode_interval(terms: Sequence[tuple[float, int, int]], level: float = LEVEL,
                     null: float = 0.0) -> tuple[float, float, float]:
    """A contrast of table columns on the episodes pooled over each row's seeds, ``sum c * k / n`` over
    ``terms`` of ``(c, successes, episodes)``, in points: its interval (``contrast_interval``; A - B is
    Newcombe's) and the two-sided p-value of contrast = ``null`` dual to it, the level at which the bound
    nearer ``null`` reaches it (1 when the contrast is ``null``). The rows drove the same episodes, and
    treating them as independent ignores that pairing, which widens the interval: it is a floor for the
    episodes' luck, not an estimate of its own."""
    lo, hi = contrast_interval(terms, level)
    value = 100.0 * sum(c * k / n for c, k, n in terms)
    if abs(value - null) < 1e-9:
        return lo, hi, 1.0
    return lo, hi, contrast_level(terms, "lo" if value > null else "hi", null)


def contrast_level(terms: Sequence[tuple[float, int, int]], bound: str, target: float) -> float:
    """The alpha at which the two-sided (1 - alpha) ``contrast_interval``'s ``bound`` ("lo" or "hi")
    reaches ``target`` (points) as the interval narrows toward the contrast itself: the p-value dual to
    the interval (root-found). 0 when even the (1 - 1e-12) interval's bound lies beyond ``target``, 1 when
    the contrast itself does not."""
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
    c, k, n = (np.array(x, dtype=float) for x in zip(*terms))
    p = k / n
    lo, hi = proportion_confint(k, n, alpha=1.0 - level, method="wilson")  # every term's in one call
    down, up = np.where(c > 0, p - lo, hi - p), np.where(c > 0, hi - p, p - lo)  # c < 0 swaps the sides
    value = float(np.sum(c * p))
    return 100.0 * (value - math.sqrt(np.sum((c * down) ** 2))), 100.0 * (value + math.sqrt(np.sum((c * up) ** 2)))


def with_episode_floor(d: Difference, terms: Sequence[tuple[float, int, int]], level: float = LEVEL,
                       null: float = 0.0) -> Difference:
    """``d`` (a contrast of table columns between rows A and B, its ``terms`` the pooled episodes)
    widened to contain the episodes' interval (``episode_interval``), its p-value (of A - B = ``null``)
    the larger of the two: seeds whose differences happen to agree (rates come in steps of 1/64 or 1/96,
    and an easy column often sits at 100% for every seed) leave the t-interval no width, but never remove
    the episodes' luck. The method says so where the floor moved a bound (a larger p-value alone is not
    remarked: it may be the seeds' mean and the pooled value differing in the 15th digit)."""
    e = d.estimate
    if e.lo is None or e.hi is None or d.p is None:
        return d
    lo, hi, p = episode_interval(terms, level, null)
    if lo >= e.lo and hi <= e.hi and p <= d.p:
        return d
    moved = lo < e.lo or hi > e.hi
    return Difference(Estimate(e.mean, min(e.lo, lo), max(e.hi, hi)), max(d.p, p),
                      d.method + (", widened to the episodes' interval" if moved else ""), d.paired, d.n)


def holm(pvalues: Sequence[float], alpha: float = ALPHA,
         family_size: int | None = None) -> tuple[list[float], list[bool]]:
    """Holm's step-down adjustment of a family of p-values (statsmodels ``multipletests``, method "holm"):
    the adjusted p-values and which are rejected at family-wise error ``alpha``.

    ``family_size``: the family fixed in advance, of which ``pvalues`` are the members tested so far; the
    untested ones count as p = 1 (they can reject nothing), so a verdict reached here can only stay
    reached as they are filled in (Holm's procedure is monotone in every p-value)."""
    if not len(pvalues):
        return [], []

    n = len(pvalues)
    if family_size is not None and family_size < n:
        raise ValueError(f"a family of {family_size} cannot hold {n} p-values")
    padded = list(pvalues) + [1.0] * ((family_size or n) - n)
    reject, adj, _, _ = multipletests(padded, alpha=alpha, method="holm")
    return [float(x) for x in adj[:n]], [bool(x) for x in reject[:n]]

