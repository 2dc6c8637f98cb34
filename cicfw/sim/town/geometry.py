"""Plane geometry for building towns: resampled polylines, rounded corners, cuts at a circle, polygons."""
from __future__ import annotations

import math

import numpy as np

STEP = 0.5  # metres between centreline samples


def unit(v: np.ndarray) -> np.ndarray:
    """``v`` scaled to length 1 (a zero vector stays zero)."""
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def left_normal(v: np.ndarray) -> np.ndarray:
    """``v`` turned 90 degrees counter-clockwise (to the left of a direction of travel)."""
    return np.array([-v[1], v[0]])


def resample(poly: np.ndarray, step: float = STEP) -> np.ndarray:
    """Resample a polyline at (about) ``step`` metres, keeping both end points."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    poly, s = poly[keep], np.concatenate([[0.0], np.cumsum(seg[seg > 1e-9])])
    n = max(int(math.ceil(s[-1] / step)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(t, s, poly[:, 0]), np.interp(t, s, poly[:, 1])], axis=1)


def frames_at(c: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, unit tangents and left normals of polyline ``c`` at arc lengths ``s`` (clipped to its length)."""
    seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.clip(s, 0.0, cum[-1])
    p = np.stack([np.interp(s, cum, c[:, 0]), np.interp(s, cum, c[:, 1])], axis=1)
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(c) - 2)
    t = c[i + 1] - c[i]
    t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
    return p, t, np.stack([-t[:, 1], t[:, 0]], axis=1)


def rounded_polyline(pts: list, radius: float, end_keep: float) -> np.ndarray:
    """A polyline through ``pts`` with each interior corner rounded by an arc of ``radius`` (or less
    where the segments are short; the end segments keep ``end_keep`` metres straight)."""
    out = [pts[0]]
    n = len(pts)
    for i in range(1, n - 1):
        p0, p1, p2 = pts[i - 1], pts[i], pts[i + 1]
        u1, u2 = unit(p1 - p0), unit(p2 - p1)
        cross = u1[0] * u2[1] - u1[1] * u2[0]
        phi = math.atan2(abs(cross), float(np.dot(u1, u2)))  # turn angle
        if phi < 1e-3:
            out.append(p1)
            continue
        l_in, l_out = np.linalg.norm(p1 - p0), np.linalg.norm(p2 - p1)
        lim_in = l_in - end_keep if i == 1 else 0.5 * l_in
        lim_out = l_out - end_keep if i == n - 2 else 0.5 * l_out
        t = min(radius * math.tan(phi / 2), max(lim_in, 0.0), max(lim_out, 0.0))
        r = t / math.tan(phi / 2)
        a0 = p1 - u1 * t
        sign = 1.0 if cross > 0 else -1.0  # left turn: centre on the left
        c = a0 + sign * left_normal(u1) * r
        ang0 = math.atan2(*(a0 - c)[::-1])
        k = max(int(math.ceil(r * phi / 0.1)), 2)
        angs = ang0 + sign * np.linspace(0.0, phi, k + 1)
        out.extend(c + r * np.stack([np.cos(angs), np.sin(angs)], axis=1))
    out.append(pts[-1])
    return np.vstack(out)


def trim_start(poly: np.ndarray, centre: np.ndarray, radius: float) -> tuple[np.ndarray, bool]:
    """Drop the start of ``poly`` inside the circle (centre, radius); the new start lies on the circle."""
    d = np.linalg.norm(poly - centre, axis=1)
    out = np.nonzero(d >= radius)[0]
    if len(out) == 0:
        return poly[-1:], False
    i = int(out[0])
    if i == 0:
        return poly, True
    p, q = poly[i - 1], poly[i]
    # solve |p + t (q - p) - c| = radius for t in [0, 1]
    dvec, f = q - p, p - centre
    a, b, cc = dvec @ dvec, 2 * f @ dvec, f @ f - radius * radius
    disc = max(b * b - 4 * a * cc, 0.0)
    t = (-b + math.sqrt(disc)) / (2 * a)
    start = p + np.clip(t, 0.0, 1.0) * dvec
    return np.vstack([start, poly[i:]]), True


def line_intersection(p: np.ndarray, u: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray | None:
    """Where the lines ``p + t u`` and ``q + s v`` meet; None when they are (nearly) parallel."""
    den = u[0] * v[1] - u[1] * v[0]
    if abs(den) < 1e-6:
        return None
    t = ((q[0] - p[0]) * v[1] - (q[1] - p[1]) * v[0]) / den
    return p + t * u


def polygon_area(poly: np.ndarray) -> float:
    """The signed area (shoelace): positive when the polygon runs counter-clockwise."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def rect(centre: np.ndarray, along: np.ndarray, w: float, d: float) -> np.ndarray:
    """CCW rectangle of width ``w`` along unit ``along`` and depth ``d`` across it."""
    ac = left_normal(along)
    hw, hd = along * (w / 2), ac * (d / 2)
    return np.array([centre - hw - hd, centre + hw - hd, centre + hw + hd, centre - hw + hd])
