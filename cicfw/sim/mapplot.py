"""Top-down map of a town (roads, junctions, buildings, props) with optional routes coloured by command."""
from __future__ import annotations

import io
from pathlib import Path
from typing import Iterable

import numpy as np

from cicfw.core.errors import ConfigError
from cicfw.core.files import atomic_write
from cicfw.sim.town import Town

MAP_FORMATS = ("png", "svg", "pdf")
COMMAND_COLOURS = {2: "#888888", 3: "#1f77b4", 4: "#d62728", 5: "#2ca02c"}  # follow, left, right, straight


def draw_town(ax, town: Town, routes: Iterable = (), labels: bool = True) -> None:
    """Draw ``town`` on a matplotlib axis; ``routes`` are objects with ``.points`` (N, 2) and ``.commands``."""
    from matplotlib.patches import Circle, Polygon

    st = town.style
    rgb = lambda c: tuple(v / 255 for v in c)  # noqa: E731
    ax.set_facecolor(rgb(st.terrain))
    hw, sw = town.lane_width, town.sidewalk_width
    for r in town.roads:
        c = r.centreline
        ax.plot(c[:, 0], c[:, 1], color=rgb(st.sidewalk), lw=0.0)
        for off, col in ((hw + sw, st.sidewalk), (hw, st.road)):
            _band(ax, c, off, rgb(col))
        ax.plot(c[:, 0], c[:, 1], color=rgb(st.centre_line), lw=0.6)
        if labels:
            m = c[len(c) // 2]
            ax.text(m[0], m[1], r.id, fontsize=5, ha="center", va="center", color="k")
    for j in town.junctions:
        ax.add_patch(Polygon(j.polygon, closed=True, fc=rgb(st.road), ec=rgb(st.sidewalk), lw=1.0))
        if labels:
            ax.text(j.centre[0], j.centre[1], j.id, fontsize=7, ha="center", va="center", color="w",
                    weight="bold")
    for b in town.buildings:
        ax.add_patch(Polygon(b.footprint, closed=True, fc=rgb(st.facades[b.facade]), ec="k", lw=0.3))
    for p in town.props:
        col = rgb(st.vegetation) if p.kind == "tree" else rgb(st.pole)
        ax.add_patch(Circle(p.position, max(p.radius, 0.5), fc=col, ec="none"))
    for route in routes:
        pts, cmd = np.asarray(route.points), np.asarray(route.commands)
        for code, col in COMMAND_COLOURS.items():
            m = cmd == code
            ax.scatter(pts[m, 0], pts[m, 1], s=1.5, color=col, zorder=5)
        ax.plot(*pts[0], "o", color="k", ms=3, zorder=6)
        ax.plot(*pts[-1], "*", color="k", ms=5, zorder=6)
    x0, y0, x1, y1 = town.bounds
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")


def _band(ax, c: np.ndarray, off: float, colour) -> None:
    from matplotlib.patches import Polygon

    t = np.gradient(c, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)
    poly = np.vstack([c + n * off, (c - n * off)[::-1]])
    ax.add_patch(Polygon(poly, closed=True, fc=colour, ec="none"))


def pyplot():
    """matplotlib.pyplot on the Agg backend: pictures are files, never windows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def png_bytes(fig, fmt: str = "png") -> bytes:
    """``fig`` as PNG (or ``fmt``) bytes, the figure closed: for a caller that writes several files together."""
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=110, bbox_inches="tight")
    pyplot().close(fig)
    return buf.getvalue()


def save_png(fig, path: Path, fmt: str = "png") -> Path:
    """``fig`` as a PNG (or ``fmt``) at ``path``, written whole or not at all; the figure is closed."""
    atomic_write(path, png_bytes(fig, fmt))
    return path


def save_map(town: Town, path: str | Path, routes: Iterable = (), title: str | None = None,
             size: float = 10.0) -> Path:
    """Write a map of ``town`` (and routes) to ``path``, in the format its suffix names (png, svg or pdf)."""
    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in MAP_FORMATS:  # a file's name must not lie about its bytes
        raise ConfigError("path", str(path), "a file name ending in " + ", ".join("." + f for f in MAP_FORMATS))
    x0, y0, x1, y1 = town.bounds
    fig, ax = pyplot().subplots(figsize=(size, size * (y1 - y0) / (x1 - x0) + 0.4))
    draw_town(ax, town, routes)
    ax.set_title(title or town.name)
    return save_png(fig, path, fmt)
