"""Do a row's seeds differ by more than their episodes' luck? One test per row and group of episodes.

cicfw's intervals take the seed as the unit of replication (``cicfw.reproduction.report``); this looks at what the
seeds' spread is made of. If every seed of a row had the same true success rate on a group of episodes (a
table column, or one command inside it), the seeds' (successes, failures) there would form a 2 x k table
whose spread is the episodes' luck alone. The test is Pearson's chi-square of that table, its p-value by
Monte Carlo over the tables with the same margins (``scipy.stats.chi2_contingency`` with
``MonteCarloMethod``: valid where the asymptotic chi-square is not, as in columns near 100%). A small p says
the seeds trained models of different quality there, so "seed 2 read 88.5% where seed 0 read 99.0%" is not
the luck of 96 episodes; a large p says the episodes alone could give that spread.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import stats

#: Monte Carlo tables per test: the p-value's standard error is below 0.005 at any p
N_RESAMPLES = 9999


@dataclass(frozen=True)
class SpreadTest:
    """The chi-square of the seeds' (successes, failures) table and its Monte Carlo p-value."""

    successes: tuple[int, ...]
    episodes: tuple[int, ...]
    statistic: float
    pvalue: float

    @property
    def failures(self) -> tuple[int, ...]:
        return tuple(n - s for s, n in zip(self.successes, self.episodes))


def seed_spread(successes: Sequence[int], episodes: Sequence[int], n_resamples: int = N_RESAMPLES,
                seed: int = 0) -> SpreadTest | None:
    """Test "every seed has the same success rate" on per-seed (successes, episodes); ``None`` with fewer than
    two seeds. When no seed failed (or none succeeded) every table with these margins is the same: p = 1."""
    s, n = np.asarray(successes, dtype=int), np.asarray(episodes, dtype=int)
    if s.shape != n.shape or s.ndim != 1:
        raise ValueError(f"successes and episodes must be two equal-length lists, got {s.shape} and {n.shape}")
    if ((s < 0) | (s > n)).any():
        raise ValueError(f"every seed needs 0 <= successes <= episodes, got {s.tolist()} of {n.tolist()}")
    if len(s) < 2 or (n == 0).any():
        return None
    table = np.stack([s, n - s])
    if (table.sum(axis=1) == 0).any():
        return SpreadTest(tuple(s.tolist()), tuple(n.tolist()), 0.0, 1.0)
    res = stats.chi2_contingency(table, correction=False, method=stats.MonteCarloMethod(
        n_resamples=n_resamples, rng=np.random.default_rng(seed)))
    return SpreadTest(tuple(s.tolist()), tuple(n.tolist()), float(res.statistic), float(res.pvalue))
