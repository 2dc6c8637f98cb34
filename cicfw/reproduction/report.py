"""The paper's comparison as results: per-cell outcomes -> Table 4 with 95% intervals -> a verdict per claim.

A *cell* is one (row, seed) of a reproduction: a model trained with that seed and driven on the suite;
``cell.json`` keeps every episode's outcome. This module writes the report (results.json/.csv, RESULTS.md, the
pictures); the parts it reads live beside it (the package's docstring lists them). Where each figure comes from:
a Table-4 entry, ``analysis.row_estimate``; a claim's part, ``claims.judge`` -> ``seed_stats.difference`` ->
``seed_stats.with_episode_floor`` (its terms from ``claims.part_terms``) -> ``seed_stats.holm``; a relative
change, ``seed_stats.ratio_interval`` -> ``seed_stats.with_ratio_floor`` (its terms from
``claims.ratio_terms``); the bootstrap, ``analysis.bootstrap_replicates``; which row drives best,
``ranking.best`` (MCB), and the forest plot, ``ranking.forest``. The
method below, from **Intervals (primary)** up to **Verdicts**, is copied into every report (results.json's
``method``). *Overall* is always the mean of the four table columns (each column weighs the same, as in
reading the paper's table), never the success pooled over all episodes; a seed's overall is the mean of
its four column rates.

**Intervals (primary): the seed is the unit of replication.** A row's value in a column is the mean over
its seeds of each seed's success rate there; its 95% interval is Student's t-interval over those per-seed
rates, ``mean ± t_{0.975, n-1} · sd / sqrt(n)`` (``scipy.stats.t``; ``sd`` with ``n - 1``), widened to
contain the interval of the episodes pooled over the seeds (in a table column their Clopper-Pearson interval,
``statsmodels ... proportion_confint(method="beta")``; on a mean of columns, overall or a town's or weather's
two, the MOVER interval below of that mean of proportions), so that seeds that all drove 100% (or 0%, or
the same number of episodes) do not get a zero-width interval. A row with one seed has no interval. A difference between two rows (A - B) is
computed on per-seed values: where the rows share seeds (the same seed trains on the same
train/validation split, so the cells are paired), the t-interval over the per-seed differences
``A_s - B_s`` of the seeds both ran, with ``n - 1`` degrees of freedom (a row's other seeds are left out,
and the method says how many); only where they share no seed, Welch's t-interval
(``scipy.stats.ttest_ind(equal_var=False)``, Welch-Satterthwaite degrees of freedom) over all seeds of
each; it too is widened, to contain the interval of the same contrast of the two rows' success on their
pooled episodes (a column, a mean of columns with 1/k on each of its k columns, or a gap between two of
them: Zou & Donner's MOVER from each proportion's Wilson interval,
``statsmodels ... proportion_confint(method="wilson")``; on one column this is Newcombe's hybrid score
interval), and its p-value is then the larger of the t-test's and the one dual to
that interval, so seeds whose differences happen to agree (a column's rates come in steps of 1/64 or 1/96,
an easy column often sits at 100%) do not get a zero-width interval and p = 0; the method column says
"widened to the episodes' interval" where it moved a bound. Which row drives best (MCB) reads its one-sided
bounds widened the same way. Cells record their machine, and the same seed
trains another model on another kind of CPU: a difference is computed on the cells of one CPU kind where
both rows have at least 3 seeds there (the method says "within" that kind and how many cells of other
kinds it left out), and where no kind has that, on all cells, marked "mixed CPUs" with each kind's cells.
Every interval is two-sided at 95%, and every test is the two-sided t-test dual to it. A relative change
(``A / B - 1``) gets Fieller's interval for a ratio of means, with the same variances, covariance (paired)
and degrees of freedom, widened likewise to contain the ratio interval of the two rows' success on their
pooled episodes (each a proportion, or a mean of columns' proportions, with its Wilson or MOVER interval
above; the ratio by Donner & Zou's MOVER-R), the relative change saying "widened to the episodes'
interval" where that moved a bound; it is unbounded when B is not clearly above 0 (Fieller's, or the
pooled B's lower limit at 0).
Simulated experiments with a known truth (``tests/test_results_coverage.py``) check that these intervals
cover the truth in at least 93% of experiments at 3 and at 5 seeds.

Whether a row's seeds differ beyond the episodes' luck (the premise of the seed as the unit) is tested per
row and column by ``cicfw.reproduction.seed_spread`` and shown as a table of its own.

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
difference against the part's null (paired t-test on the per-seed differences, or Welch's), so the
verdict and the 95% interval agree: *significant* means the interval excludes the null. A directional
part, ``greater`` (A beats B) or ``less``, is tested against 0: *supported* when A - B is significantly on
the claim's side, *contradicted* when significantly on the other, *inconclusive* otherwise (each side is
the one-sided test at 2.5%). A margin part, ``not_greater`` ("A failed to improve on B") or ``not_less``
("A is no worse than B"), is tested against the equivalence margin (``equivalence_margin`` points):
``not_greater`` is *supported* when the interval lies below +margin (non-superiority: the upper of TOST's
two one-sided tests, at 2.5%), *contradicted* when it lies above +margin (A better by more than the
margin), *not shown* otherwise; ``not_less`` mirrors it at -margin. A part whose rows have fewer than 3
seeds (either row) gets no verdict: *too few seeds* (its difference is still shown). **Family-wise
control:** the family is fixed in advance, every part of every claim in the list (a part without a
verdict, its rows not run or short of seeds, counts as p = 1), adjusted by Holm's step-down method
(``statsmodels.stats.multitest.multipletests(method="holm")``, family-wise error 5%), so a Holm verdict
does not weaken when another row's cells arrive; the Holm verdict uses the adjusted p-value in place of the
interval and is shown beside the uncorrected one. A claim of several parts is *contradicted* when any part
is, *not run* when a part's rows were not run, *too few seeds* when a part lacks seeds, *supported* when
every part is, *inconclusive* (or *not shown*) otherwise.

**Which row drives best.** Fixed before it is run (``cicfw.reproduction.ranking``): only rows with at least
``MIN_SEEDS`` seeds are ranked, the others listed apart; Hsu's multiple comparisons with the best (MCB) over
the ranked rows, each pair paired over the seeds both ran (Welch where none is shared), Bonferroni's
one-sided bounds at 0.05 / (k - 1), gives each row an interval for its success minus the best of the others',
95% jointly, and the set of rows that may drive best.

**Words.** Every comparison of two rows reads as one of *ahead* / *behind* (its interval, after the
correction the report names beside it, excludes 0), *equivalent within ±margin* (the interval lies inside
±``equivalence_margin``: both one-sided tests of TOST pass), or *not separated* (neither). The corrections:
a claim's part, Bonferroni over the parts of its Holm family; a row against CIL (the forest plot), Bonferroni
over the ranked rows' comparisons with CIL; which row drives best, MCB.

**Resumed cells.** A cell whose training was stopped and resumed from an epoch checkpoint records it in
``cell.json`` (``resumed``); the report marks its row and seed (‡) with a footnote: a resumed training does
not restore the data pipeline's and augmentation's random state, so its numbers can differ from an
uninterrupted run's (``RESUME_EXAMPLE``). Every file the report and ``published`` write is readable by others as the umask allows
(0644 under umask 022), like any file the user writes, not owner-only as a bare temporary file would be.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from hydra import compose, initialize_config_module
from hydra.errors import HydraException
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from cicfw.benchmark.evaluation_report import md_row, md_table
from cicfw.benchmark.plots import _plt, _save
from cicfw.benchmark.suite import named_weather_family, with_weather_family
from cicfw.core.errors import CicfwError, install_app_handlers
from cicfw.core.files import atomic_write, write_together
from cicfw.core.json_files import read_json
from cicfw.core.locks import describe_holder, holder_name, live_holder
from cicfw.core.run_folder import claim_folder
from cicfw.reproduction.analysis import analyse
from cicfw.reproduction.cells import (COLUMN_NAMES, COLUMNS, MIXED_CPUS, MIXED_MACHINES, CellPin, CellResult,
                                     check_cell_pin, check_families, check_rows_agree, pinned_epochs, pinned_recipe,
                                     cpu_counts, kind_noun, load_cells, most_first)
from cicfw.reproduction.claims import (Claim, check_margin, default_claims, default_margin, holm_families, judge,
                                       load_claims)
from cicfw.reproduction.published import PUBLISHED_FILES, check_publish_outside, check_publish_target, publish
from cicfw.reproduction.ranking import BASELINE, apart, best, forest, in_catalogue_order, ranking
from cicfw.reproduction.lock import LOCK_FILE, RunLocks
from cicfw.reproduction.relation_choice import (relation_data, shipped_candidates, unusable_errors, unusable_text,
                                                val_errors)
from cicfw.reproduction.seed_spread import seed_spread
from cicfw.reproduction.seed_stats import LEVEL, MIN_SEEDS, TOO_FEW, on_scale
from cicfw.sim.mapplot import png_bytes
from cicfw.sim.render.weather import LEGACY_FAMILY

#: what resuming a killed training changed, measured once: the report's footnote on resumed cells
RESUME_EXAMPLE = ("measured once: GTU's validation steering error after its last epoch was 0.12519 uninterrupted "
                  "and 0.12743 when the run was killed after epoch 1 and resumed")
RESUMED_MARK = "‡"


def pinned_weather_family(manifest: Mapping[str, Any]) -> str | None:
    """The weather family a results folder's suite was driven under: the one its pinned suite names, the
    harsh one for a folder pinned before the families were, None for another simulator."""
    suite = (manifest.get("pinned") or {}).get("suite") or []
    return named_weather_family(with_weather_family(suite, default=LEGACY_FAMILY))


def folder_weather_family(manifest: Mapping[str, Any]) -> str | None:
    """``pinned_weather_family`` of a folder with a pinned suite; None (not known) for one without."""
    return pinned_weather_family(manifest) if (manifest.get("pinned") or {}).get("suite") is not None else None


def folder_pin(manifest: Mapping[str, Any]) -> CellPin:
    """What a results folder's pin (reproduce.json's ``pinned``) says each of its cells was made with: its
    dataset, its weather family, the epochs and the recipe keys its training overrides set."""
    pinned = manifest.get("pinned") or {}
    train = pinned.get("train") or []
    return CellPin(dataset=pinned.get("dataset"), weather_family=folder_weather_family(manifest),
                   family_known=pinned.get("suite") is not None, epochs=pinned_epochs(train),
                   recipe=pinned_recipe(train))


def weathers_said(manifest: Mapping[str, Any]) -> str:
    """``; weathers: the `carla` family`` for a folder pinned to a weather family of the embedded simulator;
    nothing for a folder without a pinned suite or driven by another simulator."""
    if (manifest.get("pinned") or {}).get("suite") is None:
        return ""
    family = pinned_weather_family(manifest)
    return f"; weathers: the `{family}` family" if family else ""


def _families(claims: Sequence[Mapping[str, Any]]) -> str:
    """The Holm families, fixed in advance, in words: one family, or each adjusted on its own."""
    sizes = holm_families(claims)
    if len(sizes) <= 1:
        return f"a family fixed in advance, the {sum(sizes.values())} parts of the claims below"
    named = [f"the {n} parts of the {f!r} claims" for f, n in sizes.items()]
    return f"families fixed in advance, each adjusted on its own: {', '.join(named)}"


def _method_text(kinds: Sequence[str] = ()) -> str:
    """results.json's ``method``: this module's docstring from **Intervals (primary)** up to **Verdicts**
    (editing that span changes every re-rendered report under docs/results), and where a GPU is among the
    cells' ``kinds``, what a kind then is."""
    doc = __doc__ or ""
    text = ""
    if "**Intervals (primary):" in doc:
        text = doc.split("**Intervals (primary):")[1].split("**Verdicts.**")[0].strip()
    if kind_noun(kinds) == "machine":
        text += (" Some of these cells ran on a GPU, where the same seed trains another model again (its kernels sum "
                 "in another order): a kind is then the CPU kind plus the GPU where there was one, and a comparison "
                 f"that pools a GPU's cells with others is marked \"{MIXED_MACHINES}\".")
    return text


def spread_data(cs: Sequence[CellResult]) -> dict[str, dict[str, Any]]:
    """Per column (and per command in the bar's column, training town / training weathers): do the row's seeds
    differ beyond the episodes' luck (``cicfw.reproduction.seed_spread``)? Empty with fewer than two seeds."""
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


def machine_counts(cells: Sequence[CellResult]) -> dict[str, int]:
    """Each machine the cells ran on (``cell.json``'s ``machine``) -> its number of cells, most first."""
    return most_first(str(c.meta.get("machine") or "an unrecorded machine") for c in cells)


def report_data(cells: Sequence[CellResult], failed: Sequence[Mapping[str, Any]],
                catalogue: Mapping[str, Mapping[str, Any]], manifest: Mapping[str, Any],
                n_boot: int = 4000, claims: Sequence[Claim] | None = None,
                margin: float | None = None, relation_candidates: Sequence[str] | None = None) -> dict[str, Any]:
    """Everything RESULTS.md shows, as JSON-ready data (``claims``, the equivalence ``margin`` and fine tuning's
    ``relation_candidates``: the paper's and conf/reproduce.yaml's when not given)."""
    an = analyse(cells, n_boot=n_boot)
    claims = default_claims() if claims is None else list(claims)
    margin = default_margin() if margin is None else check_margin(margin)
    candidates = shipped_candidates() if relation_candidates is None else list(relation_candidates)
    kinds = cpu_counts(cells)
    labels = {r: str((catalogue.get(r) or {}).get("label", r)) for r in {*catalogue, *an.rows}}
    paper = {r: list(catalogue[r]["paper"]) for r in catalogue if (catalogue[r] or {}).get("paper")}
    machines = {c.meta.get("machine") for cs in an.rows.values() for c in cs}
    rows = []
    for r in in_catalogue_order(an.rows, catalogue):
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
            "per_seed": {str(c.seed): {**{col: c.rate(col) for col in COLUMNS}, "overall": c.rate()} for c in cs},
            "manoeuvres": {m: float(np.mean(v)) for m, v in man.items()},
            "spread": spread_data(cs),
            "paper": paper.get(r),
            "wall_s": {str(c.seed): c.meta.get("wall_s") for c in cs},
            "code": {str(c.seed): c.meta["code"] for c in cs if c.meta.get("code")},
            # each cell's machine, only where the folder's cells come from more than one (``continue_from``)
            "machine": {str(c.seed): c.meta.get("machine") for c in cs} if len(machines) > 1 else {},
            # the row's cells per machine kind (CPU, plus GPU where it had one), only where the folder's cells
            # span kinds
            "cpus": cpu_counts(cs) if len(kinds) > 1 else {},
            "resumed": {str(c.seed): c.meta["resumed"] for c in cs if c.meta.get("resumed")},
            "curve": {str(c.seed): c.meta.get("curve", []) for c in cs if c.meta.get("curve")},
        })
    ranked, few = ranking(an, list(catalogue)), apart(an, list(catalogue))
    named = {f"{c.row}/seed{c.seed}": c.meta for c in cells}  # row/seedK -> cell.json, as relation_choice reads them
    return {"manifest": dict(manifest), "method": _method_text(list(kinds)), "n_boot": n_boot, "level": LEVEL,
            "min_seeds": MIN_SEEDS, "overall": "mean of the four table columns (not pooled episodes)",
            "equivalence_margin": margin, "machines": machine_counts(cells), "cpus": kinds,
            "ranking": ranked, "apart": few, "best": best(an, ranked, margin),
            "forest": forest(an, ranked, paper, margin, few),
            "rows": rows, "claims": judge(an, claims, paper, labels, margin),
            "relation": relation_data(val_errors(named, candidates), candidates, labels,
                                      unusable_errors(named, candidates)),
            "failed": [{"row": f.get("row"), "seed": f.get("seed"), "error": f.get("error")} for f in failed]}


def _paper_value(paper: Sequence[float] | None, i: int) -> float | None:
    """The paper's value in column ``i`` of ``[*COLUMNS, "overall"]`` (overall: the mean of its four)."""
    return None if not paper else (paper[i] if i < 4 else float(np.mean(paper)))


def results_csv(data: Mapping[str, Any]) -> str:
    """One line per (row, column): the mean over seeds, the t-interval, the bootstrap's (secondary), the
    paper's value and the per-seed values."""
    lines = ["row,label,decoder,column,seeds,mean,lo,hi,boot_lo,boot_hi,paper,per_seed"]
    nz = lambda v: "" if v is None else v  # noqa: E731
    for r in data["rows"]:
        for i, col in enumerate([*COLUMNS, "overall"]):
            e, b = r["columns"][col], r["bootstrap"][col]
            pv = "" if not r["paper"] else f"{_paper_value(r['paper'], i):.2f}"
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


def _diff(e: Mapping[str, Any]) -> str:
    """A difference of two success rates with its interval, clipped to [−100, +100] (``seed_stats.on_scale``)."""
    lo, hi = on_scale(e.get("lo"), e.get("hi"))
    return _est({**e, "lo": lo, "hi": hi}, "+")


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
    widened = ", widened to the episodes' interval" if "widened" in rel.get("method", "") else ""
    return f"; relative {rel['mean']:+.0f}% [{rel['lo']:+.0f}, {rel['hi']:+.0f}]{widened}"


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
            w = p.get("word") or {}
            said = f"; {word_text(w)}, {w.get('correction')}" if w.get("word") else ""
            bits.append(f"{p['comparison']}{ab}: {_est(p['measured'], '+')} points{_relative(rel)} "
                        f"({p['method']}{paper}{said})")
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


def machine_line(data: Mapping[str, Any]) -> str:
    """The header's bullet naming every machine the cells ran on, with its number of cells."""
    machines = data.get("machines") or {}
    if len(machines) <= 1:
        m = next(iter(machines), data["manifest"].get("machine", "?"))
        return f"- **Machine:** {m}" + (f" (all {machines[m]} cells)." if m in machines else ".")
    line = "- **Machines:** " + "; ".join(f"{n} cells on {m}" for m, n in machines.items()) + "."
    if len(data.get("cpus") or {}) > 1:
        line += (f" {len(data['cpus'])} kinds of {kind_noun(data['cpus'])} ("
                 + ", ".join(f"{k}: {n} cells" for k, n in data["cpus"].items())
                 + "), and the same seed trains another model on another kind: rows are compared on the cells of "
                 f"one kind where both have {data.get('min_seeds', MIN_SEEDS)} seeds there, and a comparison that "
                 f"pools kinds says {_mixed_marks(data)}.")
    return line


def _mixed_marks(data: Mapping[str, Any]) -> str:
    """How a comparison that pools kinds is marked: *mixed CPUs*, and *mixed machines* where a GPU is among them."""
    gpu = kind_noun(data.get("cpus") or {}) == "machine"
    return f"*{MIXED_CPUS}*" + (f" (*{MIXED_MACHINES}* where a GPU is among them)" if gpu else "")


def _cpus(counts: Mapping[str, int]) -> str:
    return ", ".join(f"{k} {n}" for k, n in counts.items())


def _bounds(lo: float | None, hi: float | None, rates: bool = False) -> str:
    """An interval without its point: ``[−12.3, +0.0]`` (``–`` for a missing bound); ``rates``: one of a
    difference of two success rates, clipped to [−100, +100] (``seed_stats.on_scale``)."""
    lo, hi = on_scale(lo, hi) if rates else (lo, hi)
    f = lambda v: "–" if v is None else f"{v:+.1f}"  # noqa: E731
    return f"[{f(lo)}, {f(hi)}]"


def word_text(w: Mapping[str, Any] | None, rates: bool = False) -> str:
    """A comparison's word with the corrected interval it is read on: ``not separated [−20.1, +15.3]``
    (``rates``: clipped as ``_bounds`` clips); *too few seeds* where it has none."""
    if not w or not w.get("word"):
        return TOO_FEW
    return f"{w['word']} {_bounds(w.get('lo'), w.get('hi'), rates)}"


def answer_lines(data: Mapping[str, Any], pictures: str = "") -> list[str]:
    """The report's opening: which row drives best by Hsu's MCB (``ranking``), the rows that may, those behind
    the best, the ranked rows with their MCB intervals, the rows with too few seeds listed apart, and the forest
    plot (``pictures``: its folder prefix)."""
    by = {r["row"]: r for r in data["rows"]}
    b = data.get("best")
    if not b:
        return []
    min_seeds = data.get("min_seeds", MIN_SEEDS)
    label = lambda row: by[row]["label"]  # noqa: E731
    res = {r["row"]: r for r in b["rows"]}
    k = len(b["rows"])
    how = (f"Hsu's multiple comparisons with the best (MCB) over the {k} rows with at least {min_seeds} seeds, "
           f"each row against every other by a one-sided {100 * b['confidence']:.2f}% bound (Bonferroni over its "
           f"{b['comparisons']} comparisons; paired over the seeds both rows ran, Welch's t where they share none), "
           "95% jointly")
    if len(b["best"]) == 1:
        text = (f"**Which row drives best?** **{label(b['best'][0])}**, "
                f"{_est(by[b['best'][0]]['columns']['overall'])}% overall: ahead of every other ranked row ({how}).")
    else:
        text = (f"**Which row drives best?** Not one row: {len(b['best'])} of the {k} ranked rows may drive best "
                f"({how}): " + ", ".join(label(r) for r in b["best"]) + ".")
        behind = [label(r["row"]) for r in b["rows"] if r["word"] == "behind"]
        if behind:
            text += " Behind the best: " + ", ".join(behind) + "."
    few = data.get("apart") or []
    if few:
        text += (f" Fewer than {min_seeds} seeds, listed apart and not ranked: "
                 + ", ".join(f"{label(r)} ({len(by[r]['seeds'])} seed{'s' if len(by[r]['seeds']) != 1 else ''})"
                             for r in few) + ".")
    marks = [m for m in (MIXED_CPUS, MIXED_MACHINES) if any(m in p["method"] for p in b.get("pairs") or [])]
    mixed = sum(any(m in p["method"] for m in marks) for p in b.get("pairs") or [])
    if mixed:
        text += (f" {mixed} of the {len(b['pairs'])} pairs pool cells of different {kind_noun(data.get('cpus') or {})} "
                 f"kinds (" + " or ".join(f"*{m}*" for m in marks) + ").")
    lines = [text, "", f"Rows with at least {min_seeds} seeds by overall success, best first: mean over seeds [95% "
             "t-interval], then the MCB interval of the row's success minus the best of the others' (an upper "
             "bound of +0.0: some row drives better; a lower bound of +0.0: it drives best) and its word:", ""]
    for n, row in enumerate(data.get("ranking") or [], 1):
        r, m = by[row], res[row]
        cpus = f"; {_cpus(r['cpus'])}" if r.get("cpus") else ""
        lines.append(f"{n}. **{r['label']}** {_est(r['columns']['overall'])}%, {len(r['seeds'])} seeds{cpus}: "
                     f"MCB {_bounds(m['lo'], m['hi'], rates=True)}: {m['word']}.")
    if any(res[row]["lo"] is None or res[row]["hi"] is None for row in data.get("ranking") or []):
        lines += ["", f"A bound shown as – rests on a pair with fewer than {min_seeds} seeds to compare on (the "
                      f"seeds both ran): {TOO_FEW}, no bound (the table of pairs below says which)."]
    if few:
        lines += ["", f"Listed apart (fewer than {min_seeds} seeds: no interval that could rank them), in the "
                      "catalogue's order:", ""]
        lines += [f"- {by[r]['label']}: {_est(by[r]['columns']['overall'])}%, {len(by[r]['seeds'])} seed(s) †"
                  for r in few]
    if data.get("forest"):
        base = by[BASELINE]["label"]
        lines += ["", f"![each row's overall success minus {base}'s, 95% intervals, the paper's difference beside]"
                      f"({pictures}forest.png)"]
    return lines + [""]


def forest_lines(data: Mapping[str, Any]) -> list[str]:
    """RESULTS.md's table of the forest plot: each row minus CIL overall, its method, the paper's difference
    and its word on the corrected interval; the rows with too few seeds below, with no word."""
    rows = data.get("forest") or []
    if not rows:
        return []
    by = {r["row"]: r for r in data["rows"]}
    base = by[BASELINE]["label"]
    size = sum(not r.get("apart") for r in rows)
    lines = ["", f"## Each row against {base} (the forest plot)", "",
             f"Each row's overall success minus {base}'s (points) with its 95% t-interval: paired over the seeds "
             "both ran, Welch's t where they share none, widened to the pooled episodes' interval where that is "
             "wider (the method says so). Its word (*ahead*, *behind*, *equivalent within "
             f"±{data.get('equivalence_margin', 5):g}*, *not separated*) is read on the interval corrected by "
             f"Bonferroni over the {size} comparisons of the ranked rows with {base}, shown beside it; a row with "
             "too few seeds gets none.", ""]
    return lines + md_table(
        ["Row", "Seeds", f"Row − {base} [95% t]", "Method", "Paper", "Word [corrected interval]"], "lrrlrl",
        ([by[r["a"]]["label"], f"{len(by[r['a']]['seeds'])}{'' if not r.get('apart') else ' †'}",
          _diff(r["measured"]), r["method"], "–" if r.get("paper") is None else f"{r['paper']:+.1f}",
          word_text(r.get("word"), rates=True)] for r in rows))


def pair_lines(data: Mapping[str, Any]) -> list[str]:
    """RESULTS.md's table of every pair of ranked rows MCB compares: the difference with its 95% t-interval,
    which test (paired over the seeds both ran, or Welch), and the one-sided bounds MCB uses (*too few seeds*
    where the pair has none: ``ranking._mcb``), these clipped to [−100, +100] (the word's corrected interval is
    printed whole: the published reports print it so)."""
    b = data.get("best")
    if not b or not b.get("pairs"):
        return []
    by = {r["row"]: r for r in data["rows"]}
    lines = ["", "## Each pair of ranked rows (MCB's comparisons)", "",
             f"A − B overall (points) with its 95% t-interval and test (widened to the pooled episodes' interval "
             f"where the method says so); the one-sided {100 * b['confidence']:.2f}% bounds MCB reads (lower, upper; "
             f"never closer than the pooled episodes' at that confidence); and the pair's own word, read on the interval corrected by Bonferroni "
             f"over all {len(b['pairs'])} pairs.", ""]
    return lines + md_table(
        ["A", "B", "A − B [95% t]", "Method", "MCB's bounds", "Word [corrected interval]"], "llrlrl",
        ([by[p["a"]]["label"], by[p["b"]]["label"], _diff(p["measured"]), p["method"],
          TOO_FEW if p["lower"] is None and p["upper"] is None else _bounds(p["lower"], p["upper"], rates=True),
          word_text(p.get("word"))] for p in b["pairs"]))


def _table4_lines(data: Mapping[str, Any]) -> list[str]:
    """Table 4: each row's mean over seeds [95% t] per column and overall, the paper's value below; a CPU
    column (Machine where a GPU is among the kinds) where the folder's cells span kinds."""
    cpu = len(data.get("cpus") or {}) > 1
    head = "CPU (cells)" if kind_noun(data.get("cpus") or {}) == "CPU" else "Machine (cells)"
    lines = md_table(["Row", "Decoder", "Seeds", *([head] if cpu else []), *COLUMN_NAMES, "Overall"],
                     "llr" + ("l" if cpu else "") + "r" * 5)
    for r in data["rows"]:
        cells = [f"{_est(r['columns'][col])}<br>*{_pct(_paper_value(r['paper'], i))}*"
                 for i, col in enumerate([*COLUMNS, "overall"])]
        seeds = (f"{len(r['seeds'])}" + ("" if r["enough_seeds"] else " †")
                 + (f" {RESUMED_MARK}" if r.get("resumed") else ""))
        lines.append(md_row([r["label"], r["decoder"] or "–", seeds, *([_cpus(r.get("cpus") or {})] if cpu else []),
                             *cells]))
    return lines


def _claims_intro(data: Mapping[str, Any]) -> str:
    """The paragraph above the claims' table: how each part is tested and read."""
    min_seeds = data.get("min_seeds", MIN_SEEDS)
    margin = data.get("equivalence_margin")
    return ("Each part of a claim is a difference of per-seed values (A − B, points) with its two-sided 95% "
            "t-interval and the two-sided t-test dual to it: **paired t** over the per-seed differences when both "
            "rows ran the same seeds (the same seed trains on the same split), **Welch t** otherwise; on the cells "
            f"of one {kind_noun(data.get('cpus') or {})} kind where both rows have {min_seeds} seeds there (the method "
            f"says *within* it), else on all of them, marked {_mixed_marks(data)}. A part that A beats B (>, or <) "
            "is tested against 0: *supported* when the interval lies on the claim's side of 0, *contradicted* on the "
            "other side, *inconclusive* when it holds 0. A part that A is *not better than* B is tested against "
            "the equivalence margin, "
            f"+{margin:g} points (`equivalence_margin` in conf/reproduce.yaml): *supported* when the interval lies "
            f"below +{margin:g} (non-superiority, the upper of TOST's two one-sided tests), *contradicted* when "
            f"above +{margin:g}, *not shown* when it holds +{margin:g}; p is the test against the part's null. "
            f"*Holm*: the same with Holm-adjusted p-values over {_families(data['claims'])}, a part "
            f"without a verdict counting as p = 1 (family-wise error 5%). A part whose rows have fewer than {min_seeds} "
            "seeds: *too few seeds*. *Word*: how A and B compare, whatever the claim, read on the interval "
            "corrected by Bonferroni over the parts of the claim's family (shown beside it): *ahead* or *behind* "
            f"when it excludes 0, *equivalent within ±{margin:g}* when it lies inside ±{margin:g} (TOST), else *not "
            "separated*. *Bootstrap* is the two-level episode bootstrap's 95% interval, a secondary "
            "figure (too narrow with few seeds), not used for a verdict.")


def markdown(data: Mapping[str, Any], pictures: str = "") -> str:
    """RESULTS.md: which row drives best (the answer, the rows by overall success, the forest plot), the
    machines and budget, Table 4 with t-intervals over seeds and the paper's values, the claims
    (uncorrected and Holm verdicts, each with its method, the episode bootstrap beside as a secondary
    figure, the paper's sentences), a generated summary, per-seed values, success by manoeuvre, the
    learning curve and each cell's wall time. ``pictures``: the prefix of the pictures' links."""
    m = data["manifest"]
    min_seeds = data.get("min_seeds", MIN_SEEDS)
    lines = [TITLE, "", *answer_lines(data, pictures)]
    lines += [f"- **Budget:** `{m.get('budget')}`; suite: `{m.get('suite', {}).get('name')}` "
              f"({m.get('episodes', '?')} episodes per cell){weathers_said(m)}; dataset: {m.get('dataset_summary', '?')}.",
              machine_line(data),
              *[f"- **Continued from:** `{c.get('from')}` ({len(c.get('cells') or [])} finished cells copied"
                + (f", only those made on a machine with {c['only_machine']!r}" if c.get("only_machine") else
                   f", made on {c['machine']}" if c.get("machine") else "") + f", {c.get('date', '?')})."
                for c in m.get("continued_from") or []],
              f"- **Cells:** {sum(len(r['seeds']) for r in data['rows'])} finished"
              + (f", {len(data['failed'])} failed" if data["failed"] else "") + ".",
              "- **Intervals:** 95% t-intervals over seeds (the seed is the unit of replication: "
              "`mean ± t(0.975, n−1) · sd / √n` over the per-seed success rates; never narrower than the interval of "
              "the episodes pooled over the seeds: Clopper-Pearson's in a column, MOVER's overall). Success in %; each cell "
              "`mean over seeds [95% interval]`, the paper's value in *italics* below. *Overall* is the mean of "
              "the four columns (per seed, then over seeds), not the success pooled over episodes. The rows keep "
              "the paper's order here (by overall success above). "
              f"A row with fewer than {min_seeds} seeds is shown but gets no verdict (†).", ""]
    lines += _table4_lines(data)
    if any(not r["enough_seeds"] for r in data["rows"]):
        lines += ["", f"† fewer than {min_seeds} seeds: too few seeds for a verdict (with 2 seeds the t-interval "
                      "uses t(0.975, 1) = 12.7; with 1 seed there is none)."]
    resumed = resumed_text(data)
    if resumed:
        lines += ["", resumed]
    lines += ["", "## The paper's claims", "", _claims_intro(data), "", *md_table(
        ["Claim", "Comparison", "Method", "Measured (points) [95% t]", "Paper", "p", "Holm p", "Verdict",
         "Holm verdict", "Word [corrected interval]", "Bootstrap (secondary)"], "lllrrrrlllr")]
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
            lines.append(md_row([head, p["comparison"], p.get("method", "–"), ms, pp, _p(p.get("p")),
                                 _p(p.get("p_holm")), p["verdict"], p.get("verdict_holm", "–"),
                                 word_text(p.get("word")) if "measured" in p else "–", boot]))
    quoted = [c for c in data["claims"] if c.get("quote")]
    if quoted:
        lines += ["", "### The claims in the paper's words", ""]
        lines += [f"- **{c['claim']}** — “{c['quote']}” ({c['source']})" for c in quoted]
    lines += forest_lines(data)
    lines += pair_lines(data)
    lines += relation_lines(data.get("relation"))
    lines += ["", "## Summary (generated from the numbers above)", "", *summary_lines(data)]
    lines += ["", "## Per seed (success %, overall = mean of the four columns)", "", *md_table(
        ["Row", "Seed", *COLUMN_NAMES, "Overall"], "lrrrrrr",
        ([r["label"], s + (f" {RESUMED_MARK}" if s in (r.get("resumed") or {}) else ""),
          *(f"{v[c]:.1f}" for c in [*COLUMNS, "overall"])] for r in data["rows"] for s, v in r["per_seed"].items()))]
    lines += ["", f"## Secondary: the two-level episode bootstrap ({data['n_boot']} replicates)", "",
              "Seeds, then episodes within each column, drawn with replacement (paired by episode between rows). "
              "Kept for comparison with earlier reports; with few seeds its intervals are too narrow "
              "(docs/reproduce.md gives its simulated coverage).", "", *md_table(
                  ["Row", "Seeds", *COLUMN_NAMES, "Overall"], "lrrrrrr",
                  ([r["label"], len(r["seeds"]), *(_est(r["bootstrap"][c]) for c in [*COLUMNS, "overall"])]
                   for r in data["rows"]))]
    if any(r["manoeuvres"] for r in data["rows"]):
        names = [n for n in ("left", "right", "straight") if any(n in r["manoeuvres"] for r in data["rows"])]
        lines += ["", "## Success by manoeuvre (mean over seeds, %)", "", *md_table(
            ["Row", *(n.capitalize() for n in names)], "l" + "r" * len(names),
            ([r["label"], *(_pct(r["manoeuvres"].get(n)) for n in names)] for r in data["rows"]))]
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
    lines += ["", f"## Wall time per cell (s, {where})", "", *md_table(
        ["Row", "Seed", "Train", "Evaluate", "Curve evaluations", *(n for n, _ in optional)],
        "lrrrr" + "l" * len(optional),
        ([r["label"], s, *(_pct((w or {}).get(k)) for k in ("train", "evaluate", "curve")),
          *(value(r, s) for _, value in optional)] for r in data["rows"] for s, w in r["wall_s"].items()))]
    if data["failed"]:
        lines += ["", "## Failed cells", ""] + [f"- {f['row']} seed {f['seed']}: {f['error']}" for f in data["failed"]]
    return "\n".join(lines) + "\n"


def relation_lines(rel: Mapping[str, Any] | None) -> list[str]:
    """Fine tuning's R: each candidate's validation steering error per seed and over the seeds all share, and
    the row chosen (the lowest mean; the paper sets R by hand and does not publish it)."""
    if not rel:
        return []
    seeds = [str(s) for s in rel["seeds"]]
    left = rel.get("unusable") or {}  # row/seedK -> its val_steer_mae that is no finite number
    every = sorted({s for c in rel["candidates"] for s in c["val_steer_mae"]}
                   | {k.split("/seed")[1] for k in left}, key=int)
    lines = ["", "## Fine tuning's R, chosen by validation error", "",
             "The paper sets Table 1's relationship matrix R by hand and does not publish it. Each candidate R "
             "trains as a row of its own; the one with the lowest mean validation steering error (the held-out "
             "part of the training town's data, never the suite) over the seeds every candidate has "
             f"({', '.join(seeds) or 'none yet'}) is the fine-tuning row, a tie keeping the earlier.", "",
             *md_table(["Candidate", *(f"Seed {s}" for s in every), "Mean over shared seeds"],
                       "l" + "r" * (len(every) + 1))]
    for c in rel["candidates"]:
        chosen = c["row"] == rel["chosen"]
        mean = "–" if c["mean"] is None else f"{c['mean']:.5f}" + (" (chosen)" if chosen else "")
        errors = (f"{c['val_steer_mae'][s]:.5f}" if s in c["val_steer_mae"] else left.get(f"{c['row']}/seed{s}", "–")
                  for s in every)
        lines.append(md_row(["**" + c["label"] + "**" if chosen else c["label"], *errors, mean]))
    if left:
        lines += ["", f"Left out: {unusable_text(left)}; a cell without a finite validation error leaves its "
                      "candidate out at that seed, so the means are over the seeds where every candidate has one."]
    if rel["chosen"] is None:
        lines += ["", "Not chosen yet: no seed has a finite validation error for every candidate." if left else
                  "Not chosen yet: some candidate has no finished cell at a seed the others have."]
    return lines


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
             "same margins, `cicfw.reproduction.seed_spread`), then each seed's failures in seed order. A small p: "
             "the seeds trained models of different quality, beyond what the episodes' luck gives.", ""]
    return lines + md_table(
        ["Row", "Seeds", *COLUMN_NAMES, *(f"{COLUMN_NAMES[0]}: {m} turns" if m != "straight"
                                          else f"{COLUMN_NAMES[0]}: straight" for m in commands)],
        "lr" + "r" * (len(COLUMNS) + len(commands)),
        ([r["label"], len(r["seeds"]), *(_spread(r["spread"][c]["all"]) for c in COLUMNS),
          *(_spread(r["spread"][COLUMNS[0]].get(m)) for m in commands)] for r in rows))


def curve_points(data: Mapping[str, Any]) -> dict[str, list[tuple[int, float, float, float, int]]]:
    """row -> [(samples seen, mean, min, max of overall success over seeds, number of seeds)] for rows
    with a curve (a point without an overall, from a suite that lacks a column, is left out)."""
    out = {}
    for r in data["rows"]:
        by_samples: dict[int, list[float]] = {}
        for pts in r["curve"].values():
            for p in pts:
                if p.get("overall") is not None:
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

    def point(m: float, lo: float, hi: float, n: int) -> str:  # one seed has a value, not a range
        return f"{m:.1f}" if n == 1 else f"{m:.1f} [{lo:.1f}, {hi:.1f}] ({n} seeds)"

    cells = {label: {s: rest for s, *rest in v} for label, v in pts.items()}
    return md_table(["Row", *(f"{s:,} samples" for s in samples)], "l" + "r" * len(samples),
                    ([label, *(point(*d[s]) if s in d else "–" for s in samples)] for label, d in cells.items()))


def row_colours(rows: Sequence[str], order: Sequence[str] = ()) -> dict[str, int]:
    """Each row's colour index: its place in ``order`` (the catalogue, the paper's Table-4 order), so a row
    keeps its colour in every folder's picture whichever rows are present; rows outside it follow it."""
    order = list(order)
    extras = [r for r in rows if r not in order]
    return {r: order.index(r) if r in order else len(order) + extras.index(r) for r in rows}


def _colour(plt: Any, k: int) -> Any:
    """Colour ``k``: tab10's ten, then their light shades (tab20's odd entries), then round again."""
    return plt.get_cmap("tab20")((2 * k) % 20 + (k // 10) % 2)


def results_figure(data: Mapping[str, Any], order: Sequence[str] = ()) -> Any:
    """Success per column with 95% t-interval bars (over seeds, widened to the episodes' floor, as the
    table's) for each row; the paper's values as crosses
    in the row's colour. ``order``: the catalogue's rows, which fix each row's colour (``row_colours``).
    Returns the figure, not yet saved (``plot_results`` saves it)."""
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
    # the bars are row_estimate's: the t-interval widened to the pooled episodes' interval
    ax.set_title(f"Suite {suite}, budget {data['manifest'].get('budget')}: mean over seeds, 95% t-interval over seeds\n"
                 f"(never narrower than the interval of the episodes pooled over the seeds)", fontsize=10)
    return fig


def forest_figure(data: Mapping[str, Any], order: Sequence[str] = ()) -> Any:
    """Each row's overall success minus CIL's (``data["forest"]``): the ranked rows best first, with the 95%
    t-interval (thick) and the Bonferroni interval its word is read on (thin), the paper's difference as a
    cross beside it, the numbers and the word at the right; below a line, apart, the rows with too few seeds
    (not ranked, no word). A hollow point where the comparison pools kinds. The figure, not yet saved;
    None (nothing drawn) without CIL or another row."""
    rows = data.get("forest") or []
    if not rows:
        return None

    plt = _plt()
    by = {r["row"]: r for r in data["rows"]}
    colour = row_colours(list(by), order)
    ranked = [r for r in rows if not r.get("apart")]
    few = [r for r in rows if r.get("apart")]
    gap = 1.0 if few and ranked else 0.0
    ys = [len(rows) - 1 + gap - i for i in range(len(ranked))] + [len(few) - 1 - i for i in range(len(few))]
    fig, ax = plt.subplots(figsize=(8.8, 0.55 * (len(rows) + gap) + 1.9), layout="constrained")
    for y, rec in zip(ys, [*ranked, *few]):
        m, c = rec["measured"], _colour(plt, colour[rec["a"]])
        face = "white" if rec["cpu"] == "mixed" else c
        w = rec.get("word") or {}
        if w.get("lo") is not None:
            ax.plot([w["lo"], w["hi"]], [y, y], color=c, lw=1, alpha=0.6)
        if m["lo"] is not None:
            ax.errorbar(m["mean"], y, xerr=[[m["mean"] - m["lo"]], [m["hi"] - m["mean"]]], fmt="o", color=c,
                        mfc=face, capsize=4, ms=7, elinewidth=2.5)
        else:
            ax.plot(m["mean"], y, "o", color=c, mfc=face, ms=7)
        if rec["paper"] is not None:
            ax.plot(rec["paper"], y - 0.25, "x", color=c, ms=8, mew=2)
        said = f"{_diff(m)}" + ("" if rec["paper"] is None else f"  (paper {rec['paper']:+.1f})")
        said += f": {w['word']}" if w.get("word") else (": apart" if rec.get("apart") else "")
        ax.text(1.02, y, said, transform=ax.get_yaxis_transform(), va="center", fontsize=8)
    labels = [by[r["a"]]["label"] + ("" if by[r["a"]]["enough_seeds"] else " †") for r in [*ranked, *few]]
    ax.set_yticks(ys, labels)
    ax.set_ylim(-0.8, len(rows) + gap - 0.4)
    if few and ranked:
        ax.axhline(len(few) - 0.5 + gap / 2, color="grey", lw=0.8, ls="--")
        ax.text(0.01, len(few) - 0.5 + gap / 2, f"fewer than {data.get('min_seeds', MIN_SEEDS)} seeds: listed apart, "
                "not ranked", transform=ax.get_yaxis_transform(), va="bottom", fontsize=8, color="grey")
    ax.axvline(0.0, color="grey", lw=1)
    ax.grid(axis="x", alpha=0.3)
    ax.set_xlabel(f"overall success minus {by[BASELINE]['label']}'s (points)")
    handles = [ax.plot([], [], "o-", color="black", lw=2.5, label="mean over seeds, 95% interval (t, never narrower than the episodes')")[0]]
    if any((r.get("word") or {}).get("lo") is not None for r in rows):
        handles.append(ax.plot([], [], "-", color="black", lw=1, alpha=0.6,
                               label="Bonferroni interval (the word's)")[0])
    if any(r["cpu"] == "mixed" for r in rows):
        noun = kind_noun(data.get("cpus") or {})
        handles.append(ax.plot([], [], "o", color="black", mfc="white",
                               label=f"hollow: pools {noun} kinds ({MIXED_CPUS}"
                                     + (")" if noun == "CPU" else f" or {MIXED_MACHINES})"))[0])
    if any(r["paper"] is not None for r in rows):
        handles.append(ax.plot([], [], "x", color="black", mew=2, label="the paper's difference (its Table 4)")[0])
    fig.legend(handles=handles, fontsize=8, loc="outside lower center", ncol=len(handles), frameon=False)
    suite = (data["manifest"].get("suite") or {}).get("name", "?")
    ax.set_title(f"Each row against {by[BASELINE]['label']}, suite {suite}, budget {data['manifest'].get('budget')}",
                 fontsize=10)
    return fig


def curve_figure(data: Mapping[str, Any], order: Sequence[str] = ()) -> Any:
    """Overall success against training samples seen, per row (mean over seeds, band = min..max), each row
    in its colour of ``plot_results``. The figure, not yet saved; None without a curve."""
    pts = curve_points(data)
    if not pts:
        return None

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
    suite = (data["manifest"].get("suite") or {}).get("name", "?")  # a budget may drive another suite
    ax.set_title(f"Learning curve on suite {suite} (band: min..max over seeds)")
    return fig


def plot_results(data: Mapping[str, Any], path: Path, order: Sequence[str] = ()) -> Path:
    """``results_figure`` written to ``path``."""
    return _save(results_figure(data, order), Path(path))


def plot_forest(data: Mapping[str, Any], path: Path, order: Sequence[str] = ()) -> Path | None:
    """``forest_figure`` written to ``path``; None (nothing written) without one."""
    fig = forest_figure(data, order)
    return None if fig is None else _save(fig, Path(path))


def plot_curve(data: Mapping[str, Any], path: Path, order: Sequence[str] = ()) -> Path | None:
    """``curve_figure`` written to ``path``; None (nothing written) without one."""
    fig = curve_figure(data, order)
    return None if fig is None else _save(fig, Path(path))


def _prefix(pics: Path | str) -> str:
    """A pictures folder as the prefix of a Markdown link: "" for the report's own folder."""
    pics = str(pics).rstrip("/")
    return "" if pics in ("", ".") else pics + "/"


def _with_pictures(data: Mapping[str, Any], pics: Path | str, curve: bool) -> str:
    """The Markdown with its pictures linked from ``pics`` (the forest plot at the top, the others last)."""
    prefix = _prefix(pics)
    return (markdown(data, prefix) + f"\n![success per column with 95% intervals]({prefix}results.png)\n"
            + (f"\n![learning curve]({prefix}learning_curve.png)\n" if curve else ""))


def write_report(results_dir: Path, catalogue: Mapping[str, Mapping[str, Any]], n_boot: int = 4000,
                 claims: Sequence[Claim] | None = None, margin: float | None = None,
                 relation_candidates: Sequence[str] | None = None) -> dict[str, Any]:
    """results.json, results.csv, RESULTS.md and the pictures (success per column, the forest plot, the
    learning curve) in ``results_dir``, all or none: everything is rendered first, then written together
    (``write_together``), so a full disk leaves the earlier report whole. Returns the data. ``claims``, the
    equivalence ``margin`` and ``relation_candidates``: the paper's and conf/reproduce.yaml's when not given."""
    results_dir = Path(results_dir)
    manifest = read_json(results_dir / "reproduce.json", default={}, kind=dict)
    cells, failed = load_cells(results_dir)
    check_families(cells, folder_weather_family(manifest), str(results_dir))
    pin = folder_pin(manifest)
    for c in cells:  # a cell of another reproduction would be pooled into its row: the check a run makes
        check_cell_pin(results_dir / "cells" / c.row / f"seed{c.seed}" / "cell.json", c.meta, pin,
                       "reproduce.json pins", "keep only this reproduction's cells in its folder")
    check_rows_agree(results_dir, cells)  # a row redefined between runs: its cells' overrides differ
    if not cells:
        raise CicfwError(f"no finished cell in {str(results_dir)!r} (cells/<row>/seed<k>/cell.json): nothing to report"
                         + (f"; {len(failed)} failed" if failed else ""))
    data = report_data(cells, failed, catalogue, manifest, n_boot=n_boot, claims=claims, margin=margin,
                       relation_candidates=relation_candidates)
    order = list(catalogue)
    files = {"results.json": json.dumps(data, indent=1).encode(), "results.csv": results_csv(data).encode()}
    for name, figure in (("results.png", results_figure), ("forest.png", forest_figure),
                         ("learning_curve.png", curve_figure)):
        fig = figure(data, order)
        if fig is not None:
            files[name] = png_bytes(fig)
    data["has_curve"] = "learning_curve.png" in files  # results.json is written without it, as ever
    files["RESULTS.md"] = _with_pictures(data, ".", data["has_curve"]).encode()
    write_together({results_dir / name: content for name, content in files.items()})
    return data


#: the reproduce config's keys the report reads (``write_configured``): a run's overrides of them (a row of its own
#: with its label, another margin) are kept in its reproduce.json, so ``cicfw report`` rewrites the report as
#: the run wrote it rather than with conf/reproduce.yaml's defaults
REPORT_KEYS = ("catalogue", "claims", "equivalence_margin", "relation_candidates")
REPORT_OVERRIDES = "report_overrides"


def report_overrides(overrides: Sequence[str]) -> list[str]:
    """The overrides among ``overrides`` that change what the report reads (``REPORT_KEYS``), in order."""
    def root(o: str) -> str:
        return o.lstrip("+~").split("=", 1)[0].split(".", 1)[0].split("[", 1)[0].strip()

    return [str(o) for o in overrides if root(str(o)) in REPORT_KEYS]


def run_report_config(results_dir: Path) -> Any:
    """conf/reproduce.yaml composed with the report overrides the folder's runs recorded (``REPORT_OVERRIDES``
    in reproduce.json; none in a folder made before they were recorded); one error line when they no longer
    compose."""
    manifest = read_json(Path(results_dir) / "reproduce.json", default={}, kind=dict)
    overrides = list(manifest.get(REPORT_OVERRIDES) or [])
    try:
        return compose("reproduce", overrides=overrides)
    except (HydraException, OmegaConfBaseException) as err:  # an entry this cicfw's config no longer takes
        raise CicfwError(f"{str(Path(results_dir) / 'reproduce.json')!r} records the report overrides {overrides}, "
                         f"which do not compose with this cicfw's conf/reproduce.yaml ({str(err).splitlines()[0]}); "
                         f"edit or remove its {REPORT_OVERRIDES!r}", key=REPORT_OVERRIDES, value=overrides) from None


def write_configured(results_dir: Path, cfg: Any, publish_dir: str | Path | None = None) -> dict[str, Any]:
    """``write_report`` with a composed reproduce config's catalogue, claims, margin and fine tuning's
    candidates; then ``publish`` into ``publish_dir`` when given."""
    data = write_report(Path(results_dir), OmegaConf.to_container(cfg.catalogue, resolve=True),
                        claims=load_claims(OmegaConf.to_container(cfg.claims, resolve=True)),
                        margin=cfg.get("equivalence_margin"), relation_candidates=list(cfg.relation_candidates))
    if publish_dir:
        publish(Path(results_dir), Path(publish_dir))
    return data


#: the report's first line: what a file the report may replace (``--markdown``) starts with
TITLE = "# Reproduction of the paper's Table 4"


def check_markdown_target(path: Path, folders: Sequence[Path] = ()) -> None:
    """``--markdown`` replaces a file only where it is an earlier copy of a report (its first line the report's
    title): a document of one's own (docs/RESULTS.md, composed from its prose; a README) is refused in one line,
    and so is a file the report writes into ``folders`` but RESULTS.md (results.csv, which may not exist yet)."""
    written = {(Path(d) / n).resolve() for d in folders for n in PUBLISHED_FILES if n != "RESULTS.md"}
    if Path(path).resolve() in written:
        raise CicfwError(f"--markdown {str(path)!r} is a file the report itself writes; give a new file or an earlier "
                         f"copy of the report", key="--markdown", value=str(path))
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            first = f.readline().rstrip("\n")
    except FileNotFoundError:
        return
    except OSError as err:
        raise CicfwError(f"--markdown {str(path)!r} cannot be read ({err.strerror or err}); give a file path",
                         key="--markdown", value=str(path)) from None
    if first != TITLE:
        raise CicfwError(f"--markdown {str(path)!r} is not a copy of a reproduction report (its first line is not "
                         f"{TITLE!r}), which this would replace; give a new file or an earlier copy",
                         key="--markdown", value=str(path))


def write_markdown_copy(data: Mapping[str, Any], path: Path, pictures: Path) -> Path:
    """The report's Markdown at ``path`` (a file of its own, or an earlier copy: ``check_markdown_target``,
    which the caller runs before anything is written), its pictures linked from ``pictures``."""
    rel = os.path.relpath(Path(pictures), Path(path).parent)
    atomic_write(Path(path), _with_pictures(data, rel, bool(data.get("has_curve"))))
    return Path(path)


def check_no_live_reproduction(results_dir: Path) -> None:
    """The report of a folder a live process holds (``reproduce.lock``: a running ``reproduce`` or another
    ``cicfw report``, named from its record) is refused: that run rewrites the report, and a report written
    beside it would be replaced mid-run. A stale lock (its holder dead) stops nothing."""
    path = results_dir / LOCK_FILE
    found = live_holder(path)
    if found is None:
        return
    holder, certain = found
    tail = "" if certain else f"; if it is no longer running, delete {str(path)!r}"
    raise CicfwError(f"results_dir={str(results_dir)!r} is in use by {holder_name(holder)} "
                     f"({describe_holder(holder)}), which rewrites its report meanwhile; run cicfw report after "
                     f"it ends{tail}", key="results_dir", value=str(results_dir))


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cicfw.reproduction.report RESULTS_DIR [--publish DEST]``: (re)write a reproduction's report."""
    ap = argparse.ArgumentParser(prog="cicfw report", description=main.__doc__)
    ap.add_argument("results_dir")
    ap.add_argument("--publish", default=None, help="also copy the small results into this folder")
    ap.add_argument("--markdown", default=None,
                    help="also write the Markdown to this file (new, or an earlier copy of the report)")
    a = ap.parse_args(argv)
    try:
        claim_folder(Path(a.results_dir), "reproduce", "results_dir")  # before anything is written
        check_no_live_reproduction(Path(a.results_dir))
        if a.publish:
            check_publish_outside(a.results_dir, a.publish, "--publish")
            claim_folder(Path(a.publish), "reproduce", "--publish")
        if a.markdown:
            check_markdown_target(Path(a.markdown), [Path(a.results_dir), *([Path(a.publish)] if a.publish else [])])

        # held while it writes, as a reproduce run holds them: no run takes either folder meanwhile
        held = RunLocks(Path(a.results_dir), a.publish, publish_key="--publish").acquire()
        try:
            if a.publish:  # a published table without some of its published cells: refused before any write
                check_publish_target(a.results_dir, a.publish, "--publish",
                                     f"report a results folder that holds them (python -m cicfw.reproduce "
                                     f"continue_from={a.publish} copies them into one)")
            with initialize_config_module("cicfw.conf", version_base="1.3"):
                data = write_configured(Path(a.results_dir), run_report_config(Path(a.results_dir)), a.publish)
        finally:
            held.release()
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
    install_app_handlers()  # a closed or full stdout: cicfw/core/errors.py, GuardedStdout
    raise SystemExit(main())
