"""Finding and loading town files: a shipped name (``conf/town/<name>.yaml``) or a path, each file parsed
and built once per version (modification time)."""
from __future__ import annotations

import functools
from importlib import resources
from pathlib import Path

import yaml

from cicfw.sim.town.layout import build_town
from cicfw.sim.town.model import Town, TownError


def _town_dir():
    """The shipped towns' folder (``conf/town``, in the package as ``cicfw.conf/town``)."""
    return resources.files("cicfw.conf") / "town"


def town_names() -> list[str]:
    """Names of the shipped towns (``conf/town/*.yaml``)."""
    return sorted(p.name[:-5] for p in _town_dir().iterdir() if p.name.endswith(".yaml"))


def town_path(name_or_path: str | Path) -> Path:
    """The YAML file of a shipped town name, or the given path; error naming the known towns."""
    s = str(name_or_path)
    if s.endswith((".yaml", ".yml")) or "/" in s or "\\" in s:
        p = Path(s).expanduser()
        if not p.is_file():
            raise TownError(f"town file {s!r} does not exist")
        return p.resolve()
    p = _town_dir() / f"{s}.yaml"
    if not p.is_file():
        raise TownError(
            f"unknown town {s!r}; shipped towns: {', '.join(town_names())} "
            f"(or give a path to a town .yaml file)"
        )
    return Path(str(p)).resolve()


def load_town(name_or_path: str | Path) -> Town:
    """Load, validate and build a town: ``"town_a"``, ``"town_b"`` or a path to a YAML file."""
    p = town_path(name_or_path)
    return _load_cached(str(p), p.stat().st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _load_cached(path: str, _mtime: int) -> Town:
    try:
        spec = yaml.safe_load(Path(path).read_text())
    except yaml.YAMLError as err:
        raise TownError(f"{path}: not valid YAML ({err})") from None
    return build_town(spec, source=path)
