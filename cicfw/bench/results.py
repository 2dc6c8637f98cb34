"""The paper's comparison as results: per-cell outcomes -> Table 4 with 95% intervals -> a verdict per claim.

A *cell* is one (row, seed) of a reproduction: a model trained with that seed and driven on the suite;
``cell.json`` keeps every episode's outcome. Everything here is plain numpy over those outcomes, so
``cicfw report`` and the tests use it without training anything.

**Intervals.** A two-level (hierarchical) percentile bootstrap: each replicate draws the row's seeds
with replacement and, independently within each table column, the suite's episodes with replacement
(the same episode draw for every row, since every row drives the same episodes: differences are
paired by episode); the statistic is the mean over the drawn seeds of the success rate on the drawn
episodes. The 95% interval is the 2.5th..97.5th percentile of ``B`` replicates. With few seeds the
seed level is coarse (3 seeds have 10 distinct draws): the interval is a floor on the uncertainty,
not a ceiling. *Overall* is the mean of the four table columns (each column weighs the same, as in
reading the paper's table).

**Verdicts.** A claim "A beats B" is *supported* when the 95% interval of A - B lies above 0,
*contradicted* when it lies below 0, *inconclusive* otherwise; a claim made of several parts is
supported when all are, contradicted when any is. A claim whose rows were not run is *not run*.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from cicfw.bench.runs import atomic_write, cell_key, cell_name
from cicfw.bench.suite import CELLS

COLUMNS = tuple(cell_key(*c) for c in CELLS)  # training_town/training_weathers ... new_town/new_weathers
COLUMN_NAMES = tuple(cell_name(*c) for c in CELLS)
SUPPORTED, CONTRADICTED, INCONCLUSIVE, NOT_RUN = "supported", "contradicted", "inconclusive", "not run"
LEVEL = 0.95


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


def load_cells(results_dir: Path) -> tuple[list[CellResult], list[dict[str, Any]]]:
    """The finished cells (status ok) and the failed ones (their cell.json) under ``results_dir``."""
    ok, failed = [], []
    for p in sorted(Path(results_dir).glob("cells/*/seed*/cell.json")):
        d = json.loads(p.read_text())
        if d.get("status") == "ok":
            ok.append(CellResult(row=d["row"], seed=int(d["seed"]), episodes=d["episodes"], meta=d))
        else:
            failed.append(d)
    return ok, failed


# ------------------------------------------------------------------------------------------------
# the bootstrap


def _matrix(cells: Sequence[CellResult], keys: Sequence[str]) -> np.ndarray:
    """(seeds, episodes) success matrix of one row's cells, episodes in ``keys`` order."""
    return np.array([[float(c.episodes[k]["success"]) for k in keys] for c in cells])


def _replicates(cells: Sequence[CellResult], keys: Sequence[str], columns: Sequence[str],
                ep_draws: Mapping[str, np.ndarray], rng: np.random.Generator, n_boot: int) -> np.ndarray:
    """(n_boot, 5) bootstrap replicates of [column rates..., overall] (in %) for one row."""
    m = _matrix(cells, keys)  # (S, N)
    s = m.shape[0]
    seeds = rng.integers(0, s, size=(n_boot, s))  # seed draw, per replicate
    cols = []
    for c in COLUMNS:
        idx = ep_draws[c]  # (n_boot, n_c) episode draw within column c (shared across rows)
        # m[seeds][:, :, idx] per replicate: mean over drawn seeds and drawn episodes
        per_seed_rates = m[:, idx]  # (S, n_boot, n_c)
        per_seed_rates = per_seed_rates.mean(axis=2).T  # (n_boot, S)
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


@dataclass
class Estimate:
    mean: float
    lo: float
    hi: float

    def as_dict(self) -> dict[str, float]:
        return {"mean": round(self.mean, 2), "lo": round(self.lo, 2), "hi": round(self.hi, 2)}

    def fmt(self) -> str:
        return f"{self.mean:.1f} [{self.lo:.1f}, {self.hi:.1f}]"


@dataclass
class Analysis:
    """Every row's estimates (per column + overall) and its bootstrap replicates, on one episode draw."""

    rows: dict[str, list[CellResult]]
    estimates: dict[str, list[Estimate]]  # row -> 5 estimates (4 columns + overall)
    replicates: dict[str, np.ndarray]  # row -> (n_boot, 5)
    n_boot: int

    def diff(self, a: str, b: str, index: int = 4) -> Estimate:
        """A - B on column ``index`` (4: overall), with its paired bootstrap interval."""
        d = self.replicates[a][:, index] - self.replicates[b][:, index]
        mean = float(np.mean([c.rate(None if index == 4 else COLUMNS[index]) for c in self.rows[a]])
                     - np.mean([c.rate(None if index == 4 else COLUMNS[index]) for c in self.rows[b]]))
        return Estimate(mean, *percentile_interval(d))

    def gap_change(self, a: str, b: str, hard: int, easy: int) -> Estimate:
        """(A - B) on column ``hard`` minus (A - B) on column ``easy``: where A's advantage is larger."""
        ra, rb = self.replicates[a], self.replicates[b]
        d = (ra[:, hard] - rb[:, hard]) - (ra[:, easy] - rb[:, easy])
        pt = self.diff(a, b, hard).mean - self.diff(a, b, easy).mean
        return Estimate(pt, *percentile_interval(d))


def analyse(cells: Sequence[CellResult], n_boot: int = 4000, seed: int = 0) -> Analysis:
    """Group cells by row, check they drove the same episodes, and bootstrap every row."""
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
    reps, est = {}, {}
    for row, cs in rows.items():
        reps[row] = _replicates(cs, keys, columns, draws, rng, n_boot)
        means = [float(np.mean([c.rate(col) for c in cs])) for col in COLUMNS]
        means.append(float(np.mean(means)))
        est[row] = [Estimate(m, *percentile_interval(reps[row][:, i])) for i, m in enumerate(means)]
    return Analysis(rows=rows, estimates=est, replicates=reps, n_boot=n_boot)


# ------------------------------------------------------------------------------------------------
# the paper's claims


@dataclass(frozen=True)
class Comparison:
    """One testable part of a claim: ``a`` beats ``b`` on a column (4: overall), or ``a``'s advantage
    over ``b`` is larger on column ``hard`` than on column ``easy`` (``kind="gap"``)."""

    a: str
    b: str
    index: int = 4
    kind: str = "beats"
    hard: int = 3
    easy: int = 0

    def text(self, labels: Mapping[str, str]) -> str:
        la, lb = labels.get(self.a, self.a), labels.get(self.b, self.b)
        if self.kind == "gap":
            return f"{la} − {lb} larger in {COLUMN_NAMES[self.hard]} than in {COLUMN_NAMES[self.easy]}"
        where = "overall" if self.index == 4 else COLUMN_NAMES[self.index]
        return f"{la} > {lb} ({where})"

    def estimate(self, an: Analysis) -> Estimate:
        return an.gap_change(self.a, self.b, self.hard, self.easy) if self.kind == "gap" else an.diff(self.a, self.b, self.index)

    def paper(self, paper: Mapping[str, Sequence[float]]) -> float | None:
        if self.a not in paper or self.b not in paper:
            return None
        pa, pb = list(paper[self.a]), list(paper[self.b])
        pa.append(float(np.mean(pa)))
        pb.append(float(np.mean(pb)))
        if self.kind == "gap":
            return (pa[self.hard] - pb[self.hard]) - (pa[self.easy] - pb[self.easy])
        return pa[self.index] - pb[self.index]


@dataclass(frozen=True)
class Claim:
    text: str
    parts: tuple[Comparison, ...]


#: the paper's claims (Section 4 and the conclusion), as comparisons of reproduction rows
CLAIMS = (
    Claim("GTU (co-learning) beats CIL", (Comparison("gtu", "cil"),)),
    Claim("GTU's gain over CIL is largest in the new town under new weathers",
          (Comparison("gtu", "cil", kind="gap", hard=3, easy=0),)),
    Claim("CCE+MSE (hybrid) beats plain classification", (Comparison("hybrid", "classification"),)),
    Claim("CCE+MSE beats CIL in the new town under new weathers (+21%)", (Comparison("hybrid", "cil", index=3),)),
    Claim("Classification does not beat CIL (CIL is better)", (Comparison("cil", "classification"),)),
    Claim("Co-existence beats classification but not CIL",
          (Comparison("coexistence", "classification"), Comparison("cil", "coexistence"))),
    Claim("MoE lands between CIL and GTU", (Comparison("moe", "cil"), Comparison("gtu", "moe"))),
    Claim("Soft sharing lands between CIL and GTU",
          (Comparison("soft_sharing", "cil"), Comparison("gtu", "soft_sharing"))),
    Claim("Sluice lands between CIL and GTU", (Comparison("sluice", "cil"), Comparison("gtu", "sluice"))),
    Claim("Sine encoding is (slightly) above CIL", (Comparison("sine", "cil"),)),
)
#: "cross-stitch fails to learn": its overall success is below this share of CIL's
FAILS_TO_LEARN_SHARE = 0.25


def part_verdict(e: Estimate) -> str:
    if e.lo > 0:
        return SUPPORTED
    if e.hi < 0:
        return CONTRADICTED
    return INCONCLUSIVE


def combine(verdicts: Sequence[str]) -> str:
    if not verdicts or NOT_RUN in verdicts:
        return NOT_RUN
    if CONTRADICTED in verdicts:
        return CONTRADICTED
    return SUPPORTED if all(v == SUPPORTED for v in verdicts) else INCONCLUSIVE


def judge(an: Analysis, paper: Mapping[str, Sequence[float]], labels: Mapping[str, str]) -> list[dict[str, Any]]:
    """Every claim with each part's measured difference, interval, the paper's difference and a verdict."""
    out = []
    for claim in CLAIMS:
        parts = []
        for p in claim.parts:
            if p.a not in an.rows or p.b not in an.rows:
                parts.append({"comparison": p.text(labels), "verdict": NOT_RUN, "paper": p.paper(paper)})
                continue
            e = p.estimate(an)
            parts.append({"comparison": p.text(labels), "measured": e.as_dict(), "paper": p.paper(paper),
                          "verdict": part_verdict(e)})
        out.append({"claim": claim.text, "verdict": combine([p["verdict"] for p in parts]), "parts": parts})
    out.append(cross_stitch_claim(an, labels))
    return out


def cross_stitch_claim(an: Analysis, labels: Mapping[str, str]) -> dict[str, Any]:
    """"Cross-stitch fails to learn the driving task": its overall success stays below
    ``FAILS_TO_LEARN_SHARE`` x CIL's (supported when the interval of the ratio's numerator says so)."""
    text = "Cross-stitch fails to learn the driving task"
    rule = f"cross-stitch overall < {FAILS_TO_LEARN_SHARE:.2f} x CIL overall"
    if "cross_stitch" not in an.rows or "cil" not in an.rows:
        return {"claim": text, "verdict": NOT_RUN, "parts": [{"comparison": rule, "verdict": NOT_RUN}]}
    d = an.replicates["cross_stitch"][:, 4] - FAILS_TO_LEARN_SHARE * an.replicates["cil"][:, 4]
    mean = an.estimates["cross_stitch"][4].mean - FAILS_TO_LEARN_SHARE * an.estimates["cil"][4].mean
    e = Estimate(mean, *percentile_interval(d))
    v = SUPPORTED if e.hi < 0 else CONTRADICTED if e.lo > 0 else INCONCLUSIVE
    return {"claim": text, "verdict": v, "parts": [{"comparison": rule + " (measured: cross-stitch − 0.25 x CIL)",
                                                    "measured": e.as_dict(), "paper": None, "verdict": v}]}


# ------------------------------------------------------------------------------------------------
# the report


def _row_order(rows: Sequence[str], catalogue: Mapping[str, Mapping[str, Any]]) -> list[str]:
    order = list(catalogue)
    return sorted(rows, key=lambda r: (order.index(r) if r in order else len(order), r))


def report_data(cells: Sequence[CellResult], failed: Sequence[Mapping[str, Any]],
                catalogue: Mapping[str, Mapping[str, Any]], manifest: Mapping[str, Any],
                n_boot: int = 4000) -> dict[str, Any]:
    """Everything RESULTS.md shows, as JSON-ready data."""
    an = analyse(cells, n_boot=n_boot)
    labels = {r: str((catalogue.get(r) or {}).get("label", r)) for r in {*catalogue, *an.rows}}
    paper = {r: list(catalogue[r]["paper"]) for r in catalogue if catalogue[r].get("paper")}
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
            "seeds": [c.seed for c in cs],
            "columns": {col: est.as_dict() for col, est in zip([*COLUMNS, "overall"], an.estimates[r])},
            "per_seed": {str(c.seed): {**{col: round(c.rate(col), 2) for col in COLUMNS}, "overall": round(c.rate(), 2)}
                         for c in cs},
            "manoeuvres": {m: round(float(np.mean(v)), 2) for m, v in man.items()},
            "paper": paper.get(r),
            "wall_s": {str(c.seed): c.meta.get("wall_s") for c in cs},
            "curve": {str(c.seed): c.meta.get("curve", []) for c in cs if c.meta.get("curve")},
        })
    return {"manifest": dict(manifest), "method": __doc__.split("**Intervals.**")[1].split("**Verdicts.**")[0].strip(),
            "n_boot": n_boot, "level": LEVEL, "rows": rows, "claims": judge(an, paper, labels),
            "failed": [{"row": f.get("row"), "seed": f.get("seed"), "error": f.get("error")} for f in failed]}


def results_csv(data: Mapping[str, Any]) -> str:
    lines = ["row,label,decoder,column,mean,lo,hi,paper,per_seed"]
    for r in data["rows"]:
        for i, col in enumerate([*COLUMNS, "overall"]):
            e = r["columns"][col]
            paper = r["paper"]
            pv = "" if not paper else f"{(paper[i] if i < 4 else float(np.mean(paper))):.2f}"
            per_seed = ";".join(f"{s}:{v[col]}" for s, v in r["per_seed"].items())
            lines.append(f"{r['row']},\"{r['label']}\",{r['decoder'] or ''},{col},{e['mean']},{e['lo']},{e['hi']},{pv},{per_seed}")
    return "\n".join(lines) + "\n"


def _pct(v: float | None) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.1f}"


def markdown(data: Mapping[str, Any]) -> str:
    """RESULTS.md: the machine and budget, Table 4 with intervals and the paper's values, the claims,
    success by manoeuvre, the learning curve and each cell's wall time."""
    m = data["manifest"]
    lines = ["# Reproduction of the paper's Table 4", ""]
    lines += [f"- **Budget:** `{m.get('budget')}`; suite: `{m.get('suite', {}).get('name')}` "
              f"({m.get('episodes', '?')} episodes per cell); dataset: {m.get('dataset_summary', '?')}.",
              f"- **Machine:** {m.get('machine', '?')}.",
              f"- **Cells:** {sum(len(r['seeds']) for r in data['rows'])} finished"
              + (f", {len(data['failed'])} failed" if data["failed"] else "") + ".",
              f"- **Intervals:** 95%, {data['n_boot']} replicates of a two-level bootstrap "
              "(seeds, then episodes within each column; paired by episode between rows). "
              "Success in %; each cell `mean over seeds [95% interval]`, the paper's value in *italics* below.", ""]
    lines += ["| Row | Decoder | Seeds | " + " | ".join(COLUMN_NAMES) + " | Overall |",
              "|---|---|---:|" + "---:|" * 5]
    for r in data["rows"]:
        cells = []
        for i, col in enumerate([*COLUMNS, "overall"]):
            e = r["columns"][col]
            paper = r["paper"]
            pv = None if not paper else (paper[i] if i < 4 else float(np.mean(paper)))
            cells.append(f"{e['mean']:.1f} [{e['lo']:.1f}, {e['hi']:.1f}]<br>*{_pct(pv)}*")
        lines.append(f"| {r['label']} | {r['decoder'] or '–'} | {len(r['seeds'])} | " + " | ".join(cells) + " |")
    lines += ["", "## The paper's claims", "",
              "Verdict per claim at this budget: *supported* when the 95% interval of the measured "
              "difference lies above 0, *contradicted* when below, *inconclusive* when it contains 0.", "",
              "| Claim | Comparison | Measured (points) | Paper | Verdict |", "|---|---|---:|---:|---|"]
    for c in data["claims"]:
        for k, p in enumerate(c["parts"]):
            meas = p.get("measured")
            ms = f"{meas['mean']:+.1f} [{meas['lo']:+.1f}, {meas['hi']:+.1f}]" if meas else "–"
            pp = "–" if p.get("paper") is None else f"{p['paper']:+.1f}"
            head = f"{c['claim']} (**{c['verdict']}**)" if k == 0 else ""
            lines.append(f"| {head} | {p['comparison']} | {ms} | {pp} | {p['verdict']} |")
    if any(r["manoeuvres"] for r in data["rows"]):
        names = [n for n in ("left", "right", "straight") if any(n in r["manoeuvres"] for r in data["rows"])]
        lines += ["", "## Success by manoeuvre (mean over seeds, %)", "",
                  "| Row | " + " | ".join(n.capitalize() for n in names) + " |", "|---|" + "---:|" * len(names)]
        for r in data["rows"]:
            lines.append(f"| {r['label']} | " + " | ".join(_pct(r["manoeuvres"].get(n)) for n in names) + " |")
    curve = curve_table(data)
    if curve:
        lines += ["", "## Learning curve (overall success, mean over seeds [min, max])", "", *curve]
    lines += ["", "## Wall time per cell (s, on the machine above)", "", "| Row | Seed | Train | Evaluate | Curve evaluations |",
              "|---|---:|---:|---:|---:|"]
    for r in data["rows"]:
        for s, w in r["wall_s"].items():
            w = w or {}
            lines.append(f"| {r['label']} | {s} | {_pct(w.get('train'))} | {_pct(w.get('evaluate'))} | {_pct(w.get('curve'))} |")
    if data["failed"]:
        lines += ["", "## Failed cells", ""] + [f"- {f['row']} seed {f['seed']}: {f['error']}" for f in data["failed"]]
    return "\n".join(lines) + "\n"


def curve_points(data: Mapping[str, Any]) -> dict[str, list[tuple[int, float, float, float]]]:
    """row -> [(samples seen, mean, min, max of overall success over seeds)] for rows with a curve."""
    out = {}
    for r in data["rows"]:
        by_samples: dict[int, list[float]] = {}
        for pts in r["curve"].values():
            for p in pts:
                by_samples.setdefault(int(p["samples"]), []).append(float(p["overall"]))
        if by_samples:
            out[r["label"]] = [(s, float(np.mean(v)), float(np.min(v)), float(np.max(v)))
                               for s, v in sorted(by_samples.items())]
    return out


def curve_table(data: Mapping[str, Any]) -> list[str]:
    pts = curve_points(data)
    if not pts:
        return []
    samples = sorted({s for v in pts.values() for s, *_ in v})
    lines = ["| Row | " + " | ".join(f"{s:,} samples" for s in samples) + " |", "|---|" + "---:|" * len(samples)]
    for label, v in pts.items():
        d = {s: (m, lo, hi) for s, m, lo, hi in v}
        lines.append(f"| {label} | " + " | ".join(f"{d[s][0]:.1f} [{d[s][1]:.1f}, {d[s][2]:.1f}]" if s in d else "–"
                                                for s in samples) + " |")
    return lines


def plot_results(data: Mapping[str, Any], path: Path) -> Path:
    """Success per column with 95% interval bars for each row; the paper's values as crosses in the row's colour."""
    from cicfw.bench.plots import _plt, _save

    plt = _plt()
    rows = data["rows"]
    fig, ax = plt.subplots(figsize=(max(7.5, 1.2 * len(rows) + 4), 4.4))
    cmap = plt.get_cmap("tab10")
    x = np.arange(5)
    width = 0.8 / max(len(rows), 1)
    for k, r in enumerate(rows):
        xs = x - 0.4 + width * (k + 0.5)
        est = [r["columns"][c] for c in [*COLUMNS, "overall"]]
        mean = np.array([e["mean"] for e in est])
        err = np.array([[e["mean"] - e["lo"] for e in est], [e["hi"] - e["mean"] for e in est]])
        ax.errorbar(xs, mean, yerr=err, fmt="o", color=cmap(k % 10), capsize=3, label=r["label"])
        if r["paper"]:
            pv = [*r["paper"], float(np.mean(r["paper"]))]
            ax.scatter(xs, pv, marker="x", color=cmap(k % 10), s=36, zorder=3)
    ax.scatter([], [], marker="x", color="grey", label="the paper's value (row's colour)")
    ax.set_xticks(x, [n.replace(" / ", "\n") for n in COLUMN_NAMES] + ["Overall\n(mean of columns)"])
    ax.set_ylim(-3, 105)
    ax.set_ylabel("reach destination success (%)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.17), ncol=min(len(rows) + 1, 4), frameon=False)
    suite = (data["manifest"].get("suite") or {}).get("name", "?")
    ax.set_title(f"Suite {suite}, budget {data['manifest'].get('budget')}: mean over seeds, 95% bootstrap interval")
    return _save(fig, Path(path))


def plot_curve(data: Mapping[str, Any], path: Path) -> Path | None:
    """Overall success against training samples seen, per row (mean over seeds, band = min..max)."""
    pts = curve_points(data)
    if not pts:
        return None
    from cicfw.bench.plots import _plt, _save

    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.0))
    for label, v in pts.items():
        s, m, lo, hi = (np.array(a) for a in zip(*v))
        ax.plot(s, m, "o-", label=label)
        ax.fill_between(s, lo, hi, alpha=0.2)
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


def write_report(results_dir: Path, catalogue: Mapping[str, Mapping[str, Any]], n_boot: int = 4000) -> dict[str, Any]:
    """results.json, results.csv, RESULTS.md and the two pictures in ``results_dir``; returns the data."""
    results_dir = Path(results_dir)
    manifest = json.loads((results_dir / "reproduce.json").read_text()) if (results_dir / "reproduce.json").is_file() else {}
    cells, failed = load_cells(results_dir)
    if not cells:
        raise ValueError(f"no finished cell in {str(results_dir)!r} (cells/<row>/seed<k>/cell.json): nothing to report"
                         + (f"; {len(failed)} failed" if failed else ""))
    data = report_data(cells, failed, catalogue, manifest, n_boot=n_boot)
    atomic_write(results_dir / "results.json", json.dumps(data, indent=1))
    atomic_write(results_dir / "results.csv", results_csv(data))
    plot_results(data, results_dir / "results.png")
    data["has_curve"] = plot_curve(data, results_dir / "learning_curve.png") is not None
    atomic_write(results_dir / "RESULTS.md", _with_pictures(markdown(data), ".", data["has_curve"]))
    return data


def write_markdown_copy(data: Mapping[str, Any], path: Path, pictures: Path) -> Path:
    """The report's Markdown at ``path`` (e.g. docs/RESULTS.md), its pictures linked from ``pictures``."""
    import os

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
    for f in files:
        target = dest / f.relative_to(results_dir)
        atomic_write(target, f.read_bytes())
        out.append(target)
    return out


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
            catalogue = OmegaConf.to_container(compose("reproduce").catalogue, resolve=True)
        data = write_report(Path(a.results_dir), catalogue)
        if a.publish:
            publish(Path(a.results_dir), Path(a.publish))
        if a.markdown:
            write_markdown_copy(data, Path(a.markdown), Path(a.publish) if a.publish else Path(a.results_dir))
    except (ValueError, FileNotFoundError) as err:
        print(f"cicfw: error: {err}", file=sys.stderr)
        return 2
    print(f"{sum(len(r['seeds']) for r in data['rows'])} cells of {len(data['rows'])} rows; "
          f"report in {Path(a.results_dir) / 'RESULTS.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
