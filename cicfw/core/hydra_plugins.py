"""A guard for the plugins' Hydra modules (``hydra_plugins.*``), which Hydra imports when any app starts.

A plugin's module that fails to import would stop every Hydra app; ``guard_hydra_plugins`` imports them first
and hides a failing one from Hydra's scan with one warning naming its distribution, so the rest works.
"""
from __future__ import annotations

import importlib
import pkgutil
import sys
import types
import warnings
from importlib.metadata import distributions

from hydra.core.plugins import Plugins
from hydra.core.singleton import Singleton

#: ``hydra_plugins.*`` modules skipped by ``guard_hydra_plugins``: module -> (distribution, error).
SKIPPED_HYDRA_MODULES: dict[str, tuple[str, str]] = {}


def _distribution_of(module: str, origin: str | None) -> str:
    """The installed distribution whose files hold ``module`` (``hydra_plugins.x`` -> ``x-mixer``);
    else the module's file, so the warning still says where it is."""
    parts = tuple(module.split("."))
    for dist in distributions():
        for f in dist.files or ():
            if tuple(f.parts[: len(parts)]) == parts:
                return dist.metadata["Name"] or "?"
    return f"unknown (not in any installed distribution's file list: {origin or module})"


def guard_hydra_plugins() -> dict[str, tuple[str, str]]:
    """Import every ``hydra_plugins`` module the way Hydra's start-up scan will, before it does.

    Hydra imports all of them when any app starts, and a module whose import raises anything but an
    ``ImportError`` (typically a plugin's SearchPathPlugin importing its own broken package) stops
    every Hydra app. Each module that fails here is hidden from Hydra's scan and reported with one
    warning naming its distribution; the rest of the scan, and cicfw, go on. Call it before the first
    Hydra app or config composition of the process (``cicfw <command>`` and ``python -m cicfw.train``
    do); later calls, once Hydra has scanned, do nothing. Returns the skipped modules."""
    if Plugins in Singleton._instances:
        return {}
    try:
        namespace = importlib.import_module("hydra_plugins")
    except ImportError:
        return {}  # no Hydra plugin installed at all
    broken: dict[str, BaseException] = {}
    where: dict[str, str] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Hydra's own scan reports a plugin's import warnings
        # onerror: a _private package the walk could not import to look inside; Hydra skips it silently too
        for info in pkgutil.walk_packages(namespace.__path__, "hydra_plugins.", lambda name: None):
            last = info.name.rsplit(".", 1)[-1]
            if last.startswith("_") and not last.startswith("__"):
                continue  # Hydra does not import _private modules
            try:
                importlib.import_module(info.name)
            except (Exception, SystemExit) as err:
                broken[info.name] = err
                where[info.name] = f"{getattr(info.module_finder, 'path', '?')}/{last}"
                stub = types.ModuleType(info.name)  # an empty package in its place: the walk does not
                stub.__path__ = []  # type: ignore[attr-defined]  # execute it again to look inside
                sys.modules[info.name] = stub
    if not broken:
        return {}
    for name, err in broken.items():
        dist = _distribution_of(name, where[name])
        if not any(d == dist for d, _ in SKIPPED_HYDRA_MODULES.values()):  # one warning per distribution
            warnings.warn(
                f"cicfw: skipped plugin distribution {dist!r}: its Hydra module {name!r} failed to import "
                f"({type(err).__name__}: {err}); its configs are not available, everything else works",
                stacklevel=2,
            )
        SKIPPED_HYDRA_MODULES[name] = (dist, f"{type(err).__name__}: {err}")
    real_walk = pkgutil.walk_packages

    def walk_without_broken(*args, **kwargs):
        for info in real_walk(*args, **kwargs):
            if info.name not in broken:
                yield info

    pkgutil.walk_packages = walk_without_broken  # only while Hydra scans, below
    try:
        Plugins.instance()  # Hydra's scan, now without the broken modules; every app reuses it
    finally:
        pkgutil.walk_packages = real_walk
        for name in broken:
            if getattr(sys.modules.get(name), "__path__", None) == []:
                del sys.modules[name]
    return dict(SKIPPED_HYDRA_MODULES)
