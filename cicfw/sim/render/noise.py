"""Deterministic value noise for textures (ground, sky, facades): smooth random fields from a seed."""
from __future__ import annotations

import zlib

import cv2
import numpy as np


def stable_seed(*parts: object) -> int:
    """A seed that is the same in every process for the same parts (unlike ``hash``)."""
    return zlib.crc32("/".join(map(str, parts)).encode())


def smooth_noise(shape: tuple[int, int], cell: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 field, about N(0, 0.6), varying over ``cell`` pixels (bicubic upsampled)."""
    h, w = shape
    gh, gw = int(np.ceil(h / cell)) + 3, int(np.ceil(w / cell)) + 3
    g = rng.standard_normal((gh, gw), dtype=np.float32)
    big = cv2.resize(g, (int(round(gw * cell)), int(round(gh * cell))), interpolation=cv2.INTER_CUBIC)
    o = int(round(cell))
    return np.ascontiguousarray(big[o:o + h, o:o + w])


def fbm(shape: tuple[int, int], cell: float, rng: np.random.Generator, octaves: int = 3,
        gain: float = 0.5) -> np.ndarray:
    """Fractal sum of ``octaves`` smooth fields from ``cell`` pixels down, normalised to std ~1."""
    out = np.zeros(shape, np.float32)
    amp = 1.0
    for k in range(octaves):
        out += amp * smooth_noise(shape, max(cell / 2 ** k, 1.0), rng)
        amp *= gain
    out *= 1.0 / max(float(out.std()), 1e-6)
    return out
