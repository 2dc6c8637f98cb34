"""O(1) lookups of where a point is in a town: nearest road, signed offset from its centreline,
inside a junction or not. Used for the off-road / opposite-lane flags of every step.

A raster (0.25 m) holds, per cell, the index of the nearest road-centreline sample (OpenCV's
distance transform with labels) and whether the cell is inside a junction's paved polygon.
"""
from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from cicfw.sim.town import Town


class TownMap:
    RES = 0.25

    def __init__(self, town: Town) -> None:
        self.town = town
        self.hw = town.lane_width
        self.sw = town.sidewalk_width
        x0, y0, x1, y1 = town.bounds
        self.x0, self.y0 = x0, y0
        self.w = int(math.ceil((x1 - x0) / self.RES)) + 1
        self.h = int(math.ceil((y1 - y0) / self.RES)) + 1
        pts = np.vstack([r.centreline for r in town.roads])
        tang = np.vstack([np.gradient(r.centreline, axis=0) for r in town.roads])
        tang /= np.linalg.norm(tang, axis=1, keepdims=True)
        self.pts, self.tang = pts, tang
        px = self._px(pts[:, 0], pts[:, 1])
        src = np.ones((self.h, self.w), np.uint8)
        src[px[1], px[0]] = 0
        _, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        # label k (1-based) belongs to the k-th zero pixel in row-major order
        zy, zx = np.nonzero(src == 0)
        owner = np.full((self.h, self.w), -1, np.int64)
        owner[px[1], px[0]] = np.arange(len(pts))
        lab2sample = np.concatenate([[0], owner[zy, zx]])
        self.nearest = lab2sample[labels].astype(np.int32)
        self.junction = np.zeros((self.h, self.w), np.uint8)
        for j in town.junctions:
            poly = np.round((j.polygon - (x0, y0)) / self.RES).astype(np.int32)
            cv2.fillPoly(self.junction, [poly.reshape(-1, 1, 2)], 1)

    def _px(self, x, y):
        ix = np.clip(np.round((np.asarray(x) - self.x0) / self.RES).astype(np.int64), 0, self.w - 1)
        iy = np.clip(np.round((np.asarray(y) - self.y0) / self.RES).astype(np.int64), 0, self.h - 1)
        return ix, iy

    def query(self, x: float, y: float, yaw: float, half_width: float = 0.9) -> tuple[bool, float, float, float]:
        """(in_junction, opposite-lane fraction, off-road fraction, lateral offset) for a car at (x, y, yaw).

        The offset is signed, positive = left of the centreline in the car's direction of travel (the
        car's own lane centre is at -lane_width/2). Fractions are of the car's width (CIL's targets 14, 15).
        """
        ix, iy = self._px(x, y)
        k = self.nearest[iy, ix]
        in_j = bool(self.junction[iy, ix])
        t = self.tang[k]
        dx, dy = x - self.pts[k, 0], y - self.pts[k, 1]
        d = -t[1] * dx + t[0] * dy  # left of the road's a->b direction
        if t[0] * math.cos(yaw) + t[1] * math.sin(yaw) < 0:
            d = -d
        if in_j:
            return True, 0.0, 0.0, d
        w2 = 2 * half_width
        opp = min(max((d + half_width) / w2, 0.0), 1.0)
        off = min(max((abs(d) + half_width - self.hw) / w2, 0.0), 1.0)
        return False, opp, off, d


@functools.lru_cache(maxsize=8)  # a Town hashes by identity (eq=False)
def town_map(town: Town) -> TownMap:
    """The (cached) TownMap of a town."""
    return TownMap(town)
