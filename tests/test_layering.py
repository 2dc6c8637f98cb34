"""Imports run one way, and every module of the package has its place in it::

    apps (each feature package's app, schema and __main__ modules, cli, testing, the entry modules
          evaluate.py and reproduce.py, carla_client.check)
      -> feature libraries (benchmark | reproduction | collect | carla_client | diagnose)
      -> sim | model | data | export.agent
      -> registry
      -> core

A module imports its own layer and those below, never one above, and no module imports itself back
through others (no circle). ``cicfw.export.agent`` is the model's inference path (a checkpoint or an
exported model in, steering out): it sits with the model, and the benchmark's checkpoint policy and the
export app build on it. ``cicfw.reproduction`` (a reproduction's lock, statistics and report) builds on the
benchmark, never the other way. A feature package's config schema is its ``schema`` subpackage, which Hydra's
``pkg://cicfw.<package>.schema`` search path imports when it composes that app's config. No
module imports an app (``cicfw.<package>.app``) but the entry points (cli, the entry modules, a package's
``__main__`` and schema) and the apps that run other apps (``APP_USERS``). A new module must be placed in
``LAYER_OF`` (a package entry places all of its modules; a more precise entry wins). The registry builds on
core (its errors, the guard of the plugins' Hydra modules); core imports no registry.

``cicfw.sim`` is the backend interface and the embedded simulator: it imports no benchmark, no dataset
code, no model, and neither the CARLA client nor the collection stage that build on it. ``cicfw.model``
and ``cicfw.data`` import no simulator (and no benchmark). The CARLA client implements sim's interface
and imports no benchmark, dataset or collection code. The collection stage (sim + data) and the CARLA
check (benchmark + the CARLA client + collection) are imported by apps only. ``FORBIDDEN`` holds a
package's library modules to this; its app modules are apps.

Every ``import`` and ``from ... import`` in the package is read with ``ast`` (function-level ones
included: a lazy import is still a dependency), so a lower layer reaching up fails here.

Imports sit at the top of their module. A function imports only what ``LAZY_ANYWHERE`` and ``LAZY_IN`` name:
an optional extra (CARLA, ONNX, Optuna, submitit) or a heavy library that one rarely used path needs
(matplotlib); a circle that importing at the top would make is the real problem: move the function to the
module it belongs in.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

import cicfw

PKG = Path(cicfw.__file__).parent
#: the feature packages: each holds its library, and its app modules (``app``, ``schema``, ``__main__``)
FEATURES = ("train", "collect", "benchmark", "export", "reproduction", "diagnose", "carla_client")
#: the apps: the feature packages' app modules, the console script, the entry modules and the plugin checks
APPS = ("cicfw.train", "cicfw.cli", "cicfw.testing", "cicfw.evaluate", "cicfw.reproduce", "cicfw.carla_client.check",
        *(f"cicfw.{f}.{m}" for f in FEATURES for m in ("app", "schema", "__main__")))
#: the layers, lowest first
LAYERS = ("base", "lib", "feature", "app")
#: module or package -> its layer (a package places every module under it)
LAYER_OF = {
    "cicfw": "base", "cicfw.registry": "base", "cicfw.core": "base",
    "cicfw.sim": "lib", "cicfw.model": "lib", "cicfw.data": "lib", "cicfw.export.agent": "lib",
    "cicfw.benchmark": "feature", "cicfw.reproduction": "feature", "cicfw.collect": "feature",
    "cicfw.carla_client": "feature", "cicfw.diagnose": "feature",
    "cicfw.export": "app",  # its __init__ (which registers the schema), app and schema; its agent is "lib"
    **{app: "app" for app in APPS},
}
#: package -> what none of its library modules may import
#: (``carla`` is CARLA's own client library: only the CARLA client may import it)
BENCH = ("cicfw.benchmark", "cicfw.reproduction")
FORBIDDEN = {
    "sim": (*BENCH, "cicfw.data", "cicfw.model", "cicfw.export", "cicfw.carla_client", "cicfw.collect", "carla"),
    "model": (*BENCH, "cicfw.sim", "cicfw.carla_client", "cicfw.collect", "carla"),
    "data": (*BENCH, "cicfw.sim", "cicfw.carla_client", "cicfw.collect", "carla"),
    "carla_client": (*BENCH, "cicfw.data", "cicfw.model", "cicfw.collect"),
    # the collection stage sits on the simulator interface and the data layer, nothing beside it
    "collect": (*BENCH, "cicfw.model", "cicfw.carla_client", "carla"),
    # the agent runs the model: no simulator, dataset or benchmark code
    "export": (*BENCH, "cicfw.sim", "cicfw.data", "cicfw.carla_client", "cicfw.collect", "carla"),
    # the benchmark drives and reports runs; a reproduction builds on it, never the other way
    "benchmark": ("cicfw.reproduction", "cicfw.diagnose"),
    # what every app shares sits under the registry, which raises its errors and lists its plugins
    "core": ("cicfw.registry",),
}
#: what only apps may import: the collection stage (an app's engine) and the CARLA check (an app)
APPS_ONLY = ("cicfw.collect", "cicfw.carla_client.check")
#: the apps that run another app: a reproduction trains and evaluates its cells, ``evaluate_after=true``
#: evaluates the trained model through the evaluate app, ``cicfw.testing.fast_dev_run`` trains through the
#: train app
APP_USERS = ("cicfw.reproduction.app", "cicfw.train.app", "cicfw.testing")
#: the most entries the top level of the package holds besides ``__init__.py`` (DESIGN's "Layout")
TOP_LEVEL_MAX = 16
#: what a function may import rather than its module's top: an optional extra or a heavy library only one
#: rarely used path needs (the first name of the imported module)
LAZY_ANYWHERE = ("carla", "onnx", "onnxruntime", "optuna", "submitit", "matplotlib")
#: module -> what it alone may import in a function, beside LAZY_ANYWHERE
LAZY_IN = {
    # the error family is what an entry point imports before it installs its signal handlers: it stays
    # stdlib-only at its top, and asks Hydra whether this is a multirun only when an error is reported
    "cicfw.core.errors": ("hydra",),
    # the console script installs its signal handlers before it imports Hydra (through the guard)
    "cicfw.cli": ("cicfw.core.hydra_plugins",),
    # the compiler stack: seconds to import, needed only when a run compiles its model
    "cicfw.model.speed": ("torch._inductor", "torch._dynamo"),
    # torch's ONNX exporter's private constants, whose absence (a torch that moved them) is handled
    "cicfw.export.app": ("torch.onnx",),
    # the run folder's owner check asks Lightning whether this is SLURM only when the folder holds an HPC
    # checkpoint: at the top it would load torch into every app that claims a folder (collect has none)
    "cicfw.core.slurm_requeue": ("lightning",),
}


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


def function_imports(path: Path, root: Path = PKG.parent) -> list[tuple[int, str]]:
    """(line, module) of each import inside a function of ``path``, relative imports resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    name = _module_name(path, root)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.Import):
                found += [(node.lineno, a.name) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)] if node.level else []
                found.append((node.lineno, ".".join(base + ([node.module] if node.module else []))))
    return sorted(set(found))


def lazy_imports_not_allowed(path: Path, root: Path = PKG.parent) -> list[str]:
    """The imports inside functions of ``path`` that LAZY_ANYWHERE and LAZY_IN do not allow."""
    allowed = LAZY_ANYWHERE + LAZY_IN.get(_module_name(path, root), ())
    return [f"line {line}: {mod}" for line, mod in function_imports(path, root) if not _reaches({mod}, allowed)]


def _reaches(imported: set[str], target: str | tuple[str, ...]) -> bool:
    """Whether a module in ``imported`` is ``target`` (or one of them) or one of its submodules."""
    targets = (target,) if isinstance(target, str) else target
    return any(m == t or m.startswith(t + ".") for m in imported for t in targets)


def _modules_of(names) -> list[Path]:
    """The files of each top-level package (every module under it) or module named in ``names``."""
    return sorted(p for sub in names for p in ((PKG / sub).rglob("*.py") if (PKG / sub).is_dir()
                                               else [PKG / f"{sub}.py"]))


def layer_of(name: str) -> str | None:
    """The layer of module ``name``: its own entry in LAYER_OF or its nearest package's; None if unplaced."""
    while name not in LAYER_OF and name.count(".") > 1:
        name = name.rsplit(".", 1)[0]
    return LAYER_OF.get(name)


def upward_imports(path: Path, root: Path = PKG.parent) -> list[str]:
    """The cicfw modules ``path`` imports from a layer above its own."""
    name = _module_name(path, root)
    rank = LAYERS.index(layer_of(name))
    return sorted(m for m in imports_of(path, root) if m.startswith("cicfw.") and m != name
                  and layer_of(m) is not None and LAYERS.index(layer_of(m)) > rank)


def module_graph(root: Path = PKG.parent) -> dict[str, set[str]]:
    """module -> the package modules it imports (``from pkg import sub`` counts as ``pkg.sub``; a module's
    own parent packages are left out: importing a submodule always runs them, which is no circle)."""
    files = {_module_name(p, root): p for p in (root / "cicfw").rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        deps = set()
        for m in imports_of(path, root):
            if m not in files and m.rsplit(".", 1)[0] in files:
                continue  # a name imported from a module (its module is in the set too)
            while m and m not in files:
                m = m.rsplit(".", 1)[0] if "." in m else ""
            if m and m != name and not name.startswith(m + "."):
                deps.add(m)
        graph[name] = deps
    return _without_package_edges(graph)


def _without_package_edges(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """Drop ``pkg`` when a module imports ``pkg.sub`` from it too (``from pkg import sub``)."""
    return {n: {d for d in deps if not any(o.startswith(d + ".") for o in deps)} for n, deps in graph.items()}


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Each set of modules that import each other round a circle (Tarjan's strongly connected components)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while part[-1:] != [v]:
                part.append(stack.pop())
            if len(part) > 1:
                circles.append(sorted(part))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return circles


def forbidden_imports(path: Path, root: Path = PKG.parent) -> list[str]:
    """What ``path`` imports that FORBIDDEN denies its package's library modules (its apps are apps)."""
    name = _module_name(path, root)
    if layer_of(name) == "app":
        return []
    package = name.split(".")[1]
    found = imports_of(path, root)
    return [m for m in FORBIDDEN.get(package, ()) if _reaches(found, m)]


def test_the_checker_sees_an_upward_import(tmp_path):
    bad = tmp_path / "cicfw" / "benchmark" / "bad.py"
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


def test_the_checker_sees_core_reaching_up_to_the_registry(tmp_path):
    bad = tmp_path / "cicfw" / "core" / "bad.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("def f():\n    from cicfw.registry import MIXERS\n")
    assert forbidden_imports(bad, tmp_path) == ["cicfw.registry"]


def test_every_module_has_a_layer():
    unplaced = [_module_name(p) for p in sorted(PKG.rglob("*.py")) if layer_of(_module_name(p)) is None]
    assert not unplaced, (f"{unplaced}: place each new module in its layer (LAYER_OF in tests/test_layering.py; "
                          f"its docstring draws the layers)")


def test_the_checker_refuses_an_unplaced_module_and_an_upward_import(tmp_path):
    assert layer_of("cicfw.brand_new") is None and layer_of("cicfw.benchmark.brand_new") == "feature"
    assert layer_of("cicfw.reproduction.cells") == "feature" and layer_of("cicfw.reproduction.app") == "app"
    assert layer_of("cicfw.export.agent") == "lib" and layer_of("cicfw.export.app") == "app"
    assert layer_of("cicfw.core.files") == "base" and layer_of("cicfw.benchmark.schema") == "app"
    bad = tmp_path / "cicfw" / "export" / "agent.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("def f():\n    from cicfw.benchmark.checkpoint_policy import CheckpointPolicy\n"
                   "    from cicfw.core import files\n")
    assert upward_imports(bad, tmp_path) == ["cicfw.benchmark.checkpoint_policy",
                                             "cicfw.benchmark.checkpoint_policy.CheckpointPolicy"]


@pytest.mark.parametrize("path", sorted(PKG.rglob("*.py")), ids=lambda p: str(p.relative_to(PKG)))
def test_each_module_imports_only_its_layer_and_below(path):
    if layer_of(_module_name(path)) is None:
        pytest.skip("unplaced: test_every_module_has_a_layer says so")
    up = upward_imports(path)
    assert not up, (f"{path.relative_to(PKG.parent)} ({layer_of(_module_name(path))}) imports {up} from a higher "
                    f"layer; move the shared code down (tests/test_layering.py's docstring draws the layers)")


def test_the_checker_finds_a_circle_but_not_a_package_importing_its_submodule(tmp_path):
    pkg = tmp_path / "cicfw"
    (pkg / "benchmark").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "benchmark" / "__init__.py").write_text("from cicfw.benchmark.a import A\n")
    (pkg / "benchmark" / "a.py").write_text("from cicfw.benchmark import b\nA = 1\n")
    (pkg / "benchmark" / "b.py").write_text("B = 2\n")
    assert import_circles(module_graph(tmp_path)) == []
    (pkg / "benchmark" / "b.py").write_text("def f():\n    from cicfw.benchmark.a import A\n")
    assert import_circles(module_graph(tmp_path)) == [["cicfw.benchmark.a", "cicfw.benchmark.b"]]


def test_no_import_circle():
    circles = import_circles(module_graph())
    assert not circles, f"modules that import each other (lazily or not): {circles}; move the shared piece down"


@pytest.mark.parametrize("path", _modules_of(FORBIDDEN), ids=lambda p: str(p.relative_to(PKG)))
def test_each_layer_imports_only_what_it_may(path):
    bad = forbidden_imports(path)
    assert not bad, (f"{path.relative_to(PKG.parent)} imports {bad}, which its layer may not "
                     f"(tests/test_layering.py's docstring draws the layers)")


def test_only_apps_import_the_collection_stage_and_the_carla_check():
    offenders = []
    for path in sorted(PKG.rglob("*.py")):
        name = _module_name(path)
        if layer_of(name) == "app" or (path.name == "__init__.py" and name in APPS_ONLY):
            continue
        found = imports_of(path)
        offenders += [f"{name} imports {target}" for target in APPS_ONLY
                      if _reaches(found, target) and not (name == target or name.startswith(target + "."))]
    assert not offenders, offenders


def test_plots_and_report_do_not_import_each_other():
    plots, report = PKG / "benchmark" / "plots.py", PKG / "benchmark" / "evaluation_report.py"
    assert not _reaches(imports_of(plots), "cicfw.benchmark.evaluation_report"), \
        "benchmark/plots.py imports benchmark/evaluation_report.py"
    # report may draw its bar chart with plots, so only one direction is allowed
    assert _reaches(imports_of(report), "cicfw.benchmark.plots")


def test_registry_sits_just_above_core():
    """The registry imports the error family (its unknown name is a user error) and the guard of the plugins'
    Hydra modules (it lists what the guard skipped), and nothing else of cicfw."""
    found = imports_of(PKG / "registry.py")
    allowed = ("cicfw.registry", "cicfw.core.errors", "cicfw.core.hydra_plugins")
    assert not [m for m in found if m.startswith("cicfw.") and m != "cicfw.core" and not m.startswith(allowed)], \
        sorted(found)


def test_the_error_family_sits_at_the_bottom():
    """Every module may raise a CicfwError: cicfw.core.errors imports nothing of cicfw, so using it never pulls
    a layer in by the back door."""
    found = imports_of(PKG / "core" / "errors.py")
    assert not [m for m in found if m.startswith("cicfw.")], sorted(found)


def app_imports(path: Path, root: Path = PKG.parent) -> list[str]:
    """The apps (``cicfw.<package>.app``) ``path`` imports that it may not: only the entry points (cli, the
    entry modules, a package's ``__main__``, and its ``schema`` its own app) and ``APP_USERS`` may."""
    name = _module_name(path, root)
    if name in ("cicfw.cli", "cicfw.evaluate", "cicfw.reproduce") or name in APP_USERS or name.endswith(".__main__"):
        return []
    package = name.rsplit(".", 1)[0] if name.endswith(".schema") else None
    return sorted({a for m in imports_of(path, root) if m.startswith("cicfw.")
                   for a in [".".join(m.split(".")[:3])] if a.endswith(".app") and a.count(".") == 2
                   and a != name and a != f"{package}.app"})


def test_the_checker_sees_an_app_importing_another_app(tmp_path):
    bad = tmp_path / "cicfw" / "diagnose" / "app.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("def f():\n    from cicfw.reproduction.app import row_overrides\n")
    assert app_imports(bad, tmp_path) == ["cicfw.reproduction.app"]
    schema = tmp_path / "cicfw" / "export" / "schema.py"
    schema.parent.mkdir(parents=True)
    schema.write_text("from cicfw.export.app import export_model\n")
    assert app_imports(schema, tmp_path) == []  # a schema taken from its own app's signature
    main = tmp_path / "cicfw" / "train" / "__main__.py"
    main.parent.mkdir(parents=True)
    main.write_text("from cicfw.train.app import main\n")
    assert app_imports(main, tmp_path) == []


@pytest.mark.parametrize("path", sorted(PKG.rglob("*.py")), ids=lambda p: str(p.relative_to(PKG)))
def test_no_module_imports_an_app_but_the_entry_points(path):
    bad = app_imports(path)
    assert not bad, (f"{path.relative_to(PKG.parent)} imports {bad}: move what it needs out of the app into its "
                     f"package's library (tests/test_layering.py's docstring draws the layers)")


def test_the_top_level_of_the_package_stays_small():
    entries = sorted(p.name for p in PKG.iterdir() if p.name not in ("__init__.py", "__pycache__"))
    assert len(entries) <= TOP_LEVEL_MAX, (f"cicfw/ holds {len(entries)} entries besides __init__.py: {entries}; "
                                           f"put a new module in its feature package (CONTRIBUTING.md's Layout)")


def test_the_checker_sees_a_function_importing_what_belongs_at_the_top(tmp_path):
    plots = tmp_path / "cicfw" / "benchmark" / "plots.py"
    plots.parent.mkdir(parents=True)
    plots.write_text("import json\n\ndef f():\n    import matplotlib.pyplot as plt\n    from .suite import town_label\n"
                     "    class A:\n        def g(self):\n            import torch\n")
    assert lazy_imports_not_allowed(plots, tmp_path) == ["line 5: cicfw.benchmark.suite", "line 8: torch"]


@pytest.mark.parametrize("path", sorted(PKG.rglob("*.py")), ids=lambda p: str(p.relative_to(PKG)))
def test_functions_import_only_optional_or_rarely_needed_heavy_libraries(path):
    bad = lazy_imports_not_allowed(path)
    assert not bad, (f"{path.relative_to(PKG.parent)} imports {bad} inside a function: import it at the module's "
                     f"top (a circle that makes is the real problem: move the function where it belongs); "
                     f"only LAZY_ANYWHERE and LAZY_IN in tests/test_layering.py may be imported lazily")
