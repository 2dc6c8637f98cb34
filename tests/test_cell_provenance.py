"""Each cell and manifest names the cicfw that made it (``reproduce.code``): version, git commit, and whether
tracked files differed from the commit. Checked against git asked directly, and outside a clone."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

import cicfw
from cicfw import reproduce

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
