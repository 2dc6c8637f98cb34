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
from typing import Any

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
    too-few-seeds mark, and its results.json had neither ``bootstrap`` nor ``enough_seeds`` nor the seeds'
    ``spread`` (whose table its RESULTS.md lacks too: only the committed Markdown's tables are compared)."""
    rows = [{**r, "columns": r["bootstrap"], "enough_seeds": True} for r in data["rows"]]
    as_json = [{k: v for k, v in r.items() if k not in ("bootstrap", "enough_seeds", "spread")} for r in rows]
    return {**data, "rows": as_json}, {**data, "rows": rows}


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
    claims (every part's estimate, p-values and verdicts), the answer (the ranking, the leader's lead, the
    forest plot's differences), fine tuning's R, the failed cells, and the Markdown's tables. ``legacy``: the
    folder was made by cicfw 0.1 (``legacy_view``); its claims and answer are not compared."""
    committed = json.loads((folder / "results.json").read_text())
    data, md = recompute(folder)
    keys = ["rows", "claims", "ranking", "leader", "forest", "relation", "failed"]
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
    edit(folder_copy / "results.json", '"mean": 58.98', '"mean": 58.99')
    edit(folder_copy / "RESULTS.md", "| 1280.6 |", "| 1280.9 |")
    got = folder_mismatches(folder_copy)
    assert any("columns.overall.mean: recomputed 58.98, committed 58.99" in m for m in got), got
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


def test_every_interval_the_prose_quotes_is_in_the_generated_report():
    """docs/RESULTS.md's hand-written prose, the README's results and the studies' index quote intervals
    (``+7.5 [+3.9, +11.2]``); each must be one a generated report prints (the head and the tail quote both
    budgets, the head and the README also the one-CPU-kind folder and the carla weathers', converged4.md only
    the 4-epoch one) or, for the index, one its study's pages give, so the prose cannot drift from the tables.
    The carla folder's answer is checked too, against the reports and its forest plot's row − CIL labels.
    An interval broken over two lines is still one quote."""
    def text(*rels: str) -> str:
        return "".join((DOCS / "results" / r).read_text() for r in rels).replace("−", "-")

    both = text("converged6/RESULTS.md", "converged/RESULTS.md")
    # the head also quotes the one-CPU-kind folder (converged6's Xeon cells), the carla weathers' folder, its
    # comparison with the harsh weathers (its README's table, made by paired_switch and checked below) and its
    # forest plot's differences to CIL (results.json, as the picture labels them)
    carla_readme = text("converged6_carla/README.md").splitlines()
    forest = json.loads((DOCS / "results" / "converged6_carla" / "results.json").read_text())["forest"]
    carla = text("converged6_xeon/RESULTS.md", "converged6_carla/RESULTS.md") + "\n".join(
        [line for line in carla_readme if line.startswith("|")]
        + [f"{m['mean']:+.1f} [{m['lo']:+.1f}, {m['hi']:+.1f}]" for m in (f["measured"] for f in forest)
           if m["lo"] is not None])
    sources = {"head.md": both + carla, "converged4.md": text("converged/RESULTS.md"),
               "tail.md": both}
    assert set(sources) == {p[1] for p in COMPOSITION if p[0] == "prose"}
    prose = {name: text(f"prose/{name}") for name in sources}
    prose["converged6_carla/README.md"] = "\n".join(line for line in carla_readme if not line.startswith("|"))
    sources["converged6_carla/README.md"] = carla + both
    # the README's results section quotes the head's reports; the index of studies, each study's own pages
    prose |= {"README.md": (DOCS.parent / "README.md").read_text().replace("−", "-"), "results/README.md":
              text("README.md")}
    studies = "".join(f.read_text() for f in sorted((DOCS / "results").glob("*/*.md"))
                      if f.parent.name != "prose").replace("−", "-")
    sources |= {"README.md": both + carla, "results/README.md": studies}
    missing, counts = [], {}
    for name, report in sources.items():
        quoted = re.findall(r"([+-]?\d+\.\d)(?: points)? (\[[+-]?\d+\.\d, [+-]?\d+\.\d\])",
                            " ".join(prose[name].split()))
        counts[name] = len(quoted)
        missing += [f"{name}: {m} {iv}" for m, iv in quoted if f"{m} {iv}" not in report]
    assert counts["head.md"] >= 5 and counts["converged4.md"] >= 10 and counts["README.md"] >= 10 \
        and counts["converged6_carla/README.md"] >= 10, \
        f"the prose quotes the tables' intervals: {counts}"
    assert missing == [], missing


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
        got = {e.on: e for e in compare(a, b, 5.0)}
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
    """One cell of the carla − harsh table: ``+26.0 [+10.7, +41.4]``, then (harsh per seed → carla per seed)."""
    text = f"{e.mean:+.1f} [{e.lo:+.1f}, {e.hi:+.1f}]"
    return text + (f" ({', '.join(f'{x:.1f}' for x in e.b)} → {', '.join(f'{x:.1f}' for x in e.a)})" if seeds else "")


if __name__ == "__main__":  # after editing the prose: python tests/test_published_results.py recomposes docs/RESULTS.md
    (DOCS / "RESULTS.md").write_text(composed_results_md(DOCS))
    print(f"wrote {DOCS / 'RESULTS.md'} from {', '.join(p for _, p in COMPOSITION)}")
