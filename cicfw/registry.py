"""One small name -> class registry for every swappable part (encoders, mixers, heads, sim backends).

Built-ins register with a decorator when their package is imported; third-party packages register
through an entry-point group (``cicfw.mixers`` ...), loaded lazily on first lookup. A plugin that
fails to load is reported with a warning naming it and skipped, so the built-ins keep working
(``cicfw.core.hydra_plugins`` does the same for the plugins' Hydra modules).
"""
from __future__ import annotations

import argparse
import importlib
import json
import warnings
from importlib.metadata import PackageNotFoundError, entry_points, version
from typing import Callable, Generic, TypeVar

from hydra import initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from rich.console import Console
from rich.table import Table

from cicfw.core import hydra_plugins
from cicfw.core.errors import CicfwError

T = TypeVar("T")

BUILTIN = "cicfw"


class UnknownNameError(CicfwError, KeyError):
    """An unknown registry name (``value``); the message lists the names that are registered. A ``KeyError``
    too, as a lookup that missed."""

    def __str__(self) -> str:  # KeyError would repr() the message and add quotes
        return str(self.args[0])


class Registry(Generic[T]):
    """Maps names to classes of one kind, e.g. ``MIXERS.get("gtu")``."""

    def __init__(self, kind: str, group: str | None = None, builtins: str | tuple[str, ...] | None = None) -> None:
        self.kind = kind
        self.group = group  # entry-point group third-party packages register under
        # modules whose import registers the built-in entries (one per package that implements the kind)
        self._builtins = (builtins,) if isinstance(builtins, str) else tuple(builtins or ())
        self._entries: dict[str, T] = {}
        self._origin: dict[str, str] = {}
        self._loaded = False
        self.failed: dict[str, str] = {}  # "dist:entry" -> error, for plugins that did not load

    def register(self, name: str, origin: str = BUILTIN) -> Callable[[T], T]:
        """Decorator: ``@MIXERS.register("gtu")``. A name can be registered once."""

        def deco(obj: T) -> T:
            if name in self._entries and self._entries[name] is not obj:
                raise CicfwError(
                    f"{self.kind} name {name!r} is already registered by {self._origin[name]!r}; "
                    f"pick another name (registered: {', '.join(sorted(self._entries))})"
                )
            self._entries[name] = obj
            self._origin[name] = origin
            return obj

        return deco

    def get(self, name: str) -> T:
        self._load()
        if name not in self._entries:
            raise UnknownNameError(
                f"unknown {self.kind} {name!r}; registered {self.kind}s: {', '.join(self.names())}", value=name
            )
        return self._entries[name]

    def names(self) -> list[str]:
        self._load()
        return sorted(self._entries)

    def origin(self, name: str) -> str:
        """The distribution a name came from (``cicfw`` for built-ins)."""
        self.get(name)
        return self._origin[name]

    def __contains__(self, name: str) -> bool:
        self._load()
        return name in self._entries

    def _load(self) -> None:
        if self._loaded:
            return
        self._loaded = True  # set first: plugin modules may import this registry while loading
        for module in self._builtins:
            importlib.import_module(module)
        if self.group:
            for ep in entry_points(group=self.group):
                self._load_entry_point(ep)

    def _load_entry_point(self, ep) -> None:
        dist = ep.dist.name if ep.dist is not None else "?"
        label = f"{dist}:{ep.name}"
        try:
            obj = ep.load()
        except (Exception, SystemExit) as err:  # a broken plugin must not break cicfw
            self.failed[label] = f"{type(err).__name__}: {err}"
            if not any(d == dist for d, _ in hydra_plugins.SKIPPED_HYDRA_MODULES.values()):  # else warned
                warnings.warn(
                    f"cicfw: skipped {self.kind} plugin {ep.name!r} from distribution {dist!r} "
                    f"({ep.value}): it failed to load: {type(err).__name__}: {err}",
                    stacklevel=3,
                )
            return
        if ep.name in self._entries and self._entries[ep.name] is not obj:
            self.failed[label] = f"name {ep.name!r} already registered by {self._origin[ep.name]!r}"
            warnings.warn(
                f"cicfw: skipped {self.kind} plugin {ep.name!r} from distribution {dist!r}: "
                f"the name is already registered by {self._origin[ep.name]!r}",
                stacklevel=3,
            )
            return
        self._entries[ep.name] = obj
        self._origin[ep.name] = dist


ENCODERS: Registry = Registry("encoder", "cicfw.encoders", "cicfw.model.encoders")
MIXERS: Registry = Registry("mixer", "cicfw.mixers", "cicfw.model.mixers")
HEADS: Registry = Registry("head", "cicfw.heads", "cicfw.model.heads")
# the embedded simulator and the CARLA client each register their backend; neither imports the other
SIM_BACKENDS: Registry = Registry("sim backend", "cicfw.sim_backends",
                                  ("cicfw.sim.backends", "cicfw.carla_client.backend"))

ALL = {"encoders": ENCODERS, "mixers": MIXERS, "heads": HEADS, "sim backends": SIM_BACKENDS}

# ---- `python -m cicfw.registry` / `cicfw plugins` ------------------------------------------------

CONFIG_GROUPS = {"encoders": "encoder", "mixers": "mixer", "heads": "head", "sim backends": "sim"}
"""The Hydra config group whose option selects an entry of each registry (``mixer=<name>``)."""


def _version(dist: str) -> str:
    try:
        return version(dist)
    except PackageNotFoundError:
        return "?"


def _config_options() -> dict[str, set[str]]:
    """Options of each config group on cicfw's search path (SearchPathPlugins included)."""
    hydra_plugins.guard_hydra_plugins()
    try:
        with initialize_config_module("cicfw.conf", version_base="1.3"):
            loader = GlobalHydra.instance().config_loader()
            return {g: set(loader.get_group_options(g)) for g in CONFIG_GROUPS.values()}
    except Exception:  # a broken Hydra plugin must not stop the listing
        return {}


def listing() -> tuple[list[tuple[str, str, str, str, str]], list[tuple[str, str, str]]]:
    """Every registered entry as (kind, name, distribution, class, config option) and every
    failure as (kind, plugin, error). Loads all plugins; their warnings are returned as failures."""
    rows, failures = [], []
    options = _config_options()
    for kind, reg in ALL.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # failures are listed below rather than warned twice
            try:
                names = reg.names()
            except Exception as err:
                failures.append((kind, f"cicfw built-ins ({', '.join(reg._builtins)})", f"{type(err).__name__}: {err}"))
                names = sorted(reg._entries)
        group = CONFIG_GROUPS[kind]
        for name in names:
            obj = reg._entries[name]
            dist = reg._origin[name]
            config = f"{group}={name}" if name in options.get(group, ()) else "-"
            rows.append((kind, name, f"{dist} {_version(dist)}",
                         f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', obj)}", config))
        failures += [(kind, label, error) for label, error in reg.failed.items()]
    failures += [("hydra modules", f"{dist}:{name}", error) for name, (dist, error)
                 in hydra_plugins.SKIPPED_HYDRA_MODULES.items()]
    return rows, failures


def as_json(rows: list[tuple[str, str, str, str, str]], failures: list[tuple[str, str, str]]) -> str:
    """The listing as JSON: ``{"registered": [{kind, name, distribution, version, class, config}],
    "failed": [{kind, plugin, error}]}`` (``config`` is null where no config file selects the entry)."""
    registered = []
    for kind, name, dist, cls, config in rows:
        dist_name, _, version = dist.rpartition(" ")
        registered.append({"kind": kind, "name": name, "distribution": dist_name, "version": version,
                           "class": cls, "config": None if config == "-" else config})
    failed = [{"kind": kind, "plugin": plugin, "error": error} for kind, plugin, error in failures]
    return json.dumps({"registered": registered, "failed": failed}, indent=2)


def main(argv: list[str] | None = None) -> int:
    """Print the registered encoders, mixers, heads and sim backends with the distribution each came
    from, and the plugins that failed to load. ``--strict``: exit 1 if any failed. ``--json``: the
    same as JSON on stdout (no table wrapping when piped)."""
    parser = argparse.ArgumentParser(prog="cicfw plugins", description=main.__doc__)
    parser.add_argument("--strict", action="store_true", help="exit with status 1 if a plugin failed to load")
    parser.add_argument("--json", action="store_true", help="print the listing as JSON instead of tables")
    args = parser.parse_args(argv)
    rows, failures = listing()
    if args.json:
        print(as_json(rows, failures))
        return 1 if failures and args.strict else 0
    console = Console()
    table = Table(title="cicfw registry", title_justify="left")
    for col in ("kind", "name", "distribution", "class", "config"):
        table.add_column(col, overflow="fold")
    for row in rows:
        table.add_row(*row)
    console.print(table)
    if failures:
        bad = Table(title="plugins that failed to load (skipped; everything above works)",
                    title_justify="left", title_style="bold red")
        for col in ("kind", "plugin (distribution:entry point)", "error"):
            bad.add_column(col, overflow="fold")
        for row in failures:
            bad.add_row(*row)
        console.print(bad)
    else:
        console.print("no plugin failed to load")
    return 1 if failures and args.strict else 0


if __name__ == "__main__":
    # Run as a script this file is ``__main__``, a second copy of the module: the built-ins register
    # into ``cicfw.registry``'s registries, so list those.
    from cicfw.core.errors import install_app_handlers
    from cicfw.registry import main as _main

    install_app_handlers()
    raise SystemExit(_main())
