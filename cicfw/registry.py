"""One small name -> class registry for every swappable part (encoders, mixers, heads, sim backends).

Built-ins register with a decorator when their package is imported; third-party packages register
through an entry-point group (``cicfw.mixers`` ...), loaded lazily on first lookup. A plugin that
fails to load is reported with a warning naming it and skipped, so the built-ins keep working.
"""
from __future__ import annotations

import importlib
import warnings
from importlib.metadata import entry_points
from typing import Callable, Generic, TypeVar

T = TypeVar("T")

BUILTIN = "cicfw"


class UnknownNameError(KeyError):
    """An unknown registry name; the message lists the names that are registered."""

    def __str__(self) -> str:  # KeyError would repr() the message and add quotes
        return str(self.args[0])


class Registry(Generic[T]):
    """Maps names to classes of one kind, e.g. ``MIXERS.get("gtu")``."""

    def __init__(self, kind: str, group: str | None = None, builtins: str | None = None) -> None:
        self.kind = kind
        self.group = group  # entry-point group third-party packages register under
        self._builtins = builtins  # module whose import registers the built-in entries
        self._entries: dict[str, T] = {}
        self._origin: dict[str, str] = {}
        self._loaded = False
        self.failed: dict[str, str] = {}  # "dist:entry" -> error, for plugins that did not load

    def register(self, name: str, origin: str = BUILTIN) -> Callable[[T], T]:
        """Decorator: ``@MIXERS.register("gtu")``. A name can be registered once."""

        def deco(obj: T) -> T:
            if name in self._entries and self._entries[name] is not obj:
                raise ValueError(
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
                f"unknown {self.kind} {name!r}; registered {self.kind}s: {', '.join(self.names())}"
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
        if self._builtins:
            importlib.import_module(self._builtins)
        if self.group:
            for ep in entry_points(group=self.group):
                self._load_entry_point(ep)

    def _load_entry_point(self, ep) -> None:
        dist = ep.dist.name if ep.dist is not None else "?"
        label = f"{dist}:{ep.name}"
        try:
            obj = ep.load()
        except Exception as err:  # a broken plugin must not break cicfw
            self.failed[label] = f"{type(err).__name__}: {err}"
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
SIM_BACKENDS: Registry = Registry("sim backend", "cicfw.sim_backends", "cicfw.sim.backends")

ALL = {"encoders": ENCODERS, "mixers": MIXERS, "heads": HEADS, "sim backends": SIM_BACKENDS}

# ---- `python -m cicfw.registry` / `cicfw plugins` ------------------------------------------------

CONFIG_GROUPS = {"encoders": "encoder", "mixers": "mixer", "heads": "head", "sim backends": "sim"}
"""The Hydra config group whose option selects an entry of each registry (``mixer=<name>``)."""


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "?"


def _config_options() -> dict[str, set[str]]:
    """Options of each config group on cicfw's search path (SearchPathPlugins included)."""
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

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
                failures.append((kind, f"cicfw built-ins ({reg._builtins})", f"{type(err).__name__}: {err}"))
                names = sorted(reg._entries)
        group = CONFIG_GROUPS[kind]
        for name in names:
            obj = reg._entries[name]
            dist = reg._origin[name]
            config = f"{group}={name}" if name in options.get(group, ()) else "-"
            rows.append((kind, name, f"{dist} {_version(dist)}",
                         f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', obj)}", config))
        failures += [(kind, label, error) for label, error in reg.failed.items()]
    return rows, failures


def main(argv: list[str] | None = None) -> int:
    """Print the registered encoders, mixers, heads and sim backends with the distribution each came
    from, and the plugins that failed to load. ``--strict``: exit 1 if any failed."""
    import argparse

    from rich.console import Console
    from rich.table import Table

    parser = argparse.ArgumentParser(prog="cicfw plugins", description=main.__doc__)
    parser.add_argument("--strict", action="store_true", help="exit with status 1 if a plugin failed to load")
    args = parser.parse_args(argv)
    rows, failures = listing()
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
    from cicfw.registry import main as _main

    raise SystemExit(_main())
