"""``python -m cicfw.sim.weather_sheet``: the sheet written where ``--out`` says, and a bad argument one line
(exit status 2) before any folder is made or image rendered."""
from __future__ import annotations

import json

from conftest import assert_refused, run_app_in_process

TOOL = "cicfw.sim.weather_sheet"
ONE = ["--towns", "town_b", "--weathers", "ClearNoon"]


def test_the_sheet_is_written_into_out(tmp_path):
    out = tmp_path / "new" / "img"
    result = run_app_in_process(TOOL, "--out", str(out), "--prefix", "sim_", *ONE)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip() == str(out / "sim_weather_families.png")
    assert (out / "sim_weather_families.png").read_bytes().startswith(b"\x89PNG")


def test_an_out_that_is_a_file_is_one_line(tmp_path):
    out = tmp_path / "a_file"
    out.write_text("mine")
    assert_refused(run_app_in_process(TOOL, "--out", str(out), *ONE), "--out", out)
    assert out.read_text() == "mine"


def test_an_unknown_weather_or_town_is_one_line_and_makes_no_folder(tmp_path):
    out = tmp_path / "img"
    for args, key, value in ((["--towns", "town_b", "--weathers", "Foggy"], "--weathers", "Foggy"),
                             (["--towns", "nowhere", "--weathers", "ClearNoon"], None, "nowhere"),
                             ([*ONE, "--colours", "1"], "--colours", 1),
                             (["--towns", "town_b", "town_b", "--weathers", "ClearNoon"], "--towns", "town_b"),
                             ([*ONE, "ClearNoon"], "--weathers", "ClearNoon"),  # drawn twice otherwise
                             ([*ONE, "--prefix", "../up_"], "--prefix", "../up_")):  # a name outside --out
        assert_refused(run_app_in_process(TOOL, "--out", str(out), *args), key, value)
        assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_an_out_holding_another_app_s_run_is_one_line(tmp_path):
    """Another app's outputs (here an evaluation's episode log) are not a picture folder: refused, untouched."""
    out = tmp_path / "eval_run"
    out.mkdir()
    (out / "episodes.jsonl").write_text((json.dumps({"format": "cicfw-episode-log/1", "fingerprint": {}}) + "\n"))  # an evaluation's log header
    assert_refused(run_app_in_process(TOOL, "--out", str(out), *ONE), "--out", out)
    assert sorted(p.name for p in out.iterdir()) == ["episodes.jsonl"]
