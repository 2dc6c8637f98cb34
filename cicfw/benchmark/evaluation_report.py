"""Evaluation reports: one row per episode (JSON + CSV), the paper's success table, joined runs.

A run folder holds ``episodes.json`` (rows + run metadata), ``episodes.csv``, ``summary.json``,
``table.md`` / ``table.tex`` (the paper's layout: rows are models; columns Training town / New town x
Training weathers / New weathers; reach-destination success in percent), and pictures.
``python -m cicfw.benchmark.evaluation_report DIR...`` (or ``cicfw report DIR...``) joins run folders, or folders
holding them (a multirun sweep), into one table with its bar chart.
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import os
import re
import sys
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from cicfw.benchmark.finished_run import Run, atomic_write, cell_key, cell_name, load_run, table_rows
from cicfw.benchmark.journal import read_log
from cicfw.benchmark.plots import bar_chart_png
from cicfw.core.run_folder import check_name_lengths, claim_folder, folder_owner, is_reproduction_results
from cicfw.benchmark.suite import CELLS, town_label
from cicfw.core.errors import CicfwError, install_app_handlers
from cicfw.core.files import writable_folder, write_together

ROW_FIELDS = (
    "model", "episode", "key", "town", "weather", "town_set", "weather_set", "pair", "route", "command",
    "success", "reason", "time_s", "timeout_s", "distance_m", "route_length_m", "goal_distance_m", "progress",
    "offroad_fraction", "opposite_lane_fraction", "steps",
)
CAPTION = "Reach destination success rate (%)"


def summary(run: Run) -> dict[str, Any]:
    """The run's success overall and per cell (what ``summary.json`` holds and ``evaluate`` returns).

    ``success`` is the overall reach-destination rate in percent over the episodes driven (pooled: each
    episode weighs the same), ``null`` while none is (an evaluation stopped before its first episode
    finished: no episodes, no rate); ``cells`` and ``manoeuvres`` hold only what has episodes, each with
    its ``success`` count, ``episodes`` and ``rate`` (%)."""
    cells = run.cells()
    rate = run.success_rate()
    return {
        "model": run.label, "episodes": len(run.rows), "success": None if rate is None else round(rate, 2),
        "cells": {cell_key(*c): {"name": cell_name(*c), "success": ok, "episodes": n,
                                 "rate": round(100.0 * ok / n, 2)}
                  for c in CELLS if c in cells for ok, n in [cells[c]]},
        "manoeuvres": {m: {"success": ok, "episodes": n, "rate": round(100.0 * ok / n, 2)}
                       for m, (ok, n) in run.manoeuvres().items()},
        "suite": run.suite_name(),
        "reasons": dict(sorted(Counter(r["reason"] for r in run.rows).items())),
        **{k: run.meta[k] for k in ("policy", "checkpoint", "checkpoint_file", "seed", "wall_s", "steps")
           if k in run.meta},
        "complete": is_complete(run),
        **({"episodes_total": run.meta["episodes_total"]} if "episodes_total" in run.meta else {}),
    }


# ------------------------------------------------------------------------------------------------
# partial runs (an evaluation killed before its last episode; rerunning it finishes it)


def is_complete(run: Run) -> bool:
    """False for a run whose evaluation has not driven every episode of its suite yet (runs written
    before runs were marked are complete: they were only written at the end)."""
    return run.meta.get("complete", True) is not False


def partial_note(run: Run) -> str:
    """``k of N episodes`` for a partial run."""
    return f"{len(run.rows)} of {run.meta.get('episodes_total', '?')} episodes"


def _marked(runs: Sequence[Run]) -> list[Run]:
    """The runs with each partial one's row label marked ``(PARTIAL k/N)``."""
    return [r if is_complete(r) else Run(label=f"{r.label} (PARTIAL {len(r.rows)}/{r.meta.get('episodes_total', '?')})",
                                         rows=r.rows, meta=r.meta, path=r.path) for r in runs]


def _partial_lines(runs: Sequence[Run]) -> list[str]:
    return [f"**PARTIAL**: {md_cell(r.label)} had {partial_note(r)} when this table was written (its evaluation "
            f"had not finished); the rates "
            f"cover those only. Run the same evaluate command with the same output folder to finish it."
            for r in runs if not is_complete(r)]


# ------------------------------------------------------------------------------------------------
# the table


def _fmt(v: float | None) -> str:
    return "–" if v is None else f"{v:.2f}"


def markdown_table(runs: Sequence[Run]) -> str:
    """The paper's table as Markdown: a header row for the towns, one for the weathers, a row per model.
    A partial run's row is marked, with a PARTIAL line under the caption."""
    notes = _partial_lines(runs)
    runs = _marked(runs)
    rows = table_rows(runs)
    lines = [
        f"**{CAPTION}**",
        "",
        *[x for note in notes for x in (note, "")],
        "| Model | Training town | | New town | |",
        "|---|---:|---:|---:|---:|",
        "| | *Training weathers* | *New weathers* | *Training weathers* | *New weathers* |",
    ]
    lines += [md_row([label, *map(_fmt, rates)]) for label, rates, _ in rows]
    counts = {tuple(n) for _, _, n in rows}
    if len(counts) == 1:
        n = next(iter(counts))
        lines += ["", "Episodes per column: " + ", ".join(str(k) if k else "–" for k in n) + "."]
    else:
        lines += ["", "Episodes per column differ between rows: "
                  + "; ".join(f"{label}: {', '.join(map(str, n))}" for label, _, n in rows) + "."]
    lines += routes_note(runs)
    suites = sorted({run.suite_name() for run in runs})
    lines += [f"Suite: {', '.join(suites)}" + (" (the paper's single-turn task: turns only)"
                                               if suites == ["single_turn"] else "") + "."]
    return "\n".join(lines) + "\n" + manoeuvre_table(runs)


def routes_note(runs: Sequence[Run]) -> list[str]:
    """A note line when the rows drove different routes (other ``suite.pairs`` or ``limit``, another town):
    their rates are over other start/goal pairs even where their episode counts agree. Each group of rows
    that drove the same routes is named with its pairs per town (``pair``, else the route's name)."""
    groups: dict[frozenset, list[str]] = {}
    for run in runs:
        driven = frozenset((str(r.get("town")), str(r.get("pair", r.get("route")))) for r in run.rows)
        groups.setdefault(driven, []).append(run.label)
    if len(groups) < 2:
        return []

    def pairs(driven: frozenset) -> str:
        by_town: dict[str, list[str]] = {}
        for town, pair in sorted(driven, key=lambda tp: (tp[0], _natural(Path(tp[1])))):
            by_town.setdefault(town, []).append(pair)
        return " and ".join(f"{town} pairs {', '.join(p[:8])}{f' and {len(p) - 8} more' if len(p) > 8 else ''}"
                         for town, p in by_town.items()) or "no episode"

    return ["Routes differ between rows (their rates are over other start/goal pairs): "
            + "; ".join(f"{', '.join(map(md_cell, labels))}: {pairs(driven)}" for driven, labels in groups.items())
            + "."]


def manoeuvre_table(runs: Sequence[Run]) -> str:
    """Success by manoeuvre (left / right / straight where the suite has it), a row per model."""
    names = [m for m in ("left", "right", "straight") if any(m in run.manoeuvres() for run in runs)]
    if not names:
        return ""
    table = md_table(["Model", *(n.capitalize() for n in names)], "l" + "r" * len(names), (
        [run.label, *(f"{100.0 * m[n][0] / m[n][1]:.2f} ({m[n][0]}/{m[n][1]})" if n in m else "–"
                                  for n in names)] for run in runs for m in [run.manoeuvres()]))
    return "\n".join(["", "**Success by manoeuvre (%, successes/episodes)**", "", *table]) + "\n"


#: a ``|`` with the backslashes right before it (each doubled and the pipe escaped, both stay literal)
_PIPE = re.compile(r"(\\*)\|")
_LINE_BREAK = re.compile(r"\r\n|\r|\n")


def md_cell(value: Any) -> str:
    """``value`` as one Markdown table cell: a ``|`` escaped (``\\|``) so it splits no cell, a line break read
    as a space so it ends no row (a label may hold either)."""
    return _PIPE.sub(lambda m: m.group(1) * 2 + "\\|", _LINE_BREAK.sub(" ", str(value)))


def md_row(cells: Iterable[Any]) -> str:
    """One row of a Markdown table: ``| a | b |``, each cell through ``md_cell``."""
    return "| " + " | ".join(map(md_cell, cells)) + " |"


def md_table(head: Sequence[str], align: str, rows: Iterable[Iterable[Any]] = ()) -> list[str]:
    """A Markdown table's lines: ``head``, its rule (``align``: ``l`` or ``r`` per column) and ``rows``."""
    return [md_row(head), "|" + "".join("---:|" if a == "r" else "---|" for a in align), *map(md_row, rows)]


def latex_table(runs: Sequence[Run]) -> str:
    """The same table as the paper's LaTeX tabular (a partial run's row marked)."""
    runs = _marked(runs)
    body = "\n".join(
        f"{_tex_escape(label)} & " + " & ".join(_fmt(v).replace("–", "--") for v in rates) + r" \\ \hline"
        for label, rates, _ in table_rows(runs))
    return "\n".join([
        r"\begin{tabular}{|c|c|c|c|c|}", r"\hline",
        r"\multirow{3}{*}{Model} & \multicolumn{4}{c|}{Reach destination success rate} \\ \cline{2-5}",
        r" & \multicolumn{2}{c|}{Training town} & \multicolumn{2}{c|}{New town} \\ \cline{2-5}",
        r" & Training weathers & New weathers & Training weathers & New weathers \\ \hline\hline",
        body, r"\end{tabular}", ""])


#: LaTeX's special characters in text, each as it prints itself (one pass: an escape's own braces stay)
_TEX = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "_": r"\_", "#": r"\#", "$": r"\$", "{": r"\{",
        "}": r"\}", "^": r"\textasciicircum{}", "~": r"\textasciitilde{}"}


def _tex_escape(s: str) -> str:
    return "".join(_TEX.get(c, c) for c in str(s))


def table_csv(runs: Sequence[Run]) -> str:
    runs = _marked(runs)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["model"] + [cell_key(*c) for c in CELLS] + [f"n:{cell_key(*c)}" for c in CELLS])
    for label, rates, n in table_rows(runs):
        w.writerow([label] + ["" if v is None else f"{v:.2f}" for v in rates] + n)
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------
# writing and reading run folders


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


def find_runs(paths: Sequence[str | Path], partial: str = "refuse") -> list[Run]:
    """Runs in the given folders: each folder is a run, or is searched for run folders (a sweep);
    order: as given, then by folder name (Hydra's job numbers) within each. A partial run (an
    evaluation stopped before its last episode; its rows read from its episode log) raises one error
    (``partial="refuse"``), is kept and marked in every table (``"include"``), or left out (``"skip"``)."""
    if partial not in ("refuse", "include", "skip"):
        raise ValueError(f"find_runs: partial must be refuse, include or skip, got {partial!r}")
    runs = _find_runs(paths)
    check_each_run_once(runs)
    for r in runs:
        if not is_complete(r) and partial == "refuse":
            raise CicfwError(f"report: {str(r.path)!r} is a partial evaluation run ({partial_note(r)} finished); "
                             f"finish it by running its evaluate command again with the same output folder "
                             f"(hydra.run.dir={r.path}), or pass --partial to include it marked PARTIAL")
    runs = [r for r in runs if is_complete(r) or partial == "include"]
    check_one_suite(runs)
    return _unique_labels(runs)


def check_each_run_once(runs: Sequence[Run]) -> None:
    """A run found twice (the same folder given twice, through a symlink or another spelling, or inside a
    sweep also given), or two folders of one measurement (``_measurement``: a run copied elsewhere, even run
    again there, which rewrites its report's timings), would be two rows of one run: one ``CicfwError`` naming
    both paths."""
    seen: dict[str, Path] = {}
    for r in runs:
        real = os.path.realpath(r.path)
        if real in seen:
            raise CicfwError(f"report: {str(seen[real])!r} and {str(r.path)!r} are the same run folder, which one "
                             f"table would show twice; give each run once", key="dirs", value=str(r.path))
        seen[real] = r.path
    digests: dict[str, Path] = {}
    for r in runs:
        digest = _measurement(r)
        if digest is None:
            continue
        if digest in digests:
            raise CicfwError(f"report: {str(digests[digest])!r} and {str(r.path)!r} hold one measurement: the same "
                             f"policy, suite and simulator and the same episodes (a run and its copy, or its copy run "
                             f"again), which one table would show as two rows; give one of them", key="dirs",
                             value=str(r.path))
        digests[digest] = r.path


def _measurement(run: Run) -> str | None:
    """A digest of what ``run`` measured: its fingerprint (policy, suite, simulator) and its episode rows, the
    row label aside; a run recorded without a fingerprint is its ``episodes.json``'s bytes. None for a partial
    run read from its episode log without a report of its own."""
    fingerprint = run.meta.get("fingerprint")
    if fingerprint is None:
        try:
            return hashlib.sha256((Path(run.path) / "episodes.json").read_bytes()).hexdigest()
        except (OSError, TypeError):
            return None
    rows = [{k: v for k, v in row.items() if k != "model"} for row in run.rows]
    return hashlib.sha256(json.dumps([fingerprint, rows], sort_keys=True, default=str).encode()).hexdigest()


#: the suite settings that say what a table's columns are: runs joined in one table agree on them
SUITE_KEYS = ("name", "training_towns", "training_weathers")


def check_one_suite(runs: Sequence[Run]) -> None:
    """Runs joined into one table drove one suite: the same suite name and training towns and weathers (the
    columns' meaning; towns, weathers or pairs subsets may differ, the table counts each row's episodes).
    Otherwise one ``CicfwError`` naming the key, both runs and both values."""
    def settings(run: Run) -> dict[str, Any]:
        suite = run.meta.get("suite")
        found = {"name": run.suite_name()}
        for key in SUITE_KEYS[1:]:
            value = suite.get(key) if isinstance(suite, Mapping) else None
            found[key] = sorted(map(str, value)) if isinstance(value, (list, tuple)) else value
        return {k: v for k, v in found.items() if v is not None}

    _one_setting(runs, settings, "suite", "drove different suites")
    check_one_town_per_name(runs)
    check_one_episode_rule(runs)


def check_one_town_per_name(runs: Sequence[Run]) -> None:
    """Runs joined into one table that drove a town given as a file of one name drove the same town: a file
    counts by its contents (its fingerprint's ``town_files``, as resuming an evaluation counts it), so two
    files named ``town_x.yaml`` with other roads, whose rows would share one column and one town name, are one
    ``CicfwError`` naming both runs and both files."""
    seen: dict[str, tuple[str, str, Run]] = {}  # town name -> (contents' hash, file, the first run)
    for run in runs:
        fp = run.meta.get("fingerprint")
        files = fp.get("town_files") if isinstance(fp, Mapping) else None
        for path, digest in (files.items() if isinstance(files, Mapping) else ()):
            name = town_label(str(path))
            first = seen.setdefault(name, (str(digest), str(path), run))
            if first[0] != str(digest):
                raise CicfwError(f"report: {first[2].path} and {run.path} drove two different towns named {name!r} "
                                 f"(the files {first[1]} and {path} differ), whose success rates one table cannot "
                                 f"compare; report them separately", key="suite.towns", value=str(path))


#: the fingerprint's parts (cicfw/benchmark/app.py ``run_fingerprint``) that decide what an episode sees and
#: what counts as a success: the simulator (weather family, success radius ...) and the runner's episode rules
EPISODE_RULE_PARTS = ("sim", "runner")


def check_one_episode_rule(runs: Sequence[Run]) -> None:
    """Runs joined into one table drove under one simulator and one set of episode rules, else a rate of one
    row means another thing than its neighbour's (a 2 m and an 8 m success radius, another weather family).
    A key only one run records (a run of an older cicfw) is not compared. One ``CicfwError`` naming the key."""
    for name in EPISODE_RULE_PARTS:
        def settings(run: Run, name: str = name) -> dict[str, Any]:
            fp = run.meta.get("fingerprint")
            value = fp.get(name) if isinstance(fp, Mapping) else None
            return dict(sorted(value.items(), key=lambda kv: str(kv[0]))) if isinstance(value, Mapping) else {}

        _one_setting(runs, settings, name, f"drove under different {name} settings")


def _one_setting(runs: Sequence[Run], settings: Callable[[Run], Mapping[str, Any]], part: str, what: str) -> None:
    """Each of ``settings(run)``'s keys (``part.<key>``) the same in every run that records it, else one
    ``CicfwError``: the first run and the one that differs ``what``, with both values."""
    if not runs:
        return
    first, others = settings(runs[0]), [(r, settings(r)) for r in runs[1:]]
    for key in first:
        for r, other in others:
            if key in other and first[key] != other[key]:
                raise CicfwError(f"report: {runs[0].path} and {r.path} {what} ({part}.{key}: {first[key]} and "
                                 f"{other[key]}), whose success rates one table cannot compare; report them "
                                 f"separately", key=f"{part}.{key}", value=other[key])


def load_current_run(run_dir: str | Path) -> Run:
    """``load_run``, with a partial run's rows read from its episode log (what has finished so far,
    even when its evaluation was killed after writing the report)."""
    run = load_run(Path(run_dir))
    if not is_complete(run):
        _, rows, _, _ = read_log(run_dir, trajectories=False)
        if rows:
            run.rows = [{"model": run.label, **rows[i]} for i in sorted(rows)]
    return run


def _find_runs(paths: Sequence[str | Path]) -> list[Run]:
    runs: list[Run] = []
    for p in paths:
        p = Path(p).expanduser()
        if not p.is_dir():
            raise FileNotFoundError(f"report: {str(p)!r} is not a folder; give evaluation run folders "
                                    f"(holding episodes.json) or folders that contain them")
        if (p / "episodes.json").is_file():
            runs.append(load_current_run(p))
            continue
        found = sorted({f.parent for f in p.rglob("episodes.json")}, key=_natural)
        if not found:
            raise FileNotFoundError(f"report: no evaluation run (episodes.json) under {str(p)!r}")
        runs.extend(load_current_run(f) for f in found)
    return runs


def _natural(p: Path) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(p))]


def _unique_labels(runs: list[Run]) -> list[Run]:
    """Rows need distinct names: runs sharing a label get their folder name appended."""
    seen = Counter(r.label for r in runs)
    for r in runs:
        if seen[r.label] > 1 and r.path is not None:
            ck = r.meta.get("checkpoint")
            r.label = f"{r.label} ({Path(ck).stem if ck else r.path.name})"
    counts = Counter(r.label for r in runs)
    for r in runs:  # the same checkpoint name in different runs (last.ckpt): their folders tell them apart
        if counts[r.label] > 1 and r.path is not None:
            r.label = f"{r.label} {r.path}"
    return runs


def write_joined(runs: Sequence[Run], out_dir: Path, plots: bool = True, record: bool = False,
                 new: Iterable[Path] = ()) -> str:
    """Write the joined table (md, tex, csv) and its bar chart into ``out_dir`` (with ``record``, ``cicfw
    report``'s record of the runs it joined there too), all or none: the chart is drawn first, so a failure
    leaves no new table beside an old chart. ``new``: names that were free when the folder was checked, only
    created (another report's file written there meanwhile is one line, left as it is). Return the Markdown."""
    out_dir = Path(out_dir)
    md = markdown_table(runs)
    files = {out_dir / "table.md": md.encode(), out_dir / "table.tex": latex_table(runs).encode(),
             out_dir / "table.csv": table_csv(runs).encode()}
    if record:  # with the tables, never without: a folder of tables and no record is refused as no report's
        files[out_dir / REPORT_RECORD] = json.dumps({"written_by": "cicfw report", "runs": _joined(runs)},
                                                    indent=1).encode()
    if plots:
        files[out_dir / "success_bars.png"] = bar_chart_png(_marked(runs))
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_together(files, new=new)  # all or none (a full disk, a file-size limit)
    except FileExistsError as err:
        raise CicfwError(f"report: {err.filename!r} was written by another process while this report ran (another "
                         f"report into the same folder?), and is left as it is; nothing of this report was "
                         f"written: give another --out", key="--out", value=str(out_dir)) from None
    except OSError as err:  # e.g. the disk filled up: the same command writes them again
        where = f"{err.filename!r}" if err.filename else f"into {out_dir}"
        raise CicfwError(f"report: cannot write {where} ({err.strerror or err}); give a writable folder "
                         f"with --out, or free some space and run the same command") from None
    return md


#: what ``cicfw report`` writes into its folder, and its record of the runs it joined there
REPORT_FILES = ("table.md", "table.tex", "table.csv", "success_bars.png")
REPORT_RECORD = "report.json"
#: what ``--out`` must be (``writable_folder`` checks it before anything is written)
REPORT_FOLDER = "a folder you can write (created if missing) for table.md/.tex/.csv and success_bars.png"


def _joined(runs: Sequence[Run]) -> list[str]:
    return sorted(os.path.realpath(r.path) for r in runs)


def check_report_folder(out: Path, runs: Sequence[Run], dirs: Sequence[str], what: str, overwrite: bool) -> None:
    """The report writes into ``out`` only where it holds none of ``REPORT_FILES``, where cicfw writes those
    itself (``out`` is the one run joined, whose tables its evaluation writes, or an evaluation sweep's
    folder, whose tables the sweep joins), where it holds the report of the same runs (``report.json``), or with
    ``--overwrite``: a user's file of the same name, another run's table or another report is refused in
    one line before anything is written. ``dirs``: the folders given (``out`` defaults to the one given)."""
    held = [n for n in (*REPORT_FILES, REPORT_RECORD) if (Path(out) / n).exists()]
    if overwrite or not held:
        return
    given = any(os.path.realpath(out) == os.path.realpath(d) for d in dirs)
    one_run = [os.path.realpath(r.path) for r in runs] == [os.path.realpath(out)]
    # an evaluation sweep's folder, by Hydra's record there (an empty multirun.yaml names no job)
    sweep = not (Path(out) / ".hydra").exists() and folder_owner(out) == "evaluate"
    if given and (one_run or sweep):
        return
    try:
        earlier = json.loads((Path(out) / REPORT_RECORD).read_text()).get("runs")
    except (OSError, ValueError, AttributeError):
        earlier = None
    if earlier == _joined(runs):
        return
    whose = "of a report of other runs" if earlier is not None else "that no report of these runs wrote"
    raise CicfwError(f"report: {what} {str(out)!r} holds {', '.join(held)} {whose}, which this report would "
                     f"replace; give another --out, or --overwrite to replace them", key="--out", value=str(out))


def refuse_reproduction_among(dirs: Sequence[str | Path]) -> None:
    """A reproduction's results folder given with other folders, in any order: its report is its Table 4,
    of it alone, and its cells' evaluations are no rows beside other runs. One ``CicfwError`` naming it."""
    if len(dirs) < 2:
        return
    for d in dirs:
        if is_reproduction_results(Path(d).expanduser()):
            others = ", ".join(repr(str(o)) for o in dirs if o is not d)
            raise CicfwError(f"report: {str(d)!r} is a reproduction's results folder, given with {others}; give "
                             f"either one reproduction folder alone (cicfw report {d}: its Table 4) or evaluation "
                             f"run folders (or folders holding them), not both", key="dirs", value=str(d))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="cicfw report", description="Join evaluation runs (folders written by cicfw evaluate, or folders "
                                         "holding them such as a multirun sweep) into the paper's table.")
    parser.add_argument("dirs", nargs="+", help="run folders or folders containing them")
    parser.add_argument("--out", help="where to write table.md/.tex/.csv and success_bars.png "
                                      "(default: the folder given, when one; else ./report)")
    parser.add_argument("--no-plots", action="store_true", help="skip the bar chart")
    parser.add_argument("--partial", action="store_true",
                        help="include partial runs (evaluations stopped before their last episode), marked PARTIAL; "
                             "without it they are refused")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace tables in the folder that are not an earlier report of the same runs")
    args = parser.parse_args(argv)
    try:  # before any path is looked up, which a name too long for the filesystem makes a traceback
        for key, path in [("--out", args.out), *(("dirs", d) for d in args.dirs)]:
            if path:
                check_name_lengths(Path(path).expanduser(), key)
        refuse_reproduction_among(args.dirs)
        runs = find_runs(args.dirs, partial="include" if args.partial else "refuse")
    except (FileNotFoundError, ValueError) as err:
        print(f"cicfw: error: {err}", file=sys.stderr)
        return 2
    if not args.out and len(args.dirs) == 1 and (Path(args.dirs[0]) / "reproduce.json").is_file():
        print(f"cicfw: error: report: {args.dirs[0]!r} is a reproduction's results folder, whose report is its Table 4 "
              f"(cicfw report {args.dirs[0]}); to join the evaluations it holds into one table, give --out <a folder>",
              file=sys.stderr)
        return 2
    out = Path(args.out).expanduser() if args.out else (Path(args.dirs[0]) if len(args.dirs) == 1 else Path("report"))
    what = "--out" if args.out else "the report folder (default: the folder given; choose one with --out)"
    free = [out / n for n in (*REPORT_FILES, REPORT_RECORD) if not os.path.lexists(out / n)]  # only created
    try:
        if args.out or len(args.dirs) > 1:  # not the one folder given: its own tables, joined from what it holds
            claim_folder(out, "report", "--out", inputs=[*args.dirs, *(r.path for r in runs)],
                         foreign_ok=args.overwrite)
        check_report_folder(out, runs, args.dirs, what, args.overwrite)
        writable_folder(out, "--out", REPORT_FOLDER, what)
        md = write_joined(runs, out, plots=not args.no_plots, record=True, new=free)
    except ValueError as err:
        print(f"cicfw: error: {err}", file=sys.stderr)
        return 2
    print(md)
    print(f"{len(runs)} run(s) joined; table and chart in {out}")
    return 0


if __name__ == "__main__":
    install_app_handlers()  # a closed or full stdout: cicfw/core/errors.py, GuardedStdout
    sys.exit(main())
