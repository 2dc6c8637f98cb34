"""Each cell and manifest names the cicfw that made it (``reproduce.code``): version, git commit, and whether
tracked files differed from the commit. Checked against git asked directly, and outside a clone."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

import cicfw
from cicfw.reproduction import app as reproduce

ROOT = Path(__file__).resolve().parent.parent


def git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=True).stdout.strip()


def in_a_clone() -> bool:
    try:
        return Path(git("rev-parse", "--show-toplevel")).resolve() == ROOT
    except (OSError, subprocess.CalledProcessError):
        return False


@pytest.mark.skipif(not in_a_clone(), reason="the tests run outside a git clone of cicfw")
def test_a_clone_names_its_commit_and_whether_tracked_files_differ():
    got = reproduce.code()
    assert got["version"] == cicfw.__version__
    assert got["commit"] == git("rev-parse", "HEAD") and len(got["commit"]) == 40
    assert got["modified"] == (git("diff", "HEAD", "--name-only") != "")


def test_without_git_the_version_alone(monkeypatch):
    def no_git(*args, **kwargs):
        raise FileNotFoundError("git")

    monkeypatch.setattr(subprocess, "run", no_git)
    assert reproduce.code() == {"version": cicfw.__version__, "commit": None, "modified": None}


def test_an_installed_copy_inside_another_repository_names_no_commit(tmp_path, monkeypatch):
    """cicfw installed under some other project's git tree: that project's commit is not cicfw's."""
    other = tmp_path / "project"
    (other / "site" / "cicfw").mkdir(parents=True)
    subprocess.run(["git", "init", "-q", str(other)], check=True)
    subprocess.run(["git", "-C", str(other), "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q",
                    "--allow-empty", "-m", "theirs"], check=True)
    monkeypatch.setattr(cicfw, "__file__", str(other / "site" / "cicfw" / "__init__.py"))
    assert reproduce.code()["commit"] is None


def test_continuing_with_a_machine_copies_only_that_machines_finished_cells(tmp_path):
    """``continue_published(..., machine=...)``: a table within one kind of CPU takes only the finished cells
    whose ``machine`` holds the text; the others are named, not copied; a failed cell is never copied."""
    import json

    from cicfw.reproduction.published import continue_published

    src, dst = tmp_path / "published", tmp_path / "results"
    made = {"seed0": ("2 cores (Alpha CPU), no GPU", "ok"), "seed1": ("2 cores (Beta CPU), no GPU", "ok"),
            "seed2": ("2 cores (Alpha CPU), no GPU", "failed")}
    for seed, (machine, status) in made.items():
        (src / "cells" / "cil" / seed).mkdir(parents=True)
        (src / "cells" / "cil" / seed / "cell.json").write_text(json.dumps({"machine": machine, "status": status}))
    got = continue_published(src, dst, machine="Alpha")
    assert got == {"copied": ["cil/seed0"], "kept": [], "other_machine": ["cil/seed1"]}
    assert sorted(p.parent.name for p in dst.glob("cells/*/*/cell.json")) == ["seed0"]
    got = continue_published(src, dst)  # no filter: the other machine's cell too, seed 0 kept
    assert got == {"copied": ["cil/seed1"], "kept": ["cil/seed0"], "other_machine": []}


@pytest.mark.parametrize("folder", ["cells/cil/seed2", "cells/gtu/seed0"])
def test_a_cell_copied_under_another_row_or_seed_is_refused(tmp_path, folder):
    """seed0's cell copied to seed2 counted seed 0 twice: a row of two seeds reported three and got verdicts."""
    import json

    from cicfw.core.errors import CicfwError
    from cicfw.reproduction.cells import load_cells

    cell = {"status": "ok", "row": "cil", "seed": 0, "episodes": {}}
    for where in ("cells/cil/seed0", folder):
        (tmp_path / where).mkdir(parents=True)
        (tmp_path / where / "cell.json").write_text(json.dumps(cell))
    with pytest.raises(CicfwError) as err:
        load_cells(tmp_path)
    assert err.value.value == str(tmp_path / folder / "cell.json")
    (tmp_path / folder / "cell.json").unlink()
    assert [(c.row, c.seed) for c in load_cells(tmp_path)[0]] == [("cil", 0)]


def test_a_row_s_cells_of_two_definitions_are_refused_by_the_key_that_differs(tmp_path):
    """The row's experiment file edited between two runs into one folder: its cells trained two models under one
    row name, each recording its recipe; pooled, they would be reported as seeds of one model."""
    import json

    from cicfw.core.errors import CicfwError
    from cicfw.reproduction.cells import check_rows_agree, load_cells

    def cell(seed: int, w: int, mae: float) -> None:
        where = tmp_path / "cells" / "gtu" / f"seed{seed}"
        where.mkdir(parents=True, exist_ok=True)
        (where / "cell.json").write_text(json.dumps({
            "status": "ok", "row": "gtu", "seed": seed, "episodes": {}, "val_steer_mae": mae,
            "recipe": {"mixer": {"name": "gtu", "W": w}, "model": {"lr": 2e-4}}}))

    cell(0, 5, 0.1)
    cell(1, 5, 0.2)
    cells = load_cells(tmp_path)[0]
    assert [(c.row, c.seed) for c in cells] == [("gtu", 0), ("gtu", 1)]
    check_rows_agree(tmp_path, cells)
    cell(1, 10, 0.2)
    with pytest.raises(CicfwError) as err:
        check_rows_agree(tmp_path, load_cells(tmp_path)[0])
    assert err.value.key == "recipe.mixer.W" and err.value.value == 10
