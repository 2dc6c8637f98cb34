"""Evaluation reports: one row per episode (JSON + CSV), the paper's success table, joined runs.

A run folder holds ``episodes.json`` (rows + run metadata), ``episodes.csv``, ``summary.json``,
``table.md`` / ``table.tex`` (the paper's layout: rows are models; columns Training town / New town x
Training weathers / New weathers; reach-destination success in percent), and pictures.
``python -m cicfw.bench.report DIR...`` (or ``cicfw report DIR...``) joins run folders, or folders
holding them (a multirun sweep), into one table with its bar chart.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from cicfw.bench.suite import CELLS

ROW_FIELDS = (
    "model", "episode", "key", "town", "weather", "town_set", "weather_set", "pair", "route", "command",
    "success", "reason", "time_s", "timeout_s", "distance_m", "route_length_m", "goal_distance_m", "progress",
    "offroad_fraction", "opposite_lane_fraction", "steps",
)
SET_NAMES = {"training": "Training", "new": "New"}
CAPTION = "Reach destination success rate (%)"


def cell_name(town_set: str, weather_set: str) -> str:
    """``Training town / New weathers`` ..."""
    return f"{SET_NAMES[town_set]} town / {SET_NAMES[weather_set]} weathers"


def cell_key(town_set: str, weather_set: str) -> str:
    """``training_town/new_weathers`` (JSON keys and metric names)."""
    return f"{town_set}_town/{weather_set}_weathers"


@dataclass
class Run:
    """One evaluation run: its label (the table's row name), rows, metadata and folder."""

    label: str
    rows: list[dict[str, Any]]
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def cells(self) -> dict[tuple[str, str], tuple[int, int]]:
        """(town_set, weather_set) -> (successes, episodes), for the cells this run has."""
        out: dict[tuple[str, str], list[int]] = {}
        for r in self.rows:
            c = out.setdefault((r["town_set"], r["weather_set"]), [0, 0])
            c[0] += bool(r["success"])
            c[1] += 1
        return {k: (v[0], v[1]) for k, v in out.items()}

    def manoeuvres(self) -> dict[str, tuple[int, int]]:
        """command (left/right/straight) -> (successes, episodes), in that order, for those present."""
        out: dict[str, list[int]] = {}
        for r in self.rows:
            c = out.setdefault(str(r["command"]), [0, 0])
            c[0] += bool(r["success"])
            c[1] += 1
        order = {"left": 0, "right": 1, "straight": 2}
        return {k: (v[0], v[1]) for k, v in sorted(out.items(), key=lambda kv: (order.get(kv[0], 9), kv[0]))}

    def suite_name(self) -> str:
        """The suite the run drove (``junctions``, ``single_turn``), from its metadata."""
        suite = self.meta.get("suite") or {}
        return str(suite.get("name", "junctions")) if isinstance(suite, Mapping) else "junctions"

    def success_rate(self) -> float:
        return 100.0 * sum(bool(r["success"]) for r in self.rows) / max(len(self.rows), 1)


def summary(run: Run) -> dict[str, Any]:
    """The run's success overall and per cell (what ``summary.json`` holds and ``evaluate`` returns)."""
    cells = run.cells()
    reasons: dict[str, int] = {}
    for r in run.rows:
        reasons[r["reason"]] = reasons.get(r["reason"], 0) + 1
    return {
        "model": run.label, "episodes": len(run.rows), "success": round(run.success_rate(), 2),
        "cells": {cell_key(*c): {"name": cell_name(*c), "success": ok, "episodes": n,
                                 "rate": round(100.0 * ok / n, 2)}
                  for c in CELLS if c in cells for ok, n in [cells[c]]},
        "manoeuvres": {m: {"success": ok, "episodes": n, "rate": round(100.0 * ok / n, 2)}
                       for m, (ok, n) in run.manoeuvres().items()},
        "suite": run.suite_name(),
        "reasons": dict(sorted(reasons.items())),
        **{k: run.meta[k] for k in ("policy", "checkpoint", "seed", "wall_s", "steps") if k in run.meta},
    }


# ------------------------------------------------------------------------------------------------
# the table


def table_rows(runs: Sequence[Run]) -> list[tuple[str, list[float | None], list[int]]]:
    """Per run: (label, success % per paper column or None, episodes per column)."""
    out = []
    for run in runs:
        cells = run.cells()
        rates = [100.0 * cells[c][0] / cells[c][1] if c in cells else None for c in CELLS]
        out.append((run.label, rates, [cells[c][1] if c in cells else 0 for c in CELLS]))
    return out


def _fmt(v: float | None) -> str:
    return "–" if v is None else f"{v:.2f}"


def markdown_table(runs: Sequence[Run]) -> str:
    """The paper's table as Markdown: a header row for the towns, one for the weathers, a row per model."""
    rows = table_rows(runs)
    lines = [
        f"**{CAPTION}**",
        "",
        "| Model | Training town | | New town | |",
        "|---|---:|---:|---:|---:|",
        "| | *Training weathers* | *New weathers* | *Training weathers* | *New weathers* |",
    ]
    for label, rates, _ in rows:
        lines.append(f"| {_md_escape(label)} | " + " | ".join(_fmt(v) for v in rates) + " |")
    counts = {tuple(n) for _, _, n in rows}
    if len(counts) == 1:
        n = next(iter(counts))
        lines += ["", "Episodes per column: " + ", ".join(str(k) if k else "–" for k in n) + "."]
    else:
        lines += ["", "Episodes per column differ between rows: "
                  + "; ".join(f"{label}: {', '.join(map(str, n))}" for label, _, n in rows) + "."]
    suites = sorted({run.suite_name() for run in runs})
    lines += [f"Suite: {', '.join(suites)}" + (" (the paper's single-turn task: turns only)"
                                               if suites == ["single_turn"] else "") + "."]
    return "\n".join(lines) + "\n" + manoeuvre_table(runs)


def manoeuvre_table(runs: Sequence[Run]) -> str:
    """Success by manoeuvre (left / right / straight where the suite has it), a row per model."""
    names = [m for m in ("left", "right", "straight") if any(m in run.manoeuvres() for run in runs)]
    if not names:
        return ""
    lines = ["", "**Success by manoeuvre (%, successes/episodes)**", "",
             "| Model | " + " | ".join(n.capitalize() for n in names) + " |",
             "|---|" + "---:|" * len(names)]
    for run in runs:
        m = run.manoeuvres()
        cells = [f"{100.0 * m[n][0] / m[n][1]:.2f} ({m[n][0]}/{m[n][1]})" if n in m else "–" for n in names]
        lines.append(f"| {_md_escape(run.label)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _md_escape(s: str) -> str:
    return str(s).replace("|", "\\|")


def latex_table(runs: Sequence[Run]) -> str:
    """The same table as the paper's LaTeX tabular."""
    body = "\n".join(
        f"{_tex_escape(label)} & " + " & ".join(_fmt(v).replace("–", "--") for v in rates) + r" \\ \hline"
        for label, rates, _ in table_rows(runs))
    return "\n".join([
        r"\begin{tabular}{|c|c|c|c|c|}", r"\hline",
        r"\multirow{3}{*}{Model} & \multicolumn{4}{c|}{Reach destination success rate} \\ \cline{2-5}",
        r" & \multicolumn{2}{c|}{Training town} & \multicolumn{2}{c|}{New town} \\ \cline{2-5}",
        r" & Training weathers & New weathers & Training weathers & New weathers \\ \hline\hline",
        body, r"\end{tabular}", ""])


def _tex_escape(s: str) -> str:
    for a, b in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#")):
        s = str(s).replace(a, b)
    return s


def table_csv(runs: Sequence[Run]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["model"] + [cell_key(*c) for c in CELLS] + [f"n:{cell_key(*c)}" for c in CELLS])
    for label, rates, n in table_rows(runs):
        w.writerow([label] + ["" if v is None else f"{v:.2f}" for v in rates] + n)
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------
# writing and reading run folders


def atomic_write(path: Path, data: str | bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def episodes_csv(rows: Iterable[Mapping[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=ROW_FIELDS, extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow(r)
    return buf.getvalue()


def write_run(run_dir: Path, run: Run) -> dict[str, Any]:
    """Write a run's episode rows, summary and table into ``run_dir``; return the summary."""
    run_dir = Path(run_dir)
    rows = [{"model": run.label, **r} for r in run.rows]
    s = summary(run)
    atomic_write(run_dir / "episodes.json", json.dumps({"meta": {**run.meta, "model": run.label},
                                                        "episodes": rows}, indent=1))
    atomic_write(run_dir / "episodes.csv", episodes_csv(rows))
    atomic_write(run_dir / "summary.json", json.dumps(s, indent=2))
    atomic_write(run_dir / "table.md", markdown_table([run]))
    atomic_write(run_dir / "table.tex", latex_table([run]))
    return s


def load_run(run_dir: Path) -> Run:
    """A run from its folder (``episodes.json``); a clear error if it is not one."""
    p = Path(run_dir) / "episodes.json"
    try:
        data = json.loads(p.read_text())
        rows, meta = data["episodes"], data.get("meta", {})
        label = meta.get("model") or (rows[0]["model"] if rows else Path(run_dir).name)
    except FileNotFoundError:
        raise FileNotFoundError(f"{str(run_dir)!r} is not an evaluation run folder (no episodes.json)") from None
    except (json.JSONDecodeError, KeyError, TypeError, IndexError) as err:
        raise ValueError(f"{str(p)!r} is not an evaluation report written by cicfw ({err})") from None
    return Run(label=str(label), rows=rows, meta=meta, path=Path(run_dir))


def find_runs(paths: Sequence[str | Path]) -> list[Run]:
    """Runs in the given folders: each folder is a run, or is searched for run folders (a sweep);
    order: as given, then by folder name (Hydra's job numbers) within each."""
    runs: list[Run] = []
    for p in paths:
        p = Path(p).expanduser()
        if not p.is_dir():
            raise FileNotFoundError(f"report: {str(p)!r} is not a folder; give evaluation run folders "
                                    f"(holding episodes.json) or folders that contain them")
        if (p / "episodes.json").is_file():
            runs.append(load_run(p))
            continue
        found = sorted({f.parent for f in p.rglob("episodes.json")}, key=_natural)
        if not found:
            raise FileNotFoundError(f"report: no evaluation run (episodes.json) under {str(p)!r}")
        runs.extend(load_run(f) for f in found)
    return _unique_labels(runs)


def _natural(p: Path) -> list:
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(p))]


def _unique_labels(runs: list[Run]) -> list[Run]:
    """Rows need distinct names: runs sharing a label get their folder name appended."""
    seen: dict[str, int] = {}
    for r in runs:
        seen[r.label] = seen.get(r.label, 0) + 1
    for r in runs:
        if seen[r.label] > 1 and r.path is not None:
            ck = r.meta.get("checkpoint")
            r.label = f"{r.label} ({Path(ck).stem if ck else r.path.name})"
    return runs


def write_joined(runs: Sequence[Run], out_dir: Path, plots: bool = True) -> str:
    """Write the joined table (md, tex, csv) and its bar chart into ``out_dir``; return the Markdown."""
    out_dir = Path(out_dir)
    md = markdown_table(runs)
    atomic_write(out_dir / "table.md", md)
    atomic_write(out_dir / "table.tex", latex_table(runs))
    atomic_write(out_dir / "table.csv", table_csv(runs))
    if plots:
        from cicfw.bench.plots import bar_chart

        bar_chart(runs, out_dir / "success_bars.png")
    return md


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="cicfw report", description="Join evaluation runs (folders written by cicfw evaluate, or folders "
                                         "holding them such as a multirun sweep) into the paper's table.")
    parser.add_argument("dirs", nargs="+", help="run folders or folders containing them")
    parser.add_argument("--out", help="where to write table.md/.tex/.csv and success_bars.png "
                                      "(default: the folder given, when one; else ./report)")
    parser.add_argument("--no-plots", action="store_true", help="skip the bar chart")
    args = parser.parse_args(argv)
    try:
        runs = find_runs(args.dirs)
    except (FileNotFoundError, ValueError) as err:
        print(f"cicfw: error: {err}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else (Path(args.dirs[0]) if len(args.dirs) == 1 else Path("report"))
    md = write_joined(runs, out, plots=not args.no_plots)
    print(md)
    print(f"{len(runs)} run(s) joined; table and chart in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
