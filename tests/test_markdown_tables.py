"""Every Markdown table cicfw writes keeps its columns whatever a row label holds: a ``|`` is escaped and
a line break read as a space, so each row has as many cells as its header (RESULTS.md, table.md)."""
from __future__ import annotations

import pytest

from cicfw.benchmark.evaluation_report import Run, markdown_table, md_cell, md_row
from cicfw.reproduction import report as results
from cicfw.reproduction.cells import COLUMNS, CellResult

#: labels a table must survive: a pipe, a pipe after a backslash, a pipe at the end
LABELS = {"cil": "CIL | reg, ü", "gtu": "GTU \\| gated", "re_all": "RE |", "re_pairs": "pairs", "re_none": "none"}


def gfm_cells(line: str) -> list[str]:
    """A table row split as GitHub's Markdown splits it: on each ``|`` not taken by a backslash escape."""
    body = line.strip()
    assert body.startswith("|") and body.endswith("|"), line
    cells, cell, k = [], "", 1
    while k < len(body) - 1:
        ch = body[k]
        if ch == "\\" and k + 1 < len(body) - 1:
            cell += body[k:k + 2]
            k += 2
            continue
        if ch == "|":
            cells.append(cell)
            cell = ""
        else:
            cell += ch
        k += 1
    return [*cells, cell]


def tables(md: str) -> list[list[str]]:
    """The Markdown's tables: each a run of consecutive lines starting with ``|``."""
    out: list[list[str]] = []
    previous = False
    for line in md.splitlines():
        is_row = line.startswith("|")
        if is_row and not previous:
            out.append([])
        if is_row:
            out[-1].append(line)
        previous = is_row
    return out


def assert_rows_fit_headers(md: str) -> int:
    """Every table row has as many cells as its header; returns the number of tables."""
    found = tables(md)
    for table in found:
        width = len(gfm_cells(table[0]))
        for line in table[1:]:
            assert len(gfm_cells(line)) == width, (table[0], line)
    return len(found)


def test_md_cell_escapes_a_pipe_and_keeps_a_backslash_before_it():
    # by hand: a pipe gets one backslash; a backslash right before a pipe is doubled so it escapes nothing
    assert md_cell("a | b") == "a \\| b"
    assert md_cell("a\\|b") == "a\\\\\\|b"
    assert md_cell("x\r\ny\nz") == "x y z"
    assert md_cell("Regression (CIL)") == "Regression (CIL)" and md_cell(3) == "3"
    assert gfm_cells(md_row(["a | b", "a\\|b", "|"])) == [" a \\| b ", " a\\\\\\|b ", " \\| "]


def cell(row: str, seed: int, pct: int) -> CellResult:
    eps = {f"{c}/{k:03d}": {"success": k < pct, "column": c, "command": "left" if k % 2 else "right"}
           for c in COLUMNS for k in range(20)}
    meta = {"row": row, "seed": seed, "status": "ok", "episodes": eps, "decoder": None, "wall_s": {"train": 1.0},
            "val_steer_mae": 0.1 + 0.01 * seed + 0.001 * len(row)}
    return CellResult(row=row, seed=seed, episodes=eps, meta=meta)


def test_results_md_tables_keep_their_columns_with_a_pipe_in_a_label():
    cells = [cell(r, s, 8 + s + 2 * i) for i, r in enumerate(LABELS) for s in range(3)]
    catalogue = {r: {"label": label} for r, label in LABELS.items()}
    data = results.report_data(cells, [], catalogue, {"budget": "smoke", "suite": {"name": "single_turn"}}, n_boot=50)
    md = results.markdown(data)
    assert "| CIL \\| reg, ü |" in md and "| GTU \\\\\\| gated |" in md  # Table 4's rows
    assert "## Fine tuning's R" in md and "## The paper's claims" in md and "## Each pair" in md
    assert assert_rows_fit_headers(md) >= 9


@pytest.mark.parametrize("label", ["CIL | reg, ü", "two\nlines", "end \\|"])
def test_the_evaluation_table_keeps_its_columns_whatever_the_label(label):
    rows = [{"episode": k, "key": f"town_a/ClearNoon/{k:03d}", "town": "town_a", "weather": "ClearNoon",
             "town_set": "training", "weather_set": "training", "pair": k, "route": "town_a/j/a>b/left",
             "command": "left", "success": k < 3, "reason": "success"} for k in range(5)]
    md = markdown_table([Run(label, rows), Run("other", rows)])
    assert assert_rows_fit_headers(md) == 2  # the paper's table and success by manoeuvre
    assert len([ln for ln in md.splitlines() if ln.startswith("|")]) == 3 + 2 + 2 + 2  # no row split over two lines
