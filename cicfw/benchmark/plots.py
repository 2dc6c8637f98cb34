"""Pictures of an evaluation: each town's map with the driven paths coloured by success (one panel
per weather), and a bar chart of the paper's table (success per column, one bar per model)."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from cicfw.benchmark.finished_run import Run, cell_name, table_rows
from cicfw.benchmark.suite import CELLS
from cicfw.core.files import atomic_write
from cicfw.sim.mapplot import draw_town, png_bytes, pyplot as _plt, save_png as _save  # the report's too
from cicfw.sim.town import load_town

SUCCESS, FAILURE = "#1a9850", "#d73027"
REASON_MARKERS = {"off_road": "X", "off_route": "P", "timeout": "s"}


def town_maps(run: Run, trajectories: Mapping[str, Mapping[str, np.ndarray]], out_dir: Path,
              towns: Mapping[str, str] | None = None, town_loader=None) -> list[Path]:
    """``map_<town>.png`` per town of the run: the town drawn from its data, every driven path on it
    (green = reached the goal, red = failed, with a marker where it ended: X off road, + off route,
    square timeout), one panel per weather. ``towns`` maps a row's town name to what the loader takes
    (a path for towns outside conf/town/). Towns the loader cannot draw (e.g. CARLA's) are skipped."""
    if town_loader is None:
        town_loader = load_town
    plt = _plt()
    out = []
    by_town: dict[str, list[dict]] = {}
    for r in run.rows:
        by_town.setdefault(r["town"], []).append(r)
    for town_name, rows in by_town.items():
        try:
            town = town_loader((towns or {}).get(town_name, town_name))
        except (ValueError, OSError):
            continue
        weathers = list(dict.fromkeys(r["weather"] for r in rows))
        ncol = min(len(weathers), 2)
        nrow = (len(weathers) + ncol - 1) // ncol
        x0, y0, x1, y1 = town.bounds
        panel = 8.0  # inches per panel, wide
        fig, axes = plt.subplots(nrow, ncol, squeeze=False, layout="constrained",
                                 figsize=(panel * ncol, nrow * (panel * (y1 - y0) / (x1 - x0) + 0.35) + 0.7))
        for ax, weather in zip(axes.flat, weathers):
            draw_town(ax, town, labels=False)
            sel = [r for r in rows if r["weather"] == weather]
            ok = sum(bool(r["success"]) for r in sel)
            # successes first, failures on top so they stay visible
            for r in sorted(sel, key=lambda r: bool(r["success"]), reverse=True):
                tr = trajectories.get(r["key"])
                if tr is None or len(tr["x"]) == 0:
                    continue
                col = SUCCESS if r["success"] else FAILURE
                xs = np.append(tr["x"], tr["end"][0]) if "end" in tr else tr["x"]
                ys = np.append(tr["y"], tr["end"][1]) if "end" in tr else tr["y"]
                ax.plot(xs, ys, color=col, lw=1.8 if r["success"] else 2.2, alpha=0.8, zorder=7)
                ax.plot(xs[0], ys[0], "o", color=col, ms=3, zorder=8)
                if not r["success"]:
                    ax.plot(xs[-1], ys[-1], REASON_MARKERS.get(r["reason"], "o"), color="k", mfc=FAILURE,
                            ms=7, zorder=9)
            ax.set_title(f"{town_name} · {weather}: {ok}/{len(sel)} reached the goal", fontsize=10)
            ax.set_xticks([])
            ax.set_yticks([])
        for ax in list(axes.flat)[len(weathers):]:
            ax.axis("off")
        from matplotlib.lines import Line2D

        handles = [Line2D([], [], color=SUCCESS, lw=2, label="success"),
                   Line2D([], [], color=FAILURE, lw=2, label="failure")]
        handles += [Line2D([], [], ls="", marker=m, color="k", mfc=FAILURE, label=k.replace("_", " "))
                    for k, m in REASON_MARKERS.items()]
        fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), frameon=False)
        # named as the rows name it (a town file by its stem, whatever its own name: two files may share one)
        fig.suptitle(f"{run.label}: driven paths in {town_name}", fontsize=12)
        out.append(_save(fig, Path(out_dir) / f"map_{town_name}.png"))
    return out


def bar_chart(runs: Sequence[Run], path: Path) -> Path:
    """``bar_chart_png`` written at ``path`` (whole or not at all)."""
    atomic_write(path, bar_chart_png(runs))
    return Path(path)


def bar_chart_png(runs: Sequence[Run]) -> bytes:
    """Grouped bars as PNG bytes: the paper's four columns, one bar per model, success rate in percent;
    bytes, so that a report writes them together with its tables."""
    plt = _plt()
    rows = table_rows(runs)
    n = len(rows)
    width = 0.8 / max(n, 1)
    fig, ax = plt.subplots(figsize=(max(7.0, 1.6 + 1.9 * len(CELLS) * max(n, 1) * 0.35), 4.2))
    cmap = plt.get_cmap("tab10")
    x = np.arange(len(CELLS))
    for k, (label, rates, counts) in enumerate(rows):
        vals = [np.nan if v is None else v for v in rates]
        bars = ax.bar(x - 0.4 + width * (k + 0.5), vals, width * 0.92, label=label, color=cmap(k % 10))
        for b, v, c in zip(bars, rates, counts):
            if v is not None:
                ax.text(b.get_x() + b.get_width() / 2, v + 1, f"{v:.0f}", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(x, [cell_name(*c).replace(" / ", "\n") for c in CELLS])
    ax.set_ylim(0, 109)
    ax.set_ylabel("reach destination success (%)")
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=min(n, 3), frameon=False)
    suites = sorted({run.suite_name() for run in runs})
    ax.set_title(f"Suite: {', '.join(suites)}" + (" (turns only)" if suites == ["single_turn"] else ""))
    return png_bytes(fig)

