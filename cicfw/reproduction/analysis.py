"""One results folder analysed: every row's estimate per column with its t-interval over seeds (primary)
and the two-level episode bootstrap beside it (secondary)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from cicfw.core.errors import CicfwError
from cicfw.reproduction.cells import (COLUMNS, MIXED_CPUS, MIXED_MACHINES, SELECTORS, CellResult,
                                     check_same_episodes, episode_terms, kind_noun, pooled_counts)
from cicfw.reproduction.seed_stats import (LEVEL, MIN_SEEDS, Estimate, contrast_interval, pooled_clopper_pearson,
                                           t_interval)


def row_estimate(cells: Sequence[CellResult], on: str, level: float = LEVEL) -> Estimate:
    """A row's mean over seeds on ``on`` with its t-interval over seeds, widened to contain the interval of
    the episodes pooled over its seeds: on a single table column their Clopper-Pearson interval, on a mean
    of columns (overall, a town, a weather) the MOVER interval of that mean of proportions
    (``seed_stats.contrast_interval``). No interval for one seed."""
    v = np.array([c.value(on) for c in cells])
    mean, lo, hi = (float(x) for x in t_interval(v, level))
    if len(v) < 2:
        return Estimate(mean, None, None)
    if len(SELECTORS[on]) == 1:
        floor = pooled_clopper_pearson(*pooled_counts(cells, COLUMNS[SELECTORS[on][0]]), level)
    else:
        terms = episode_terms({"row": cells}, [(1.0, "row", on)])
        floor = contrast_interval(terms, level) if terms else (lo, hi)
    lo, hi = min(lo, floor[0]), max(hi, floor[1])
    return Estimate(mean, max(lo, 0.0), min(hi, 100.0))  # a rate lies in [0, 100]


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


def episode_draws(columns: Sequence[str], rng: np.random.Generator, n_boot: int) -> dict[str, np.ndarray]:
    """Per table column, ``n_boot`` draws (with replacement) of that column's episode positions
    (``columns``: each episode's column, in the order of the success matrix)."""
    cols = np.asarray(columns)
    out = {}
    for c in COLUMNS:
        pos = np.flatnonzero(cols == c)
        if len(pos) == 0:
            raise CicfwError(f"the suite has no episode in column {c!r}: the table needs all four columns")
        out[c] = pos[rng.integers(0, len(pos), size=(n_boot, len(pos)))]
    return out


def percentile_interval(samples: np.ndarray, level: float = LEVEL) -> tuple[float, float]:
    """The percentile interval of bootstrap replicates: their (1 - level) / 2 and (1 + level) / 2 quantiles."""
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(samples, [a, 1.0 - a])
    return float(lo), float(hi)


def boot_value(rep: np.ndarray, on: str) -> np.ndarray:
    """A selector's value (the mean of its columns) in each of ``bootstrap_replicates``' replicates."""
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
    keys: list[str] = field(default_factory=list)  # the episodes, in the success matrices' order
    draws: dict[str, np.ndarray] = field(default_factory=dict)  # the episode draws every row shares

    def replicates_of(self, row: str, cells: Sequence[CellResult]) -> np.ndarray:
        """``row``'s bootstrap replicates on ``cells``: the stored ones when they are all its cells, else
        drawn again on the shared episode draws (a comparison within one CPU kind), the seed draw from a
        generator seeded by the cells' seeds so that the report is reproducible."""
        if len(cells) == len(self.rows[row]):
            return self.replicates[row]
        rng = np.random.default_rng([1, *sorted(c.seed for c in cells)])
        return bootstrap_replicates(_matrix(cells, self.keys), self.draws, rng, self.n_boot)

    def pair(self, a: str, b: str, min_seeds: int = MIN_SEEDS) -> "Pairing":
        """The cells a comparison of rows ``a`` and ``b`` uses (``pair_cells``)."""
        return pair_cells(self.rows[a], self.rows[b], min_seeds)


@dataclass(frozen=True)
class Pairing:
    """The cells a comparison of rows A and B uses, and the machine kinds behind them (``CellResult.cpu``): ``cpu``
    names the one kind they all ran on, or None where they mix kinds ("mixed CPUs", "mixed machines" where a
    GPU is among them); ``left_out`` counts the cells of
    other kinds a comparison within one kind leaves out; ``kinds``: each kind's cells of A and of B;
    ``unshared``: the cells of A and of B left out because the other row did not run their seed (rows that
    share seeds are compared paired over the seeds both ran)."""

    a: tuple[CellResult, ...]
    b: tuple[CellResult, ...]
    cpu: str | None
    left_out: int
    kinds: dict[str, tuple[int, int]]
    unshared: tuple[int, int] = (0, 0)

    @property
    def mixed(self) -> bool:
        """The comparison pools cells of more than one machine kind."""
        return self.cpu is None

    def note(self) -> str:
        """What the report's method column adds: which seeds were left out to pair (none when the rows ran the
        same seeds), then "" on one kind throughout, else within which kind or "mixed CPUs" ("mixed machines"
        where a GPU is among the kinds) with each kind's cells of A and of B."""
        out = []
        if any(self.unshared):
            out.append(f"on the seeds both ran ({self.unshared[0]} of A's and {self.unshared[1]} of B's cells "
                       "left out)")
        if len(self.kinds) > 1:
            cpus = kind_noun(self.kinds) == "CPU"  # else a GPU is among the kinds: they are machines, not CPUs
            if self.cpu is not None:
                other = "other CPUs" if cpus else "other machine kinds"
                out.append(f"within {self.cpu} ({self.left_out} cell(s) of {other} left out)")
            else:  # the kinds of the cells compared
                used = {k: (sum(c.cpu == k for c in self.a), sum(c.cpu == k for c in self.b)) for k in self.kinds}
                side = lambda i: ", ".join(f"{k} {n[i]}" for k, n in used.items() if n[i])  # noqa: E731
                out.append(f"{MIXED_CPUS if cpus else MIXED_MACHINES} (A: {side(0)}; B: {side(1)})")
        return ", ".join(out)


def _on_shared_seeds(a: Sequence[CellResult], b: Sequence[CellResult]) -> tuple[tuple, tuple, tuple[int, int]]:
    """The cells of A and B whose seed both rows ran (all of them where no seed is shared: Welch), and how
    many of each were left out."""
    shared = {c.seed for c in a} & {c.seed for c in b}
    if not shared:
        return tuple(a), tuple(b), (0, 0)
    sa, sb = tuple(c for c in a if c.seed in shared), tuple(c for c in b if c.seed in shared)
    return sa, sb, (len(a) - len(sa), len(b) - len(sb))


def pair_cells(a: Sequence[CellResult], b: Sequence[CellResult], min_seeds: int = MIN_SEEDS) -> Pairing:
    """Compare within one machine kind, CPU plus GPU (the same seed trains another model on another kind): all
    cells when both rows ran on one kind; where they span kinds, the cells of the kind on which both rows have at
    least ``min_seeds`` (the most common seeds, then the most cells, then the name decide between kinds);
    where no kind has that, all cells, marked mixed. Then, where the rows share seeds (and so splits), only
    the cells of the seeds both ran: they are compared paired; rows that share none, by Welch's t."""
    kinds = sorted({c.cpu for c in (*a, *b)})
    counts = {k: (sum(c.cpu == k for c in a), sum(c.cpu == k for c in b)) for k in kinds}
    if len(kinds) == 1:
        return Pairing(*_paired(a, b, kinds[0], 0, counts))
    shared = [k for k in kinds if min(counts[k]) >= min_seeds]
    if not shared:
        return Pairing(*_paired(a, b, None, 0, counts))

    def rank(k: str) -> tuple[int, int]:
        common = {c.seed for c in a if c.cpu == k} & {c.seed for c in b if c.cpu == k}
        return len(common), sum(counts[k])

    best = max(shared, key=rank)  # the first of equals in name order
    sa, sb = tuple(c for c in a if c.cpu == best), tuple(c for c in b if c.cpu == best)
    return Pairing(*_paired(sa, sb, best, len(a) + len(b) - len(sa) - len(sb), counts))


def _paired(a: Sequence[CellResult], b: Sequence[CellResult], cpu: str | None, left_out: int,
            counts: dict[str, tuple[int, int]]) -> tuple:
    sa, sb, unshared = _on_shared_seeds(a, b)
    kinds = {c.cpu for c in (*sa, *sb)}
    if cpu is None and len(kinds) == 1:  # pairing left the cells of one kind
        cpu = kinds.pop()
    return sa, sb, cpu, left_out, counts, unshared


def analyse(cells: Sequence[CellResult], n_boot: int = 4000, seed: int = 0) -> Analysis:
    """Group cells by row, check they drove the same episodes, estimate every row (t over seeds) and
    bootstrap it (secondary): ``n_boot`` replicates, drawn with the random seed ``seed`` (not a training
    seed)."""
    rows: dict[str, list[CellResult]] = {}
    for c in sorted(cells, key=lambda c: (c.row, c.seed)):
        rows.setdefault(c.row, []).append(c)
    if not rows:
        raise CicfwError("no finished cell to analyse")
    first = next(iter(rows.values()))[0]
    keys = sorted(first.episodes)
    for cs in rows.values():
        for c in cs:
            check_same_episodes(c, first, "cells of one results folder must share the suite")
    columns = [first.episodes[k]["column"] for k in keys]
    rng = np.random.default_rng(seed)
    draws = episode_draws(columns, rng, n_boot)
    reps, est, boot = {}, {}, {}
    for row, cs in rows.items():
        reps[row] = bootstrap_replicates(_matrix(cs, keys), draws, rng, n_boot)
        est[row] = [row_estimate(cs, on) for on in [*COLUMNS, "overall"]]
        boot[row] = [Estimate(e.mean, *percentile_interval(reps[row][:, i])) for i, e in enumerate(est[row])]
    return Analysis(rows=rows, estimates=est, bootstrap=boot, replicates=reps, n_boot=n_boot, keys=keys, draws=draws)
