"""Imports run one way: apps -> bench / sim / model / data -> registry (issue 11, section 7).

Every ``import`` and ``from ... import`` in the package is read with ``ast`` (function-level ones
included: a lazy import is still a dependency), so a lower layer reaching up fails here.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

import cicfw

PKG = Path(cicfw.__file__).parent
APPS = ("cicfw.train", "cicfw.evaluate", "cicfw.collect", "cicfw.reproduce", "cicfw.cli")
LOWER = ("bench", "sim", "model", "data")


def _module_name(path: Path, root: Path = PKG.parent) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path, root: Path = PKG.parent) -> set[str]:
    """Every module ``path`` (under ``root``) imports: absolute names, relative imports resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    name = _module_name(path, root)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)  # `from cicfw import train` names a module too
    return out


def _reaches(imported: set[str], target: str) -> bool:
    return any(m == target or m.startswith(target + ".") for m in imported)


def _lower_modules() -> list[Path]:
    return sorted(p for sub in LOWER for p in (PKG / sub).rglob("*.py"))


def test_the_checker_sees_an_upward_import(tmp_path):
    bad = tmp_path / "cicfw" / "bench" / "bad.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("def f():\n    from cicfw.evaluate import load_trajectories\n    from .. import train\n")
    found = imports_of(bad, tmp_path)
    assert _reaches(found, "cicfw.evaluate") and _reaches(found, "cicfw.train")


@pytest.mark.parametrize("path", _lower_modules(), ids=lambda p: str(p.relative_to(PKG)))
def test_lower_layers_never_import_an_app(path):
    found = imports_of(path)
    upward = [app for app in APPS if _reaches(found, app)]
    assert not upward, f"{path.relative_to(PKG.parent)} imports the app module(s) {upward}; move the shared code down"


def test_plots_and_report_do_not_import_each_other():
    plots, report = PKG / "bench" / "plots.py", PKG / "bench" / "report.py"
    assert not _reaches(imports_of(plots), "cicfw.bench.report"), "bench/plots.py imports bench/report.py"
    # report may draw its bar chart with plots, so only one direction is allowed
    assert _reaches(imports_of(report), "cicfw.bench.plots")


def test_registry_is_the_bottom_layer():
    found = imports_of(PKG / "registry.py")
    assert not [m for m in found if m.startswith("cicfw.") and not m.startswith("cicfw.registry")], sorted(found)
