"""The one atomic writer (cicfw.core.files) and its users below the apps: files get the umask's mode, a failed
write leaves the final name untouched and no temporary file behind, and the module sits at the bottom. The
one check of an output folder, `writable_folder`: one `ConfigError` naming the key that chose the folder."""
from __future__ import annotations

import ast
import errno
import os
import stat
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

import cicfw
import cicfw.core.files as files_mod
from cicfw.data.cil_hdf5 import N_TARGETS, write_file
from cicfw.core.errors import ConfigError
from cicfw.core.files import atomic_write, writable_folder, write_together
from cicfw.model.diagnostics import save_png


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    try:
        yield 0o640  # what a plain open() gives under this umask
    finally:
        os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _png(path: Path) -> None:
    fig = Figure(figsize=(1, 1))
    fig.add_subplot().plot([0, 1])
    save_png(fig, str(path))


def _h5(path: Path) -> None:
    write_file(path, np.zeros((2, 88, 200, 3), np.uint8), np.zeros((2, N_TARGETS), np.float32))


@pytest.mark.parametrize("write", [lambda p: atomic_write(p, "text"), _png, _h5], ids=["atomic_write", "save_png", "cil_file"])
def test_files_get_the_umask_mode_not_owner_only(tmp_path, umask_027, write):
    path = tmp_path / "sub" / "out.bin"
    write(path)
    assert path.is_file() and path.stat().st_size > 0
    assert _mode(path) == umask_027, oct(_mode(path))
    assert [p.name for p in path.parent.iterdir()] == ["out.bin"], "a temporary file was left behind"


@pytest.mark.parametrize("write", [lambda p: atomic_write(p, "text"), _png, _h5], ids=["atomic_write", "save_png", "cil_file"])
def test_a_file_written_over_keeps_its_mode_under_an_owner_only_umask(tmp_path, write):
    """A shared report (0664) rewritten by a user whose umask is 077 stays readable by its group; a new file
    beside it gets the umask's 0600."""
    kept, new = tmp_path / "out.bin", tmp_path / "new.bin"
    kept.write_text("old")
    kept.chmod(0o664)
    old = os.umask(0o077)
    try:
        write(kept)
        write(new)
    finally:
        os.umask(old)
    assert kept.read_bytes() != b"old"
    assert (_mode(kept), _mode(new)) == (0o664, 0o600), (oct(_mode(kept)), oct(_mode(new)))


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "table.md"
    path.write_text("old")
    def disk_full() -> None:
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        write_together({path: b"half"}, before_rename=disk_full)
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.md"]


def test_atomic_write_writes_text_as_utf8_and_bytes_as_given(tmp_path):
    atomic_write(tmp_path / "a", "é")
    atomic_write(tmp_path / "b", b"\x00\xff")
    assert (tmp_path / "a").read_bytes() == "é".encode("utf-8")
    assert (tmp_path / "b").read_bytes() == b"\x00\xff"


def test_a_group_of_files_appears_whole_or_not_at_all(tmp_path, monkeypatch):
    group = {tmp_path / "a.h5": b"a" * 10, tmp_path / "b.h5": b"b" * 10, tmp_path / "c.json": b"{}"}
    (tmp_path / "a.h5").write_bytes(b"old")  # a file the group replaces
    real, calls = files_mod.write_all, []

    def full_on_the_second(fd, data):
        calls.append(data)
        if len(calls) == 2:
            real(fd, data[:3])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd, data)

    def untouched():
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5"], "a file or a temporary was left"
        assert (tmp_path / "a.h5").read_bytes() == b"old"

    monkeypatch.setattr(files_mod, "write_all", full_on_the_second)
    with pytest.raises(OSError) as err:
        write_together(group, fsync=True, suffix=".part")
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(tmp_path / "b.h5")  # the final name
    untouched()
    monkeypatch.setattr(files_mod, "write_all", real)
    # a check before the renames (the collector's: is its parent still there?) stops it just the same
    with pytest.raises(RuntimeError, match="gone"):
        write_together(group, before_rename=lambda: (_ for _ in ()).throw(RuntimeError("gone")))
    untouched()
    write_together(iter(group.items()))  # pairs made as they are written
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == {p.name: data for p, data in group.items()}


def test_the_writer_is_the_bottom_layer():
    """files.py imports nothing from cicfw but its errors, which import nothing from cicfw."""
    def cicfw_imports(name: str) -> list[str]:
        tree = ast.parse((Path(cicfw.__file__).parent / "core" / f"{name}.py").read_text())
        found = {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        found |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        return sorted(m for m in found if m == "cicfw" or m.startswith("cicfw."))

    assert cicfw_imports("files") == ["cicfw.core.errors"]
    assert cicfw_imports("errors") == []


@pytest.mark.parametrize("where", ["a file", "under a file", "read-only"])
def test_a_folder_that_cannot_be_made_or_written_is_a_config_error_naming_its_key(tmp_path, monkeypatch, where):
    blocker = tmp_path / "a_file"
    blocker.write_text("mine")
    folder = {"a file": blocker, "under a file": blocker / "sub", "read-only": tmp_path / "ro"}[where]
    if where == "read-only":  # as a read-only mount refuses it, whoever runs the test (root ignores modes)
        folder.mkdir()
        real_open = os.open

        def refusing_open(path, *a, **k):
            if os.path.dirname(os.fspath(path)) == str(folder):
                raise PermissionError(errno.EACCES, "Permission denied", os.fspath(path))
            return real_open(path, *a, **k)

        monkeypatch.setattr(os, "open", refusing_open)
    with pytest.raises(ConfigError) as err:
        writable_folder(folder, "--out", "a folder you can write")
    assert (err.value.key, err.value.value) == ("--out", str(folder))
    assert blocker.read_text() == "mine"
    with pytest.raises(ConfigError) as err:  # the setting that chose the folder, when it is not the path itself
        writable_folder(folder, "CICFW_CACHE", "a folder you can write", value=str(tmp_path))
    assert (err.value.key, err.value.value) == ("CICFW_CACHE", str(tmp_path))


def test_a_writable_folder_is_made_and_left_as_it_was(tmp_path):
    folder = tmp_path / "a" / "b"
    assert writable_folder(folder, "--out", "a folder you can write") == folder
    assert list(folder.iterdir()) == []
    (folder / "kept").write_text("x")
    writable_folder(folder, "--out", "a folder you can write")
    assert [p.name for p in folder.iterdir()] == ["kept"]  # no probe left behind


def test_a_held_run_folder_loses_only_the_temporaries_of_writers_that_no_longer_run(tmp_path):
    """A writer killed mid-write (SIGKILL) leaves its ``.<name>.<pid>-<hex>.tmp``; holding the folder for a
    run (a resume) removes it, and keeps those of writers still running and every other file."""
    import subprocess
    import sys

    from cicfw.core.run_folder import hold_train_folder, release_run_folder

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / "checkpoints").mkdir()
        stale = tmp_path / "checkpoints" / f".epoch000.ckpt.{dead.pid}-0123abcd.tmp"
        busy = tmp_path / "checkpoints" / f".last.ckpt.{alive.pid}-89abcdef.tmp"
        mine = tmp_path / f".data.json.{os.getpid()}-00ff00ff.tmp"
        kept = [busy, mine, tmp_path / "notes.tmp", tmp_path / f".x.{dead.pid}.tmp"]
        for p in [stale, *kept]:
            p.write_bytes(b"half")
        hold_train_folder(tmp_path, "last")
        release_run_folder(tmp_path)
        assert not stale.exists() and all(p.exists() for p in kept)
    finally:
        alive.kill()
        alive.wait()


def test_a_new_name_published_without_hard_links_is_left_free_when_the_rename_fails(tmp_path, monkeypatch):
    """A file system without hard links: the name is made exclusively, then the file renamed onto it; a rename
    that fails (here EIO) leaves no empty file under that name, which a rerun would take for another's."""
    from cicfw.core import files
    from cicfw.core.files import write_together

    def no_link(src, dst):
        raise OSError(errno.EPERM, "Operation not permitted")

    def failing_replace(src, dst):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(files.os, "link", no_link)
    monkeypatch.setattr(files.os, "replace", failing_replace)
    out = tmp_path / "model.onnx"
    with pytest.raises(OSError) as err:
        write_together({out: b"model"}, new=[out])
    assert (err.value.errno, err.value.filename) == (errno.EIO, str(out))
    assert list(tmp_path.iterdir()) == []
