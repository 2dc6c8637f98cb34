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
