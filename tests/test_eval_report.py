"""The report: the paper's table from episode rows, run folders, joining runs, pictures."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from cicfw.benchmark import evaluation_report as report
from cicfw.benchmark.evaluation_report import Run, find_runs, latex_table, markdown_table, summary, write_run


def rows(successes: dict[tuple[str, str], tuple[int, int]]) -> list[dict]:
    """Synthetic episode rows: (town_set, weather_set) -> (successes, episodes)."""
    out = []
    for (ts, ws), (ok, n) in successes.items():
        for k in range(n):
            town = "town_a" if ts == "training" else "town_b"
            weather = "ClearNoon" if ws == "training" else "MidRainyNoon"
            out.append({"episode": len(out), "key": f"{town}/{weather}/{k:03d}", "town": town, "weather": weather,
                        "town_set": ts, "weather_set": ws, "pair": k, "route": f"{town}/j/a>b/left",
                        "command": "left", "success": k < ok, "reason": "success" if k < ok else "off_route",
                        "time_s": 10.0, "timeout_s": 30.0, "distance_m": 50.0, "route_length_m": 60.0,
                        "goal_distance_m": 1.0, "progress": 1.0, "offroad_fraction": 0.0,
                        "opposite_lane_fraction": 0.0, "steps": 100})
    return out


CIL = Run("Regression (CIL)", rows({("training", "training"): (36, 38), ("training", "new"): (33, 38),
                                    ("new", "training"): (21, 40), ("new", "new"): (37, 80)}))
GTU = Run("Co-learning (GTU)", rows({("training", "training"): (38, 38), ("new", "new"): (60, 80)}))


def test_markdown_table_has_the_papers_layout():
    md = markdown_table([CIL, GTU]).splitlines()
    assert md[0] == "**Reach destination success rate (%)**"
    # rows are models; columns Training town / New town, each split Training weathers / New weathers
    assert md[2] == "| Model | Training town | | New town | |"
    assert md[4] == "| | *Training weathers* | *New weathers* | *Training weathers* | *New weathers* |"
    assert md[5] == "| Regression (CIL) | 94.74 | 86.84 | 52.50 | 46.25 |"  # the paper's own first row
    assert md[6] == "| Co-learning (GTU) | 100.00 | – | – | 75.00 |"  # cells a run did not cover
    assert any(line.startswith("Episodes per column differ") for line in md)
    one = markdown_table([CIL]).splitlines()
    assert one[7] == "Episodes per column: 38, 38, 40, 80."
    assert one[8] == "Suite: junctions."  # the run's metadata names no suite: the library default
    assert one[-1] == "| Regression (CIL) | 64.80 (127/196) |"  # 36+33+21+37 successes, all left turns


def test_latex_table_and_summary():
    tex = latex_table([CIL])
    assert r"\multicolumn{2}{c|}{Training town} & \multicolumn{2}{c|}{New town}" in tex
    assert r"Regression (CIL) & 94.74 & 86.84 & 52.50 & 46.25 \\ \hline" in tex
    s = summary(CIL)
    assert s["episodes"] == 196 and s["success"] == pytest.approx(100 * 127 / 196, abs=0.01)
    assert list(s["cells"]) == ["training_town/training_weathers", "training_town/new_weathers",
                                "new_town/training_weathers", "new_town/new_weathers"]
    assert s["cells"]["new_town/training_weathers"] == {"name": "New town / Training weathers", "success": 21,
                                                        "episodes": 40, "rate": 52.5}
    assert s["reasons"] == {"off_route": 69, "success": 127}


def test_a_row_label_with_latex_specials_prints_as_written():
    """Every character LaTeX treats as special is escaped in a row label, and an escape's own braces are not
    escaped again (the expected row is written out by hand)."""
    tex = latex_table([Run(r"a_b$c{d}^e~f\g&h%i#", CIL.rows)])
    assert (r"a\_b\$c\{d\}\textasciicircum{}e\textasciitilde{}f\textbackslash{}g\&h\%i\# & 94.74 & 86.84 & 52.50 "
            r"& 46.25 \\ \hline") in tex


def test_runs_are_written_read_back_and_joined(tmp_path: Path):
    for name, run in (("job0", CIL), ("job1", GTU), ("job2", Run("Regression (CIL)", CIL.rows[:40]))):
        write_run(tmp_path / "sweep" / name, Run(run.label, run.rows, {"checkpoint": f"/ck/{name}.ckpt"}))
    run_dir = tmp_path / "sweep" / "job0"
    assert {p.name for p in run_dir.iterdir()} == {"episodes.json", "episodes.csv", "summary.json", "table.md",
                                                   "table.tex"}
    csv_lines = (run_dir / "episodes.csv").read_text().splitlines()
    assert csv_lines[0].split(",")[:6] == ["model", "episode", "key", "town", "weather", "town_set"]
    assert len(csv_lines) == 1 + len(CIL.rows)
    assert json.loads((run_dir / "summary.json").read_text())["success"] == summary(CIL)["success"]
    runs = find_runs([tmp_path / "sweep"])
    # sweep order; equal labels told apart by their checkpoint
    assert [r.label for r in runs] == ["Regression (CIL) (job0)", "Co-learning (GTU)", "Regression (CIL) (job2)"]
    assert runs[0].rows[0]["model"] == "Regression (CIL)"
    # the command line joins them into one table with its bar chart
    out = tmp_path / "joined"
    assert report.main([str(tmp_path / "sweep"), "--out", str(out)]) == 0
    md = (out / "table.md").read_text()
    assert md.count("\n| Regression (CIL) (job") == 2 * 2 and "| Co-learning (GTU) | 100.00 |" in md
    assert (out / "success_bars.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "table.csv").read_text().splitlines()[2].startswith("Co-learning (GTU),100.00,,,75.00")


def test_report_command_errors_are_one_line(tmp_path: Path):
    from conftest import run_app_in_process

    proc = run_app_in_process("cicfw.benchmark.evaluation_report", str(tmp_path / "nope"))
    assert proc.returncode == 2
    assert proc.stderr.strip() == (f"cicfw: error: report: {str(tmp_path / 'nope')!r} is not a folder; give "
                                   f"evaluation run folders (holding episodes.json) or folders that contain them")
    (tmp_path / "empty").mkdir()
    assert report.main([str(tmp_path / "empty")]) == 2


def test_a_full_disk_while_reporting_leaves_a_folder_the_same_command_finishes(tmp_path: Path, monkeypatch,
                                                                                 capsys):
    """The disk fills as ``cicfw report`` writes its chart: one line, the tables and the record of the runs
    written together, so that the same command (with room again) finishes the folder instead of refusing its
    tables as files no report wrote."""
    from conftest import fill_the_disk_for_pictures

    write_run(tmp_path / "runs" / "a", Run(CIL.label, CIL.rows, {"checkpoint": "/ck/a.ckpt"}))
    out = tmp_path / "joined"
    with monkeypatch.context() as mp:
        fill_the_disk_for_pictures(mp)
        assert report.main([str(tmp_path / "runs"), "--out", str(out)]) == 2
    line = capsys.readouterr().err.strip()
    assert line.startswith("cicfw: error:") and "No space left on device" in line and "\n" not in line, line
    assert report.main([str(tmp_path / "runs"), "--out", str(out)]) == 0
    assert (out / "success_bars.png").is_file() and (out / "report.json").is_file()


def test_a_report_whose_chart_cannot_be_written_leaves_the_folder_as_it_was(tmp_path: Path, monkeypatch, capsys):
    """The chart fails to write (a full disk at the PNG): one line naming the chart, and the folder as it was,
    an earlier report whole (no new tables beside the old chart) and a fresh folder without tables."""
    from conftest import fill_the_disk_for_pictures

    write_run(tmp_path / "runs" / "a", Run(CIL.label, CIL.rows, {"checkpoint": "/ck/a.ckpt"}))
    out, fresh = tmp_path / "joined", tmp_path / "fresh"
    assert report.main([str(tmp_path / "runs"), "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert {"table.md", "table.tex", "table.csv", "report.json", "success_bars.png"} <= set(before)
    write_run(tmp_path / "runs" / "a", Run(CIL.label, GTU.rows, {"checkpoint": "/ck/a.ckpt"}))  # new rates
    capsys.readouterr()
    with monkeypatch.context() as mp:
        fill_the_disk_for_pictures(mp)
        assert report.main([str(tmp_path / "runs"), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and repr(str(out / "success_bars.png")) in err[0], err
        assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
        assert report.main([str(tmp_path / "runs"), "--out", str(fresh)]) == 2
        assert not [n for n in (*report.REPORT_FILES, report.REPORT_RECORD) if (fresh / n).exists()]
    assert not [p for p in (*out.iterdir(), *fresh.iterdir()) if p.name.startswith(".") and p.is_file()]
    assert report.main([str(tmp_path / "runs"), "--out", str(out)]) == 0  # with room again, the new report
    assert (out / "table.md").read_bytes() != before["table.md"]


def test_a_report_written_to_the_same_folder_meanwhile_is_never_replaced(tmp_path: Path, monkeypatch, capsys):
    """Another report fills ``--out`` after this one checked it (both found it empty): this one is one line
    naming the folder and writes nothing there, the other's tables and record stay byte for byte."""
    write_run(tmp_path / "runs" / "a", Run(CIL.label, CIL.rows, {"checkpoint": "/ck/a.ckpt"}))
    write_run(tmp_path / "other" / "b", Run(GTU.label, GTU.rows, {"checkpoint": "/ck/b.ckpt"}))
    assert report.main([str(tmp_path / "other"), "--out", str(tmp_path / "theirs"), "--no-plots"]) == 0
    theirs = {p.name: p.read_bytes() for p in (tmp_path / "theirs").iterdir()}
    out = tmp_path / "joined"
    original = report.latex_table

    def another_report_finishes(runs):
        out.mkdir(exist_ok=True)
        for name, data in theirs.items():
            (out / name).write_bytes(data)
        return original(runs)

    monkeypatch.setattr(report, "latex_table", another_report_finishes)
    capsys.readouterr()
    assert report.main([str(tmp_path / "runs"), "--out", str(out), "--no-plots"]) == 2
    line = capsys.readouterr().err.strip()
    assert line.startswith("cicfw: error:") and str(out) in line and "\n" not in line, line
    assert {p.name: p.read_bytes() for p in out.iterdir()} == theirs


def test_a_run_and_its_copy_are_refused_as_two_rows(tmp_path: Path):
    """A run folder copied elsewhere (its episodes.json byte for byte) would be one run reported twice; the same
    episodes written as two runs of other metadata (another checkpoint) are two runs."""
    import shutil

    from cicfw.core.errors import CicfwError

    write_run(tmp_path / "a", Run(CIL.label, CIL.rows, {"checkpoint": "/ck/a.ckpt"}))
    shutil.copytree(tmp_path / "a", tmp_path / "copy")
    with pytest.raises(CicfwError) as err:
        find_runs([tmp_path / "a", tmp_path / "copy"])
    assert err.value.key == "dirs" and str(tmp_path / "copy") in str(err.value)
    write_run(tmp_path / "b", Run(CIL.label, CIL.rows, {"checkpoint": "/ck/b.ckpt"}))
    assert len(find_runs([tmp_path / "a", tmp_path / "b"])) == 2


def test_a_copy_run_again_is_still_one_measurement(tmp_path: Path):
    """Running a copy's evaluate command again rewrites its report's timings (wall_s, episodes reused), so the
    bytes differ; the same fingerprint and episodes are one measurement. Another fingerprint (the exported model
    of the same checkpoint, driving the same episodes) is another run."""
    from cicfw.core.errors import CicfwError

    fp = {"policy": {"name": "checkpoint", "checkpoint_sha256": "ab"}, "suite": {"name": "single_turn"}}
    write_run(tmp_path / "a", Run(CIL.label, CIL.rows, {"fingerprint": fp, "wall_s": 3.6, "episodes_reused": 0}))
    write_run(tmp_path / "copy", Run("Copy", CIL.rows, {"fingerprint": fp, "wall_s": 0.0, "episodes_reused": 156}))
    with pytest.raises(CicfwError) as err:
        find_runs([tmp_path / "a", tmp_path / "copy"])
    assert err.value.key == "dirs" and str(tmp_path / "copy") in str(err.value)
    onnx = {**fp, "policy": {"name": "checkpoint", "checkpoint_sha256": "cd"}}
    write_run(tmp_path / "onnx", Run("ONNX", CIL.rows, {"fingerprint": onnx}))
    assert len(find_runs([tmp_path / "a", tmp_path / "onnx"])) == 2
