"""Rows are compared within one kind of CPU (plus GPU, where a cell had one): the same seed trains another
model on another kind, so a comparison whose cells span kinds uses the kind where both rows have 3 seeds, or
says *mixed CPUs* (*mixed machines* where a GPU is among them); the
report's header lists every machine with its cells, and Table 4 each row's kinds where they differ."""
from __future__ import annotations

import math

import pytest

from cicfw.reproduction.analysis import analyse, pair_cells
from cicfw.reproduction.cells import COLUMNS, CellResult, cpu_counts, cpu_kind, machine_kind
from cicfw.reproduction.claims import SUPPORTED, Claim, Part, judge
from cicfw.reproduction.report import markdown, report_data

AMD = "2 cores (AMD EPYC), no GPU, Python 3.11.7, torch 2.13.0+cpu"
XEON = "2 cores (Intel(R) Xeon(R) Processor), no GPU, Python 3.11.7, torch 2.13.0+cpu"
T_975_2 = 4.303  # t_{0.975, 2} from a printed table


def at(row: str, seed: int, pct: int, machine: str, n: int = 100) -> CellResult:
    """A cell of ``machine`` with ``pct`` successes of ``n`` episodes in every column (overall ``pct``%)."""
    eps = {f"{c}/{k:03d}": {"success": k < pct, "column": c, "command": "left"} for c in COLUMNS for k in range(n)}
    return CellResult(row=row, seed=seed, episodes=eps, meta={"decoder": None, "wall_s": {}, "machine": machine})


def test_the_cpu_kind_is_the_machine_s_processor_without_marks():
    assert cpu_kind(AMD) == "AMD EPYC" and cpu_kind(XEON) == "Intel Xeon"
    assert cpu_kind("8 cores (Intel(R) Xeon(R) Platinum 8375C CPU @ 2.90GHz), no GPU") == "Intel Xeon Platinum 8375C"
    assert cpu_kind("16 cores (AMD EPYC 7763 64-Core Processor), NVIDIA H100") == "AMD EPYC 7763 64-Core"
    assert cpu_kind(None) == "unknown CPU" and cpu_kind("arm64") == "arm64"
    cells = [at("a", 0, 50, XEON), at("a", 1, 50, AMD), at("a", 2, 50, XEON)]
    assert cpu_counts(cells) == {"Intel Xeon": 2, "AMD EPYC": 1}


def test_pairing_keeps_one_kind_where_both_rows_have_three_seeds_there():
    a = [at("a", s, 50, AMD) for s in range(3)] + [at("a", s, 50, XEON) for s in range(3, 6)]
    b = [at("b", s, 50, AMD) for s in range(3)] + [at("b", s, 50, XEON) for s in (3, 4)]
    p = pair_cells(a, b)
    assert p.cpu == "AMD EPYC" and p.left_out == 5 and [c.seed for c in p.a] == [0, 1, 2] and not p.mixed
    assert p.note() == "within AMD EPYC (5 cell(s) of other CPUs left out)"
    # both kinds qualify: the one where more seeds pair wins (Xeon: 3 common seeds; AMD: 3 vs 3 on other seeds)
    b2 = [at("b", s, 50, AMD) for s in (6, 7, 8)] + [at("b", s, 50, XEON) for s in range(3, 6)]
    assert pair_cells(a, b2).cpu == "Intel Xeon"
    # one kind throughout: everything, no note
    same = pair_cells(a[:3], b[:3])
    assert same.cpu == "AMD EPYC" and same.left_out == 0 and same.note() == ""


def test_rows_on_different_kinds_are_pooled_and_marked_mixed():
    a = [at("a", s, 50, XEON) for s in range(3)]
    b = [at("b", s, 50, AMD) for s in range(5)] + [at("b", 5, 50, XEON)]
    p = pair_cells(a, b)
    assert p.mixed and len(p.a) == 3 and len(p.b) == 3 and p.left_out == 0  # paired on seeds 0-2
    assert p.note() == "on the seeds both ran (0 of A's and 3 of B's cells left out), mixed CPUs (A: Intel Xeon 3; B: AMD EPYC 3)"
    b3 = [at("b", s, 50, AMD) for s in range(5, 10)] + [at("b", 10, 50, XEON)]  # no seed shared: Welch on all
    p = pair_cells(a, b3)
    assert p.mixed and len(p.b) == 6 and p.note() == "mixed CPUs (A: Intel Xeon 3; B: AMD EPYC 5, Intel Xeon 1)"


def test_a_claim_is_judged_within_the_kind_both_rows_share():
    """CIL on the AMD at 50% (seeds 0-2) and on the Xeon at 70% (seeds 3-5); GTU on the AMD at 58, 60, 62
    and on the Xeon at 40% (seeds 3, 4). Within the AMD: +8, +10, +12 paired, mean 10, se 2 / sqrt 3,
    [10 - 4.97, 10 + 4.97]: supported; the Xeon cells, which would turn it around, are left out and said so."""
    cells = [at("cil", s, 50, AMD) for s in range(3)] + [at("cil", s, 70, XEON) for s in range(3, 6)]
    cells += [at("gtu", s, p, AMD) for s, p in zip(range(3), (58, 60, 62))] + [at("gtu", s, 40, XEON) for s in (3, 4)]
    rec = judge(analyse(cells, n_boot=200), [Claim("g", "GTU beats CIL", (Part("gtu", "cil"),))], {}, {},
                margin=5.0)[0]["parts"][0]
    half = T_975_2 * 2 / math.sqrt(3)
    assert rec["measured"] == pytest.approx({"mean": 10.0, "lo": 10 - half, "hi": 10 + half}, abs=5e-3)
    assert rec["method"] == "paired t, 3 seeds, within AMD EPYC (5 cell(s) of other CPUs left out)"
    assert rec["cpu"] == "AMD EPYC" and rec["cpus"] == {"AMD EPYC": [3, 3], "Intel Xeon": [2, 3]}
    assert rec["verdict"] == SUPPORTED and rec["seeds"] == [3, 3]
    assert rec["bootstrap"]["mean"] == pytest.approx(10.0)  # the secondary figure on the same cells


def test_the_report_lists_every_machine_and_flags_mixed_comparisons():
    cells = [at("cil", s, 50 + s, AMD) for s in range(3)] + [at("gtu", s, 60 - s, XEON) for s in range(3)]
    catalogue = {"cil": {"label": "CIL"}, "gtu": {"label": "GTU"}}
    data = report_data(cells, [], catalogue, {"budget": "smoke", "machine": XEON}, n_boot=50,
                       claims=[Claim("g", "GTU beats CIL", (Part("gtu", "cil"),))], margin=5.0)
    md = markdown(data)
    assert "- **Machines:** 3 cells on " + AMD + "; 3 cells on " + XEON + "." in md
    assert "2 kinds of CPU (AMD EPYC: 3 cells, Intel Xeon: 3 cells)" in md
    assert "| Row | Decoder | Seeds | CPU (cells) |" in md and "| CIL | – | 3 | AMD EPYC 3 |" in md
    claim_row = next(line for line in md.splitlines() if line.startswith("| GTU beats CIL"))
    assert "mixed CPUs (A: Intel Xeon 3; B: AMD EPYC 3)" in claim_row
    assert data["claims"][0]["parts"][0]["cpu"] == "mixed" and data["rows"][0]["cpus"] == {"AMD EPYC": 3}
    # one kind: no CPU column, the one machine named with its cells, no per-row kinds
    one = report_data([at("cil", s, 50, AMD) for s in range(3)], [], catalogue, {"budget": "smoke"}, n_boot=50,
                      claims=[], margin=5.0)
    md1 = markdown(one)
    assert "CPU (cells)" not in md1 and f"- **Machine:** {AMD} (all 3 cells)." in md1
    assert one["rows"][0]["cpus"] == {}


XEON_H100 = "2 cores (Intel(R) Xeon(R) Processor), NVIDIA H100 80GB HBM3, Python 3.11.7, torch 2.13.0+cu126"


def test_a_gpu_is_part_of_the_kind_and_no_gpu_reads_as_before():
    assert machine_kind(XEON_H100) == "Intel Xeon + NVIDIA H100" and cpu_kind(XEON_H100) == "Intel Xeon"
    assert machine_kind(XEON) == "Intel Xeon" == machine_kind("8 cores (Intel(R) Xeon(R) Processor), no GPU, "
                                                              "Python 3.12.1, torch 2.14.0+cpu")
    assert machine_kind("16 cores (AMD EPYC 7763 64-Core Processor), NVIDIA A100-SXM4-40GB, Python 3.11.7, "
                        "torch 2.13.0+cu126") == "AMD EPYC 7763 64-Core + NVIDIA A100-SXM4"
    assert machine_kind(None) == "unknown CPU" and machine_kind("arm64") == "arm64"
    cells = [at("a", 0, 50, XEON), at("a", 1, 50, XEON_H100), at("a", 2, 50, XEON)]
    assert cpu_counts(cells) == {"Intel Xeon": 2, "Intel Xeon + NVIDIA H100": 1}


def test_gpu_cells_and_cpu_cells_of_one_processor_are_compared_as_mixed_machines():
    a = [at("gtu", s, 60, XEON_H100) for s in range(3)] + [at("gtu", s, 60, XEON) for s in (3, 4)]
    b = [at("cil", s, 50, XEON) for s in range(5)]
    p = pair_cells(a, b)
    assert p.mixed and p.note() == "mixed machines (A: Intel Xeon 2, Intel Xeon + NVIDIA H100 3; B: Intel Xeon 5)"
    # with 3 seeds of each row on the CPU alone (GTU's seeds 3-5), the comparison stays there
    a3 = a + [at("gtu", 5, 60, XEON)]
    b3 = b + [at("cil", 5, 50, XEON)]
    assert pair_cells(a3, b3).note() == ("on the seeds both ran (0 of A's and 3 of B's cells left out), "
                                         "within Intel Xeon (3 cell(s) of other machine kinds left out)")
    catalogue = {"cil": {"label": "CIL"}, "gtu": {"label": "GTU"}}
    data = report_data([*a, *b], [], catalogue, {"budget": "smoke"}, n_boot=50,
                       claims=[Claim("g", "GTU beats CIL", (Part("gtu", "cil"),))], margin=5.0)
    md = markdown(data)
    assert data["claims"][0]["parts"][0]["cpu"] == "mixed"
    claim_row = next(line for line in md.splitlines() if line.startswith("| GTU beats CIL"))
    assert "paired t, 5 seeds" in claim_row
    assert "mixed machines (A: Intel Xeon 2, Intel Xeon + NVIDIA H100 3; B: Intel Xeon 5)" in claim_row
    assert "2 kinds of machine (Intel Xeon: 7 cells, Intel Xeon + NVIDIA H100: 3 cells)" in md
    assert "| Row | Decoder | Seeds | Machine (cells) |" in md
    assert "1 of the 1 pairs pool cells of different machine kinds (*mixed machines*)" in md
    assert "CPU kind" not in md and "mixed CPUs (" not in md
