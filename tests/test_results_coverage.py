"""Do the reproduction's 95% intervals cover the truth 95% of the time? Simulated experiments with a known
truth: two rows with known success probabilities per table column, a seed-to-seed spread like the laptop
cells' (about 6 points overall), the suite's single-turn columns (96 / 96 / 64 / 64 episodes, 320 in all),
3 or 5 seeds per row. The t-intervals over seeds (``cicfw.reproduction.seed_stats``) must cover the true difference
in at least 93% of experiments, and Fieller's interval the true ratio, bare and widened by the episodes'
floor; the old two-level episode bootstrap is measured beside them (it covers
less: printed, and only asserted to be below the t-interval's on the same experiments).

``python tests/test_results_coverage.py`` prints the figures quoted in docs/reproduce.md."""
from __future__ import annotations

import numpy as np
import pytest

from cicfw.reproduction import analysis, cells, seed_stats

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

N_EP = np.array([96, 96, 64, 64])  # episodes per table column in the single-turn suite
P_A = np.array([0.65, 0.55, 0.50, 0.45])  # the truth: row A's success probability per column ...
P_B = np.array([0.60, 0.45, 0.45, 0.35])  # ... and row B's
TRUE_OVERALL = 100 * float(np.mean(P_A - P_B))  # 7.5 points
TRUE_NEW_NEW = 100 * float(P_A[3] - P_B[3])  # 10 points
TRUE_GAP = TRUE_NEW_NEW - 100 * float(P_A[0] - P_B[0])  # A's advantage grows by 5 points, easy column to hard
# a seed's shift of all its columns and its own shift per column, as probabilities: like the laptop cells,
# whose seeds differ by 10-17 points within a column but about 6 overall
SD_SEED, SD_SEED_COLUMN = 0.02, 0.12
N_EXP = 20000


def seed_probabilities(rng: np.random.Generator, n_exp: int, n_seeds: int, split_share: float) -> tuple[np.ndarray, np.ndarray]:
    """(n_exp, n_seeds, 4) success probabilities of rows A and B. A seed moves a row by a normal shift
    (SD_SEED, common to its columns, plus SD_SEED_COLUMN per column); a share ``split_share`` of the shift's
    variance is common to both rows (the same seed trains on the same split), the rest is each row's own.
    Shifts have mean 0, so the truth is P_A - P_B (clipping to [0, 1], about 3 sd away, moves it by about
    0.02 points, measured on 200,000 draws: nothing against intervals 20-80 points wide)."""
    def shift(size: tuple[int, ...], sd: float) -> tuple[np.ndarray, np.ndarray]:
        common = rng.normal(0.0, sd, size)
        own_a, own_b = rng.normal(0.0, sd, size), rng.normal(0.0, sd, size)
        w, v = np.sqrt(split_share), np.sqrt(1 - split_share)
        return w * common + v * own_a, w * common + v * own_b

    sa, sb = shift((n_exp, n_seeds, 1), SD_SEED)
    ca, cb = shift((n_exp, n_seeds, 4), SD_SEED_COLUMN)
    return np.clip(P_A + sa + ca, 0, 1), np.clip(P_B + sb + cb, 0, 1)


def column_rates(rng: np.random.Generator, prob: np.ndarray) -> np.ndarray:
    """Each seed drives the suite: per-column success rates (%) from Binomial(episodes, p)."""
    return 100.0 * rng.binomial(N_EP, prob) / N_EP


def t_coverage(n_seeds: int, split_share: float = 0.0, n_exp: int = N_EXP, seed: int = 0) -> dict[str, float]:
    """Coverage and mean width of the module's intervals over ``n_exp`` simulated experiments."""
    rng = np.random.default_rng(seed)
    pa, pb = seed_probabilities(rng, n_exp, n_seeds, split_share)
    ra, rb = column_rates(rng, pa), column_rates(rng, pb)  # (n_exp, n_seeds, 4)
    oa, ob = ra.mean(axis=2), rb.mean(axis=2)  # per-seed overall: the mean of the four columns
    out = {"seed_sd_overall": float(np.mean(np.std(oa, axis=1, ddof=1)))}
    _, lo, hi = seed_stats.t_interval(oa - ob)  # paired by seed
    out["paired_overall"] = float(np.mean((lo <= TRUE_OVERALL) & (TRUE_OVERALL <= hi)))
    out["paired_overall_width"] = float(np.mean(hi - lo))
    _, lo, hi = seed_stats.t_interval(ra[:, :, 3] - rb[:, :, 3])
    out["paired_new_new"] = float(np.mean((lo <= TRUE_NEW_NEW) & (TRUE_NEW_NEW <= hi)))
    out["paired_new_new_width"] = float(np.mean(hi - lo))
    _, lo, hi = seed_stats.t_interval(oa)
    truth_a = 100 * float(P_A.mean())
    out["row_overall"] = float(np.mean((lo <= truth_a) & (truth_a <= hi)))
    out["row_overall_width"] = float(np.mean(hi - lo))
    return out


def welch_coverage(n_a: int, n_b: int, n_exp: int = N_EXP, seed: int = 1) -> float:
    """Rows with different seeds (not paired): Welch's interval of the overall difference."""
    rng = np.random.default_rng(seed)
    pa, _ = seed_probabilities(rng, n_exp, n_a, 0.0)
    _, pb = seed_probabilities(rng, n_exp, n_b, 0.0)
    oa, ob = column_rates(rng, pa).mean(axis=2), column_rates(rng, pb).mean(axis=2)
    _, lo, hi = seed_stats.welch_t_interval(oa, ob)
    return float(np.mean((lo <= TRUE_OVERALL) & (TRUE_OVERALL <= hi)))


def bootstrap_coverage(n_seeds: int, n_exp: int = 300, n_boot: int = 400, seed: int = 2) -> dict[str, float]:
    """The old two-level episode bootstrap (``analysis.bootstrap_replicates``, seeds then episodes, episode
    draw shared by the rows) on the same kind of experiments, episode by episode; and the paired
    t-interval on the very same experiments."""
    rng = np.random.default_rng(seed)
    columns = np.repeat(np.array(cells.COLUMNS), N_EP)  # episode -> its column
    pa, pb = seed_probabilities(rng, n_exp, n_seeds, 0.0)
    hit_boot, hit_t, widths = 0, 0, []
    for e in range(n_exp):
        ma = (rng.random((n_seeds, len(columns))) < np.repeat(pa[e], N_EP, axis=1)).astype(float)
        mb = (rng.random((n_seeds, len(columns))) < np.repeat(pb[e], N_EP, axis=1)).astype(float)
        draws = analysis.episode_draws(columns, rng, n_boot)
        d = (analysis.bootstrap_replicates(ma, draws, rng, n_boot)[:, 4]
             - analysis.bootstrap_replicates(mb, draws, rng, n_boot)[:, 4])
        lo, hi = analysis.percentile_interval(d)
        hit_boot += lo <= TRUE_OVERALL <= hi
        widths.append(hi - lo)
        per_col = lambda m: np.stack([m[:, columns == c].mean(axis=1) for c in cells.COLUMNS], 1).mean(1)  # noqa: E731
        _, tlo, thi = seed_stats.t_interval(100 * per_col(ma) - 100 * per_col(mb))
        hit_t += tlo <= TRUE_OVERALL <= thi
    return {"bootstrap": hit_boot / n_exp, "bootstrap_width": float(np.mean(widths)), "paired_t": hit_t / n_exp}


@pytest.mark.parametrize("n_seeds", [3, 5])
@pytest.mark.parametrize("split_share", [0.0, 0.5])
def test_paired_t_interval_covers_the_true_difference(n_seeds, split_share):
    got = t_coverage(n_seeds, split_share)
    print(f"\n{n_seeds} seeds, split share {split_share}: {got}")
    assert 5.0 < got["seed_sd_overall"] < 7.5  # the spread of the laptop cells (CIL 4.9, GTU 7.2 points)
    assert got["paired_overall"] >= 0.93
    assert got["paired_new_new"] >= 0.93
    assert got["row_overall"] >= 0.93
    assert got["paired_overall"] <= 0.97  # not bought with a uselessly wide interval


@pytest.mark.parametrize("n_a, n_b", [(3, 3), (5, 3), (5, 5)])
def test_welch_interval_covers_when_seeds_do_not_match(n_a, n_b):
    assert welch_coverage(n_a, n_b) >= 0.93


#: what the floor is simulated on: its columns with their weights, and the truth
FLOOR_ON = {"new_new": (((3, 1.0),), TRUE_NEW_NEW), "gap": (((3, 1.0), (0, -1.0)), TRUE_GAP),
            "overall": (tuple((c, 0.25) for c in range(4)), TRUE_OVERALL)}


def floor_coverage(n_seeds: int, on: str = "new_new", n_exp: int = 1000, seed: int = 2) -> dict[str, float]:
    """Coverage of the new town / new weathers difference (``on`` "gap": that difference minus the one in
    the training town under training weathers, TRUE_GAP; "overall": the mean of the four columns'),
    paired t and then widened by the episodes' floor (``with_episode_floor`` on the pooled episodes'
    contrast, as ``judge`` applies it), on the same experiments; how often the floor moved a bound. Fewer
    experiments than above: the floor root-finds its p-value per experiment."""
    rng = np.random.default_rng(seed)
    pa, pb = seed_probabilities(rng, n_exp, n_seeds, 0.5)
    ka, kb = rng.binomial(N_EP, pa), rng.binomial(N_EP, pb)  # (n_exp, n_seeds, 4) successes
    cols, truth = FLOOR_ON[on]
    covered_t = covered_floor = moved = 0
    for a, b in zip(ka, kb):
        va = {s: sum(sign * 100.0 * a[s, c] / N_EP[c] for c, sign in cols) for s in range(n_seeds)}
        vb = {s: sum(sign * 100.0 * b[s, c] / N_EP[c] for c, sign in cols) for s in range(n_seeds)}
        d = seed_stats.difference(va, vb)
        terms = [(sign * side, int(k[:, c].sum()), n_seeds * int(N_EP[c]))
                 for c, sign in cols for k, side in ((a, 1.0), (b, -1.0))]
        f = seed_stats.with_episode_floor(d, terms)
        covered_t += d.estimate.lo <= truth <= d.estimate.hi
        covered_floor += f.estimate.lo <= truth <= f.estimate.hi
        moved += (f.estimate.lo, f.estimate.hi) != (d.estimate.lo, d.estimate.hi)
    return {"t": covered_t / n_exp, "floor": covered_floor / n_exp, "moved": moved / n_exp}


@pytest.mark.parametrize("on", ["new_new", "gap", "overall"])
@pytest.mark.parametrize("n_seeds", [3, 5])
def test_the_episodes_floor_keeps_coverage_and_only_widens(n_seeds, on):
    """The floor on a difference in one column (Newcombe on the pooled episodes), on a gap between two
    columns (its four-term MOVER) or overall (the eight-term MOVER of the four columns' mean) covers the
    truth at least as often as the paired t-interval it widens, and at least 93% of the time."""
    # 500 experiments (the figures printed by this file's __main__ use 1,000): coverage 0.95-0.97 measured,
    # so 0.93 stays 2 standard errors below; a floor that narrows or never moves a bound still fails
    got = floor_coverage(n_seeds, on, n_exp=500)
    print(f"\n{n_seeds} seeds, {on}: {got}")
    assert got["floor"] >= got["t"] and got["floor"] >= 0.93 and got["moved"] > 0


def ratio_coverage(n_seeds: int, n_exp: int = 4000, seed: int = 3) -> dict[str, float]:
    """Coverage of the relative change in the new town under new weathers (the headline's ``A / B - 1``):
    Fieller's paired interval (``ratio_interval``) against the true ratio of the rows' expected success,
    P_A / P_B there. Where it is unbounded (B not clearly above 0) the report gives no bound, which covers
    the truth; that share is reported, and the coverage of the bounded intervals alone."""
    rng = np.random.default_rng(seed)
    pa, pb = seed_probabilities(rng, n_exp, n_seeds, 0.5)
    ra, rb = column_rates(rng, pa)[:, :, 3], column_rates(rng, pb)[:, :, 3]
    truth = float(P_A[3] / P_B[3])
    hits, unbounded = 0, 0
    for a, b in zip(ra, rb):
        _, lo, hi = seed_stats.ratio_interval(a, b, paired=True)
        if lo is None or hi is None:
            unbounded += 1
        else:
            hits += lo <= truth <= hi
    bounded = n_exp - unbounded
    return {"covered": (hits + unbounded) / n_exp, "unbounded": unbounded / n_exp,
            "covered_if_bounded": hits / bounded if bounded else float("nan")}


@pytest.mark.parametrize("n_seeds", [3, 5])
def test_the_relative_change_covers_the_true_ratio(n_seeds):
    """Fieller's interval for a ratio of means covers the true ratio in at least 93% of experiments, as
    reported (an unbounded one gives no bound); with 5 seeds it is almost always bounded, and its bounded
    intervals alone cover too. With 3 seeds a third are unbounded here (B at 35% with a 12-point spread of
    seeds in the column): the report says so rather than print a bound it does not have."""
    got = ratio_coverage(n_seeds)
    print(f"\n{n_seeds} seeds, relative change in the new town / new weathers: {got}")
    assert got["covered"] >= 0.93
    if n_seeds == 5:
        assert got["unbounded"] < 0.05 and got["covered_if_bounded"] >= 0.93


def ratio_floor_coverage(n_seeds: int, n_exp: int = 500, seed: int = 4) -> dict[str, float]:
    """Fieller's relative change in the new town under new weathers (as ``ratio_coverage``) and the same
    widened by the episodes' floor (``with_ratio_floor``: MOVER-R of A's and B's pooled successes there, as
    ``judge`` applies it) on the same experiments; an unbounded interval covers; how often the floor moved
    a bound (made one unbounded included)."""
    rng = np.random.default_rng(seed)
    pa, pb = seed_probabilities(rng, n_exp, n_seeds, 0.5)
    ka, kb = rng.binomial(N_EP, pa)[:, :, 3], rng.binomial(N_EP, pb)[:, :, 3]
    truth, n = float(P_A[3] / P_B[3]), int(N_EP[3])
    covered = lambda lo, hi: lo is None or hi is None or lo <= truth <= hi  # noqa: E731
    hit_fieller = hit_floor = moved = 0
    for a, b in zip(ka, kb):
        _, lo, hi = seed_stats.ratio_interval(100.0 * a / n, 100.0 * b / n, paired=True)
        flo, fhi, m = seed_stats.with_ratio_floor(lo, hi, [(1.0, int(a.sum()), n_seeds * n)],
                                                  [(1.0, int(b.sum()), n_seeds * n)])
        hit_fieller += covered(lo, hi)
        hit_floor += covered(flo, fhi)
        moved += m
    return {"fieller": hit_fieller / n_exp, "floor": hit_floor / n_exp, "moved": moved / n_exp}


@pytest.mark.parametrize("n_seeds", [3, 5])
def test_the_relative_changes_floor_keeps_coverage(n_seeds):
    """Fieller's relative interval widened to the pooled episodes' MOVER-R interval covers the true ratio
    at least as often as Fieller's on the same experiments, and at least 93% of the time, and moves a bound
    in some of them."""
    got = ratio_floor_coverage(n_seeds)
    print(f"\n{n_seeds} seeds, relative change with the episodes' floor: {got}")
    assert got["floor"] >= got["fieller"] and got["floor"] >= 0.93 and got["moved"] > 0


def test_the_old_bootstrap_covers_less():
    """A documented figure, not a requirement: with 3 seeds the two-level bootstrap's interval covers the
    true difference in fewer experiments than the paired t-interval on the same data (deterministic draws)."""
    got = bootstrap_coverage(3)
    print(f"\nbootstrap vs paired t, 3 seeds: {got}")
    assert got["bootstrap"] < got["paired_t"]


if __name__ == "__main__":
    for s in (3, 5):
        for share in (0.0, 0.5):
            print(f"{s} seeds, split share {share}:", {k: round(v, 3) for k, v in t_coverage(s, share).items()})
        print(f"{s} seeds, bootstrap:", {k: round(v, 3) for k, v in bootstrap_coverage(s, n_exp=1000).items()})
    for a, b in ((3, 3), (5, 3), (5, 5)):
        print(f"Welch {a} vs {b} seeds:", round(welch_coverage(a, b), 3))
    for s in (3, 5):
        for on in FLOOR_ON:
            print(f"{s} seeds, episodes' floor, {on}:", floor_coverage(s, on))
        print(f"{s} seeds, relative change (Fieller):", {k: round(v, 3) for k, v in ratio_coverage(s).items()})
        print(f"{s} seeds, relative change, episodes' floor:", ratio_floor_coverage(s, n_exp=4000))
