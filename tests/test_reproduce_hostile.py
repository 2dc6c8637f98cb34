"""``python -m cicfw.reproduce`` against a hostile user, without training anything (its
tracebacks included): every bad plan is refused in one line *before the budget's dataset is
collected* (the tests make collecting raise, so a check that comes too late fails them), one run per
results folder (a lock naming its holder; a stale one taken over with a warning), unknown keys refused,
the docs' own custom-row example parses, report files readable under umask 022, resumed cells marked."""
from __future__ import annotations

import functools
import json
import logging
import os
import re
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cicfw.core.config_checks import SchemaError
from cicfw.core.errors import CicfwError
from cicfw.reproduction import app as reproduce
from cicfw.reproduction import report as results
from cicfw.reproduction.cells import COLUMNS, CellResult
from cicfw.reproduction.published import publish

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

DOCS = Path(__file__).resolve().parents[1] / "docs" / "reproduce.md"


class Collected(Exception):
    """Raised where the app would start collecting the budget's dataset: the expensive work."""


@pytest.fixture
def no_collect(monkeypatch):
    import cicfw.train.app

    def collect(*args, **kwargs):
        raise Collected("the app went on to collect the dataset")

    monkeypatch.setattr(cicfw.train.app, "ensure_data", collect)
    monkeypatch.setattr(reproduce, "ensure_data", collect)  # the app imported it by name


def refused(args: list[str], capsys) -> str:
    """Run the app; it must exit 2 with exactly one line on stderr, which is returned."""
    assert reproduce.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cicfw: error: "), err
    return err[0][len("cicfw: error: "):]


# ------------------------------------------------------------------------------------------------
# unknown keys; unparsable overrides


@pytest.mark.parametrize("arg, kind, key", [
    ("+foo=1", "unknown key", "foo"),
    ("+evaluate_aftr=true", "unknown key", "evaluate_aftr"),
    ("publish_dirr=x", "unknown key", "publish_dirr"),
    ("+budget.foo=1", "unknown key", "budget.foo"),
])
def test_unknown_keys_are_refused_in_one_line(arg, kind, key, no_collect, tmp_path, capsys):
    out = tmp_path / "results"
    with pytest.raises(SchemaError) as err:
        reproduce.compose_plan(["budget=smoke", arg, f"results_dir={out}"])
    assert (err.value.kind, err.value.key) == (kind, key), err.value
    msg = refused(["budget=smoke", arg, f"results_dir={out}"], capsys)
    assert msg == str(err.value) and "accepted" in msg, msg
    assert not out.exists()
    if arg == "publish_dirr=x":
        assert "did you mean 'publish_dir'?" in msg, msg


@pytest.mark.parametrize("arg, key", [("hydra.run.dir={x}", "hydra.run.dir"),
                                      ("+hydra.sweep.dir={x}", "hydra.sweep.dir"),
                                      ("hydra.sweep.subdir=mine", "hydra.sweep.subdir")])
def test_a_hydra_folder_key_is_refused_naming_results_dir(arg, key, no_collect, tmp_path, capsys):
    """reproduce writes under results_dir only: a Hydra folder key would be ignored or scatter the cells."""
    out, elsewhere = tmp_path / "results", tmp_path / "elsewhere"
    given = arg.format(x=elsewhere)
    with pytest.raises(CicfwError) as err:
        reproduce.compose_plan(["budget=smoke", given, f"results_dir={out}"])
    assert err.value.key == key
    msg = refused(["budget=smoke", given, f"results_dir={out}"], capsys)
    assert key in msg and "results_dir" in msg, msg
    assert not out.exists() and not elsewhere.exists()


def test_an_unparsable_override_is_one_line(no_collect, tmp_path, capsys):
    out = tmp_path / "results"
    msg = refused(["rows=[cil", f"results_dir={out}"], capsys)
    assert "'rows=[cil'" in msg, msg  # the override refused
    assert not out.exists()


# ------------------------------------------------------------------------------------------------
# custom rows: the docs' example, unknown heads and experiments


def docs_example() -> str:
    m = re.search(r"(\+catalogue\.mine=\{[^}]*\})", DOCS.read_text())
    assert m, "docs/reproduce.md has no custom-row example"
    return m.group(1)


def test_the_docs_custom_row_example_parses(no_collect, tmp_path):
    example = docs_example()
    cfg = reproduce.compose_plan([example, "rows=[mine]"])
    assert list(cfg.catalogue.mine.overrides) == ["head=hybrid"] and cfg.catalogue.mine.label == "GTU+hybrid"
    with pytest.raises(Collected):  # every check passed: the app goes on to collect
        reproduce.main([example, "rows=[mine]", "budget=smoke", f"results_dir={tmp_path / 'results'}"])


@pytest.mark.parametrize("row, message", [
    ("{experiment: paper_nosuch, label: x}",
     "row 'mine': unknown experiment 'paper_nosuch'; known experiments: main, paper_cil, "),
    ("{experiment: paper_gtu, overrides: ['head=nosuch'], label: x}",
     "row 'mine' (experiment paper_gtu, overrides ['head=nosuch']): unknown head 'nosuch'; known heads: coexistence, "
     "hybrid, regression, sine, softmax"),
    ("{experiment: paper_gtu, overrides: ['head.name=nosuch'], label: x}",
     "row 'mine' (experiment paper_gtu, overrides ['head.name=nosuch']): unknown head 'nosuch'"),
    ("{experiment: paper_gtu, overrides: ['mixer=gtuu'], label: x}",
     "row 'mine' (experiment paper_gtu, overrides ['mixer=gtuu']): unknown mixer 'gtuu'; known mixers: "),
    ("{experiment: paper_gtu, overrides: ['head.WW=3'], label: x}",
     "row 'mine' (experiment paper_gtu, overrides ['head.WW=3']): head.WW is not an argument of head 'regression'"),
])
def test_a_bad_custom_row_is_refused_up_front(row, message, no_collect, tmp_path, capsys):
    out = tmp_path / "results"
    msg = refused([f"+catalogue.mine={row}", "rows=[cil,mine]", f"results_dir={out}"], capsys)
    assert msg.startswith(message), msg
    assert not out.exists()


@pytest.mark.parametrize("row, kind, key", [
    ("{experiment: paper_gtu, overides: ['head=hybrid'], label: x}", "unknown key", "catalogue.mine.overides"),
    ("{label: x}", "missing", "catalogue.mine.experiment"),
    ("{experiment: paper_gtu, label: x, paper: [1, a, 3, 4]}", "wrong type", "catalogue.mine.paper[1]"),
])
def test_a_custom_row_against_the_schema_is_refused_up_front(row, kind, key, no_collect, tmp_path, capsys):
    out = tmp_path / "results"
    args = [f"+catalogue.mine={row}", "rows=[cil,mine]", f"results_dir={out}"]
    with pytest.raises(SchemaError) as err:
        reproduce.compose_plan(args)
    assert (err.value.kind, err.value.key) == (kind, key), err.value
    assert refused(args, capsys) == str(err.value)
    assert not out.exists()


@pytest.mark.parametrize("override, key", [
    ("model.lr=abc", "model.lr"), ("+mixer.foo=1", "mixer.foo"), ("+trainer.foo=1", "trainer.foo"), ("+foo=1", "'foo'"),
])
def test_a_custom_row_with_a_bad_value_is_refused_up_front(override, key, no_collect, tmp_path, capsys):
    """A value only the training would refuse (``model.lr=abc``) is refused before collecting, in one line
    naming the row, not by every cell of the row after the dataset is collected."""
    out = tmp_path / "results"
    row = f"{{experiment: paper_cil, overrides: ['{override}'], label: mine}}"
    msg = refused([f"+catalogue.mine={row}", "rows=[cil,mine]", "budget=smoke", f"results_dir={out}"], capsys)
    assert "'mine'" in msg and override in msg and key in msg, msg  # the row, its override and the key refused
    assert not out.exists()


@pytest.mark.parametrize("override", ["trainer.max_epochs=5", "+trainer.limit_train_batches=9", "data.batch_size=16",
                                      "seed=7"])
def test_a_custom_row_setting_what_the_budget_sets_is_refused_up_front(override, no_collect, tmp_path, capsys):
    """The budget's overrides and the cell's seed come after the row's: a row's own value for one of them
    would be ignored, its cells trained with the budget's (the row's label saying otherwise)."""
    out = tmp_path / "results"
    row = f"{{experiment: paper_gtu, overrides: ['{override}'], label: mine}}"
    args = [f"+catalogue.mine={row}", "rows=[cil,mine]", "budget=smoke", f"results_dir={out}"]
    with pytest.raises(reproduce.ReproduceError) as err:
        reproduce.check_plan(reproduce.compose_plan(args))
    assert (err.value.key, err.value.value) == ("catalogue.mine.overrides", override)
    refused(args, capsys)
    assert not out.exists()


def test_a_custom_row_with_another_row_s_label_is_refused_up_front(no_collect, tmp_path, capsys):
    """The report names each row by its label: a row of its own labelled as a catalogue row would print two
    rows of one name in the table and the claims, which no reader can tell apart."""
    out = tmp_path / "results"
    args = ["+catalogue.mine={experiment: paper_gtu, label: 'Regression (CIL)'}", "rows=[cil,mine]", "budget=smoke",
            f"results_dir={out}"]
    with pytest.raises(reproduce.ConfigError) as err:
        reproduce.check_plan(reproduce.compose_plan(args))
    assert (err.value.key, err.value.value) == ("catalogue.mine.label", "Regression (CIL)")
    refused(args, capsys)
    assert not out.exists()


@pytest.mark.parametrize("arg, key, label", [
    ("catalogue.cil.label='CIL\nsecond line'", "catalogue.cil.label", "CIL\nsecond line"),
    ("+catalogue.mine={experiment: paper_gtu, label: 'GTU\r\nx'}", "catalogue.mine.label", "GTU\r\nx"),
])
def test_a_label_with_a_line_break_is_refused_up_front(arg, key, label, no_collect, tmp_path, capsys):
    """A Markdown table row is one line: a label holding a line break would end its row mid-table."""
    out = tmp_path / "results"
    args = [arg, "rows=[cil]", "budget=smoke", f"results_dir={out}"]
    with pytest.raises(reproduce.ConfigError) as err:
        reproduce.check_plan(reproduce.compose_plan(args))
    assert (err.value.key, err.value.value) == (key, label)
    refused(args, capsys)
    assert not out.exists()


def test_the_catalogues_rows_set_nothing_a_budget_sets(no_collect):
    from cicfw.reproduction.catalogue import budget_settings_in_row

    for budget in ("smoke", "laptop", "converged", "converged6", "paper"):
        cfg = reproduce.compose_plan([f"budget={budget}"])
        assert {row: budget_settings_in_row(cfg, row) for row in cfg.catalogue
                if budget_settings_in_row(cfg, row)} == {}, budget


@pytest.mark.parametrize("arg, kind, key", [
    ("budget.curve_epochs=[abc]", "wrong type", "budget.curve_epochs[0]"),
    ("budget.curve_seeds=abc", "wrong type", "budget.curve_seeds"),
    ("budget.curve_seeds=[1.5]", "wrong type", "budget.curve_seeds[0]"),
    ("equivalence_margin=abc", "wrong type", "equivalence_margin"),
])
def test_bad_curve_lists_and_margins_are_refused_by_the_schema(arg, kind, key, no_collect, tmp_path, capsys):
    out = tmp_path / "results"
    args = ["budget=smoke", "rows=[cil]", arg, f"results_dir={out}"]
    with pytest.raises(SchemaError) as err:
        reproduce.compose_plan(args)
    assert (err.value.kind, err.value.key) == (kind, key), err.value
    assert refused(args, capsys) == str(err.value)
    assert not out.exists()


def test_a_curve_epoch_below_1_is_refused_up_front(no_collect, tmp_path, capsys):
    out = tmp_path / "results"
    msg = refused(["budget=smoke", "rows=[cil]", "budget.curve_epochs=[0]", f"results_dir={out}"], capsys)
    assert "budget.curve_epochs" in msg and "[0]" in msg, msg
    assert not out.exists()


def test_a_curve_epoch_past_the_training_is_refused_up_front(no_collect, tmp_path, capsys):
    """smoke trains 2 epochs: a curve point after epoch 5 was skipped without a word, exit 0."""
    from cicfw.core.errors import ConfigError

    out = tmp_path / "results"
    with pytest.raises(ConfigError) as err:
        reproduce.check_rows(reproduce.compose_plan(["budget=smoke", "budget.curve_epochs=[1,5]"]), ["cil"])
    assert (err.value.key, err.value.value) == ("budget.curve_epochs", 5)
    msg = refused(["budget=smoke", "rows=[cil]", "budget.curve_epochs=[5]", f"results_dir={out}"], capsys)
    assert "budget.curve_epochs" in msg and "5" in msg, msg
    assert not out.exists()
    reproduce.check_rows(reproduce.compose_plan(["budget=smoke", "budget.curve_epochs=[2]"]), ["cil"])  # the last


@pytest.mark.parametrize("margin", ["-1", "0", "nan"])
def test_a_bad_equivalence_margin_is_refused_before_any_cell(margin, no_collect, tmp_path, capsys):
    """The report needs the margin after every cell has run: a bad one is refused first, naming the key."""
    out = tmp_path / "results"
    msg = refused(["budget=smoke", "rows=[cil]", f"equivalence_margin={margin}", f"results_dir={out}"], capsys)
    assert msg.startswith("equivalence_margin="), msg
    assert not out.exists()


def test_failed_cells_make_the_app_exit_1(tmp_path, capsys, monkeypatch):
    """Every cell raising (its training, here): each records its error and the app ends with one line
    naming the cells that did not finish and rc 1, so that a script sees the table is incomplete."""
    def boom(cfg, row, seed, cell_dir):
        raise RuntimeError("out of memory\ndetail")

    monkeypatch.setattr(sys, "argv", list(sys.argv))  # main hands Hydra its sweep through sys.argv
    monkeypatch.setattr(reproduce, "prepare", lambda cfg, rows: {"budget": "smoke", "episodes": 4})
    monkeypatch.setattr(reproduce, "_train_and_drive", boom)
    out = tmp_path / "results"
    assert reproduce.main(["budget=smoke", "rows=[cil,gtu]", "seeds=1", f"results_dir={out}"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("cicfw: error: ") and all(s in err[-1] for s in ("2 of 2", "cil/seed0", "gtu/seed0")), err
    cell = json.loads((out / "cells" / "cil" / "seed0" / "cell.json").read_text())
    assert cell["status"] == "failed" and cell["error"] == "RuntimeError: out of memory"
    assert not (out / "reproduce.lock").exists()
    # the results folder's own log ends as stderr does (a piped or nohup run keeps it); a rerun appends
    assert reproduce.main(["budget=smoke", "rows=[cil,gtu]", "seeds=1", f"results_dir={out}"]) == 1
    log = (out / "reproduce.log").read_text()
    assert log.count(err[-1]) == 2 and log.count("cicfw: error: no report") == 2, log
    assert log.rstrip().endswith(err[-1]), log


def test_ctrl_c_in_a_cell_advises_the_same_command(tmp_path, monkeypatch):
    """A cell's training stopped by Ctrl-C said "resume with ckpt_path=...", a key reproduce refuses: the app
    says to run the same command again, which resumes the cell."""
    from cicfw.core.errors import Interrupted

    def stopped(cfg, row, seed, cell_dir):
        raise Interrupted("during training epoch 2: ...; resume with ckpt_path=x/last.ckpt")

    monkeypatch.setattr(sys, "argv", list(sys.argv))
    monkeypatch.setattr(reproduce, "prepare", lambda cfg, rows: {"budget": "smoke", "episodes": 4})
    monkeypatch.setattr(reproduce, "_train_and_drive", stopped)
    out = tmp_path / "results"
    with pytest.raises(Interrupted) as err:
        reproduce.main(["budget=smoke", "rows=[cil]", "seeds=1", f"results_dir={out}"])
    assert "same command" in str(err.value) and "ckpt_path" not in str(err.value)
    assert not (out / "reproduce.lock").exists()


@pytest.mark.parametrize("cell", ["failed", "stopped"])
def test_ctrl_c_in_the_final_report_says_the_cells_are_kept_and_how_to_write_it(tmp_path, monkeypatch, cell):
    """Ctrl-C while the report is written, after a failed cell or after a first Ctrl-C stopped one: the line
    says the cells are kept and how to write their report, and a second Ctrl-C keeps the first's advice
    (how to resume the stopped cell)."""
    from cicfw.core.errors import Interrupted

    def failed(cfg, row, seed, cell_dir):
        raise RuntimeError("not trained here")

    def stopped(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(sys, "argv", list(sys.argv))
    monkeypatch.setattr(reproduce, "prepare", lambda cfg, rows: {"budget": "smoke", "episodes": 4})
    monkeypatch.setattr(reproduce, "_train_and_drive", failed if cell == "failed" else stopped)
    monkeypatch.setattr(reproduce, "write_configured", stopped)
    out = tmp_path / "results"
    with pytest.raises(Interrupted) as err:
        reproduce.main(["budget=smoke", "rows=[cil]", "seeds=1", f"results_dir={out}"])
    said = str(err.value)
    assert f"kept in {out}" in said and f"cicfw report {out}" in said, said
    assert cell == "failed" or "resumes the unfinished cell" in said, said
    assert not (out / "reproduce.lock").exists()


# ------------------------------------------------------------------------------------------------
# checked before any cell and before collecting


def test_publish_dir_at_a_file_is_refused_up_front(no_collect, tmp_path, capsys):
    f = tmp_path / "a_file"
    f.write_text("x")
    out = tmp_path / "results"
    # one row: the folder check does not depend on the rows, and every row's training config is composed first
    msg = refused(["budget=smoke", "rows=[cil]", f"publish_dir={f}", f"results_dir={out}"], capsys)
    assert "publish_dir" in msg and str(f) in msg, msg
    assert not out.exists()


@pytest.mark.parametrize("inside", ["cells/cil/seed0", "published"])
def test_publish_dir_inside_the_results_folder_is_refused_up_front(no_collect, tmp_path, capsys, inside):
    """A cell's folder (or any folder in the results folder) as publish_dir would put a published copy,
    reproduce.json and cells/ among the run's own files: refused before anything is written."""
    out = tmp_path / "results"
    cell = out / "cells" / "cil" / "seed0"
    (cell / ".hydra").mkdir(parents=True)  # a cell's folder is the reproduce job's own (its Hydra record)
    (cell / ".hydra" / "hydra.yaml").write_text("hydra:\n  job:\n    name: reproduce\n")
    (cell / "cell.json").write_text('{"status": "ok"}')
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    msg = refused(["budget=smoke", "rows=[cil]", f"publish_dir={out / inside}", f"results_dir={out}"], capsys)
    assert "publish_dir" in msg and str(out / inside) in msg, msg
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before


def test_the_reports_publish_into_a_folder_a_running_reproduction_holds_is_refused(tmp_path, capsys):
    """A reproduce run holds its publish_dir for its whole run: ``cicfw report RESULTS --publish DEST`` into that
    folder meanwhile is refused naming --publish and the holder, and DEST keeps the run's files."""
    import shutil

    from cicfw.reproduction.lock import ResultsLock
    from cicfw.reproduction.report import main as report

    folder, dest = tmp_path / "half", tmp_path / "dest"
    shutil.copytree(Path(__file__).resolve().parents[1] / "docs" / "results" / "converged6_half", folder)
    dest.mkdir()
    running = ResultsLock(dest, key="publish_dir").acquire()  # the other run, between two of its publishes
    try:
        before = {p: p.read_bytes() for p in dest.rglob("*") if p.is_file()}
        assert report([str(folder), "--publish", str(dest)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--publish" in err[0] and str(dest) in err[0] and "pid" in err[0], err
        assert {p: p.read_bytes() for p in dest.rglob("*") if p.is_file()} == before
    finally:
        running.release()
    assert report([str(folder), "--publish", str(dest)]) == 0  # once that run is done
    assert (dest / "RESULTS.md").is_file()


def test_the_reports_publish_inside_the_results_folder_is_refused(tmp_path, capsys):
    """``cicfw report RESULTS --publish RESULTS/pub`` is held to publish_dir's rule: nothing written."""
    import shutil

    from cicfw.reproduction.report import main as report

    folder = tmp_path / "half"
    shutil.copytree(Path(__file__).resolve().parents[1] / "docs" / "results" / "converged6_half", folder)
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    assert report([str(folder), "--publish", str(folder / "pub")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--publish" in err[0] and str(folder / "pub") in err[0], err
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before


@functools.cache
def _pin(budget: str) -> str:
    """``budget``'s pin as reproduce.json records it, as JSON: composed once per module, the same for every test."""
    cfg = reproduce.compose_plan([f"budget={budget}"])
    return json.dumps(reproduce.fingerprint(cfg, {"config_hash": "0123456789abcdef"}))


def smoke_manifest(tmp_path: Path, budget: str = "smoke", **pinned) -> Path:
    """A results folder pinned to ``budget`` as reproduce.json records it (no cell needed)."""
    pin = {**json.loads(_pin(budget)), **pinned}
    out = tmp_path / "results"
    out.mkdir()
    (out / "reproduce.json").write_text(json.dumps({"budget": budget, "pinned": pin}))
    return out


@pytest.mark.parametrize("key", ["publish_dir", "continue_from"])
@pytest.mark.parametrize("spelling", ["same", "dotdot", "link"])
def test_publish_dir_or_continue_from_at_the_results_folder_is_refused(no_collect, tmp_path, capsys, key, spelling):
    """Copying the results folder onto itself loses nothing but means nothing: a mistyped path, refused
    before the lock, the dataset or any cell, however the same folder is spelled."""
    out = smoke_manifest(tmp_path)
    (tmp_path / "sub").mkdir()
    (tmp_path / "link").symlink_to(out)
    given = {"same": out, "dotdot": tmp_path / "sub" / ".." / "results", "link": tmp_path / "link"}[spelling]
    msg = refused(["budget=smoke", "rows=[cil]", f"results_dir={out}", f"{key}={given}"], capsys)
    assert f"{key}=" in msg and str(given) in msg, msg
    assert not (out / "reproduce.lock").exists() and sorted(p.name for p in out.iterdir()) == ["reproduce.json"]


def test_another_budget_is_refused_before_collecting(no_collect, tmp_path, capsys):
    out = smoke_manifest(tmp_path, "smoke")
    msg = refused(["budget=laptop", "rows=[cil]", f"results_dir={out}"], capsys)
    assert all(s in msg for s in (str(out), "budget=smoke", "budget=laptop", "results_dir=")), msg
    assert not (out / "reproduce.lock").exists()


# ------------------------------------------------------------------------------------------------
# one run per results folder


HOLDER = """
import sys, time
from pathlib import Path
from cicfw.reproduction.lock import ResultsLock
lock = ResultsLock(Path(sys.argv[1]))
lock.acquire()
print("held", flush=True)
time.sleep(120)
"""


def test_a_folder_in_use_is_refused_naming_its_holder(no_collect, tmp_path, capsys):
    out = tmp_path / "results"
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        msg = refused(["budget=smoke", "rows=[cil]", f"results_dir={out}"], capsys)
        assert all(s in msg for s in (str(out), f"pid {holder.pid}", socket.gethostname(), "results_dir=")), msg
    finally:
        holder.kill()
        holder.wait()
    # the holder is gone: its lock is stale and the next run takes it over (then goes on to collect)
    with pytest.raises(Collected):
        reproduce.main(["budget=smoke", "rows=[cil]", f"results_dir={out}"])
    assert not (out / "reproduce.lock").exists()  # released when the run stops


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_a_stale_lock_is_taken_over_with_a_warning(no_collect, tmp_path, caplog):
    out = tmp_path / "results"
    out.mkdir()
    pid = dead_pid()
    (out / "reproduce.lock").write_text(json.dumps({"pid": pid, "host": socket.gethostname(),
                                                    "started": "2020-01-01 00:00:00"}))
    with caplog.at_level(logging.WARNING, logger="cicfw.reproduce"), pytest.raises(Collected):
        reproduce.main(["budget=smoke", "rows=[cil]", f"results_dir={out}"])
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(f"taking over the stale lock of pid {pid} on {socket.gethostname()} (started 2020-01-01 00:00:00), "
               "which is no longer running" in w for w in warned), warned
    assert not (out / "reproduce.lock").exists()


def test_a_lock_held_on_another_host_is_refused(no_collect, tmp_path, capsys):
    out = tmp_path / "results"
    out.mkdir()
    (out / "reproduce.lock").write_text(json.dumps({"pid": 1, "host": "elsewhere", "started": "2020-01-01 00:00:00"}))
    msg = refused(["budget=smoke", "rows=[cil]", f"results_dir={out}"], capsys)
    assert all(s in msg for s in (str(out), "pid 1", "elsewhere", str(out / "reproduce.lock"))), msg  # lock to delete
    assert (out / "reproduce.lock").is_file()  # someone else's lock is left alone


# ------------------------------------------------------------------------------------------------
# report files readable by a colleague; resumed cells marked


def synthetic(row: str, seed: int, pct: int, resumed: dict | None = None) -> CellResult:
    eps = {f"{c}/{k:03d}": {"success": k < pct, "column": c, "command": "left" if k % 2 else "right"}
           for c in COLUMNS for k in range(20)}
    meta = {"row": row, "seed": seed, "status": "ok", "episodes": eps, "decoder": None, "wall_s": {"train": 1.0}}
    if resumed:
        meta["resumed"] = resumed
    return CellResult(row=row, seed=seed, episodes=eps, meta=meta)


def write_cells(out: Path, cells: list[CellResult]) -> None:
    for c in cells:
        p = out / "cells" / c.row / f"seed{c.seed}" / "cell.json"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(c.meta))


CATALOGUE = {"cil": {"label": "Regression (CIL)", "paper": [94.74, 86.84, 52.5, 46.25]},
             "gtu": {"label": "Co-learning (GTU)", "paper": [100.0, 93.42, 81.25, 75.0]}}


def test_report_files_are_readable_under_umask_022(tmp_path):
    out = tmp_path / "results"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "gtu") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    old = os.umask(0o022)
    try:
        results.write_report(out, CATALOGUE, n_boot=50)
        published = publish(out, tmp_path / "published")
        md = results.write_markdown_copy(json.loads((out / "results.json").read_text()) | {"has_curve": False},
                                         tmp_path / "docs" / "RESULTS.md", tmp_path / "published")
    finally:
        os.umask(old)
    written = [out / n for n in ("RESULTS.md", "results.json", "results.csv", "results.png")] + published + [md]
    for p in written:
        assert stat.S_IMODE(p.stat().st_mode) == 0o644, (p, oct(p.stat().st_mode))


REPORT_FILES = ("results.json", "results.csv", "results.png", "forest.png", "RESULTS.md")


def too_large_over(limit: int, monkeypatch) -> None:
    """Every file write of more than ``limit`` bytes fails as under ``ulimit -f`` (EFBIG)."""
    import errno

    from cicfw.core import files

    real = files.write_all

    def write_all(fd, data):
        if len(data) > limit:
            raise OSError(errno.EFBIG, "File too large")
        real(fd, data)

    monkeypatch.setattr(files, "write_all", write_all)


def test_a_report_that_cannot_be_written_whole_leaves_the_earlier_one(tmp_path, capsys, monkeypatch):
    """A file-size limit that results.json and results.csv fit under and the pictures do not: the report
    fails in one line naming the picture, and the earlier report is left whole (no new table beside old
    figures)."""
    out = tmp_path / "results"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "gtu") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    assert results.main([str(out)]) == 0
    before = {n: (out / n).read_bytes() for n in REPORT_FILES}
    limit = max(len(before["results.json"]), len(before["results.csv"])) + 2000
    assert len(before["results.png"]) > limit
    write_cells(out, [synthetic("gtu", 0, 5)])  # another outcome: every file of the report would change
    capsys.readouterr()
    too_large_over(limit, monkeypatch)
    assert results.main([str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and repr(str(out / "results.png")) in err[0], err
    assert {n: (out / n).read_bytes() for n in REPORT_FILES} == before
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_a_publish_that_cannot_be_written_whole_leaves_the_earlier_copy(tmp_path, monkeypatch):
    """The same limit while publishing: the published folder keeps its earlier report, not a new RESULTS.md
    beside old pictures."""
    out, pub = tmp_path / "results", tmp_path / "pub"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "gtu") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    results.write_report(out, CATALOGUE, n_boot=50)
    publish(out, pub)
    before = {p: p.read_bytes() for p in pub.rglob("*") if p.is_file()}
    write_cells(out, [synthetic("gtu", 0, 5)])
    results.write_report(out, CATALOGUE, n_boot=50)
    too_large_over(len((out / "results.png").read_bytes()) - 1, monkeypatch)
    with pytest.raises(OSError) as err:
        publish(out, pub)
    assert err.value.filename == str(pub / "results.png")
    assert {p: p.read_bytes() for p in pub.rglob("*") if p.is_file()} == before


def test_cicfw_report_rewrites_the_report_with_the_runs_own_rows_and_margin(tmp_path):
    """A run given a row of its own (its label) and another margin wrote its report with them; ``cicfw report`` on
    its folder rewrote it with conf/reproduce.yaml's defaults: the row under its key, the words at ±5."""
    out = tmp_path / "results"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "mine") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    reproduce.keep_report_overrides(out, ["budget=smoke", '+catalogue.mine={experiment: paper_gtu, label: "My row"}',
                                          "rows=[cil,mine]", "seeds=3", "equivalence_margin=3"])
    assert results.main([str(out)]) == 0
    data = json.loads((out / "results.json").read_text())
    assert {r["row"]: r["label"] for r in data["rows"]}["mine"] == "My row"
    assert data["equivalence_margin"] == 3


def test_cicfw_report_reads_a_reproduction_folder_wherever_its_options_stand(tmp_path):
    """``cicfw report --no-plots DIR`` (an option first) ran the evaluation report on a reproduction's folder: it
    joined the cells' evaluations into table.md, table.tex, table.csv and report.json written into that folder."""
    from conftest import run_app_in_process

    from cicfw.benchmark import evaluation_report

    out = tmp_path / "results"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "gtu") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    row = {"episode": 0, "key": "town_a/ClearNoon/000", "town": "town_a", "weather": "ClearNoon", "town_set": "training",
           "weather_set": "training", "pair": 0, "route": "town_a/j/a>b/left", "command": "left", "success": True,
           "reason": "success", "time_s": 1.0, "timeout_s": 30.0, "distance_m": 50.0, "route_length_m": 50.0,
           "goal_distance_m": 1.0, "progress": 1.0, "offroad_fraction": 0.0, "opposite_lane_fraction": 0.0, "steps": 10}
    evaluation_report.write_run(out / "cells" / "cil" / "seed0" / "evaluate", evaluation_report.Run("cil", [row], {}))
    res = run_app_in_process("cicfw.cli", "report", "--publish", str(tmp_path / "pub"), str(out))
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "pub" / "RESULTS.md").is_file() and (out / "RESULTS.md").is_file()
    assert not any((out / n).exists() for n in evaluation_report.REPORT_FILES)
    # the evaluation report itself, given the folder alone, writes no table into it
    res = run_app_in_process("cicfw.benchmark.evaluation_report", str(out), "--no-plots")
    assert res.returncode == 2 and "--out" in res.stderr
    assert not any((out / n).exists() for n in (*evaluation_report.REPORT_FILES, "report.json"))


EPISODE_ROW = {"episode": 0, "key": "town_a/ClearNoon/000", "town": "town_a", "weather": "ClearNoon",
               "town_set": "training", "weather_set": "training", "pair": 0, "route": "town_a/j/a>b/left",
               "command": "left", "success": True, "reason": "success", "time_s": 1.0, "timeout_s": 30.0,
               "distance_m": 50.0, "route_length_m": 50.0, "goal_distance_m": 1.0, "progress": 1.0,
               "offroad_fraction": 0.0, "opposite_lane_fraction": 0.0, "steps": 10}


@pytest.mark.parametrize("reproduction_first", [True, False])
def test_cicfw_report_refuses_a_reproduction_folder_given_with_evaluations(tmp_path, reproduction_first):
    """``cicfw report RES E1`` and ``cicfw report E1 RES`` did different things: one joined the reproduction's
    cells' evaluations as rows beside E1's, the other failed on an argument. Both are one refusal naming RES."""
    from conftest import run_app_in_process

    from cicfw.benchmark import evaluation_report

    out = tmp_path / "results"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "gtu") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    evaluation_report.write_run(out / "cells" / "cil" / "seed0" / "evaluate", evaluation_report.Run("cil", [EPISODE_ROW], {}))
    other = tmp_path / "e1"
    evaluation_report.write_run(other, evaluation_report.Run("gtu", [EPISODE_ROW], {}))
    folders = [str(out), str(other)] if reproduction_first else [str(other), str(out)]
    before = {p: sorted(q.name for q in p.iterdir()) for p in (tmp_path, out, other)}
    res = run_app_in_process("cicfw.cli", "report", "--no-plots", *folders, cwd=tmp_path)
    assert res.returncode == 2, (res.returncode, res.stderr)
    line = res.stderr.strip()
    assert line.startswith("cicfw: error:") and "\n" not in line and repr(str(out)) in line, line
    assert {p: sorted(q.name for q in p.iterdir()) for p in before} == before  # nothing written anywhere
    with pytest.raises(CicfwError) as err:  # the module itself, as the cicfw script runs it
        evaluation_report.refuse_reproduction_among([Path(f) for f in folders])
    assert (err.value.key, err.value.value) == ("dirs", str(out))


def test_cicfw_report_joins_reproduction_cells_as_evaluation_folders(tmp_path):
    """A cell folder (``cells/<row>/seed<k>``, Hydra's record names reproduce) holds an evaluation run like
    any folder holding one: joining two cells is no reproduction folder among evaluations."""
    from cicfw.benchmark import evaluation_report

    cells = []
    for row in ("cil", "gtu"):
        cell = tmp_path / "results" / "cells" / row / "seed0"
        (cell / ".hydra").mkdir(parents=True)
        (cell / ".hydra" / "hydra.yaml").write_text("hydra:\n  job:\n    name: reproduce\n")
        evaluation_report.write_run(cell / "evaluate", evaluation_report.Run(row, [EPISODE_ROW], {}))
        cells.append(cell)
    evaluation_report.refuse_reproduction_among(cells)  # no refusal
    assert evaluation_report.main([*map(str, cells), "--out", str(tmp_path / "joined"), "--no-plots"]) == 0
    assert (tmp_path / "joined" / "table.md").is_file()


def test_report_markdown_copy_replaces_only_an_earlier_copy(tmp_path, capsys):
    """``--markdown`` (its help said e.g. docs/RESULTS.md, which is composed from the studies' prose) replaced
    any file with the generated report."""
    out = tmp_path / "results"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "gtu") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    notes = tmp_path / "RESULTS.md"
    notes.write_text("# Results\n\nmy prose\n")
    assert results.main([str(out), "--markdown", str(notes)]) == 2
    assert "--markdown" in capsys.readouterr().err and notes.read_text() == "# Results\n\nmy prose\n"
    assert not (out / "RESULTS.md").exists()  # refused before anything was written
    copy = tmp_path / "copy.md"
    assert results.main([str(out), "--markdown", str(copy)]) == 0
    assert results.main([str(out), "--markdown", str(copy)]) == 0  # an earlier copy: replaced
    assert copy.read_text().startswith(results.TITLE)


def test_report_markdown_copy_may_not_replace_a_file_the_report_writes(tmp_path, capsys):
    """A published folder's results.csv did not exist yet when --markdown was checked: it was published, then
    replaced by the Markdown."""
    out, pub = tmp_path / "results", tmp_path / "pub"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "gtu") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    with pytest.raises(CicfwError) as err:
        results.check_markdown_target(pub / "results.csv", [out, pub])
    assert (err.value.key, err.value.value) == ("--markdown", str(pub / "results.csv"))
    assert results.main([str(out), "--publish", str(pub), "--markdown", str(pub / "results.csv")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not (out / "RESULTS.md").exists() and not (pub / "results.csv").exists()  # refused before writing

def test_resumed_cells_are_marked_in_the_report(tmp_path):
    cells = [synthetic("cil", s, 10 + s) for s in range(3)]
    cells += [synthetic("gtu", s, 12 + s, resumed={"training": {"from_epoch": 1}} if s == 1 else None)
              for s in range(3)]
    data = results.report_data(cells, [], CATALOGUE, {"budget": "smoke", "suite": {"name": "single_turn"}}, n_boot=50)
    md = results.markdown(data)
    lines = md.splitlines()
    gtu = next(ln for ln in lines if ln.startswith("| Co-learning (GTU) | – |"))
    cil = next(ln for ln in lines if ln.startswith("| Regression (CIL) | – |"))
    assert "| 3 ‡ |" in gtu and "‡" not in cil
    note = next(ln for ln in lines if ln.startswith("‡ "))
    assert "Co-learning (GTU) seed 1 (training resumed after epoch 1)" in note
    assert "can differ from an uninterrupted run's" in note and "0.12519" in note and "0.12743" in note
    assert any(ln.startswith("| Co-learning (GTU) | 1 ‡ |") for ln in lines)  # the per-seed table
    assert data["rows"][1]["resumed"] == {"1": {"training": {"from_epoch": 1}}}


def test_a_relation_candidate_that_is_no_fine_tuning_row_is_refused_up_front(no_collect):
    """The report names the candidate chosen as fine tuning's row: CIL would be named so."""
    from cicfw.core.errors import ConfigError

    with pytest.raises(ConfigError) as err:
        reproduce.check_rows(reproduce.compose_plan(["budget=smoke", "relation_candidates=[re_all,cil]"]), ["gtu", "cil"])
    assert (err.value.key, err.value.value) == ("relation_candidates", "cil")
    reproduce.check_rows(reproduce.compose_plan(["budget=smoke"]), ["re_all"])  # a shipped candidate, as a row


@pytest.mark.parametrize("where", ["results_dir", "continue_from"])
def test_a_relation_candidate_whose_earlier_cells_are_no_fine_tuning_row_is_refused(no_collect, tmp_path, where):
    """A candidate that is no row of this run still has its cells chosen among, from an earlier run in the folder
    (or the folder continued from): CIL's would be named fine tuning's row."""
    from cicfw.core.errors import ConfigError

    folder = tmp_path / where
    for row, mixer in (("cil", "independent"), ("re_all", "re")):
        (folder / "cells" / row / "seed0").mkdir(parents=True)
        (folder / "cells" / row / "seed0" / "cell.json").write_text(json.dumps(
            {"row": row, "seed": 0, "status": "ok", "mixer": mixer, "val_steer_mae": 0.1}))
    plan = ["budget=smoke", f"results_dir={tmp_path / 'results_dir'}", f"{where}={folder}"]
    with pytest.raises(ConfigError) as err:
        reproduce.check_rows(reproduce.compose_plan([*plan, "relation_candidates=[re_all,cil]"]), ["re_pairs"])
    assert (err.value.key, err.value.value) == ("relation_candidates", "cil")
    reproduce.check_rows(reproduce.compose_plan(plan), ["re_pairs"])  # the shipped candidates: re_all's cells


@pytest.mark.parametrize("key", ["publish_dir", "continue_from", "results_dir"])
def test_a_reproduce_json_holding_null_is_refused_naming_it(no_collect, tmp_path, capsys, key):
    """A corrupt record is refused as a truncated one is, not read as a folder without one."""
    other = tmp_path / "other"
    other.mkdir()
    (other / "reproduce.json").write_text("null")
    folders = {"results_dir": tmp_path / "results", key: other}
    msg = refused(["budget=smoke", "rows=[cil]", *(f"{k}={v}" for k, v in folders.items())], capsys)
    assert str(other / "reproduce.json") in msg and "null" in msg, msg


@pytest.mark.parametrize("text", ["null", "[]"])
def test_a_cell_json_holding_no_object_is_refused_naming_it(no_collect, tmp_path, capsys, text):
    """A cell's record edited by hand is refused as a reproduce.json holding null is, not an AttributeError."""
    cell = tmp_path / "results" / "cells" / "cil" / "seed0" / "cell.json"
    cell.parent.mkdir(parents=True)
    cell.write_text(text)
    msg = refused(["budget=smoke", "rows=[cil]", "seeds=1", f"results_dir={tmp_path / 'results'}"], capsys)
    assert str(cell) in msg and text in msg, msg




def test_cicfw_report_is_refused_while_a_reproduction_holds_the_folder(tmp_path, capsys):
    """The running reproduction rewrites the report as its cells finish: a report written beside it would be
    replaced mid-run. Refused naming the holder's pid; once that holder is gone, its stale lock stops nothing."""
    out = tmp_path / "results"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "gtu") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = sorted(out.rglob("*"))
        assert results.main([str(out)]) == 2
        (line,) = capsys.readouterr().err.strip().splitlines()
        assert line.startswith("cicfw: error: ") and f"pid {holder.pid}" in line and "results_dir" in line, line
        assert sorted(out.rglob("*")) == before  # no report written
    finally:
        holder.kill()
        holder.wait()
    assert (out / "reproduce.lock").is_file()  # the killed holder's record stays: a stale lock
    assert results.main([str(out)]) == 0
    assert (out / "RESULTS.md").is_file()


def test_a_lock_files_holder_is_live_only_while_its_pid_runs(tmp_path):
    from cicfw.core.locks import live_holder

    lock = tmp_path / "reproduce.lock"
    assert live_holder(lock) is None and not lock.exists()  # no lock file: none made by looking
    me = {"pid": os.getpid(), "host": socket.gethostname(), "started_epoch": 0.0}
    lock.write_text(json.dumps({**me, "started_epoch": time.time()}))
    assert live_holder(lock)[0]["pid"] == os.getpid() and live_holder(lock)[1] is True
    lock.write_text(json.dumps({**me, "pid": dead_pid()}))
    assert live_holder(lock) is None
    lock.write_text(json.dumps({**me, "host": "elsewhere.invalid"}))
    assert live_holder(lock) == ({**me, "host": "elsewhere.invalid"}, False)  # its pid cannot be checked here


def test_a_lock_recorded_in_the_future_gets_the_advice_to_delete_it(tmp_path, capsys):
    """A live pid whose record says it started tomorrow (a clock set back, or a record no reproduce wrote):
    the report's refusal says the holder may be gone and which file to delete, as for another host's."""
    from cicfw.core.locks import live_holder

    out = tmp_path / "results"
    write_cells(out, [synthetic(r, s, 10 + s) for r in ("cil", "gtu") for s in range(3)])
    (out / "reproduce.json").write_text(json.dumps({"budget": "smoke", "pinned": {"hash": "x"}}))
    lock = out / "reproduce.lock"
    lock.write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "started_epoch": time.time() + 86400}))
    assert live_holder(lock)[1] is False
    assert results.main([str(out)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "results_dir=" in line and f"delete {str(lock)!r}" in line, line
    assert not (out / "RESULTS.md").exists()
