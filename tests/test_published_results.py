"""The committed results agree with the committed cells they were made from: every published folder's
results.json and RESULTS.md tables are recomputed from its cells/ (nothing is trained or written into
docs/), and docs/RESULTS.md is the 6- and 4-epoch reports between hand-written prose, verbatim."""
from __future__ import annotations

import difflib
import functools
import hashlib
import json
import math
import re
import shutil
from importlib.resources import files
from pathlib import Path
from typing import Any, Sequence

import pytest
import yaml

from cicfw.reproduction.cells import load_cells
from cicfw.reproduction.claims import load_claims
from cicfw.reproduction.report import markdown, report_data

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

DOCS = Path(__file__).resolve().parents[1] / "docs"
PUBLISHED = sorted(p for p in (DOCS / "results").glob("*/")
                   if (p / "cells").is_dir() and (p / "results.json").is_file())
#: folders made by an earlier cicfw, documented as such, whose report reads differently from today's: they
#: are checked on what that report showed (``legacy_view``), not on their claims, which were another list
LEGACY = {
    "laptop": "made by cicfw 0.1's report: bootstrap intervals in the table and an older list of claims "
              "(docs/results/laptop/README.md)",
}


@functools.cache
def app_config() -> tuple[dict, list]:
    """The catalogue and claims ``cicfw report`` uses (``main`` composes conf/reproduce.yaml with Hydra).
    Read as plain YAML, as ``claims.default_claims`` does: neither holds an interpolation, so the values
    are the composed ones (checked once, equal), and composing took 30-40 s on the loaded 2-core machine."""
    conf = yaml.safe_load(files("cicfw.conf").joinpath("reproduce.yaml").read_text())
    return conf["catalogue"], conf["claims"]


_reports: dict[str, tuple[dict[str, Any], str]] = {}


def recompute(folder: Path) -> tuple[dict[str, Any], str]:
    """The report's data (as results.json holds it) and Markdown, recomputed from ``folder``'s cells the way
    ``write_report`` makes them, with the committed results.json's number of bootstrap replicates.
    Remembered by the bytes it is made from: a copy whose cells are unchanged is not recomputed."""
    n_boot = json.loads((folder / "results.json").read_text())["n_boot"]
    inputs = [p for p in sorted(folder.glob("cells/*/seed*/cell.json")) + [folder / "reproduce.json"] if p.is_file()]
    key = hashlib.sha256(repr([(p.relative_to(folder).as_posix(), p.read_bytes()) for p in inputs] + [n_boot])
                         .encode()).hexdigest()
    if key not in _reports:
        catalogue, claims = app_config()
        cells, failed = load_cells(folder)
        manifest = json.loads((folder / "reproduce.json").read_text()) if (folder / "reproduce.json").is_file() else {}
        data = report_data(cells, failed, catalogue, manifest, n_boot=n_boot, claims=load_claims(claims))
        data = json.loads(json.dumps(data))  # as read back from results.json: string keys, lists
        _reports[key] = data, markdown(data)
    return _reports[key]


def legacy_view(data: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(results.json data, Markdown data) as cicfw 0.1 made them from the same cells: its table's interval
    was the two-level episode bootstrap (today's secondary ``bootstrap``, same draws), it had no
    too-few-seeds mark, its results.json had neither ``bootstrap`` nor ``enough_seeds`` nor the seeds'
    ``spread`` (whose table its RESULTS.md lacks too: only the committed Markdown's tables are compared), and
    it kept every figure to 2 decimals (its Markdown printed those, rounded again)."""
    rows = [_two_decimals({**r, "columns": r["bootstrap"], "enough_seeds": True}) for r in data["rows"]]
    as_json = [{k: v for k, v in r.items() if k not in ("bootstrap", "enough_seeds", "spread")} for r in rows]
    return {**data, "rows": as_json}, {**data, "rows": rows}


def _two_decimals(v: Any) -> Any:
    """``v`` with every float rounded to 2 decimals, as results.json kept them before it kept them whole."""
    if isinstance(v, dict):
        return {k: _two_decimals(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_two_decimals(x) for x in v]
    return round(v, 2) if isinstance(v, float) else v


def differences(got: Any, want: Any, where: str = "") -> list[str]:
    """Where ``got`` (recomputed) and ``want`` (committed) differ; floats within 1e-9. A key only the
    recomputed data has is allowed while it is empty (a field added after the folder was published, e.g.
    ``resumed``: {} for a row without a resumed cell)."""
    if isinstance(want, dict) and isinstance(got, dict):
        out = [f"{where}.{k}: committed {want[k]!r}, not recomputed" for k in want if k not in got]
        out += [f"{where}.{k}: recomputed {got[k]!r}, not committed" for k in got
                if k not in want and got[k] not in (None, {}, [])]
        return out + [d for k in want if k in got for d in differences(got[k], want[k], f"{where}.{k}")]
    if isinstance(want, list) and isinstance(got, list):
        if len(got) != len(want):
            return [f"{where}: {len(got)} items recomputed, {len(want)} committed"]
        return [d for i, (g, w) in enumerate(zip(got, want)) for d in differences(g, w, f"{where}[{i}]")]
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (got, want))
    if (numbers and math.isclose(got, want, rel_tol=1e-9, abs_tol=1e-9)) or got == want:
        return []
    return [f"{where}: recomputed {got!r}, committed {want!r}"]


def table_lines(md: str) -> dict[str, list[str]]:
    """The Markdown's table lines (starting with ``|``) under each heading. Only these are compared: the
    other lines are prose and the header's bullets, which come from reproduce.json (the machine, the
    creation and 'Continued from' dates, notes added after the run) or from wording that changes with the
    code without changing a number."""
    out: dict[str, list[str]] = {}
    heading = ""
    for line in md.splitlines():
        if line.startswith("#"):
            heading = line
        elif line.startswith("|"):
            out.setdefault(heading, []).append(line)
    return out


def line_diff(got: list[str], want: list[str], what: str) -> list[str]:
    """The lines that differ (``-`` committed, ``+`` recomputed), after each hunk's ``@@`` line numbers."""
    return [f"{what}: {d}" for d in list(difflib.unified_diff(want, got, lineterm="", n=0))[2:]]  # no ---/+++ header


def folder_mismatches(folder: Path, legacy: bool = False) -> list[str]:
    """Every difference between ``folder``'s committed results.json and RESULTS.md and what its cells give:
    the table rows (per-column means and intervals, per-seed values, manoeuvres, curves, wall times), the
    claims (every part's estimate, p-values, verdicts and words), the answer (the ranking, the rows listed
    apart, MCB's intervals and pairs, the forest plot's differences and words), fine tuning's R, the failed
    cells, and the Markdown's tables. ``legacy``: the folder was made by cicfw 0.1 (``legacy_view``); its
    claims and answer are not compared."""
    committed = json.loads((folder / "results.json").read_text())
    data, md = recompute(folder)
    keys = ["rows", "claims", "ranking", "apart", "best", "forest", "relation", "failed"]
    if legacy:
        data, md_data = legacy_view(data)
        md, keys = markdown(md_data), ["rows", "failed"]
    # a key added to the report after a folder was published is absent there while it is empty
    out = [d for k in keys for d in differences(data[k], committed.get(k), f"results.json {k}")]
    got, want = table_lines(md), table_lines((folder / "RESULTS.md").read_text())
    if legacy:  # cicfw 0.1 had no per-seed or bootstrap table, and other claims
        want.pop("## The paper's claims", None)
        # nor today's curve table format (one seed read "18.6 [18.6, 18.6]"); the curve's values are
        # compared above, in results.json's rows
        want = {h: v for h, v in want.items() if not h.startswith("## Learning curve")}
        got = {h: v for h, v in got.items() if h in want}
    for heading in sorted(set(got) | set(want)):
        out += line_diff(got.get(heading, []), want.get(heading, []), f"RESULTS.md {heading or 'top'!r}")
    return out


#: docs/RESULTS.md, top to bottom: hand-written prose (docs/results/prose/) that links the published reports;
#: every interval it quotes is checked against them below.
COMPOSITION = [
    ("prose", "head.md"),
    ("prose", "converged4.md"),
    ("prose", "tail.md"),
]


def composed_results_md(docs: Path) -> str:
    """docs/RESULTS.md as it is composed by hand from ``COMPOSITION``, each part followed by a blank line
    where it does not end in one."""
    parts = [(docs / "results" / "prose" / p[1]).read_text() for p in COMPOSITION]
    return "".join(part if part.endswith("\n\n") else part + "\n" for part in parts)


def results_md_mismatches(docs: Path) -> list[str]:
    got = composed_results_md(docs).splitlines()
    return line_diff(got, (docs / "RESULTS.md").read_text().splitlines(), "docs/RESULTS.md (-) vs its parts (+)")


# ------------------------------------------------------------------------------------------------


def test_every_published_folder_is_checked():
    assert {p.name for p in PUBLISHED} >= {"converged", "laptop"}  # the glob still finds what it guards
    assert set(LEGACY) <= {p.name for p in PUBLISHED}


@pytest.mark.parametrize("folder", PUBLISHED, ids=lambda p: p.name)
def test_published_results_match_their_cells(folder: Path):
    mismatches = folder_mismatches(folder, legacy=folder.name in LEGACY)
    read_as = f" (read as {LEGACY[folder.name]})" if folder.name in LEGACY else ""
    assert not mismatches, f"{folder}{read_as} differs from its cells:\n" + "\n".join(mismatches[:40])


def test_docs_results_md_is_head_published_report_tail():
    mismatches = results_md_mismatches(DOCS)
    assert not mismatches, "\n".join(mismatches[:40])


# ---- the checks can fail: each is pointed at a copy with one thing changed


@pytest.fixture
def folder_copy(tmp_path: Path) -> Path:
    """A copy of the smallest published folder (one cell), to corrupt."""
    dest = tmp_path / "converged_constant_lr"
    shutil.copytree(DOCS / "results" / "converged_constant_lr", dest)
    assert folder_mismatches(dest) == []
    return dest


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert text.count(old) >= 1, f"{old!r} not in {path}"
    path.write_text(text.replace(old, new, 1))


def test_a_changed_wall_time_in_a_cell_is_reported(folder_copy: Path):
    edit(folder_copy / "cells/cil/seed0/cell.json", '"train": 1280.6', '"train": 1280.7')
    got = folder_mismatches(folder_copy)
    assert any("results.json rows[0].wall_s.0.train: recomputed 1280.7, committed 1280.6" in m for m in got), got
    assert any("-| Regression (CIL) | 0 | 1280.6 |" in m for m in got), got


def test_one_episode_flipped_in_a_cell_is_reported(folder_copy: Path):
    cell = folder_copy / "cells/cil/seed0/cell.json"
    d = json.loads(cell.read_text())
    first = next(e for e in d["episodes"].values() if e["column"] == "new_town/new_weathers")
    first["success"] = not first["success"]
    cell.write_text(json.dumps(d))
    got = folder_mismatches(folder_copy)
    assert any("rows[0].columns.new_town/new_weathers.mean" in m for m in got), got
    table4 = "RESULTS.md \"# Reproduction of the paper's Table 4\": "
    assert any(m.startswith(table4 + "-| Regression (CIL)") for m in got), got


def test_a_changed_digit_in_results_json_or_md_is_reported(folder_copy: Path):
    edit(folder_copy / "results.json", '"mean": 58.984375', '"mean": 58.994375')
    edit(folder_copy / "RESULTS.md", "| 1280.6 |", "| 1280.9 |")
    got = folder_mismatches(folder_copy)
    assert any("columns.overall.mean: recomputed 58.984375, committed 58.994375" in m for m in got), got
    assert any("+| Regression (CIL) | 0 | 1280.6 |" in m for m in got), got


def test_a_changed_claim_is_reported():
    """The claims of the converged folder (the one with p-values and verdicts) against a copy of its
    results.json with one p-value and one verdict changed."""
    folder = DOCS / "results" / "converged"
    data, _ = recompute(folder)
    committed = json.loads((folder / "results.json").read_text())
    part = next(p for c in committed["claims"] for p in c["parts"] if p.get("p"))  # a p of 0 would not change
    part["p"] *= 1.001
    part["verdict_holm"] = "contradicted" if part["verdict_holm"] != "contradicted" else "supported"
    got = differences(data["claims"], committed["claims"])
    assert len(got) == 2 and any(".p: recomputed" in m for m in got) and any(".verdict_holm:" in m for m in got), got


def test_legacy_folder_checked_on_what_it_showed(tmp_path: Path):
    """laptop's bootstrap intervals are checked too: one digit off in its Table 4 is reported."""
    dest = tmp_path / "laptop"
    shutil.copytree(DOCS / "results" / "laptop", dest)
    edit(dest / "RESULTS.md", "60.1 [44.8, 78.1]", "60.1 [44.8, 78.2]")
    got = folder_mismatches(dest, legacy=True)
    changed = [m.split(": ", 1)[1] for m in got if "@@" not in m]
    assert len(changed) == 2, got
    assert changed[0].startswith("-| Regression (CIL) | – | 3 | 60.1 [44.8, 78.2]"), got  # committed (changed)
    assert changed[1].startswith("+| Regression (CIL) | – | 3 | 60.1 [44.8, 78.1]"), got  # recomputed


@pytest.mark.parametrize("change", ["prose", "composed"])
def test_docs_results_md_drift_is_reported(tmp_path: Path, change: str):
    docs = tmp_path / "docs"
    for rel in ["RESULTS.md", *(f"results/prose/{p[1]}" for p in COMPOSITION if p[0] == "prose")]:
        (docs / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(DOCS / rel, docs / rel)
    assert results_md_mismatches(docs) == []
    edit(docs / ("results/prose/head.md" if change == "prose" else "RESULTS.md"),
         "**Does co-learning (GTU) beat CIL?** No", "**Does co-learning (GTU) beat CIL?** Yes")
    assert results_md_mismatches(docs)


def test_the_docs_state_the_family_size_the_claims_have():
    """docs/reproduce.md and RESULTS.md's prose name Holm's family size; counted here from the YAML's parts
    (they once said 21 when the claims had 20)."""
    _, claims = app_config()
    size = sum(len(c["parts"]) for c in claims if c.get("family", "main") == "main")
    stated = re.findall(r"\((\d+) parts today", (DOCS / "reproduce.md").read_text())
    stated += re.findall(r"the main claims' (\d+) parts", (DOCS / "RESULTS.md").read_text())
    assert len(stated) == 2 and {int(n) for n in stated} == {size}, (stated, size)


#: the words a comparison reads with (``seed_stats.word``), and "too few seeds" where a row has fewer than 3
RULE_WORD = re.compile(r"ahead|behind|equivalent within ±\d+(?:\.\d+)?|not separated|too few seeds")
#: a comparison as the prose quotes it: a signed difference and its interval (``+7.5 [+3.9, +11.2]``), or a row's
#: MCB interval (``MCB [-34.5, +13.4]``); an unsigned one (``92.6 [81.7, 100.0]``) is a row's own value
COMPARISON = re.compile(r"(?<![\d.])([+-]\d+\.\d)(?: points)? (\[[+-]?\d+\.\d, [+-]?\d+\.\d\])")
MCB_QUOTE = re.compile(r"MCB (\[[+-]\d+\.\d, [+-]\d+\.\d\])")
VALUE = re.compile(r"(?<![\d.+-])(\d+\.\d)%? (\[\d+\.\d, \d+\.\d\])")
#: equivalence said with no equivalence test behind it: banned from the answers and the studies' prose
BANNED = ("tied", "as CIL does", "CIL's level", "CIL's equals", "barely feel", "cost it none", "the same as "
          "classification", "drives as", "at the level of")
#: per-seed values quoted for a named row: ``seeds 0-2: 87.1, 79.3 and 74.5%`` or ``seed 0: 90.5%`` (overall)
PER_SEED = re.compile(r"\bseeds? (\d+(?:(?:, | and |-)\d+)*): (\d+\.\d(?:(?:, | and )\d+\.\d)*)%")
#: how the prose names a row (lower case), nearest before a per-seed quote
ROW_NAMES = {"cil": "cil", "regression": "cil", "gtu": "gtu", "co-learning": "gtu", "cce+mse": "hybrid",
             "w = 10": "hybrid", "w = 5": "hybrid_w5", "w = 15": "hybrid_w15", "co-existence": "coexistence",
             "w = 0.6": "coexistence", "w = 0.4": "coexistence_w04", "w = 0.8": "coexistence_w08",
             "classification": "classification", "sine encoding": "sine", "sine wave encoding": "sine",
             "moe": "moe", "mixture of experts": "moe", "soft sharing": "soft_sharing", "sluice": "sluice",
             "cross-stitch": "cross_stitch", "fine tuning": "re_none", "r = 0": "re_none", "every pair": "re_all",
             "turn with turn": "re_pairs"}
#: the carla folder's carla − harsh table (``paired_switch``): its entries are one family for their words
SWITCH_ROWS = {"CIL": "cil", "GTU": "gtu", "CCE+MSE": "hybrid", "Classification": "classification",
               "Co-existence": "coexistence", "Sine encoding": "sine", "MoE": "moe", "Soft sharing": "soft_sharing",
               "Sluice": "sluice"}
SWITCH_FAMILY = 3 * len(SWITCH_ROWS)


def _text(path: Path) -> str:
    return " ".join(path.read_text().replace("−", "-").split())


@functools.cache
def report_words(folder: str) -> dict[str, frozenset[str]]:
    """Each comparison a published report prints (as the report prints it) -> the word(s) it reads with: every
    claim's part, every row against CIL, every pair of ranked rows and every row's MCB interval."""
    from cicfw.reproduction.report import _bounds, _est
    from cicfw.reproduction.seed_stats import word

    data = json.loads((DOCS / "results" / folder / "results.json").read_text())
    out: dict[str, set[str]] = {}

    def add(printed: str, w: Any) -> None:
        out.setdefault(printed.replace("−", "-"), set()).add((w or {}).get("word") or "too few seeds")

    for c in data["claims"]:
        for p in c["parts"]:
            if "measured" in p and "word" not in p:  # cicfw 0.1's report (laptop): the rule on its printed interval
                m = p["measured"]
                add(_est(m, "+"), {"word": word(m["lo"], m["hi"], data.get("equivalence_margin", 5.0))})
            elif "measured" in p:
                add(_est(p["measured"], "+"), p.get("word"))
    for r in data.get("forest") or []:
        add(_est(r["measured"], "+"), r.get("word"))
    best = data.get("best") or {}
    for p in best.get("pairs") or []:
        add(_est(p["measured"], "+"), p.get("word"))
    for r in best.get("rows") or []:
        add("MCB " + _bounds(r["lo"], r["hi"]), r)
    return {k: frozenset(v) for k, v in out.items()}


#: the carla − harsh table's rows, compared as ``paired_switch`` compares them (one family for their words)
CARLA_SWITCH = ("converged6_carla", "converged6_xeon", tuple(SWITCH_ROWS.values()), SWITCH_FAMILY)


@functools.cache
def switch_words(spec: tuple[str, str, tuple[str, ...], int] = CARLA_SWITCH) -> dict[str, frozenset[str]]:
    """``paired_switch.compare`` of one folder's rows against another's (the same seeds, one thing changed:
    the weather family, the CPU kind, the epochs) -> each entry's word, read on the Bonferroni interval over
    ``spec``'s family of comparisons (1: the 95% interval)."""
    from cicfw.reproduction.paired_switch import compare, load_row

    a_folder, b_folder, rows, family = spec
    out: dict[str, set[str]] = {}
    for row in rows:  # a row, or "row_a:row_b" where the switch is a row of its own (cil_bf16:cil)
        row_a, _, row_b = row.partition(":")
        a, b = (load_row(DOCS / "results" / f / "cells" / r) for f, r in ((a_folder, row_a), (b_folder, row_b or row_a)))
        for e in compare(a, b, 5.0, family):
            if e.lo is not None:
                out.setdefault(f"{e.mean:+.1f} [{e.lo:+.1f}, {e.hi:+.1f}]", set()).add(e.word or "too few seeds")
    return {k: frozenset(v) for k, v in out.items()}


@functools.cache
def offline_words() -> dict[str, frozenset[str]]:
    """The offline study's gains of picking by validation error -> their words (``gain_word``)."""
    from cicfw.reproduction.offline_vs_closed_loop import gain_word

    res = json.loads((DOCS / "results" / "offline_vs_closed_loop" / "results.json").read_text())
    out: dict[str, set[str]] = {}
    for r in [res, *res.get("families", {}).values()]:
        for s in r["scopes"].values():
            g = s["selection_gain"]
            if g.get("interval"):
                out.setdefault(f"{g['mean']:+.1f} [{g['interval'][0]:+.1f}, {g['interval'][1]:+.1f}]", set()).add(
                    gain_word(g))
    return {k: frozenset(v) for k, v in out.items()}


#: each checked text -> the published reports (folders) its comparisons come from, the paired-switch tables it
#: quotes (``switch_words``' specs) and whether it quotes the offline study; a study's README checks against its
#: own folder's report and those it compares with
PROSE_SOURCES: dict[str, tuple[tuple[str, ...], tuple[tuple[str, str, tuple[str, ...], int], ...], bool]] = {
    "prose/head.md": (("converged6", "converged", "converged6_xeon", "converged6_carla"), (CARLA_SWITCH,), True),
    "prose/converged4.md": (("converged",), (), False),
    "prose/tail.md": (("converged6", "converged"), (), False),
    "README.md": (("converged6", "converged", "converged6_xeon", "converged6_carla"), (CARLA_SWITCH,), True),
    "converged6_carla/README.md": (("converged6_carla", "converged6", "converged6_xeon"), (CARLA_SWITCH,), False),
    "converged6/README.md": (("converged6", "converged6_xeon", "converged", "converged6_rerun_xeon"),
                             (("converged6", "converged", ("cil",), 1),
                              ("converged6_xeon", "converged6", ("cil", "gtu"), 1)), False),
    "converged6_xeon/README.md": (("converged6_xeon", "converged6"),
                                  (("converged6_xeon", "converged6", ("cil", "gtu"), 1),), False),
    "converged/README.md": (("converged", "converged_dropout_v01", "converged_constant_lr"), (), False),
    "converged6_bf16_xeon/README.md": ((), (("converged6_bf16_xeon", "converged6_xeon", ("cil_bf16:cil",), 1),), False),
    "bf16_license_xeon/README.md": ((), (("bf16_license_xeon", "bf16_license_xeon", ("cil_bf16:cil",), 1),
                                         ("converged6_bf16_xeon", "converged6_xeon", ("cil_bf16:cil",), 1)), False),
    "laptop/README.md": (("laptop",), (), False),
    "results/README.md": (("converged6", "converged6_carla", "converged6_xeon", "converged"), (), True),
    "offline_vs_closed_loop/README.md": ((), (), True),
}
#: the studies whose README quotes what a paired-switch tool printed (the same seeds with and without a switch),
#: not a report's comparisons: their intervals are checked by their own tests, their words for banned ones only
PAIRED_STUDIES = ("converged6_bf16_xeon", "bf16_license_xeon", "converged6_rerun_xeon")


def _prose(docs: Path, name: str) -> str:
    if name == "README.md":  # the README's results section
        text = _text(docs.parent / "README.md")
        return text[text.index("## Results"):text.index("## Your own CIL HDF5 data")]
    if name == "results/README.md":
        return _text(docs / "results" / "README.md")
    return _text(docs / "results" / name)


def _clause(text: str, start: int, end: int) -> tuple[int, int]:
    """The clause around ``text[start:end]``: from the last ';' or sentence end before it to the next one."""
    bounds = [m.start() for m in re.finditer(r";|[.?!](?=\s|$)", text)]
    lo = max([b + 1 for b in bounds if b < start], default=0)
    hi = min([b for b in bounds if b >= end], default=len(text))
    return lo, hi


def _nearest_word(text: str, start: int, end: int) -> str | None:
    lo, hi = _clause(text, start, end)
    words = [(max(0, m.start() - end, start - m.end()), m.group()) for m in RULE_WORD.finditer(text, lo, hi)]
    return min(words)[1] if words else None


def prose_problems(docs: Path = DOCS) -> list[str]:
    """Every comparison the answers and the studies' prose quote must be one a generated report (or the
    carla − harsh table, or the offline study) prints, and the rule's word nearest to it in its clause must be
    the word the report gives it; a row's own value must be in its reports too; per-seed values quoted for a
    named row must be the cells'; no banned word of equivalence."""
    problems = []
    for name, (folders, switches, offline) in PROSE_SOURCES.items():
        text = _prose(docs, name)
        words: dict[str, set[str]] = {}
        for d in [*(report_words(f) for f in folders), *(switch_words(spec) for spec in switches),
                  offline_words() if offline else {}]:
            for k, v in d.items():
                words.setdefault(k, set()).update(v)
        reports = "".join(_text(DOCS / "results" / f / "RESULTS.md") for f in folders)
        if name == "results/README.md":  # the index quotes its studies' pages
            reports += "".join(_text(f) for f in sorted((DOCS / "results").glob("*/*.md")) if f.parent.name != "prose")
        if name == "converged6_carla/README.md":
            reports += " ".join(line for line in (DOCS / "results" / name).read_text().replace("−", "-").splitlines()
                                if line.startswith("|"))
        for m in [*COMPARISON.finditer(text), *MCB_QUOTE.finditer(text)]:
            printed = m.group() if m.re is MCB_QUOTE else f"{m.group(1)} {m.group(2)}"
            if printed not in words:
                if name == "results/README.md" and printed in reports:
                    continue  # a study's own figure (a paired-switch tool's), quoted from its page
                problems.append(f"{name}: {printed} is in no generated report")
                continue
            said = _nearest_word(text, m.start(), m.end())
            if said not in words[printed]:
                problems.append(f"{name}: {printed} reads {said!r}, the report says {' or '.join(sorted(words[printed]))}")
        for m in VALUE.finditer(text):
            if m.group() not in reports and f"{m.group(1)} {m.group(2)}" not in reports:
                problems.append(f"{name}: {m.group(1)} {m.group(2)} is in no generated report")
        problems += _per_seed_problems(name, text, folders)
    for path in [docs / "RESULTS.md", docs.parent / "README.md", *sorted((docs / "results").glob("*/README.md")),
                 *sorted((docs / "results" / "prose").glob("*.md"))]:
        text = _text(path)
        if path.name == "README.md" and path.parent == docs.parent:
            text = text[text.index("## Results"):text.index("## Your own CIL HDF5 data")]
        problems += [f"{path.relative_to(docs.parent)}: says {b!r} with no equivalence test"
                     for b in BANNED if re.search(rf"\b{re.escape(b)}\b", text, re.I)]
    return problems


def _per_seed_problems(name: str, text: str, folders: Sequence[str]) -> list[str]:
    """``seeds 0-2: 87.1, 79.3 and 74.5%`` after a row's name: those seeds' overall success in one of the
    text's folders, to the digit."""
    out = []
    per_seed = {}
    for f in folders:
        for r in json.loads((DOCS / "results" / f / "results.json").read_text())["rows"]:
            per_seed.setdefault(r["row"], []).append({int(s): f"{v['overall']:.1f}" for s, v in r["per_seed"].items()})
    names = re.compile("|".join(sorted(map(re.escape, ROW_NAMES), key=len, reverse=True)), re.I)
    for m in PER_SEED.finditer(text):
        seeds = []
        for part in re.split(r", | and ", m.group(1)):
            lo, _, hi = part.partition("-")
            seeds += list(range(int(lo), int(hi or lo) + 1))
        values = re.split(r", | and ", m.group(2))
        sentence = text[max([b.end() for b in re.finditer(r"[.?!]\s", text[:m.start()])], default=0):m.start()]
        named = [ROW_NAMES[n.group().lower()] for n in names.finditer(sentence)]
        if not named:
            out.append(f"{name}: per-seed values {m.group()!r} name no row")
            continue
        row = named[-1]
        ok = len(seeds) == len(values) and any(all(t.get(s) == v for s, v in zip(seeds, values))
                                                for t in per_seed.get(row, []))
        if not ok:
            got = [[t.get(s) for s in seeds] for t in per_seed.get(row, [])]
            out.append(f"{name}: {row} {m.group()!r}, the cells give {got}")
    return out


def test_every_comparison_the_prose_quotes_is_a_reports_with_its_word():
    """docs/RESULTS.md's hand-written prose, the README's results, the studies' index and the studies' READMEs
    quote comparisons (``+7.5 [+3.9, +11.2]``, ``MCB [-34.5, +13.4]``): each must be one a generated report
    prints, and the word nearest to it in its clause (ahead / behind / equivalent within ±5 / not separated /
    too few seeds) must be the one the report reads it with, on the correction it names; rows' own values
    (``92.6 [81.7, 100.0]``) must be in the reports, per-seed values quoted for a named row (``seeds 0-2: 87.1,
    79.3 and 74.5%``) the cells', and no sentence may call rows equal without an equivalence test. An interval
    broken over two lines is still one quote."""
    problems = prose_problems()
    counts = {name: len(COMPARISON.findall(_prose(DOCS, name))) for name in PROSE_SOURCES}
    assert counts["prose/head.md"] >= 10 and counts["README.md"] >= 4 and counts["converged6_carla/README.md"] >= 10, \
        f"the prose quotes the reports' comparisons: {counts}"
    seeds = sum(len(PER_SEED.findall(_prose(DOCS, n))) for n in PROSE_SOURCES)
    assert seeds >= 5, f"per-seed quotes: {seeds}"
    assert problems == [], "\n".join(problems)


@pytest.mark.parametrize("old, new", [("not separated", "ahead"), ("seed 0: ", "seed 1: ")])
def test_a_word_or_a_seed_changed_by_hand_is_reported(tmp_path: Path, old: str, new: str):
    """One rule word, or one per-seed quote, changed in a copy of the head's prose: the check names it."""
    docs = tmp_path / "docs"
    shutil.copytree(DOCS / "results" / "prose", docs / "results" / "prose")
    for rel in ["RESULTS.md", "results/README.md", *(f"results/{n}" for n in PROSE_SOURCES if n.endswith("/README.md")
                                                      and n != "results/README.md")]:
        (docs / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(DOCS / rel, docs / rel)
    shutil.copy(DOCS.parent / "README.md", tmp_path / "README.md")
    for p in (DOCS / "results").glob("*/README.md"):
        (docs / "results" / p.parent.name).mkdir(parents=True, exist_ok=True)
        shutil.copy(p, docs / "results" / p.parent.name / "README.md")
    assert prose_problems(docs) == []
    edit(docs / "results" / "prose" / "head.md", old, new)
    assert prose_problems(docs)


def test_the_carla_folder_quotes_paired_switch_as_it_computes():
    """converged6_carla/README.md's carla − harsh table is pasted from ``paired_switch``: each row's three
    intervals and per-seed values must be what it computes from the two folders' committed cells."""
    from cicfw.reproduction.paired_switch import compare, load_row

    readme = (DOCS / "results" / "converged6_carla" / "README.md").read_text().replace("−", "-")
    labels = {"CIL": "cil", "GTU": "gtu", "CCE+MSE": "hybrid", "Classification": "classification",
              "Co-existence": "coexistence", "Sine encoding": "sine",
              "MoE": "moe", "Soft sharing": "soft_sharing", "Sluice": "sluice"}
    rows = dict(re.findall(rf"^\| ({'|'.join(map(re.escape, labels))}) \| (.+) \|$", readme, re.M))
    assert set(rows) == set(labels), rows
    for label, row in labels.items():
        a, b = (load_row(DOCS / "results" / f / "cells" / row) for f in ("converged6_carla", "converged6_xeon"))
        got = {e.on: e for e in compare(a, b, 5.0, SWITCH_FAMILY)}
        want = " | ".join([table_cell(got["training_town/new_weathers"], seeds=True),
                           table_cell(got["new_town/new_weathers"], seeds=True), table_cell(got["overall"])])
        assert rows[label] == want, (label, rows[label], want)


def test_the_carla_folder_counts_its_matching_training_weather_episodes_right():
    """The carla cells and their harsh-weather twins (the same weights) drove the same training-weather
    episodes: the README's count of those that ended alike is recomputed from both folders' cells."""
    carla, harsh = (DOCS / "results" / f for f in ("converged6_carla", "converged6_xeon"))
    same = total = n_cells = 0
    for p in sorted(carla.glob("cells/*/seed*/cell.json")):
        twin = harsh / p.relative_to(carla)
        if not twin.is_file():
            continue
        a, b = (json.loads(f.read_text())["episodes"] for f in (p, twin))
        keys = [k for k in a if a[k]["column"].endswith("/training_weathers")]
        n_cells, total = n_cells + 1, total + len(keys)
        same += sum(a[k]["success"] == b[k]["success"] for k in keys)
    assert n_cells >= 20 and same < total  # one episode is known to differ
    said = {p.name: " ".join(p.read_text().split())
            for p in (carla / "README.md", DOCS / "results" / "prose" / "head.md", DOCS / "evaluation.md")}
    assert f"agree in {same:,} of their {total:,} episodes ({n_cells} cells)" in said["README.md"]
    assert f"agree in {same:,} of {total:,} episodes" in said["head.md"]
    assert f"agree in {same:,} of {total:,} training-weather episodes" in said["evaluation.md"]


def table_cell(e, seeds: bool = False) -> str:
    """One cell of the carla − harsh table: ``+26.0 [+10.7, +41.4] not separated`` (its word over the table's
    entries), then (harsh per seed → carla per seed)."""
    text = f"{e.mean:+.1f} [{e.lo:+.1f}, {e.hi:+.1f}] {e.word}"
    return text + (f" ({', '.join(f'{x:.1f}' for x in e.b)} → {', '.join(f'{x:.1f}' for x in e.a)})" if seeds else "")


if __name__ == "__main__":  # after editing the prose: python tests/test_published_results.py recomposes docs/RESULTS.md
    (DOCS / "RESULTS.md").write_text(composed_results_md(DOCS))
    print(f"wrote {DOCS / 'RESULTS.md'} from {', '.join(p for _, p in COMPOSITION)}")
