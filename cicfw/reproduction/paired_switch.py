"""Does a switch change driving? Two sets of cells of one row, the same seeds, one setting changed.

    python -m cicfw.reproduction.paired_switch docs/results/converged6_bf16_xeon/cells/cil_bf16 \\
        docs/results/converged6_xeon/cells/cil --margin 5

    python -m cicfw.reproduction.paired_switch --episodes docs/results/converged/cells/cil/seed2/cell.json \\
        outputs/cil_seed2_6epochs/eval_epoch6            # one seed, two models: the same episodes

A speed switch (bf16 autocast, a faster optimizer step) is licensed by driving, not by a short run's loss
(docs/training.md): each seed trains twice, with and without it, on the same split and batch order, and
both models drive the same suite. Per table column and overall this prints the paired difference A - B
over seeds (t-interval, ``seed_stats.difference``, widened by the episodes' floor) and an equivalence test
against a margin stated in advance: two one-sided t-tests (TOST,
``statsmodels.stats.weightstats.ttost_paired``), *equivalent* when both reject at 5%, i.e. the 90% interval
lies inside ±margin; the episodes pooled over the seeds must show it too (the same contrast's 90% interval
inside ±margin: Newcombe's in a column, MOVER's on the mean of the four, ``episode_tost``), as seeds that
differ by the same number of episodes leave the t-test no spread. Too few seeds or too wide an
interval reads *not shown*, never *equivalent*. Both sides must drive one suite: the same episodes on every
paired seed, under one weather family of the embedded simulator (each side's cells' recorded family, else its
results folder's pinned one), else one error line. Both must train on one dataset (each cell's ``dataset``,
else its results folder's pin): the seed draws the split and batch order from the dataset, so on two
datasets it pairs nothing and is refused in one line naming both. Sides trained for other epochs (the switch
may be the epochs) or on different CPU kinds are compared, and the header says so (the same seed trains
another model on another kind). ``--episodes`` compares two
models of one seed (a cell's ``cell.json`` or an evaluation folder's ``episodes.csv``) on the episodes both
drove: per column, the episodes one model lost and the other gained, with McNemar's exact test
(``statsmodels``); two runs that drove different suites or under different sim settings are refused as
``cicfw report`` refuses joining them (a cell read through its evaluation, else its results folder's pin), as is
an episode the two count in different columns; ``--margin`` and ``--family`` are not read there, so refused. It
also prints the cells' training wall time, which ran at different hours:
a hint, not a speed figure (bench/train_throughput.py measures speed).
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from statsmodels.stats.contingency_tables import mcnemar
from statsmodels.stats.weightstats import ttost_paired

from cicfw.benchmark.evaluation_report import check_one_episode_rule, check_one_suite
from cicfw.benchmark.finished_run import Run, cell_key, load_run
from cicfw.core.errors import CicfwError, ConfigError, install_app_handlers
from cicfw.core.json_files import read_json
from cicfw.reproduction.cells import (COLUMNS, COPY_SAID, FAMILY_KEY, CellPin, CellResult, check_cell_pin,
                                     check_families, check_one_model, check_one_recipe, check_same_episodes, cpu_counts,
                                     episode_terms, is_copy, kind_noun, load_cell, most_first)
from cicfw.reproduction.report import folder_pin, folder_weather_family
from cicfw.reproduction.seed_stats import (MIN_SEEDS, SCALE, contrast_level, difference, family_level, no_spread,
                                           on_scale, with_episode_floor, word)

ALPHA = 0.05  # each one-sided test of TOST: equivalent when the 90% interval lies inside ±margin
TOST_LEVEL = 1 - 2 * ALPHA
DEFAULT_MARGIN = 5.0  # points, where --margin is not given
ON = [*COLUMNS, None]  # the four table columns, then the mean of them ("overall")
EPISODE_COLUMNS = ("key", "town_set", "weather_set", "success")  # what --episodes reads of an episodes.csv


@dataclass
class Equivalence:
    """A - B on one table column, or overall (``on`` None), over the paired seeds: the 95% t-interval
    (widened by the episodes' floor), the TOST p-value and its verdict."""

    on: str
    a: list[float]
    b: list[float]
    mean: float
    lo: float | None
    hi: float | None
    p_tost: float | None
    verdict: str
    #: how A and B compare, read on the interval corrected over ``family`` comparisons (``seed_stats.word``:
    #: ahead / behind / equivalent within ±margin / not separated; None with too few seeds), and that interval
    word: str | None = None
    word_lo: float | None = None
    word_hi: float | None = None
    #: the interval the verdict is read on: 1 - 2 ALPHA (90%), widened by the same floor; TOST's p < ALPHA
    #: exactly when it lies inside ±margin, so a verdict and this interval never disagree
    tost_lo: float | None = None
    tost_hi: float | None = None


def load_row(folder: Path) -> dict[int, CellResult]:
    """seed -> finished cell under a row's folder (``<row>/seed<k>/cell.json``), or one error line (a results
    folder given instead names its rows to pick from)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CicfwError(f"{folder} is not a folder; give a row's cells, e.g. docs/results/converged/cells/cil")
    paths = sorted(folder.glob("seed*/cell.json"))
    loaded = [(p, c) for p, c in zip(paths, map(load_cell, paths)) if isinstance(c, CellResult)]
    check_one_model(loaded)  # a cell of another model copied in as a seed: the report's check
    out = {c.seed: c for _, c in loaded}
    if not out:
        rows = sorted(p.name for p in (folder / "cells").glob("*") if p.is_dir()) if not paths else []
        if rows:  # a reproduction's results folder given for one of its rows
            raise CicfwError(f"{folder} is a reproduction's results folder, not a row's cells; give "
                             f"{folder / 'cells' / '<row>'} (rows: {', '.join(rows)})", key="folder", value=str(folder))
        raise CicfwError(f"{folder} holds no finished cell (seed*/cell.json with status ok)")
    manifest = results_manifest(folder)
    if manifest is not None:  # a cell of another reproduction copied in would be paired: the report's check
        pin = folder_pin(manifest)
        for cell in out.values():
            check_cell_pin(folder / f"seed{cell.seed}" / "cell.json", cell.meta, pin, "reproduce.json pins",
                           "keep only this reproduction's cells in its folder")
    check_one_recipe(loaded)  # the row redefined between the runs that trained its cells: the report's check
    return out


def tost_paired(a: Sequence[float], b: Sequence[float], margin: float) -> float:
    """TOST p-value for |mean(a - b)| < margin, paired (statsmodels); 1 when the differences do not vary
    (``seed_stats.no_spread``: up to float rounding) and lie outside the margin, 0 when they lie inside it."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    if no_spread(d):
        return 0.0 if abs(float(d.mean())) < margin else 1.0

    return float(ttost_paired(np.asarray(a, float), np.asarray(b, float), -margin, margin)[0])


def episode_tost(terms: Sequence[tuple[float, int, int]], margin: float) -> float:
    """The equivalence p-value on the pooled episodes, A - B as the terms of a contrast
    (``cells.episode_terms``): the smallest alpha at which its (1 - 2 alpha) interval (MOVER; on one column
    Newcombe's) lies inside ±margin (TOST's duality: half the two-sided level at which the farther bound
    crosses its margin), 1 when the difference itself is not inside. The floor
    ``seed_stats.with_episode_floor`` gives an interval."""
    levels = contrast_level(terms, "lo", -margin), contrast_level(terms, "hi", margin)
    return 1.0 if max(levels) == 1.0 else max(levels) / 2.0


def compare(a: Mapping[int, CellResult], b: Mapping[int, CellResult], margin: float,
            family: int = 1) -> list[Equivalence]:
    """Every column and overall, on the seeds both sides ran. Both the interval and the TOST p-value answer to
    the episodes pooled over those seeds (``with_episode_floor``, ``episode_tost``), so seeds whose differences
    happen to agree are not *equivalent* by luck. Each entry's ``word`` is read on its interval at the
    Bonferroni level of ``family`` comparisons (the caller's table: 1 for one comparison)."""
    seeds = sorted(set(a) & set(b))
    out = []
    for col in ON:
        va = {s: a[s].rate(col) for s in seeds}
        vb = {s: b[s].rate(col) for s in seeds}
        d, dc = difference(va, vb), difference(va, vb, level=family_level(family))
        dt = difference(va, vb, level=TOST_LEVEL)
        on = col or "overall"
        terms = episode_terms({"a": [a[s] for s in seeds], "b": [b[s] for s in seeds]},
                              [(1.0, "a", on), (-1.0, "b", on)]) if seeds else None
        if terms:
            d = with_episode_floor(d, terms)
            dc = with_episode_floor(dc, terms, level=family_level(family))
            dt = with_episode_floor(dt, terms, level=TOST_LEVEL)
        w = word(dc.estimate.lo, dc.estimate.hi, margin) if len(seeds) >= MIN_SEEDS else None
        if len(seeds) < MIN_SEEDS:
            p, verdict = None, f"too few seeds ({len(seeds)} paired; {MIN_SEEDS} needed)"
        else:
            p = tost_paired(list(va.values()), list(vb.values()), margin)
            if terms:
                p = max(p, episode_tost(terms, margin))
            verdict = f"equivalent within ±{margin:g}" if p < ALPHA else "not shown"
        out.append(Equivalence(col or "overall", list(va.values()), list(vb.values()), d.estimate.mean,
                               *on_scale(d.estimate.lo, d.estimate.hi), p, verdict, w,
                               *(on_scale(dc.estimate.lo, dc.estimate.hi) if w else (None, None)),
                               *(on_scale(dt.estimate.lo, dt.estimate.hi) if p is not None else (None, None))))
    return out


def row_names(cells: Mapping[int, CellResult]) -> str:
    """The row name(s) the cells' ``cell.json`` give, e.g. ``cil_bf16``: printed so that two rows are seen."""
    return ", ".join(sorted({c.row for c in cells.values()}))


def check_paired(a: Mapping[int, CellResult], b: Mapping[int, CellResult], names: tuple[str, str]) -> None:
    """One error line when the two rows share no seed: a paired comparison needs the same seeds."""
    if not set(a) & set(b):
        raise CicfwError(f"{names[0]} (seeds {sorted(a)}) and {names[1]} (seeds {sorted(b)}) share no seed; "
                         f"give two rows' cells run on the same seeds")


def results_manifest(row_folder: Path) -> dict | None:
    """``<results>/reproduce.json`` of a row's results folder (``<results>/cells/<row>``); None where there is
    none (a copied row folder)."""
    manifest = Path(row_folder).resolve().parent.parent / "reproduce.json"
    if Path(row_folder).resolve().parent.name != "cells" or not manifest.is_file():
        return None
    return read_json(manifest, kind=dict)


def results_family(row_folder: Path) -> str | None:
    """The weather family a row's results folder is pinned to (``results_manifest``); None where it is not
    known."""
    manifest = results_manifest(row_folder)
    return None if manifest is None else folder_weather_family(manifest)


def check_one_family(a: Mapping[int, CellResult], b: Mapping[int, CellResult], folders: tuple[Path, Path]) -> None:
    """One error line when the two sides drove under two known, different weather families (each side's
    cells' recorded one, else its results folder's): the same episode keys, other weathers."""
    fa, fb = (check_families(list(cells.values()), results_family(f), str(f)) for cells, f in zip((a, b), folders))
    if fa and fb and fa != fb:
        raise CicfwError(f"{folders[0]} was driven under the weather family {fa!r} and {folders[1]} under {fb!r}: "
                         f"the same weather names are other weathers, so this is no switch; give two rows driven "
                         f"under one family", key=FAMILY_KEY, value=fb)


def check_same_suite(a: Mapping[int, CellResult], b: Mapping[int, CellResult], names: tuple[str, str]) -> None:
    """One error line when a paired seed drove other episodes on one side than on the other (its counts)."""
    for s in sorted(set(a) & set(b)):
        check_same_episodes(a[s], b[s], "a paired comparison needs both sides to drive the same episodes",
                            (f"{names[0]}/seed{s}", f"{names[1]}/seed{s}"))


def side_pin(row_folder: Path) -> CellPin:
    """What a row's results folder pins its cells to (``results_manifest``): the dataset and epochs a cell that
    records none was made with; an empty pin (nothing known) for a copied row folder."""
    manifest = results_manifest(row_folder)
    return CellPin() if manifest is None else folder_pin(manifest)


def trained_with(cell: CellResult, key: str, pin: CellPin) -> Any:
    """What a cell trained with of ``key`` (``dataset``, ``epochs``): its cell.json's record, else its folder's
    pin; None where neither says."""
    value = cell.meta.get(key)
    return getattr(pin, key) if value is None else value


def check_one_dataset(a: Mapping[int, CellResult], b: Mapping[int, CellResult], names: tuple[str, str],
                      pins: tuple[CellPin, CellPin] = (CellPin(), CellPin())) -> None:
    """One error line naming the first paired seed whose two cells trained on other datasets (``dataset``, the
    data's hash) and both values: the seed pairs two cells through the split and batch order it draws from one
    dataset; on two datasets it draws two, so the cells are no pair and A - B is the data's difference."""
    for s in sorted(set(a) & set(b)):
        da, db = (trained_with(side[s], "dataset", pin) for side, pin in zip((a, b), pins))
        if da and db and da != db:
            sa, sb = (str(Path(n) / f"seed{s}") for n in names)
            raise CicfwError(f"{sa} was trained on dataset={da} and {sb} on dataset={db}: a seed pairs two cells "
                             f"only through one dataset's split and batch order; give two sides trained on one "
                             f"dataset", key="dataset", value=db)


def epochs_line(a: Mapping[int, CellResult], b: Mapping[int, CellResult],
                pins: tuple[CellPin, CellPin] = (CellPin(), CellPin())) -> str | None:
    """A header line naming each side's epochs (``epochs``: each cell's record, else its folder's pin) where a
    paired seed trained for other epochs on its two sides; else None. Longer training may be the switch
    itself, so it is compared, and said."""
    seeds = sorted(set(a) & set(b))
    got = [{s: trained_with(side[s], "epochs", pin) for s in seeds} for side, pin in zip((a, b), pins)]
    if all(None in (got[0][s], got[1][s]) or got[0][s] == got[1][s] for s in seeds):
        return None
    said = [", ".join(f"{k} epochs ({n} seed{'s' if n > 1 else ''})" for k, n in
                      most_first(str(v) for v in side.values() if v is not None).items()) or "epochs not recorded"
            for side in got]
    return (f"Epochs differ: A trained for {said[0]}, B for {said[1]}; the same seed trained for other epochs is "
            f"another model, so A - B is the epochs' difference too")


def cpu_line(a: Mapping[int, CellResult], b: Mapping[int, CellResult]) -> str | None:
    """A header line naming each side's machine kinds (``cells.machine_kind``: the CPU, and its GPU where it had
    one) where a paired seed ran on different kinds; else None."""
    seeds = sorted(set(a) & set(b))
    if all(a[s].cpu == b[s].cpu for s in seeds):
        return None
    counts = [cpu_counts([side[s] for s in seeds]) for side in (a, b)]
    kinds = [", ".join(f"{k} ({n})" for k, n in c.items()) for c in counts]
    noun = kind_noun([*counts[0], *counts[1]])
    return (f"{noun[:1].upper()}{noun[1:]} kinds differ: A ran on {kinds[0]}, B on {kinds[1]}; the same seed "
            f"trains another model on another kind, so A - B is the kinds' difference too")


def check_not_copies(a: Mapping[int, CellResult], b: Mapping[int, CellResult], names: tuple[str, str]) -> None:
    """One error line naming the first paired seed whose two cells are copies (``cells.is_copy``, the check the
    report makes between a row's seeds): a seed compared with itself differs by nothing and pulls the verdict
    toward "equivalent", which says nothing about a switch."""
    for s in sorted(set(a) & set(b)):
        if is_copy(a[s], b[s]):
            sa, sb = (str(Path(n) / f"seed{s}") for n in names)
            raise CicfwError(f"{sa} and {sb} are copies of one cell ({COPY_SAID}): a seed compared with itself; give "
                             f"the cells of the run with the switch", key="cells", value=sb)


def check_distinct(a: Path, b: Path, what: str) -> None:
    """One error line when a and b are the same folder or file: it would compare a run with itself."""
    if Path(a).resolve() == Path(b).resolve():
        raise CicfwError(f"{a} and {b} are the same {what}; give two different runs to compare")


def lines(a: Mapping[int, CellResult], b: Mapping[int, CellResult], margin: float,
          names: tuple[str, str] = ("A", "B"), family: int = 1,
          pins: tuple[CellPin, CellPin] = (CellPin(), CellPin())) -> list[str]:
    """The printed report: seeds, what differs besides the switch (epochs, machine kinds), one line per column
    (its word read at the Bonferroni level of ``family`` comparisons), the cells' training times. ``pins``:
    each side's folder's (``side_pin``), for cells that record no epochs."""
    seeds = sorted(set(a) & set(b))
    out = [f"A {names[0]} (row {row_names(a)}) vs B {names[1]} (row {row_names(b)}), paired seeds {seeds} "
           f"(only in one: {sorted(set(a) ^ set(b)) or 'none'}); equivalence margin ±{margin:g} points; words read "
           + (f"on the Bonferroni interval over {family} comparisons" if family > 1 else "on the 95% interval"),
           *filter(None, [epochs_line(a, b, pins), cpu_line(a, b)]),
           f"{'column':36s} {'A per seed':>22s} {'B per seed':>22s} {'A - B [95%]':>22s} {'TOST p':>7s}  verdict; word"]
    for e in compare(a, b, margin, family):
        ci = f"{e.mean:+.1f} [{e.lo:+.1f}, {e.hi:+.1f}]" if e.lo is not None else f"{e.mean:+.1f}"
        p = "–" if e.p_tost is None else f"{e.p_tost:.3f}"
        said = "too few seeds" if e.word is None else f"{e.word} [{e.word_lo:+.1f}, {e.word_hi:+.1f}]"
        tost = "" if e.tost_lo is None else f" [{TOST_LEVEL:.0%}: {e.tost_lo:+.1f}, {e.tost_hi:+.1f}]"
        out.append(f"{e.on:36s} {' '.join(f'{x:5.1f}' for x in e.a):>22s} {' '.join(f'{x:5.1f}' for x in e.b):>22s} "
                   f"{ci:>22s} {p:>7s}  {e.verdict}{tost}; {said}")
    out.append("[95%]: the paired t-interval over seeds, widened to the pooled episodes' interval where that is "
               "wider (Newcombe's in a column, MOVER's overall)")
    out.append(f"verdict: TOST at {ALPHA:g} each side, read on the {TOST_LEVEL:.0%} interval shown beside it (inside "
               f"±{margin:g}: equivalent); word: read on the 95% interval (or Bonferroni's), stricter, so near the "
               "margin a pair can read equivalent and not separated at once")
    ta = [a[s].meta.get("wall_s", {}).get("train") for s in seeds]
    tb = [b[s].meta.get("wall_s", {}).get("train") for s in seeds]
    if all(ta) and all(tb):
        out.append(f"training wall time per seed (s): A {[round(x) for x in ta]}, B {[round(x) for x in tb]} "
                   f"(different hours: a hint, not a speed figure)")
    return out


def load_episodes(path: Path) -> dict[str, tuple[bool, str]]:
    """key -> (success, table column) from a cell's ``cell.json`` or an evaluation's folder (``episodes.csv``)."""
    path = episodes_file(path)
    if not path.is_file():
        raise CicfwError(f"{path} does not exist; give a cell.json or an evaluation folder holding episodes.csv")
    if path.suffix == ".json":
        cell = load_cell(path)
        if not isinstance(cell, CellResult) or not cell.episodes:
            raise CicfwError(f"{path} holds no episodes; give a finished cell's cell.json")
        return {k: (bool(e["success"]), e["column"]) for k, e in cell.episodes.items()}

    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in EPISODE_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise CicfwError(f"{path} lacks the column(s) {', '.join(missing)}; give a cell.json or an evaluation's "
                             f"episodes.csv (columns {', '.join(EPISODE_COLUMNS)})")
        rows = list(reader)
    if not rows:
        raise CicfwError(f"{path} holds no episodes; give a cell.json or an evaluation's episodes.csv")
    return {r["key"]: (r["success"] == "True", cell_key(r["town_set"], r["weather_set"])) for r in rows}


def episodes_run(path: Path) -> Run:
    """What ``--episodes`` knows of how ``path``'s episodes were driven, as a ``Run`` for the report's checks: an
    evaluation folder's own record; a cell's evaluation (``<cell>/evaluate``, where the reproduction drove it)
    while its folder holds it, else its results folder's suite with the cell's weather family (``episodes_family``);
    nothing for a bare episodes file."""
    path = Path(path)
    if path.is_dir():
        return load_run(path) if (path / "episodes.json").is_file() else Run(path.name, [], {}, path)
    if path.suffix != ".json":
        return Run(path.name, [], {}, path)
    evaluation = path.parent / "evaluate"
    if (evaluation / "episodes.json").is_file():
        meta = dict(load_run(evaluation).meta)
    else:
        manifest = results_manifest(path.parent.parent)
        suite = (manifest or {}).get("suite")
        meta = {"suite": suite} if isinstance(suite, Mapping) else {}
    family = episodes_family(path)
    fp = meta.get("fingerprint") if isinstance(meta.get("fingerprint"), Mapping) else {}
    sim = fp.get("sim") if isinstance(fp.get("sim"), Mapping) else {}
    meta["fingerprint"] = {**fp, "sim": {**({"weather_family": family} if family else {}), **sim}}
    return Run(path.name, [], meta, path)


def episodes_family(path: Path) -> str | None:
    """The weather family a cell's ``cell.json`` records, else its results folder's pin; None where not known."""
    cell = load_cell(path)
    return check_families([cell], results_family(path.parent.parent), str(path)) \
        if isinstance(cell, CellResult) else None


def check_same_sim(a: Path, b: Path) -> None:
    """One error line, the key and both values, when the two runs of ``--episodes`` drove different suites or
    under different sim settings: ``cicfw report``'s check of runs joined in one table (``check_one_suite``) on
    what each side records (``episodes_run``); with a side's suite not known, its sim settings only."""
    runs = [episodes_run(a), episodes_run(b)]
    if all(isinstance(r.meta.get("suite"), Mapping) for r in runs):
        check_one_suite(runs)
    else:
        check_one_episode_rule(runs)


def check_same_columns(a: Mapping[str, tuple[bool, str]], b: Mapping[str, tuple[bool, str]],
                       names: tuple[str, str] = ("A", "B")) -> None:
    """One error line naming the first episode both drove that one side counts in another table column than
    the other (another split into training and new towns or weathers): per column, they compare nothing."""
    for k in sorted(set(a) & set(b)):
        if a[k][1] != b[k][1]:
            raise CicfwError(f"episode {k} is in the column {a[k][1]} in {names[0]} and {b[k][1]} in {names[1]}: the "
                             f"two runs split the suite into other columns (suite.training_towns or "
                             f"suite.training_weathers); give two runs of one suite", key="column", value=b[k][1])


def episodes_file(path: Path) -> Path:
    """The file ``--episodes`` reads for ``path``: itself, or a folder's ``episodes.csv``."""
    path = Path(path)
    return path / "episodes.csv" if path.is_dir() else path


def episode_changes(a: Mapping[str, tuple[bool, str]], b: Mapping[str, tuple[bool, str]],
                    names: tuple[str, str] = ("A", "B")) -> list[dict]:
    """Per column (and all), on the episodes both drove: successes of each, the episodes A lost (B drove
    them, A did not) and gained, and McNemar's exact two-sided p-value on those discordant episodes. Each
    episode counts in one column on both sides (``check_same_columns``, naming the sides by ``names``)."""
    check_same_columns(a, b, names)
    keys = sorted(set(a) & set(b))
    out = []
    for col in [*COLUMNS, "all"]:
        ks = [k for k in keys if col == "all" or a[k][1] == col]
        lost = sum(1 for k in ks if b[k][0] and not a[k][0])
        gained = sum(1 for k in ks if a[k][0] and not b[k][0])
        both = sum(1 for k in ks if a[k][0] and b[k][0])
        p = float(mcnemar([[both, gained], [lost, len(ks) - both - lost - gained]], exact=True).pvalue) \
            if lost + gained else 1.0
        out.append({"column": col, "episodes": len(ks), "a": both + gained, "b": both + lost,
                    "lost": lost, "gained": gained, "p": p})
    return out


def check_episodes_options(margin: float | None, family: int | None) -> None:
    """One error line for ``--margin`` or ``--family`` given with ``--episodes``: McNemar's test per column has
    no equivalence margin and reads no word, so either would be ignored without a word."""
    for option, value in (("--margin", margin), ("--family", family)):
        if value is not None:
            raise CicfwError(f"{option} {value:g} is not read with --episodes, which prints McNemar's exact test per "
                             f"column (no equivalence margin, no words); drop {option}, or compare two rows' cells "
                             f"without --episodes", key=option, value=value)


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: two rows' cells (or, with --episodes, two runs' episodes) -> the table, rc 0."""
    ap = argparse.ArgumentParser(prog="python -m cicfw.reproduction.paired_switch",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("a", help="a row's cells with the switch, e.g. docs/results/converged_bf16/cells/cil_bf16")
    ap.add_argument("b", help="the same row's cells without it, e.g. docs/results/converged/cells/cil")
    ap.add_argument("--margin", type=float, default=None,
                    help="equivalence margin in points (default 5; not with --episodes)")
    ap.add_argument("--family", type=int, default=None, help="read each word on the Bonferroni interval over this "
                    "many comparisons (default 1: the 95%%; not with --episodes)")
    ap.add_argument("--episodes", action="store_true",
                    help="a and b are two models of one seed (cell.json or evaluation folders): McNemar per column")
    args = ap.parse_args(argv)
    try:
        if args.episodes:
            check_episodes_options(args.margin, args.family)
            check_distinct(episodes_file(args.a), episodes_file(args.b), "episodes file")
            ea, eb = load_episodes(Path(args.a)), load_episodes(Path(args.b))
            check_same_sim(Path(args.a), Path(args.b))
            if episodes_file(args.a).read_bytes() == episodes_file(args.b).read_bytes():
                raise CicfwError(f"{args.a} and {args.b} hold the same episodes file, byte for byte: a copy compared "
                                 f"with itself; give the other model's", key="episodes", value=str(args.b))
            if not set(ea) & set(eb):
                raise CicfwError(f"{args.a} and {args.b} share no episode (no key in common); "
                                 f"give two runs of the same evaluation suite")
            changes = episode_changes(ea, eb, (args.a, args.b))
            print(f"A {args.a} vs B {args.b}: the episodes both drove")
            for r in changes:
                print(f"{r['column']:34s} A {r['a']:3d} / B {r['b']:3d} of {r['episodes']:3d}; A gained {r['gained']}, "
                      f"lost {r['lost']}; McNemar exact p {r['p']:.3f}")
            return 0
        margin = DEFAULT_MARGIN if args.margin is None else args.margin
        family = 1 if args.family is None else args.family
        if not (np.isfinite(margin) and 0 < margin <= SCALE):  # past 100 every pair reads "equivalent"
            raise ConfigError("--margin", margin, f"a number of points in (0, {SCALE:g}] (success runs from 0 "
                              f"to 100 %)")
        if family < 1:
            raise ConfigError("--family", family, "a positive number of comparisons")
        check_distinct(Path(args.a), Path(args.b), "folder")
        a, b = load_row(Path(args.a)), load_row(Path(args.b))
        check_paired(a, b, (args.a, args.b))
        check_one_family(a, b, (Path(args.a), Path(args.b)))
        check_same_suite(a, b, (args.a, args.b))
        pins = side_pin(Path(args.a)), side_pin(Path(args.b))
        check_one_dataset(a, b, (args.a, args.b), pins)
        check_not_copies(a, b, (args.a, args.b))
        print("\n".join(lines(a, b, margin, (args.a, args.b), family, pins)))
    except (ValueError, OSError, json.JSONDecodeError) as err:
        print(f"cicfw: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    install_app_handlers()  # a closed or full stdout: cicfw/core/errors.py, GuardedStdout
    raise SystemExit(main())
