"""Tracebacks where one line belongs, in the small apps: ``report --out`` at a file or a
read-only folder, ``preview --out <file>``, ``carla-check --port 99999``, and a town whose ``margin``
(or extent) would make the renderer allocate ~150 GiB. Each is one line, ``cicfw: error: ...``, saying
what was wrong and what is accepted, and nothing is half-written."""
from __future__ import annotations

import json

import os
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from cicfw.benchmark import evaluation_report as report
from cicfw.benchmark.evaluation_report import Run, write_run
from cicfw.sim.town import MAX_TOWN_SIDE_M, TownError, build_town, load_town, town_path
from conftest import assert_refused, run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cicfw: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture
def read_only_folder(tmp_path: Path):
    """A folder nobody may write into: a read-only tmpfs as root (root ignores permission bits), else 0o500."""
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() == 0:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(ro)], capture_output=True,
                           text=True)
        if r.returncode:
            pytest.skip(f"cannot mount a read-only tmpfs here ({r.stderr.strip() or r.returncode})")
    else:
        ro.chmod(0o500)
    yield ro
    if os.geteuid() == 0:
        subprocess.run(["umount", "-l", str(ro)], capture_output=True)
    else:
        ro.chmod(0o700)


# ------------------------------------------------------------------------------------------------
# cicfw report --out


def _run_folder(tmp_path: Path) -> Path:
    rows = [{"episode": k, "key": f"town_a/ClearNoon/{k:03d}", "town": "town_a", "weather": "ClearNoon",
             "town_set": "training", "weather_set": "training", "pair": k, "route": "town_a/j/a>b/left",
             "command": "left", "success": k % 2 == 0, "reason": "success" if k % 2 == 0 else "off_route",
             "time_s": 10.0, "timeout_s": 30.0, "distance_m": 50.0, "route_length_m": 60.0, "goal_distance_m": 1.0,
             "progress": 1.0, "offroad_fraction": 0.0, "opposite_lane_fraction": 0.0, "steps": 100}
            for k in range(4)]
    run = tmp_path / "run"
    write_run(run, Run("CIL", rows))
    return run


@pytest.mark.parametrize("where", ["a file", "under a file"])
def test_report_out_at_a_file_is_one_line(tmp_path: Path, capsys, where: str):
    run = _run_folder(tmp_path)
    f = tmp_path / "afile"
    f.write_text("mine")
    out = f if where == "a file" else f / "sub"
    assert report.main([str(run), "--out", str(out), "--no-plots"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(out) in line and "--out" in line, line
    assert f.read_text() == "mine"


def test_report_out_at_a_read_only_folder_is_one_line(tmp_path: Path, capsys, read_only_folder: Path):
    run = _run_folder(tmp_path)
    for out in (read_only_folder, read_only_folder / "sub"):
        assert report.main([str(run), "--out", str(out), "--no-plots"]) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert str(out) in line, line


def test_report_into_a_read_only_run_folder_by_default_says_use_out(tmp_path: Path, capsys):
    """``cicfw report RUN`` writes into RUN: a colleague's read-only run folder gets a hint at --out."""
    run = _run_folder(tmp_path)
    if os.geteuid() == 0:  # a read-only bind mount of the run folder onto itself
        if subprocess.run(["mount", "--bind", str(run), str(run)], capture_output=True).returncode:
            pytest.skip("cannot bind-mount here")
        subprocess.run(["mount", "-o", "remount,bind,ro", str(run)], capture_output=True)
    else:
        run.chmod(0o500)
    try:
        if os.access(run, os.W_OK):
            pytest.skip("cannot make the run folder read-only here")
        assert report.main([str(run), "--no-plots"]) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert "--out" in line and str(run) in line, line
    finally:
        if os.geteuid() == 0:
            subprocess.run(["umount", "-l", str(run)], capture_output=True)
        else:
            run.chmod(0o700)


def test_report_cli_at_a_file_no_traceback(tmp_path: Path):
    run = _run_folder(tmp_path)
    f = tmp_path / "afile"
    f.write_text("x")
    r = run_app_in_process("cicfw.cli", "report", str(run), "--out", str(f))
    assert r.returncode == 2, r.stderr
    _one_error_line(r.stderr)


# ------------------------------------------------------------------------------------------------
# cicfw preview --out


def test_preview_out_at_a_file_is_one_line_before_rendering(tmp_path: Path, capsys, monkeypatch):
    from cicfw.sim import preview

    monkeypatch.setattr(preview, "contact_sheet", lambda *a, **k: pytest.fail("rendered before checking --out"))
    f = tmp_path / "afile"
    f.write_text("mine")
    for out in (f, f / "sub"):
        with pytest.raises(SystemExit) as exc:
            preview.main(["--out", str(out), "--towns", "town_b"])
        assert exc.value.code == 2
        line = _one_error_line(capsys.readouterr().err)
        assert str(out) in line and "--out" in line, line
    assert f.read_text() == "mine"


def test_preview_out_at_a_read_only_folder_is_one_line(capsys, monkeypatch, read_only_folder: Path):
    from cicfw.sim import preview

    monkeypatch.setattr(preview, "contact_sheet", lambda *a, **k: pytest.fail("rendered before checking --out"))
    with pytest.raises(SystemExit) as exc:
        preview.main(["--out", str(read_only_folder), "--towns", "town_b"])
    assert exc.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(read_only_folder) in line, line


# ------------------------------------------------------------------------------------------------
# cicfw carla-check --port


@pytest.mark.parametrize("option, value", [
    ("--port", "99999"), ("--port", "0"), ("--port", "-5"), ("--timeout", "0"), ("--timeout", "nan"),
])
def test_carla_check_bad_values_are_one_line(capsys, option: str, value: str):
    from cicfw.carla_client import check as carla_check

    assert carla_check.main([option, value]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert option in line and value in line, line


def test_carla_check_cli_port_99999_no_traceback():
    r = run_app_in_process("cicfw.cli", "carla-check", "--port", "99999")  # the cicfw command, in this process
    assert_refused(r, "--port", "99999")


# ------------------------------------------------------------------------------------------------
# a town too big to render


def _town_spec(**changes) -> dict:
    spec = yaml.safe_load(town_path("town_b").read_text())
    spec.update(changes)
    return spec


def test_a_huge_margin_is_refused_in_one_line_before_allocating(tmp_path: Path):
    path = tmp_path / "wide.yaml"
    path.write_text(yaml.safe_dump(_town_spec(name="wide", margin=100000)))
    t0 = time.monotonic()
    with pytest.raises(TownError) as err:
        load_town(path)
    assert time.monotonic() - t0 < 5.0
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg
    assert "margin" in msg and "100000" in msg and f"{MAX_TOWN_SIDE_M:g}" in msg, msg  # the key, value, bound


def test_nodes_too_far_apart_are_refused_in_one_line():
    spec = _town_spec()
    spec["nodes"] = {**spec["nodes"], "far": [5_000_000, 0]}
    with pytest.raises(TownError) as err:
        build_town(spec, source="far.yaml")
    assert "far.yaml" in str(err.value) and f"{MAX_TOWN_SIDE_M:g}" in str(err.value)


def test_the_shipped_towns_are_within_the_bound():
    for name in ("town_a", "town_b"):
        b = load_town(name).bounds
        assert max(b[2] - b[0], b[3] - b[1]) <= MAX_TOWN_SIDE_M


def test_the_preview_app_says_one_line_for_a_huge_town(tmp_path: Path, capsys):
    from cicfw.sim import preview

    path = tmp_path / "wide.yaml"
    path.write_text(yaml.safe_dump(_town_spec(name="wide", margin=100000)))
    with pytest.raises(SystemExit) as exc:
        preview.main(["--out", str(tmp_path / "out"), "--towns", str(path)])
    assert exc.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(path) in line and "margin" in line and "100000" in line, line


# ------------------------------------------------------------------------------------------------
# cicfw preview --seed, --prefix, and a failure after the rendering started


def test_preview_cli_seed_below_zero_is_one_line_naming_seed(tmp_path: Path):
    """``cicfw preview --seed -1`` used to render and write both sheets, then end on numpy's
    "expected non-negative integer" (no option named)."""
    out = tmp_path / "out"
    r = run_app_in_process("cicfw.cli", "preview", "--out", str(out), "--seed", "-1")
    assert_refused(r, "--seed", "-1")
    assert not out.exists()


def test_preview_prefix_with_a_folder_is_one_line_before_rendering(tmp_path: Path, capsys, monkeypatch):
    from cicfw.sim import preview

    monkeypatch.setattr(preview, "contact_sheet", lambda *a, **k: pytest.fail("rendered before checking --prefix"))
    with pytest.raises(SystemExit) as exc:
        preview.main(["--out", str(tmp_path / "out"), "--towns", "town_b", "--prefix", "../escaped_"])
    assert exc.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "--prefix" in line and "'../escaped_'" in line and "--out" in line, line
    assert list(tmp_path.iterdir()) == []


def test_a_preview_into_an_evaluations_folder_is_refused_before_rendering(tmp_path: Path, capsys, monkeypatch):
    """``cicfw preview --out <an evaluation's folder>`` replaced its map_town_a.png, the paths the model drove, with
    the preview's map of the same name."""
    from cicfw.sim import preview

    monkeypatch.setattr(preview, "contact_sheet", lambda *a, **k: pytest.fail("rendered before checking --out"))
    run = tmp_path / "evaluation"
    run.mkdir()
    (run / "episodes.jsonl").write_text((json.dumps({"format": "cicfw-episode-log/1", "fingerprint": {}}) + "\n"))  # an evaluation's log header
    (run / "map_town_a.png").write_bytes(b"the driven paths")
    with pytest.raises(SystemExit) as exc:
        preview.main(["--out", str(run), "--towns", "town_a"])
    assert exc.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "--out" in line and str(run) in line, line
    assert (run / "map_town_a.png").read_bytes() == b"the driven paths"


def test_a_preview_that_fails_after_rendering_started_writes_nothing(tmp_path: Path, capsys, monkeypatch):
    """Every picture is made before the first PNG is written, and a folder the run created is removed:
    a town whose routes cannot be drawn leaves neither sheets nor an empty --out behind."""
    import numpy as np

    from cicfw.sim import preview

    picture = lambda *a, **k: np.zeros((4, 4, 3), np.uint8)  # noqa: E731
    monkeypatch.setattr(preview, "contact_sheet", picture)
    monkeypatch.setattr(preview, "turn_sheet", picture)
    monkeypatch.setattr(preview, "town_map", picture)

    from cicfw.sim.town import TownError

    def no_routes(town, *a, **k):  # a town file whose roads hold no route that long: the user's to fix
        raise TownError(f"town {town.name} has no route of 150 m")

    monkeypatch.setattr(preview, "sample_routes", no_routes)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    for out in (tmp_path / "new" / "deeper", mine):
        with pytest.raises(SystemExit) as exc:
            preview.main(["--out", str(out), "--towns", "town_b"])
        assert exc.value.code == 2
        assert "has no route of 150 m" in _one_error_line(capsys.readouterr().err)
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == ["mine", "mine/notes.txt"]


def test_a_preview_whose_disk_fills_while_writing_leaves_no_png(tmp_path: Path, capsys, monkeypatch):
    """The PNGs are written together (``cicfw.core.files.write_together``): the disk filling on the second one
    leaves none of them, nor a temporary file or the --out the run created, and says which file in one line."""
    import errno

    import numpy as np

    import cicfw.core.files
    from cicfw.sim import preview

    picture = lambda *a, **k: np.zeros((4, 4, 3), np.uint8)  # noqa: E731
    for name in ("contact_sheet", "turn_sheet", "town_map"):
        monkeypatch.setattr(preview, name, picture)
    monkeypatch.setattr(preview, "sample_routes", lambda *a, **k: [])
    real, calls = cicfw.core.files.write_all, []

    def full_disk(fd, data):
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(fd, data)

    monkeypatch.setattr(cicfw.core.files, "write_all", full_disk)
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        preview.main(["--out", str(out), "--towns", "town_b"])
    assert exc.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert f"cannot write {out / 'turn_sheet.png'} (No space left on device)" in line, line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("seeds", ["0", "-1"])
def test_the_expert_bench_refuses_no_noise_seed_before_driving(monkeypatch, capsys, seeds: str):
    """bench/expert_suite.py --seeds 0 drove every route, then divided the noisy successes by no episode."""
    from conftest import load_bench_script

    bench = load_bench_script("expert_suite")
    monkeypatch.setattr(bench, "run_expert", lambda *a, **k: pytest.fail("drove"))
    monkeypatch.setattr("sys.argv", ["expert_suite.py", "--towns", "town_b", "--seeds", seeds])
    with pytest.raises(SystemExit) as stop:
        bench.main()
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "--seeds" in err and f"got {seeds}" in err, err
