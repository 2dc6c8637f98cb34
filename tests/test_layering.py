"""Imports run one way (issue 11, section 7; issue 17, the house)::

    apps (train, evaluate, collect, reproduce, cli, carla_check)
      -> bench | collection | carla_client  ->  sim | model | data  ->  registry

``cicfw.sim`` is the backend interface and the embedded simulator: it imports no benchmark, no dataset
code, no model, and neither the CARLA client nor the collection stage that build on it. ``cicfw.model``
and ``cicfw.data`` import no simulator (and no benchmark). The CARLA client implements sim's interface
and imports no benchmark, dataset or collection code. The collection stage (sim + data) and the CARLA
check (bench + the CARLA client + collection) are imported by apps only.

Every ``import`` and ``from ... import`` in the package is read with ``ast`` (function-level ones
included: a lazy import is still a dependency), so a lower layer reaching up fails here.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

import cicfw

PKG = Path(cicfw.__file__).parent
APPS = ("cicfw.train", "cicfw.evaluate", "cicfw.collect", "cicfw.reproduce", "cicfw.cli", "cicfw.carla_check")
LOWER = ("bench", "sim", "model", "data", "carla_client", "collection")
#: package -> what none of its modules may import
#: (``carla`` is CARLA's own client library: only the CARLA client may import it)
FORBIDDEN = {
    "sim": ("cicfw.bench", "cicfw.data", "cicfw.model", "cicfw.carla_client", "cicfw.collection", "carla"),
    "model": ("cicfw.bench", "cicfw.sim", "cicfw.carla_client", "cicfw.collection", "carla"),
    "data": ("cicfw.bench", "cicfw.sim", "cicfw.carla_client", "cicfw.collection", "carla"),
    "carla_client": ("cicfw.bench", "cicfw.data", "cicfw.model", "cicfw.collection"),
    # the collection stage sits on the simulator interface and the data layer, nothing beside it
    "collection": ("cicfw.bench", "cicfw.model", "cicfw.carla_client", "carla"),
}
#: what only apps may import: the collection stage (an app's engine) and the CARLA check (an app)
APPS_ONLY = ("cicfw.collection", "cicfw.carla_check")


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


def _modules_of(packages) -> list[Path]:
    return sorted(p for sub in packages for p in (PKG / sub).rglob("*.py"))


def forbidden_imports(path: Path, root: Path = PKG.parent) -> list[str]:
    """What ``path`` imports that FORBIDDEN denies its package."""
    package = _module_name(path, root).split(".")[1]
    found = imports_of(path, root)
    return [m for m in FORBIDDEN.get(package, ()) if _reaches(found, m)]


def test_the_checker_sees_an_upward_import(tmp_path):
    bad = tmp_path / "cicfw" / "bench" / "bad.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("def f():\n    from cicfw.evaluate import load_trajectories\n    from .. import train\n")
    found = imports_of(bad, tmp_path)
    assert _reaches(found, "cicfw.evaluate") and _reaches(found, "cicfw.train")


def test_the_checker_sees_the_simulator_reaching_into_the_data_layer(tmp_path):
    for i, line in enumerate(["from cicfw.data.cil_hdf5 import T", "from ..data import cil_hdf5",
                              "import cicfw.data", "from cicfw import data"]):
        bad = tmp_path / "cicfw" / "sim" / f"bad{i}.py"
        bad.parent.mkdir(parents=True, exist_ok=True)
        bad.write_text(f"def f():\n    {line}\n")  # a lazy import is still one
        assert forbidden_imports(bad, tmp_path) == ["cicfw.data"], line
    carla = tmp_path / "cicfw" / "sim" / "carla_inside.py"
    carla.write_text("def f():\n    import carla\n    return carla.Client\n")
    assert forbidden_imports(carla, tmp_path) == ["carla"]  # CARLA's library stays in the CARLA client
    fine = tmp_path / "cicfw" / "sim" / "fine.py"
    fine.write_text("from cicfw.registry import SIM_BACKENDS\nfrom .roadgraph import Route\n")
    assert forbidden_imports(fine, tmp_path) == []


@pytest.mark.parametrize("path", _lower_modules(), ids=lambda p: str(p.relative_to(PKG)))
def test_lower_layers_never_import_an_app(path):
    found = imports_of(path)
    upward = [app for app in APPS if _reaches(found, app)]
    assert not upward, f"{path.relative_to(PKG.parent)} imports the app module(s) {upward}; move the shared code down"


@pytest.mark.parametrize("path", _modules_of(FORBIDDEN), ids=lambda p: str(p.relative_to(PKG)))
def test_each_layer_imports_only_what_it_may(path):
    bad = forbidden_imports(path)
    assert not bad, (f"{path.relative_to(PKG.parent)} imports {bad}, which its layer may not "
                     f"(tests/test_layering.py's docstring draws the layers)")


def test_only_apps_import_the_collection_stage_and_the_carla_check():
    offenders = []
    for path in sorted(PKG.rglob("*.py")):
        name = _module_name(path)
        if name in APPS:
            continue
        found = imports_of(path)
        offenders += [f"{name} imports {target}" for target in APPS_ONLY
                      if _reaches(found, target) and not (name == target or name.startswith(target + "."))]
    assert not offenders, offenders


def test_plots_and_report_do_not_import_each_other():
    plots, report = PKG / "bench" / "plots.py", PKG / "bench" / "report.py"
    assert not _reaches(imports_of(plots), "cicfw.bench.report"), "bench/plots.py imports bench/report.py"
    # report may draw its bar chart with plots, so only one direction is allowed
    assert _reaches(imports_of(report), "cicfw.bench.plots")


def test_registry_is_the_bottom_layer():
    found = imports_of(PKG / "registry.py")
    assert not [m for m in found if m.startswith("cicfw.") and not m.startswith("cicfw.registry")], sorted(found)


def test_the_error_reporter_sits_at_the_bottom():
    """Every app and the simulator's preview use cicfw.errors: it may import the registry only, so using
    it never pulls a layer in by the back door (it once imported the data layer for one exception)."""
    found = imports_of(PKG / "errors.py")
    assert not [m for m in found if m.startswith("cicfw.") and not m.startswith("cicfw.registry")], sorted(found)
