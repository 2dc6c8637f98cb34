"""The one atomic writer (cicfw.files) and its users below the apps: files get the umask's mode, a failed
write leaves the final name untouched and no temporary file behind, and the module sits at the bottom."""
from __future__ import annotations

import ast
import os
import stat
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

import cicfw
from cicfw.data.cil_hdf5 import N_TARGETS, write_file
from cicfw.files import atomic_write, replacing
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


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "table.md"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with replacing(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.md"]


def test_atomic_write_writes_text_as_utf8_and_bytes_as_given(tmp_path):
    atomic_write(tmp_path / "a", "é")
    atomic_write(tmp_path / "b", b"\x00\xff")
    assert (tmp_path / "a").read_bytes() == "é".encode("utf-8")
    assert (tmp_path / "b").read_bytes() == b"\x00\xff"


def test_the_writer_is_the_bottom_layer():
    tree = ast.parse((Path(cicfw.__file__).parent / "files.py").read_text())
    found = {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    found |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not [m for m in found if m == "cicfw" or m.startswith("cicfw.")], sorted(found)
