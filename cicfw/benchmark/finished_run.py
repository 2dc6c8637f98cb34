"""A finished evaluation run on disk, as the apps, the report and the pictures all read it: the
``Run`` (label, episode rows, metadata), its folder (``episodes.json``, ``trajectories.npz``), the
paper's table cells. It imports nothing from the apps or from the report and plot modules, so every layer
above can share it (apps -> benchmark -> sim/model/data -> registry).
"""
from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from cicfw.benchmark.suite import CELLS
from cicfw.core.errors import CicfwError
from cicfw.core.files import atomic_write

SET_NAMES = {"training": "Training", "new": "New"}


def cell_name(town_set: str, weather_set: str) -> str:
    """``Training town / New weathers`` ..."""
    return f"{SET_NAMES[town_set]} town / {SET_NAMES[weather_set]} weathers"


def cell_key(town_set: str, weather_set: str) -> str:
    """``training_town/new_weathers`` (JSON keys and metric names)."""
    return f"{town_set}_town/{weather_set}_weathers"


@dataclass
class Run:
    """One evaluation run: its label (the table's row name), rows, metadata and folder."""

    label: str
    rows: list[dict[str, Any]]
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def _tally(self, key: Callable[[dict[str, Any]], Any]) -> dict[Any, tuple[int, int]]:
        """key(row) -> (successes, episodes) of the rows, in order of first appearance."""
        out: dict[Any, tuple[int, int]] = {}
        for r in self.rows:
            ok, n = out.get(key(r), (0, 0))
            out[key(r)] = (ok + bool(r["success"]), n + 1)
        return out

    def cells(self) -> dict[tuple[str, str], tuple[int, int]]:
        """(town_set, weather_set) -> (successes, episodes), for the cells this run has."""
        return self._tally(lambda r: (r["town_set"], r["weather_set"]))

    def manoeuvres(self) -> dict[str, tuple[int, int]]:
        """command (left/right/straight) -> (successes, episodes), in that order, for those present."""
        order = {"left": 0, "right": 1, "straight": 2}
        return dict(sorted(self._tally(lambda r: str(r["command"])).items(),
                           key=lambda kv: (order.get(kv[0], 9), kv[0])))

    def suite_name(self) -> str:
        """The suite the run drove (``junctions``, ``single_turn``), from its metadata."""
        suite = self.meta.get("suite") or {}
        return str(suite.get("name", "junctions")) if isinstance(suite, Mapping) else "junctions"

    def success_rate(self) -> float | None:
        """Reach-destination success (%) over the episodes driven; None before any (no episodes, no rate)."""
        if not self.rows:
            return None
        return 100.0 * sum(bool(r["success"]) for r in self.rows) / len(self.rows)


def table_rows(runs: Sequence[Run]) -> list[tuple[str, list[float | None], list[int]]]:
    """Per run: (label, success % per paper column or None, episodes per column)."""
    out = []
    for run in runs:
        cells = run.cells()
        rates = [100.0 * cells[c][0] / cells[c][1] if c in cells else None for c in CELLS]
        out.append((run.label, rates, [cells[c][1] if c in cells else 0 for c in CELLS]))
    return out


def load_run(run_dir: Path) -> Run:
    """A run from its folder (``episodes.json``); a clear error if it is not one."""
    p = Path(run_dir) / "episodes.json"
    try:
        data = json.loads(p.read_text())
        rows, meta = data["episodes"], data.get("meta", {})
        label = meta.get("model") or (rows[0]["model"] if rows else Path(run_dir).name)
    except FileNotFoundError:
        inner = Path(run_dir) / "evaluate"  # a training run's own evaluation (evaluate_after=true)
        hint = f"; its evaluation is in {str(inner)!r}: give that folder" if (inner / "episodes.json").is_file() else ""
        raise FileNotFoundError(f"{str(run_dir)!r} is not an evaluation run folder (no episodes.json){hint}") from None
    except (json.JSONDecodeError, KeyError, TypeError, IndexError) as err:
        raise CicfwError(f"{str(p)!r} is not an evaluation report written by cicfw ({err})") from None
    return Run(label=str(label), rows=rows, meta=meta, path=Path(run_dir))


def save_trajectories(path: Path, rows: Sequence[dict], trajectories: dict) -> None:
    """Every episode's per-step poses, speed, steering and command (``e<index>.<channel>`` arrays)."""
    arrays = {f"e{r['episode']:05d}.{k}": v for r in rows for k, v in trajectories.get(r["key"], {}).items()}
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write(path, buf.getvalue())


def load_trajectories(run_dir: Path) -> dict[str, dict[str, np.ndarray]]:
    """The trajectories of a run folder, keyed by episode key."""
    run = load_run(run_dir)
    keys = {int(r["episode"]): r["key"] for r in run.rows}
    out: dict[str, dict[str, np.ndarray]] = {}
    with np.load(Path(run_dir) / "trajectories.npz") as z:
        for name in z.files:
            ep, ch = name.split(".", 1)
            out.setdefault(keys[int(ep[1:])], {})[ch] = z[name]
    return out
