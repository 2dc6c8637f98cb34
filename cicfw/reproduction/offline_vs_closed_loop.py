"""Does a lower validation error mean a model that drives better?
``python -m cicfw.reproduction.offline_vs_closed_loop``.

Reads every published cell (``docs/results/*/cells/*/seed*/cell.json``: a row trained with one seed, its
best validation steer MAE and its closed-loop success per table column), keeps each distinct cell once
(a continued folder copies its source's cells), and relates validation error to success with Spearman's
rank correlation and a 95% interval (Fisher z with the Bonett-Wright standard error): pooled over every
cell, within rows (the fixed-effect mean over rows of the per-row z), and per row; overall and per
column; for both CPU kinds together (said so) and for each kind. It also measures what picking the
lowest validation error among a row's cells gains in success. A folder driven under another weather family
(``sim.weather_family``, docs/simulator.md) re-drives models the others already hold, so each family is
analysed on its own: the main analysis is the ``harsh`` family's, every other family gets its own section. Writes ``README.md``, ``results.json`` and
``offline_vs_closed_loop.png`` into ``--out`` (default ``docs/results/offline_vs_closed_loop``).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from scipy.stats import spearmanr

from cicfw.benchmark.evaluation_report import md_row, md_table
from cicfw.benchmark.plots import _plt, _save
from cicfw.core.errors import CicfwError, install_app_handlers, report_user_errors
from cicfw.core.files import atomic_write
from cicfw.core.json_files import read_json
from cicfw.reproduction.cells import COLUMN_NAMES, COLUMNS, load_cells, most_first
from cicfw.reproduction.report import pinned_weather_family
from cicfw.reproduction.seed_stats import t_interval, word
from cicfw.sim.render.weather import LEGACY_FAMILY

Z95 = 1.959963984540054  # the standard normal's 97.5% point
#: the paper's Table 4: the rows every published folder compares, for the figure on their cells alone (the
#: study's own figure counts every published cell, as fixed before it was first run)
TABLE4 = ("cil", "gtu", "soft_sharing", "moe", "sluice", "classification", "coexistence", "hybrid", "sine")
#: the margin (points) the pick's gain is read against, the reproduction's ``equivalence_margin``
MARGIN = 5.0
TARGETS = ("overall", *COLUMNS)
TARGET_NAMES = {"overall": "overall (mean of the 4 columns)", **dict(zip(COLUMNS, COLUMN_NAMES))}
BOTH = "both kinds (pooled)"


@dataclass
class Point:
    """One distinct cell: its row, seed, CPU kind, budget, validation error and success (%) per target."""

    row: str
    seed: int
    cpu: str
    budget: str
    val_mae: float
    success: dict[str, float]
    folders: list[str] = field(default_factory=list)
    family: str = "harsh"  # the weather family its new-weather columns were driven under

    @property
    def group(self) -> str:
        """The row as trained: one recipe, budget and kind of CPU, seeds apart."""
        return f"{self.row} / {self.budget} / {self.cpu}"


@dataclass
class Corr:
    """Spearman's rho over n points, its 95% interval (None where it is undefined) and two-sided p."""

    rho: float
    lo: float | None
    hi: float | None
    n: int
    p: float | None = None

    def text(self) -> str:
        if self.n < 3 or math.isnan(self.rho):
            return f"– (n={self.n})"
        ci = f" [{self.lo:+.2f}, {self.hi:+.2f}]" if self.lo is not None else " [–]"
        return f"{self.rho:+.2f}{ci} (n={self.n})"


# ------------------------------------------------------------------------------------------------
# the statistics


def bonett_wright_se(rho: float, n: int) -> float:
    """Standard error of atanh(rho) for Spearman's rho (Bonett & Wright 2000): sqrt((1 + rho^2/2)/(n - 3))."""
    return math.sqrt((1.0 + rho * rho / 2.0) / (n - 3))


def fisher_interval(rho: float, se: float, z: float = Z95) -> tuple[float, float]:
    """The interval tanh(atanh(rho) -+ z se)."""
    c = math.atanh(rho)
    return math.tanh(c - z * se), math.tanh(c + z * se)


def spearman_ci(x: Sequence[float], y: Sequence[float]) -> Corr:
    """Spearman's rho of (x, y) with its 95% Fisher-z interval (Bonett-Wright standard error); the interval
    is None below 4 points or at |rho| = 1, where the transform has no finite spread."""
    n = len(x)
    if n < 3 or np.ptp(np.asarray(x, float)) == 0 or np.ptp(np.asarray(y, float)) == 0:
        return Corr(float("nan"), None, None, n)  # a constant has no ranks to correlate
    res = spearmanr(x, y)
    rho, p = float(res.statistic), float(res.pvalue)
    if n < 4 or math.isnan(rho) or abs(rho) >= 1.0:
        return Corr(rho, None, None, n, p)
    return Corr(rho, *fisher_interval(rho, bonett_wright_se(rho, n)), n, p)


def pooled_within(corrs: Sequence[Corr]) -> Corr:
    """The fixed-effect mean of several groups' rho on the Fisher z scale, each weighted by its inverse
    Bonett-Wright variance, with its 95% interval; groups without an interval are left out."""
    used = [c for c in corrs if c.lo is not None]
    if not used:
        return Corr(float("nan"), None, None, 0)
    w = np.array([1.0 / bonett_wright_se(c.rho, c.n) ** 2 for c in used])
    z = float(np.sum(w * np.arctanh([c.rho for c in used])) / np.sum(w))
    se = 1.0 / math.sqrt(float(np.sum(w)))
    return Corr(math.tanh(z), math.tanh(z - Z95 * se), math.tanh(z + Z95 * se), sum(c.n for c in used))


def selection_gain(points: Sequence[Point], target: str = "overall") -> float:
    """Success (points) of the cell with the lowest validation error minus the mean success of ``points``."""
    best = min(points, key=lambda p: p.val_mae)
    return best.success[target] - float(np.mean([p.success[target] for p in points]))


# ------------------------------------------------------------------------------------------------
# the data


def _fingerprint(cell: Any) -> str:
    """What makes two cells the same cell: row, seed, validation error and every episode's outcome."""
    data = [cell.row, cell.seed, cell.meta.get("val_steer_mae"), cell.episodes]
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def collect_points(results: Path, skip: Sequence[str] = ()) -> list[Point]:
    """Every distinct finished cell with a finite validation error under ``results``/<folder>/cells (a cell
    recording none, or NaN, has no point to rank)."""
    points: dict[str, Point] = {}
    for folder in sorted(p for p in Path(results).iterdir() if p.is_dir() and p.name not in skip):
        path = folder / "reproduce.json"
        manifest = read_json(path, default={})
        budget, family = manifest.get("budget", "?"), pinned_weather_family(manifest) or "another simulator"
        for cell in load_cells(folder)[0]:
            mae = cell.meta.get("val_steer_mae")
            if not (isinstance(mae, (int, float)) and math.isfinite(mae)):  # none, or NaN (a diverged run's)
                continue
            key = _fingerprint(cell)
            if key not in points:
                points[key] = Point(cell.row, cell.seed, cell.cpu, budget, float(cell.meta["val_steer_mae"]),
                                    {t: cell.rate(None if t == "overall" else t) for t in TARGETS},
                                    family=family)
            points[key].folders.append(folder.name)
    return sorted(points.values(), key=lambda p: (p.group, p.seed))


def by_group(points: Sequence[Point]) -> dict[str, list[Point]]:
    out: dict[str, list[Point]] = {}
    for p in points:
        out.setdefault(p.group, []).append(p)
    return out


def scopes(points: Sequence[Point]) -> dict[str, list[Point]]:
    """Both CPU kinds together, then each kind alone (most cells first)."""
    kinds = most_first(p.cpu for p in points)
    return {BOTH: list(points), **{k: [p for p in points if p.cpu == k] for k in kinds}}


# ------------------------------------------------------------------------------------------------
# the analysis


def correlate(points: Sequence[Point], target: str) -> Corr:
    return spearman_ci([p.val_mae for p in points], [p.success[target] for p in points])


def analyse(points: Sequence[Point], min_group: int = 3) -> dict[str, Any]:
    """Every figure of the report, as plain data."""
    out: dict[str, Any] = {"cells": len(points), "scopes": {}, "groups": {}}
    for scope, pts in scopes(points).items():
        groups = {g: v for g, v in by_group(pts).items() if len(v) >= min_group}
        gains = [selection_gain(v) for v in groups.values()]
        out["scopes"][scope] = {
            "cells": len(pts), "groups": len(groups),
            "pooled": {t: vars(correlate(pts, t)) for t in TARGETS},
            "within_rows": {t: vars(pooled_within([correlate(v, t) for v in groups.values()])) for t in TARGETS},
            "by_budget": {b: vars(correlate([p for p in pts if p.budget == b], "overall"))
                          for b in sorted({p.budget for p in pts})},
            "selection_gain": {"mean": float(np.mean(gains)) if gains else None, "groups": len(gains),
                               "interval": tuple(map(float, t_interval(gains)[1:])) if len(gains) > 1 else None,
                               "best_picked": sum(_picks_best(v) for v in groups.values()),
                               "best_by_chance": sum(1.0 / len(v) for v in groups.values())},
            "table4": _table4(pts, min_group)}
    for g, v in by_group(points).items():
        out["groups"][g] = {"cells": len(v), "val_mae": [p.val_mae for p in v],
                            **{t: vars(correlate(v, t)) for t in TARGETS}}
    return out


def _table4(points: Sequence[Point], min_group: int) -> dict[str, Any]:
    """The overall figures on the cells of Table 4's nine rows alone (a check of how much the answer rests
    on the other rows' cells: fine tuning's, cross-stitch's, the loss weights', bf16's)."""
    pts = [p for p in points if p.row in TABLE4]
    groups = [v for v in by_group(pts).values() if len(v) >= min_group]
    return {"cells": len(pts), "pooled": vars(correlate(pts, "overall")),
            "within_rows": vars(pooled_within([correlate(v, "overall") for v in groups]))}


def gain_word(g: dict[str, Any]) -> str | None:
    """How the pick's gain reads (``seed_stats.word`` on its 95% interval, each weather family's gain one
    comparison, against the reproduction's 5-point margin): the picked cell *ahead* of its row's average,
    *behind*, *equivalent within ±5*, or *not separated*."""
    return None if g.get("interval") is None else word(g["interval"][0], g["interval"][1], MARGIN)


def _gain_text(g: dict[str, Any]) -> str:
    """The pick's gain as the answer says it, with its word."""
    ci = f" [{g['interval'][0]:+.1f}, {g['interval'][1]:+.1f}]" if g["interval"] else ""
    w = gain_word(g)
    return (f"{g['mean']:+.1f}{ci} points of overall success over the row's average cell ({g['groups']} rows"
            + (f", the picked cell {w} on the 95% interval" if w else "") + f"); it picks the row's best driver in "
            f"{g['best_picked']} of {g['groups']}, where a random pick would in {g['best_by_chance']:.1f}")


def _table4_text(t: dict[str, Any]) -> str:
    return (f"On the {t['cells']} cells of Table 4's nine rows alone: pooled {_c(t['pooled'])}, "
            f"{_verdict(t['pooled'])}; within rows {_c(t['within_rows'])}.")


def _picks_best(points: Sequence[Point]) -> bool:
    """Whether the lowest validation error is also (one of) the highest overall success."""
    best = min(points, key=lambda p: p.val_mae)
    return best.success["overall"] >= max(p.success["overall"] for p in points)


# ------------------------------------------------------------------------------------------------
# the report


def _c(d: dict[str, Any]) -> str:
    return Corr(**d).text()


def scatter(points: Sequence[Point], path: Path) -> Path:
    """Validation error against success, one panel per target and one within rows (both centred on
    their row's mean); colour by row, marker by CPU kind."""
    plt = _plt()
    rows = sorted({p.row for p in points})
    colour = {r: plt.get_cmap("tab10" if len(rows) <= 10 else "tab20")(i) for i, r in enumerate(rows)}
    marker = {k: m for k, m in zip(sorted({p.cpu for p in points}), "o^sDv")}
    fig, axes = plt.subplots(2, 3, figsize=(14, 8.5))
    panels: list[tuple[str, Callable[[Point], tuple[float, float]]]] = [
        (TARGET_NAMES[t], lambda p, t=t: (p.val_mae, p.success[t])) for t in TARGETS]
    means = {g: (np.mean([p.val_mae for p in v]), np.mean([p.success["overall"] for p in v]))
             for g, v in by_group(points).items() if len(v) >= 3}
    panels.append(("within rows of >= 3 cells: overall, minus the row's mean",
                   lambda p: (p.val_mae - means[p.group][0], p.success["overall"] - means[p.group][1])))
    for ax, (title, xy) in zip(axes.flat, panels):
        for p in (points if "within" not in title else [q for q in points if q.group in means]):
            x, y = xy(p)
            ax.scatter(x, y, color=colour[p.row], marker=marker[p.cpu], s=28, alpha=0.8, edgecolors="none")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("best validation steer MAE" + (" - row mean" if "within" in title else ""))
        ax.set_ylabel("success (%)" + (" - row mean" if "within" in title else ""))
        ax.grid(alpha=0.3)
    handles = [plt.Line2D([], [], color=colour[r], marker="o", ls="", label=r) for r in rows]
    handles += [plt.Line2D([], [], color="grey", marker=m, ls="", label=k) for k, m in marker.items()]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=8, frameon=False)
    fig.suptitle(f"Validation error vs closed-loop success, {len(points)} distinct published cells", fontsize=11)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    return _save(fig, path)


def _verdict(c: dict[str, Any]) -> str:
    """One phrase on what an interval says about the sign of rho."""
    if c["lo"] is None:
        return "no interval"
    if c["hi"] < 0:
        return "lower error, higher success"
    if c["lo"] > 0:
        return "lower error, lower success"
    lean = "lower success" if c["rho"] > 0 else "higher success"
    return f"no clear relation (the interval holds 0; if anything, lower error with {lean})"


def markdown(res: dict[str, Any], points: Sequence[Point]) -> str:
    """The README: question, data, method, answer and the tables."""
    both = res["scopes"][BOTH]
    kinds = [k for k in res["scopes"] if k != BOTH]
    folders = sorted({f for p in points if p.family not in res.get("families", {}) for f in p.folders})
    lines = [
        "# Offline validation error vs closed-loop success",
        "",
        "**Question.** Does a model's validation error (best `val/steer_mae`, the offline metric training "
        "picks its checkpoint by) predict how well it drives the closed-loop suite? Codevilla et al. (ECCV "
        "2018, *On offline evaluation of vision-based driving models*) found offline metrics only loosely "
        "related to driving in CARLA; this asks the same of every cell published here.",
        "",
        f"**Data.** {res['cells']} distinct cells (a row trained with one seed, then driven over the "
        "single-turn suite) from " + ", ".join(f"`{f}`" for f in folders) + "; a cell copied into a "
        "continued folder counts once. CPU kinds: " + ", ".join(
            f"{k} {res['scopes'][k]['cells']}" for k in kinds) + ". Budgets differ (laptop, converged: 4 "
        "epochs, converged6: 6 epochs), and so do rows (architectures, heads). The validation error is "
        "the best epoch's, the success the final epoch's weights' (the two are one checkpoint when the last "
        "epoch is the best, which the cells do not record). Overall success is the mean of the four table columns. Every "
        "new-weather column here was driven under the `harsh` weather family (docs/simulator.md, Weathers); cells "
        "driven under another family have their own section below.",
        "",
        "**Method.** Spearman's rank correlation rho (`scipy.stats.spearmanr`, ties averaged) between "
        "validation error and success; a negative rho means lower error goes with higher success. 95% "
        "interval: Fisher z with the Bonett-Wright standard error sqrt((1 + rho^2/2)/(n - 3)), chosen over "
        "`scipy.stats.bootstrap` because it is closed-form and deterministic and keeps its coverage for a "
        "rank correlation at small n, where the bootstrap's resamples duplicate cells (ties) and its "
        "percentile interval is discrete and too narrow (rows here have 3-13 cells); its coverage is "
        "simulated in tests/test_offline_vs_closed_loop.py. *Pooled*: every cell of the scope together "
        "(mixes rows and budgets, which move both quantities). *Within rows*: the fixed-effect mean of the "
        "per-row z (weights 1/SE^2) over the rows of >= 3 cells that have an interval: a row of 3 cells, or one "
        "whose rho is +-1, has no finite spread on Fisher's z and drops out, so the figure rests on the rows of "
        ">= 4 cells; it is the relation among seeds of one recipe, which is what picking a checkpoint by "
        "validation error relies on. A row is one (row, budget, CPU kind). *Pick by validation*: the success of "
        "each row's lowest-error cell minus the row's mean success, averaged over rows of >= 3 cells, with its "
        "95% t-interval over rows and its word (ahead / behind / equivalent within +-5 / not separated). "
        "*Table 4's rows alone*: the same on the cells of the paper's nine Table-4 rows, leaving out fine tuning, "
        "cross-stitch, the loss-weight rows and bf16: the study counts every published cell, fixed before it was "
        "first run, and this line shows how much the answer rests on the others.",
        "",
        "## Answer",
        "",
    ]
    lines += _answer(res, kinds)
    lines += ["", "## Pooled and within rows", ""] + _scope_table(res)
    budgets = sorted(both["by_budget"])
    lines += ["", "## Pooled within one budget (overall)", "", *md_table(
        ["scope", *budgets], "l" + "r" * len(budgets),
        ([scope, *(_c(s["by_budget"][b]) if b in s["by_budget"] else "–" for b in budgets)]
         for scope, s in res["scopes"].items()))]
    lines += ["", "## Picking the lowest validation error within a row", "", *md_table(
        ["scope", "rows", "mean gain in overall success (points) [95% t]", "word",
         "rows where it is the best driver (by chance)"], "lrrlr")]
    for scope, s in res["scopes"].items():
        g = s["selection_gain"]
        gain = "–" if g["mean"] is None else f"{g['mean']:+.1f}"
        if g["interval"] is not None:
            gain += f" [{g['interval'][0]:+.1f}, {g['interval'][1]:+.1f}]"
        lines.append(md_row([scope, g["groups"], gain, gain_word(g) or "–",
                             f"{g['best_picked']} of {g['groups']} ({g['best_by_chance']:.1f})"]))
    lines += ["", "## Per row (row / budget / CPU kind)", "", *md_table(
        ["row", *(TARGET_NAMES[t] for t in TARGETS)], "l" + "r" * len(TARGETS),
        ([g, *(_c(d[t]) for t in TARGETS)] for g, d in res["groups"].items()))]
    for family, fres in res.get("families", {}).items():
        fboth = fres["scopes"][BOTH]
        ffolders = sorted({f for p in points if p.family == family for f in p.folders})
        lines += ["", f"## Under the `{family}` weathers", "",
                  f"{fres['cells']} cells from " + ", ".join(f"`{f}`" for f in ffolders) + " drove their "
                  f"new-weather columns under the `{family}` family. Their models are trained as the cells "
                  "above are (a seed trains the same weights on the same kind of CPU), so they are kept out of "
                  "the analysis above and read here on their own. Overall rho, pooled: "
                  f"{_c(fboth['pooled']['overall'])}, {_verdict(fboth['pooled']['overall'])}; within rows: "
                  f"{_c(fboth['within_rows']['overall'])}, {_verdict(fboth['within_rows']['overall'])}. "
                  + (f"Picking each row's lowest validation error gains {_gain_text(fboth['selection_gain'])}. "
                     if fboth["selection_gain"]["mean"] is not None else "")
                  + _table4_text(fboth["table4"]),
                  ""] + _scope_table(fres)
    lines += ["", "![validation error vs success](offline_vs_closed_loop.png)", "",
              "Made by `python -m cicfw.reproduction.offline_vs_closed_loop` (figures in results.json).", ""]
    return "\n".join(lines)


def _scope_table(res: dict[str, Any]) -> list[str]:
    """Pooled and within-row rho, per scope and target."""
    scopes_ = list(res["scopes"].items())
    shown = scopes_[1:] if len(scopes_) == 2 else scopes_  # one kind: "both kinds" is that kind
    return md_table(["scope", "target", "pooled rho [95%]", "within rows rho [95%]"], "llrr",
                    ([scope, TARGET_NAMES[t], _c(s["pooled"][t]), _c(s["within_rows"][t])]
                     for scope, s in shown for t in TARGETS))


def _answer(res: dict[str, Any], kinds: list[str]) -> list[str]:
    """The answer's sentences, read off the figures."""
    both = res["scopes"][BOTH]
    out = [f"- Pooled over all {both['cells']} cells (both CPU kinds together): overall rho "
           f"{_c(both['pooled']['overall'])}: {_verdict(both['pooled']['overall'])}. Per kind: " + "; ".join(
               f"{k} {_c(res['scopes'][k]['pooled']['overall'])}" for k in kinds) + "."]
    out.append(f"- Within rows (seeds of one recipe), both kinds: overall rho {_c(both['within_rows']['overall'])}"
               f": {_verdict(both['within_rows']['overall'])}. Per kind: " + "; ".join(
                   f"{k} {_c(res['scopes'][k]['within_rows']['overall'])}" for k in kinds) + ".")
    cols = "; ".join(f"{TARGET_NAMES[t]} {_c(both['within_rows'][t])}" for t in COLUMNS)
    out.append(f"- Per column, within rows (both kinds): {cols} (five targets, uncorrected: one interval that "
               "just excludes 0 is weak evidence).")
    out.append("- Pooled within one budget (both kinds): " + "; ".join(
        f"{b} {_c(c)}" for b, c in both["by_budget"].items()) + "; " + _budget_reading(both["by_budget"]) + ".")
    g = both["selection_gain"]
    if g["mean"] is not None:
        out.append(f"- Picking each row's lowest validation error gains {_gain_text(g)}.")
    out.append(f"- {_table4_text(both['table4'])}")
    out.append("- For checkpoint selection (the main job keeps the lowest validation error): what matters is "
               "the within-row figure, the pooled one mostly ranks recipes and budgets; the main job picks among "
               "the epochs of one run, whose validation errors the cells do not record, so seeds of one recipe "
               "are the nearest comparison here. " + _selection_reading(both))
    return out


def _budget_reading(by_budget: dict[str, dict[str, Any]]) -> str:
    """Which budgets' intervals exclude 0 (the relation holds there) and which do not."""
    clear = [b for b, c in by_budget.items() if c["lo"] is not None and (c["hi"] < 0 or c["lo"] > 0)]
    unclear = [b for b in by_budget if b not in clear]
    return (f"the interval excludes 0 for {', '.join(clear) or 'no budget'}"
            + (f", not for {', '.join(unclear)}" if unclear else ""))


def _selection_reading(s: dict[str, Any]) -> str:
    c = s["within_rows"]["overall"]
    if c["lo"] is None:
        return "There are too few rows of >= 4 cells (the ones with an interval) to say."
    if c["hi"] < 0:
        return ("Among seeds of one recipe, the lower validation error does go with the better driver, so "
                "picking by it is sound, though the spread left over is wide.")
    return ("Among seeds of one recipe, the validation error does not reliably rank the drivers (the interval "
            "holds 0): picking a checkpoint by it is a weak proxy for driving, as Codevilla et al. found; a "
            "closed-loop check of the candidates is the safer choice.")


#: the files the study writes into its folder, and the keys that make a results.json this study's
STUDY_FILES = ("README.md", "results.json", "offline_vs_closed_loop.png")
STUDY_KEYS = ("cells", "scopes", "points")


def check_out(out: Path) -> None:
    """``out`` may hold the study's files only where they are an earlier run's (its results.json this study's):
    a folder with a README.md or results.json of something else (``--out .`` in a clone) is refused in one line."""
    held = [n for n in STUDY_FILES if (out / n).exists()]
    if not held:
        return
    try:
        earlier = json.loads((out / "results.json").read_text())
    except (OSError, ValueError):
        earlier = None
    if isinstance(earlier, dict) and all(k in earlier for k in STUDY_KEYS):
        return
    raise CicfwError(f"--out {str(out)!r} holds {', '.join(held)} that this study did not write, which it would "
                     f"replace; give a folder of its own (--out <new folder>)", key="--out", value=str(out))


def write_report(results: Path, out: Path) -> dict[str, Any]:
    """Analyse the cells under ``results`` and write README.md, results.json and the picture into ``out``."""
    check_out(out)
    points = collect_points(results, skip=(out.name,))
    main = [p for p in points if p.family == LEGACY_FAMILY]
    res = analyse(main)
    res["families"] = {family: analyse([p for p in points if p.family == family])
                       for family in sorted({p.family for p in points} - {LEGACY_FAMILY})}
    res["points"] = [vars(p) for p in points]
    out.mkdir(parents=True, exist_ok=True)
    scatter(main, out / "offline_vs_closed_loop.png")
    atomic_write(out / "results.json", json.dumps(res, indent=1) + "\n")
    atomic_write(out / "README.md", markdown(res, points))
    return res


def main(argv: list[str] | None = None) -> int:
    """The command line; a user error is one ``cicfw: error:`` line, exit status 2."""
    return report_user_errors(_main)(argv)


def _main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m cicfw.reproduction.offline_vs_closed_loop",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", default="docs/results", help="the folder of published studies (default: %(default)s)")
    ap.add_argument("--out", default="docs/results/offline_vs_closed_loop", help="report folder (default: %(default)s)")
    a = ap.parse_args(argv)
    res = write_report(Path(a.results), Path(a.out))
    print(f"{res['cells']} cells -> {Path(a.out) / 'README.md'}")
    return 0


if __name__ == "__main__":
    install_app_handlers()  # a closed or full stdout: cicfw/core/errors.py, GuardedStdout
    raise SystemExit(main())
