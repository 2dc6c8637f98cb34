"""``python -m cicfw.reproduce`` end to end on the smoke budget: two rows x two seeds, a rerun that skips
every finished cell, a killed run that resumes without recomputing, a resumed cell marked as such, a
failed cell recorded while the others go on, configurations that refuse to mix, a published folder
continued elsewhere (its cells skipped, its dataset checked), and one clear line for every bad input."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import shutil
import stat

import pytest

import cicfw
from cicfw.reproduction import app as reproduce
from cicfw.core.locks import FolderBusy
from cicfw.reproduction.lock import ResultsLock
from cicfw.reproduction.published import publish

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

# the smoke budget's training and validation batches (8 and the data config's 256), smaller here: what each test
# asserts holds at any size, and training costs less with them (2, not 1: batch norm trains on 2 or more)
BATCH = 2


def _smoke(part: str, replace: dict, *extra: str) -> str:
    """An override of one of the smoke budget's lists (``train`` or ``suite``, conf/budget/smoke.yaml, which
    users run unchanged): its own entries, those whose key is in ``replace`` with that value instead, then
    ``extra``. A list override replaces the whole list, so the budget's entries are repeated as written
    (interpolations unresolved)."""
    from importlib.resources import files

    from omegaconf import OmegaConf

    entries = OmegaConf.to_container(OmegaConf.load(str(files("cicfw.conf") / "budget" / "smoke.yaml"))[part])
    out, left = [], dict(replace)
    for entry in entries:
        key = entry.split("=", 1)[0]
        out.append(f"{key}={left.pop(key.lstrip('+'))}" if key.lstrip("+") in left else entry)
    assert not left and not any("'" in e for e in [*out, *extra]), (left, entries)
    return f"budget.{part}=[" + ",".join(f"'{e}'" for e in [*out, *extra]) + "]"


# Less data, smaller batches and shorter episodes than the smoke budget's, the same pipeline, in a fraction of
# the CPU time. 6 episodes of 7 s (420 frames) still hold every command and fill the 2 training batches and
# the validation batch (of BATCH, not the data config's 256: a cell validates 3 times). The untrained cells'
# episodes start 6 m before their turn (inside its command's 12 m, so at its command) and end 2 m off their
# route: a fraction of the frames each, the same 4 episodes, turns and table columns. No test here reads a
# cell's town maps (tests/test_hostile_evaluate.py does): not drawing them saves about a second a cell.
SMALL = [_smoke("train", {"data.collect.episodes": 6, "data.collect.seconds": 7, "data.batch_size": BATCH},
                f"data.val_batch_size={BATCH}"),
         _smoke("suite", {}, "sim.route_before=6", "sim.max_deviation=2", "maps=false")]
SMOKE = ["budget=smoke", "seeds=2", *SMALL]


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    """One dataset cache for the module: the smoke budget's data is collected once."""
    path = tmp_path_factory.mktemp("cache")
    old = os.environ.get("CICFW_CACHE")
    os.environ["CICFW_CACHE"] = str(path)
    yield path
    if old is None:
        os.environ.pop("CICFW_CACHE", None)
    else:
        os.environ["CICFW_CACHE"] = old


@pytest.fixture(scope="module")
def smoke_run(cache, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("smoke") / "results"
    old = os.umask(0o022)  # a shared machine's usual umask: what is written must be readable by others
    try:
        assert reproduce.main([*SMOKE, "rows=[cil,gtu]", f"results_dir={out}"]) == 0
    finally:
        os.umask(old)
    return out


@pytest.fixture(scope="module")
def one_cell(cache, smoke_run, tmp_path_factory) -> Path:
    """A results folder with one finished cell (cil seed 0): what resuming and continuing start from. The
    smoke run's cil seed 0 (the same cell a run of rows=[cil] seeds=1 trains: the first cell, on the same
    data and seed) is copied with the run's manifest, then that one-cell run reports it: the cell is
    skipped, nothing trains."""
    out = tmp_path_factory.mktemp("one") / "results"
    shutil.copytree(smoke_run / "cells" / "cil" / "seed0", out / "cells" / "cil" / "seed0")
    shutil.copy(smoke_run / "reproduce.json", out / "reproduce.json")
    assert reproduce.main([*SMOKE, "rows=[cil]", "seeds=1", f"results_dir={out}"]) == 0
    assert sorted(cells(out)) == ["cil/seed0"] and (out / "RESULTS.md").is_file()
    return out


def cells(out: Path) -> dict[str, dict]:
    return {f"{p.parent.parent.name}/{p.parent.name}": json.loads(p.read_text())
            for p in sorted(out.glob("cells/*/seed*/cell.json"))}


def test_smoke_two_rows_two_seeds_end_to_end(smoke_run):
    got = cells(smoke_run)
    assert sorted(got) == ["cil/seed0", "cil/seed1", "gtu/seed0", "gtu/seed1"]
    assert {c["status"] for c in got.values()} == {"ok"}, [c.get("error") for c in got.values()]
    one = got["gtu/seed0"]
    assert one["mixer"] == "gtu" and one["samples_seen"] == 2 * 2 * BATCH  # 2 epochs x 2 batches
    assert len(one["episodes"]) == 4 and {e["command"] for e in one["episodes"].values()} <= {"left", "right"}
    assert [p["epoch"] for p in one["curve"]] == [1, 2]  # the learning curve: epoch 1, then the final weights
    assert one["wall_s"]["train"] > 0 and one["wall_s"]["evaluate"] > 0
    assert "curve" not in got["gtu/seed1"] or got["gtu/seed1"]["curve"] == []  # curve_seeds: [0]
    data = json.loads((smoke_run / "results.json").read_text())
    assert [r["row"] for r in data["rows"]] == ["cil", "gtu"]
    by_claim = {c["claim"]: c for c in data["claims"]}
    assert by_claim["Co-learning (GTU) beats CIL"]["verdict"] == "too few seeds"  # 2 seeds: no verdict
    md = (smoke_run / "RESULTS.md").read_text()
    assert "| Regression (CIL) | – | 2 † |" in md and "*94.7*" in md
    assert (smoke_run / "results.png").read_bytes()[:4] == b"\x89PNG"
    manifest = json.loads((smoke_run / "reproduce.json").read_text())
    assert manifest["budget"] == "smoke" and manifest["suite"]["name"] == "single_turn" and manifest["episodes"] == 4
    assert one["dataset"] == manifest["pinned"]["dataset"] and one["recipe"]["mixer"]["name"] == "gtu"
    assert one["resumed"] is None
    assert one["code"]["version"] == manifest["code"]["version"] == cicfw.__version__  # who made the cell
    assert not (smoke_run / "reproduce.lock").exists()  # the run released its folder
    assert "4 cells in" in (smoke_run / "reproduce.log").read_text()  # its closing line, in its own log too


def test_what_a_run_writes_is_readable_by_others(smoke_run):
    """Under umask 022 a colleague can read the report, the manifest and every cell."""
    names = ["RESULTS.md", "results.json", "results.csv", "results.png", "reproduce.json"]
    files = [smoke_run / n for n in names] + list(smoke_run.glob("cells/*/seed*/cell.json"))
    files += list(smoke_run.glob("cells/*/seed*/train/trained.json"))
    assert len(files) == len(names) + 8
    for p in files:
        assert stat.S_IMODE(p.stat().st_mode) == 0o644, (p, oct(p.stat().st_mode))


def test_rerun_skips_every_finished_cell(smoke_run, capsys):
    before = {str(p): (p.stat().st_mtime_ns, p.read_text()) for p in smoke_run.glob("cells/*/seed*/cell.json")}
    assert reproduce.main([*SMOKE, "rows=[cil,gtu]", f"results_dir={smoke_run}"]) == 0
    after = {str(p): (p.stat().st_mtime_ns, p.read_text()) for p in smoke_run.glob("cells/*/seed*/cell.json")}
    assert after == before
    assert capsys.readouterr().out.count("finished before, skipped") == 4  # Hydra's job log goes to stdout


def test_killed_run_resumes_and_loses_nothing(cache, smoke_run, tmp_path):
    """A run killed mid-way through its second cell (once that cell's training has begun) resumes: the
    finished cell is not recomputed, the killed one completes. The finished cell is the smoke run's cil
    seed 0 (the same first cell, data and seed), copied in with the run's manifest, so the killed process
    spends nothing on a cell it is not killed in."""
    out = tmp_path / "results"
    shutil.copytree(smoke_run / "cells" / "cil" / "seed0", out / "cells" / "cil" / "seed0")
    shutil.copy(smoke_run / "reproduce.json", out / "reproduce.json")
    env = {**os.environ, "CICFW_CACHE": str(cache)}
    plan = [*SMOKE, "rows=[cil]", "seeds=2", f"results_dir={out}"]
    cmd = [sys.executable, "-m", "cicfw.reproduce", *plan]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    first = out / "cells" / "cil" / "seed0" / "cell.json"
    mid_way = out / "cells" / "cil" / "seed1" / "train"
    kept = first.read_text()
    deadline = time.time() + 900  # generous: a loaded 2-core machine trains slowly
    while not mid_way.is_dir() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)  # the whole run, mid-way through the second cell
    proc.wait()
    assert mid_way.is_dir()
    assert reproduce.main(plan) == 0
    assert first.read_text() == kept  # the finished cell was not recomputed
    got = cells(out)
    assert sorted(got) == ["cil/seed0", "cil/seed1"] and {c["status"] for c in got.values()} == {"ok"}
    assert not list(out.rglob("*.tmp"))


def test_a_dead_writer_s_temporary_files_go_when_the_folder_is_held_again(cache, one_cell, tmp_path):
    """A cell killed while saving a checkpoint leaves its half-written temporary file; the next run of the
    folder removes it once it holds the folder's lock (the cell, finished since, would never meet it again).
    A temporary file of a process still running is left to it."""
    out = tmp_path / "results"
    shutil.copytree(one_cell, out)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    ckpts = out / "cells" / "cil" / "seed0" / "train" / "checkpoints"
    stale = ckpts / f".epoch001-mae0.1364.ckpt.{dead.pid}-0936f25e.tmp"
    alive = ckpts / ".last.ckpt.1-80b05758.tmp"  # pid 1: running
    stale.write_bytes(b"half a checkpoint")
    alive.write_bytes(b"being written")
    assert reproduce.main([*SMOKE, "rows=[cil]", "seeds=1", f"results_dir={out}"]) == 0
    assert not stale.exists() and alive.read_bytes() == b"being written"
    assert (ckpts / "last.ckpt").is_file()


def test_the_report_and_publish_dir_follow_every_cell(cache, one_cell, tmp_path, monkeypatch):
    """A run of many cells publishes its table after each one, not only at its end: when the second cell
    starts, the first is in publish_dir, in its cells and its report. (Cells stand in for training and
    driving: the published cell's results, returned again.)"""
    done = json.loads((one_cell / "cells" / "cil" / "seed0" / "cell.json").read_text())
    result = {k: v for k, v in done.items() if k not in ("row", "seed", "status", "finished_s", "dataset")}
    out, published = tmp_path / "results", tmp_path / "published"
    seen = {}

    def train_and_drive(cfg, row, seed, cell_dir):
        md = published / "RESULTS.md"
        seen[seed] = (sorted(p.parent.name for p in published.glob("cells/cil/seed*/cell.json")),
                      md.read_text() if md.is_file() else None)
        return {**result, "val_steer_mae": result["val_steer_mae"] + seed * 1e-3}  # two models' own errors

    monkeypatch.setattr(reproduce, "_train_and_drive", train_and_drive)
    assert reproduce.main([*SMOKE, "rows=[cil]", f"results_dir={out}", f"publish_dir={published}"]) == 0
    assert seen[0] == ([], None)
    assert seen[1][0] == ["seed0"] and "| Regression (CIL) | – | 1 † |" in seen[1][1]
    assert "| Regression (CIL) | – | 2 † |" in (published / "RESULTS.md").read_text()  # and after the last


def test_publish_dir_is_held_for_the_whole_run(cache, one_cell, tmp_path, monkeypatch):
    """A run holds its publish_dir as it holds its results folder, from before its first cell to its last
    publish: another run taking that folder as its results folder while a cell runs is refused, naming it."""
    done = json.loads((one_cell / "cells" / "cil" / "seed0" / "cell.json").read_text())
    result = {k: v for k, v in done.items() if k not in ("row", "seed", "status", "finished_s", "dataset")}
    out, published = tmp_path / "results", tmp_path / "published"
    refused = []

    def train_and_drive(cfg, row, seed, cell_dir):  # the other run starts while this one's cell runs
        try:
            ResultsLock(published).acquire().release()
        except FolderBusy as err:
            refused.append((err.key, f"pid {os.getpid()}" in str(err)))
        return result

    monkeypatch.setattr(reproduce, "_train_and_drive", train_and_drive)
    assert reproduce.main([*SMOKE, "rows=[cil]", "seeds=1", f"results_dir={out}", f"publish_dir={published}"]) == 0
    assert refused == [("results_dir", True)]
    assert not (published / "reproduce.lock").exists() and (published / "reproduce.json").is_file()


def test_a_publish_dir_taken_after_its_check_is_refused_before_any_cell(cache, one_cell, tmp_path, monkeypatch, capsys):
    """Another run that takes publish_dir as its results folder between this run's checks and its start:
    this run is refused in one line naming publish_dir, and writes nothing into that folder."""
    out, published = tmp_path / "results", tmp_path / "published"
    other = []
    checked = reproduce.check_outputs

    def check_outputs(cfg, data=()):
        checked(cfg, data)
        other.append(ResultsLock(published).acquire())  # the other run claims the folder now

    monkeypatch.setattr(reproduce, "check_outputs", check_outputs)
    monkeypatch.setattr(reproduce, "_train_and_drive", lambda cfg, row, seed, cell_dir: pytest.fail("a cell ran"))
    try:
        assert reproduce.main([*SMOKE, "rows=[cil]", "seeds=1", f"results_dir={out}",
                               f"publish_dir={published}"]) == 2
        err = capsys.readouterr().err
        assert "publish_dir=<path>" in err and f"pid {os.getpid()}" in err, err
        assert sorted(p.name for p in published.iterdir()) == ["reproduce.lock"]  # the other run's alone
    finally:
        other[0].release()


def test_a_rerun_keeps_a_skipped_cells_hydra_records(cache, one_cell, tmp_path):
    """A rerun that skips a finished cell leaves the cell's .hydra records byte for byte as they were: the
    command it was trained with, not the rerun's (here with a publish_dir the training never had)."""
    out = tmp_path / "results"
    shutil.copytree(one_cell, out)
    hydra = out / "cells" / "cil" / "seed0" / ".hydra"
    before = {p.name: p.read_bytes() for p in hydra.iterdir()}
    assert {"config.yaml", "overrides.yaml", "hydra.yaml"} <= set(before)
    assert reproduce.main([*SMOKE, "rows=[cil]", "seeds=1", f"results_dir={out}",
                           f"publish_dir={tmp_path / 'pubX'}"]) == 0
    assert {p.name: p.read_bytes() for p in hydra.iterdir()} == before
    assert b"pubX" not in before["overrides.yaml"]


def test_a_run_whose_report_refuses_its_cells_exits_1_naming_why(cache, one_cell, tmp_path, monkeypatch, capsys):
    """Every cell finished, but the report refuses them (here two seeds that are one cell twice): the cells
    are kept, and the run says in one line that no report was written, with a failed status."""
    done = json.loads((one_cell / "cells" / "cil" / "seed0" / "cell.json").read_text())
    result = {k: v for k, v in done.items() if k not in ("row", "seed", "status", "finished_s", "dataset")}
    monkeypatch.setattr(reproduce, "_train_and_drive", lambda cfg, row, seed, cell_dir: result)
    out = tmp_path / "results"
    assert reproduce.main([*SMOKE, "rows=[cil]", f"results_dir={out}"]) == 1
    err = capsys.readouterr().err
    assert "no report" in err and "copies" in err and "seed1" in err, err
    assert len(list(out.glob("cells/cil/seed*/cell.json"))) == 2
    assert "| Regression (CIL) | – | 1 † |" in (out / "RESULTS.md").read_text()  # the table as of the last good cell


def test_cells_run_in_their_own_folder_still_pin_the_dataset(cache, one_cell, tmp_path, monkeypatch):
    """hydra.job.chdir=true moves each cell into its folder: a relative results_dir read from there missed the
    folder's manifest, and the cell recorded no dataset hash (so no later run could check it)."""
    done = json.loads((one_cell / "cells" / "cil" / "seed0" / "cell.json").read_text())
    result = {k: v for k, v in done.items() if k not in ("row", "seed", "status", "finished_s", "dataset")}
    monkeypatch.setattr(reproduce, "_train_and_drive", lambda cfg, row, seed, cell_dir: result)
    monkeypatch.chdir(tmp_path)
    assert reproduce.main([*SMOKE, "rows=[cil]", "seeds=1", "results_dir=results", "hydra.job.chdir=true"]) == 0
    pinned = json.loads((tmp_path / "results" / "reproduce.json").read_text())["pinned"]
    assert cells(tmp_path / "results")["cil/seed0"]["dataset"] == pinned["dataset"] is not None


def test_a_resumed_cell_is_marked_in_cell_json_and_the_report(cache, one_cell, tmp_path):
    """A cell whose training resumed from an epoch checkpoint (here: the first epoch's, as a killed run
    leaves it) says so in cell.json and in the report's table, with the difference resuming can make."""
    out = tmp_path / "results"
    ckpts = out / "cells" / "cil" / "seed0" / "train" / "checkpoints"
    ckpts.mkdir(parents=True)
    shutil.copy(one_cell / "cells" / "cil" / "seed0" / "train" / "checkpoints" / "epoch001.ckpt", ckpts)
    # no learning curve (the smoke run's cells drive theirs): resuming and its marks do not depend on it, and the
    # cell drives the suite once instead of twice
    assert reproduce.main([*SMOKE, "rows=[cil]", "seeds=1", "budget.curve_seeds=[]", f"results_dir={out}"]) == 0
    got = cells(out)["cil/seed0"]
    assert got["status"] == "ok" and got["resumed"] == {"training": {"from_epoch": 1}}
    assert got["epochs"] == 2
    md = (out / "RESULTS.md").read_text()
    assert "| Regression (CIL) | – | 1 † ‡ |" in md and "| Regression (CIL) | 0 ‡ |" in md
    assert "‡ Regression (CIL) seed 0 (training resumed after epoch 1)" in md and "0.12743" in md


def test_a_cell_killed_after_its_last_epoch_trains_that_epoch_again(cache, one_cell, tmp_path):
    """The last epoch's checkpoint is saved before that epoch's validation: a cell killed between the two
    resumes from the epoch before, so its validation error is measured (not NaN) and the mark says so."""
    import math

    out = tmp_path / "results"
    ckpts = out / "cells" / "cil" / "seed0" / "train" / "checkpoints"
    ckpts.mkdir(parents=True)
    for name in ("epoch001.ckpt", "epoch002.ckpt"):
        shutil.copy(one_cell / "cells" / "cil" / "seed0" / "train" / "checkpoints" / name, ckpts)
    # no learning curve: where the cell resumes does not depend on it, and the suite is driven once, not twice
    assert reproduce.main([*SMOKE, "rows=[cil]", "seeds=1", "budget.curve_seeds=[]", f"results_dir={out}"]) == 0
    got = cells(out)["cil/seed0"]
    assert got["resumed"] == {"training": {"from_epoch": 1}} and got["epochs"] == 2
    assert math.isfinite(got["val_steer_mae"])


def test_continue_from_a_published_folder_skips_its_cells(cache, one_cell, tmp_path, capsys):
    """A fresh clone continues a published folder: the published cells are copied in and
    skipped (nothing is trained), the report covers them, and publishing back records where they came
    from, so the next machine continues from there (a new cell would train and be published like any)."""
    (tmp_path / "repo" / ".git").mkdir(parents=True)  # a clone: the manifest names the folder inside it
    published = tmp_path / "repo" / "docs" / "results" / "smoke"
    publish(one_cell, published)  # what publish_dir=... writes, committed
    out = tmp_path / "clone" / "results"
    args = [*SMOKE, "rows=[cil]", "seeds=1", f"continue_from={published}", f"results_dir={out}",
            f"publish_dir={published}"]
    assert reproduce.main(args) == 0
    assert capsys.readouterr().out.count("finished before, skipped") == 1
    assert cells(out) == cells(one_cell) == cells(published)
    assert not (out / "cells" / "cil" / "seed0" / "train").exists()  # nothing recomputed
    manifest = json.loads((out / "reproduce.json").read_text())
    assert manifest["continued_from"][0]["from"] == "docs/results/smoke"
    assert manifest["continued_from"][0]["cells"] == ["cil/seed0"]
    assert json.loads((published / "reproduce.json").read_text())["continued_from"] == manifest["continued_from"]
    assert "- **Continued from:** `docs/results/smoke` (1 finished cells copied" in (published / "RESULTS.md").read_text()
    # the next machine continues the folder published back
    again = tmp_path / "third" / "results"
    assert reproduce.main([*SMOKE, "rows=[cil]", "seeds=1", f"continue_from={published}", f"results_dir={again}"]) == 0
    assert cells(again) == cells(one_cell)


def test_continue_machine_copies_only_that_machines_cells(cache, one_cell, tmp_path, capsys):
    """``continue_machine``: a table within one kind of CPU. Of a published folder whose cells came from two
    machines, only those whose machine holds the text are copied (the others are neither copied nor run
    when not asked for), and the manifest and report say so."""
    published = tmp_path / "published"
    publish(one_cell, published)
    ours = json.loads((published / "cells" / "cil" / "seed0" / "cell.json").read_text())
    other = {**ours, "seed": 1, "machine": "2 cores (Some Other CPU), no GPU",
             "val_steer_mae": ours["val_steer_mae"] + 1e-3}  # another model, not a copy of seed 0
    (published / "cells" / "cil" / "seed1").mkdir()
    (published / "cells" / "cil" / "seed1" / "cell.json").write_text(json.dumps(other))
    assert "Some Other CPU" not in ours["machine"]
    text = ours["machine"].split(",")[0]  # e.g. "2 cores (…)": this machine's, not the other's
    out = tmp_path / "results"
    args = ["budget=smoke", *SMALL, "rows=[cil]", "seeds=[0]", f"continue_from={published}",
            f"continue_machine='{text}'", f"results_dir={out}"]
    assert reproduce.main(args) == 0
    assert list(cells(out)) == ["cil/seed0"]
    entry = json.loads((out / "reproduce.json").read_text())["continued_from"][0]
    assert entry["cells"] == ["cil/seed0"] and entry["only_machine"] == text
    assert f"1 finished cells copied, only those made on a machine with {text!r}" in (out / "RESULTS.md").read_text()
    # without the filter both cells are copied
    both = tmp_path / "both"
    assert reproduce.main(["budget=smoke", *SMALL, "rows=[cil]", "seeds=[0]", f"continue_from={published}",
                            f"results_dir={both}"]) == 0
    assert sorted(cells(both)) == ["cil/seed0", "cil/seed1"]


@pytest.mark.parametrize("extra, message", [
    ([], "continue_machine='Xeon' selects cells of a published folder; give continue_from=<folder> too"),
    (["continue_from"], "continue_machine='Xeon' is in no finished cell's machine of "),
])
def test_continue_machine_typo_or_alone_is_one_line(extra, message, one_cell, tmp_path, capsys):
    published = tmp_path / "published"
    publish(one_cell, published)
    out = tmp_path / "results"
    typo = "Xeon"
    if typo in json.loads((published / "cells" / "cil" / "seed0" / "cell.json").read_text())["machine"]:
        typo = "Xeonn"  # on a Xeon, a text no machine holds
        message = message.replace("'Xeon'", "'Xeonn'")
    args = [*SMOKE, "rows=[cil]", f"continue_machine={typo}", f"results_dir={out}"]
    args += [f"continue_from={published}"] if extra else []
    assert reproduce.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"cicfw: error: {message}"), err
    if extra:
        assert "its machines: 2 cores (" in err[0]
    assert not out.exists() or not any(out.iterdir())


def test_shown_path_is_relative_to_the_clone_that_holds_the_folder(tmp_path):
    """A published manifest names where its cells came from as a clone elsewhere can follow it."""
    (tmp_path / "clone" / ".git").mkdir(parents=True)
    inside = tmp_path / "clone" / "docs" / "results" / "x"
    inside.mkdir(parents=True)
    assert reproduce.shown_path(inside) == "docs/results/x"
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    assert reproduce.shown_path(outside) == str(outside.resolve())


@pytest.mark.parametrize("what", ["manifest", "cell", "recipe", "family", "epochs"])
def test_continue_from_another_dataset_or_model_is_refused_in_one_line(what, cache, one_cell, tmp_path, capsys,
                                                                        monkeypatch):
    import cicfw.train.app

    published = tmp_path / "published"
    publish(one_cell, published)
    dataset = json.loads((one_cell / "reproduce.json").read_text())["pinned"]["dataset"]
    if what == "manifest":
        p = published / "reproduce.json"
        m = json.loads(p.read_text())
        m["pinned"]["dataset"] = "ffffffffffffffff"
        message = (f"continue_from={str(published)!r} was made with budget=smoke and another dataset "
                   f"(dataset ffffffffffffffff there, {dataset} here)")
    else:  # the cell's file, the key and both values
        p = published / "cells" / "cil" / "seed0" / "cell.json"
        m = json.loads(p.read_text())
        if what == "cell":
            m["dataset"] = "ffffffffffffffff"
            pair = ("dataset=ffffffffffffffff", f"dataset={dataset}")
        elif what == "family":  # a cell records the weather family it drove; another family's is refused
            assert m["weather_family"] == "carla"
            m["weather_family"] = "harsh"
            pair = ("weather_family=harsh", "weather_family=carla")
        elif what == "epochs":  # a cell of a budget that trains longer or shorter
            m["epochs"] += 1
            pair = (f"epochs={m['epochs']}", f"epochs={m['epochs'] - 1}")
        else:
            m["recipe"]["encoder"]["dropout_conv"] = 0.2
            pair = ("recipe.encoder.dropout_conv=0.2", "recipe.encoder.dropout_conv=0.0")
        message = f"cell {str(p)!r} was made with {pair[0]}, this run makes row cil with {pair[1]}"
    p.write_text(json.dumps(m))
    collected = []
    monkeypatch.setattr(cicfw.train.app, "ensure_data", lambda *a, **k: collected.append(1))
    monkeypatch.setattr(reproduce, "ensure_data", lambda *a, **k: collected.append(1))  # the app imported it by name
    out = tmp_path / "clone"
    assert reproduce.main([*SMOKE, "rows=[cil,gtu]", f"continue_from={published}", f"results_dir={out}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"cicfw: error: {message}"), err
    assert not list(out.glob("cells/*/seed*/cell.json")) and not (out / "reproduce.json").exists()
    assert not (out / "reproduce.lock").exists()
    if what == "manifest":
        assert not collected  # the dataset was already there: refused before asking the collector


@pytest.mark.parametrize("how", ["skip", "continue_from"])
def test_a_row_redefined_by_training_only_keys_is_refused(how, cache, one_cell, tmp_path, monkeypatch, capsys):
    """A cell records the overrides its row trained with; a row given a trainer key since (no recipe, no epochs)
    trains another model, so its finished cells are neither skipped nor continued as seeds of it: one line
    naming the cell, the key and both values, before anything is written. (Cells stand in for training.)"""
    done = json.loads((one_cell / "cells" / "cil" / "seed0" / "cell.json").read_text())
    result = {k: v for k, v in done.items() if k not in ("row", "seed", "status", "finished_s", "dataset")}
    monkeypatch.setattr(reproduce, "_train_and_drive", lambda cfg, row, seed, cell_dir:
                        {**result, "val_steer_mae": result["val_steer_mae"] + seed * 1e-3})  # two models' own errors
    out = tmp_path / "results"
    assert reproduce.main([*SMOKE, "rows=[cil]", f"results_dir={out}"]) == 0
    recorded = cells(out)["cil/seed0"]["overrides"]
    assert recorded[0] == "experiment=paper_cil" and recorded[-1] == f"data.val_batch_size={BATCH}", recorded
    assert "trainer.max_epochs=2" in recorded  # the smoke budget's, as written
    redefined = '+catalogue.cil.overrides=["+trainer.accumulate_grad_batches=2"]'
    if how == "skip":  # one cell removed: it would retrain under the new definition beside the old one
        (out / "cells" / "cil" / "seed1" / "cell.json").unlink()
        cell, folder, args = out / "cells" / "cil" / "seed0" / "cell.json", out, [f"results_dir={out}"]
    else:
        folder = tmp_path / "published"
        publish(out, folder)
        cell, args = folder / "cells" / "cil" / "seed0" / "cell.json", [f"continue_from={folder}",
                                                                          f"results_dir={tmp_path / 'clone'}"]
    before = {p: p.read_bytes() for p in folder.rglob("*.json")}
    capsys.readouterr()
    assert reproduce.main([*SMOKE, "rows=[cil]", *args, redefined]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(cell) in err[0], err
    assert "overrides.trainer.accumulate_grad_batches=(not set)" in err[0], err
    assert "overrides.trainer.accumulate_grad_batches=2" in err[0], err
    assert {p: p.read_bytes() for p in folder.rglob("*.json")} == before  # report_overrides unchanged too
    if how == "skip":
        assert not (out / "cells" / "cil" / "seed1" / "cell.json").exists()  # nothing trained
    else:
        assert not list((tmp_path / "clone").glob("cells/*/seed*/cell.json"))  # nothing copied


def test_a_failed_cell_is_recorded_and_the_others_go_on(smoke_run, capsys, monkeypatch):
    """A row whose training raises (a bad config value is refused up front, so the training itself raises
    here) fails its cells with a one-line error in cell.json; the finished cells are kept, the report lists
    the failures and the app exits 1 naming the cells that did not finish."""
    import cicfw.train.app

    def oom(*args, **kwargs):
        raise RuntimeError("CUDA out of memory.\nTried to allocate 2.00 GiB")

    monkeypatch.setattr(cicfw.train.app, "train", oom)  # cil and gtu finished before: only broken trains
    monkeypatch.setattr(reproduce, "train", oom)  # the app imported it by name
    broken = "+catalogue.broken={experiment:paper_cil,label:Broken}"
    assert reproduce.main([*SMOKE, "rows=[cil,gtu,broken]", broken, f"results_dir={smoke_run}"]) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(
        "cicfw: error: 2 of 6 cells did not finish (broken/seed0, broken/seed1): ")
    got = cells(smoke_run)
    assert [got[f"broken/seed{s}"]["status"] for s in (0, 1)] == ["failed", "failed"]
    assert {got[k]["status"] for k in got if not k.startswith("broken")} == {"ok"}
    err = got["broken/seed0"]["error"]
    assert err == "RuntimeError: CUDA out of memory." and "\n" not in err
    assert "- broken seed 0: RuntimeError: " in (smoke_run / "RESULTS.md").read_text()


def test_results_folder_of_another_configuration_is_refused(cache, smoke_run, capsys):
    assert reproduce.main([*SMOKE, "rows=[cil]", f"results_dir={smoke_run}", "budget.suite=['suite=single_turn','suite.limit=2']"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"cicfw: error: results folder '{smoke_run}' was made with budget=smoke "
                                               f"and another suite")
    assert "suite.limit=2" in err[0] and "start a new folder (results_dir=<new path>)" in err[0]


@pytest.mark.parametrize("args, message", [
    (["rows=[cil,gtx]"], "unknown row 'gtx'; known rows: cil, gtu, soft_sharing, moe, sluice, classification, "),
    (["seeds=0"], "seeds must be a whole number >= 1 (seeds 0..seeds-1 per row) or a list of distinct seeds from 0 to 4294967295 ([3,4]), got 0"),
    (["seeds=-2"], "seeds must be a whole number >= 1 (seeds 0..seeds-1 per row) or a list of distinct seeds from 0 to 4294967295 ([3,4]), got -2"),
    (["seeds=two"], "seeds must be a whole number >= 1 (seeds 0..seeds-1 per row) or a list of distinct seeds from 0 to 4294967295 ([3,4]), got 'two'"),
    (["seeds=[]"], "seeds must be a whole number >= 1 (seeds 0..seeds-1 per row) or a list of distinct seeds from 0 to 4294967295 ([3,4]), got []"),
    (["seeds=[1,1]"], "seeds must be a whole number >= 1 (seeds 0..seeds-1 per row) or a list of distinct seeds from 0 to 4294967295 ([3,4]), got [1, 1]"),
    (["seeds=[2,-1]"], "seeds must be a whole number >= 1 (seeds 0..seeds-1 per row) or a list of distinct seeds from 0 to 4294967295 ([3,4]), got [2, -1]"),
    # beyond a training run's seed range: refused after collecting and pinning the folder, as a failed cell
    (["seeds=[4294967296]"], "seeds must be a whole number >= 1 (seeds 0..seeds-1 per row) or a list of distinct seeds from 0 to 4294967295 ([3,4]), got [4294967296]"),
    (["budget=huge"], "unknown budget 'huge'; known budgets: converged, converged6, laptop, paper, smoke"),
    (["rows=[]"], "rows is empty; known rows: cil, gtu"),
])
def test_bad_input_is_one_clear_line_and_writes_nothing(args, message, tmp_path, capsys):
    out = tmp_path / "results"
    assert reproduce.main([*args, f"results_dir={out}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"cicfw: error: {message}"), err
    assert not out.exists()


def test_seeds_as_a_count_or_as_a_list_of_the_seeds_to_run():
    """``seeds=3`` runs 0, 1, 2; ``seeds=[4,1]`` runs 1 and 4 only (a second machine's share)."""
    from omegaconf import OmegaConf

    from cicfw.core.config_checks import SchemaError
    from cicfw.reproduction.schema import seed_list

    assert seed_list(3) == [0, 1, 2]
    assert seed_list(OmegaConf.create([4, 1])) == [1, 4]
    assert seed_list([0]) == [0]
    for bad in (True, 0, [True], [1.5], [], "3", [2**32]):
        with pytest.raises(SchemaError) as err:
            seed_list(bad)
        assert (err.value.kind, err.value.key) == ("wrong type", "seeds"), err.value


def test_converged6_is_converged_two_epochs_longer():
    """The 90% bar's candidate changes the training length and nothing else a cell trains with."""
    from hydra import compose, initialize_config_module

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        four, six = (compose("reproduce", overrides=[f"budget={b}"]) for b in ("converged", "converged6"))
        t4, t6 = (reproduce.compose_train(c, "cil", 2) for c in (four, six))
    assert (t4.trainer.max_epochs, t6.trainer.max_epochs) == (4, 6)
    assert t6.keep_epoch_checkpoints == [1, 2, 3, 4, 5, 6]
    t6.trainer.max_epochs, t6.keep_epoch_checkpoints = 4, t4.keep_epoch_checkpoints
    assert t6 == t4 and list(four.budget.suite) == list(six.budget.suite)
