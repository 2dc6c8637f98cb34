"""Choosing the relationship matrix R of the paper's "fine tuning" row (C = R . E) by validation error.

The paper sets R "manually before training" and does not publish it. A reproduction needs a rule that
does not peek at the driving suite: train each candidate R (conf/reproduce.yaml ``relation_candidates``)
with the same seeds, and keep the one whose mean validation steering error (``val_steer_mae`` of its
cells: the held-out part of the training town's data) is lowest; a tie keeps the earlier candidate. A cell
whose error is not a finite number (NaN: its training diverged; or none recorded) leaves its candidate out at
that seed, so that seed is no shared one, and the report and the command name it. The report shows the choice
(``relation_data``); so does

    python -m cicfw.reproduction.relation_choice outputs/reproduce/converged6_carla
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from cicfw.core.errors import CicfwError, install_app_handlers
from cicfw.core.json_files import read_json
from cicfw.reproduction.cells import cell_runs, finished_cells
from cicfw.reproduction.claims import shipped_config


@dataclass(frozen=True)
class RelationChoice:
    """The candidates' mean validation errors over the seeds they share, and the row kept."""

    seeds: tuple[int, ...]
    errors: dict[str, float]  # candidate row -> mean val_steer_mae over ``seeds``
    chosen: str | None  # None while some candidate has no finished cell at a shared seed


def _usable(value: Any) -> bool:
    """Whether a cell's ``val_steer_mae`` is a usable error: a finite number >= 0 (not NaN, infinite,
    negative, missing or text; a mean absolute error below 0 is an edited or broken record)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0


def val_errors(cells: Mapping[str, Mapping[str, Any]], rows: Sequence[str]) -> dict[str, dict[int, float]]:
    """row -> {seed: val_steer_mae} of the finished cells (``row/seedK`` -> cell.json) of ``rows`` whose error
    is a finite number (``unusable_errors`` names the others)."""
    out: dict[str, dict[int, float]] = {r: {} for r in rows}
    for key, cell in cells.items():
        row, seed = key.split("/seed")
        value = cell.get("val_steer_mae")
        if row in out and _usable(value):
            out[row][int(seed)] = float(value)
    return out


def unusable_errors(cells: Mapping[str, Mapping[str, Any]], rows: Sequence[str]) -> dict[str, str]:
    """``row/seedK`` -> what its ``val_steer_mae`` is, for each finished cell of ``rows`` that ``val_errors``
    leaves out: "NaN" (a diverged training), "inf", "missing" or the JSON value (text, a number below 0)."""
    out = {}
    for key, cell in sorted(cells.items()):
        if key.split("/seed")[0] not in rows or _usable(value := cell.get("val_steer_mae")):
            continue
        if value is None:
            out[key] = "missing"
        elif isinstance(value, float) and not math.isfinite(value):
            out[key] = "NaN" if math.isnan(value) else ("inf" if value > 0 else "-inf")
        else:
            out[key] = json.dumps(value)[:40]
    return out


def unusable_text(unusable: Mapping[str, str]) -> str:
    """The cells left out, in words: ``re_all/seed0 (val_steer_mae NaN: its training diverged)``."""
    why = {"NaN": ": its training diverged", "missing": ": none recorded"}
    return ", ".join(f"{k} (val_steer_mae {v}{why.get(v, ': below 0' if v.startswith('-') else '')})"
                     for k, v in unusable.items())


def rerun_command(folder: Path, candidates: Sequence[str], seeds: Sequence[int]) -> str:
    """The reproduce command that trains ``candidates`` at ``seeds`` into ``folder``'s reproduction: its budget
    (reproduce.json) and the folder itself as results_dir (a results folder) or as continue_from (a published
    one, whose cells hold their cell.json alone). Without them it would start the default budget elsewhere."""
    budget = read_json(Path(folder) / "reproduce.json", default={}, kind=dict).get("budget")
    where = f"results_dir={folder}" if cell_runs(folder) else f"continue_from={folder} results_dir=<a new folder>"
    return (f"python -m cicfw.reproduce{f' budget={budget}' if budget else ''} 'rows=[{','.join(candidates)}]' "
            f"'seeds=[{','.join(map(str, seeds))}]' {where}")


def choose(errors_by_seed: Mapping[str, Mapping[int, float]], candidates: Sequence[str]) -> RelationChoice:
    """The lowest mean validation error over the seeds every candidate has (ties: the earlier candidate)."""
    if not candidates:
        raise CicfwError("relation_candidates is empty; give the rows to choose R from, e.g. [re_all, re_pairs, re_none]")
    shared = set.intersection(*(set(errors_by_seed.get(r, {})) for r in candidates))
    seeds = tuple(sorted(shared))
    if not seeds:
        return RelationChoice((), {}, None)
    errors = {r: sum(errors_by_seed[r][s] for s in seeds) / len(seeds) for r in candidates}
    chosen = min(candidates, key=lambda r: (errors[r], candidates.index(r)))
    return RelationChoice(seeds, errors, chosen)


def shipped_candidates() -> list[str]:
    """The candidate rows shipped in conf/reproduce.yaml (``relation_candidates``)."""
    return list(shipped_config()["relation_candidates"])


def relation_data(errors_by_seed: Mapping[str, Mapping[int, float]], candidates: Sequence[str],
                  labels: Mapping[str, str], unusable: Mapping[str, str] | None = None) -> dict[str, Any] | None:
    """The report's account of the choice: each candidate's validation error per seed, the seeds they share,
    their means over those and the row chosen (None until every candidate has a cell at a shared seed), and
    ``unusable`` (``unusable_errors``: the cells left out) where there is one; None when no candidate has a
    cell."""
    if not candidates or not (any(errors_by_seed.get(r) for r in candidates) or unusable):
        return None
    c = choose(errors_by_seed, candidates)
    return {"seeds": list(c.seeds), "chosen": c.chosen,
            "candidates": [{"row": r, "label": labels.get(r, r),
                            "val_steer_mae": {str(s): v for s, v in sorted((errors_by_seed.get(r) or {}).items())},
                            "mean": c.errors.get(r)} for r in candidates],
            **({"unusable": dict(unusable)} if unusable else {})}


def choose_in(folder: Path, candidates: Sequence[str]) -> RelationChoice:
    """``choose`` over the finished cells of a results (or published) folder."""
    return choose(val_errors(finished_cells(folder), candidates), candidates)


def refusal(folder: Path, candidates: Sequence[str]) -> str | None:
    """Why ``folder`` and ``candidates`` cannot be read, in one line, or None: a row's or a cell's folder given
    for the results folder (``cells/<row>``, ``cells/<row>/seed<k>``), or a candidate that is neither a shipped
    catalogue row nor a row with cells in ``folder`` (the advice would rerun the typo)."""
    folder = Path(folder)
    if not (folder / "cells").is_dir() and ((folder / "cell.json").is_file() or any(folder.glob("seed*/cell.json"))):
        results = next((p.parent for p in (folder, *folder.parents) if p.name == "cells"), None)
        hint = f" ({results})" if results is not None else ""
        return (f"{str(folder)!r} is a row's or a cell's folder, not a reproduction's results folder; give the "
                f"folder that holds cells/{hint}")
    known = list(shipped_config()["catalogue"])
    known += sorted({p.name for p in folder.glob("cells/*") if p.is_dir()} - set(known))
    unknown = [r for r in candidates if r not in known]
    if unknown:
        return (f"--candidates: unknown row(s) {', '.join(unknown)}; known rows: {', '.join(known)} (conf/"
                f"reproduce.yaml's catalogue, and the rows with cells in {str(folder)!r})")
    return None


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m cicfw.reproduction.relation_choice",
                                description="The R of the fine-tuning row, chosen by validation error.")
    p.add_argument("folder", type=Path, help="a reproduction's results folder (or a published one)")
    p.add_argument("--candidates", nargs="+", default=shipped_candidates(),
                   help="the candidate rows, in order of preference on a tie (default: conf/reproduce.yaml's "
                        "relation_candidates, %(default)s)")
    args = p.parse_args(argv)
    if not args.folder.is_dir():
        print(f"relation_choice: {str(args.folder)!r} is not a folder; give a reproduction's results folder",
              file=sys.stderr)
        return 2
    refused = refusal(args.folder, args.candidates)
    if refused:
        print(f"relation_choice: {refused}", file=sys.stderr)
        return 2
    cells = finished_cells(args.folder)
    c = choose(val_errors(cells, args.candidates), args.candidates)
    unusable = unusable_errors(cells, args.candidates)
    if c.chosen is None and unusable:
        seeds = {int(k.split("/seed")[1]) for k in cells if k.split("/seed")[0] in args.candidates}
        left = {int(k.split("/seed")[1]) for k in unusable}
        clean = sorted(seeds - left) or [max(seeds) + 1]  # rerunning a left-out seed would diverge again
        print(f"no seed has a finite validation error for every candidate ({', '.join(args.candidates)}): "
              f"{unusable_text(unusable)} leaves its candidate out at that seed; run the candidates at seeds "
              f"without one: {rerun_command(args.folder, args.candidates, clean)}")
        return 1
    if c.chosen is None:
        print(f"no seed has a finished cell for every candidate ({', '.join(args.candidates)}); run "
              f"{rerun_command(args.folder, args.candidates, [0])} first")
        return 1
    if unusable:
        print(f"left out: {unusable_text(unusable)}")
    print(f"validation steering error (mean over seeds {list(c.seeds)}):")
    for r in args.candidates:
        print(f"  {r:12s} {c.errors[r]:.5f}{'  <- chosen' if r == c.chosen else ''}")
    return 0


if __name__ == "__main__":
    install_app_handlers()  # a closed or full stdout: cicfw/core/errors.py, GuardedStdout
    raise SystemExit(main())
