"""The surface atlas: texture tiles for facades (windows, shop fronts, floor bands), foliage, bark
and poles, already lit: each facade tile exists at ``SHADE_LEVELS`` sun incidences and in a blurred
far copy, so a surface's colour is one texture lookup (no per-pixel lighting at run time).

Tiles are ``TILE_M`` metres wide and ``TILE_TOP`` metres tall at ``PPM`` pixels per metre, stacked
vertically in one RGBA image one tile wide plus a copy of the first column (so a lookup whose
column is taken modulo TW interpolates across the seam). Alpha is 0 (surfaces are not reflective).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cicfw.sim.render.noise import smooth_noise, stable_seed
from cicfw.sim.render.weather import Weather

PPM = 8.0  # atlas pixels per metre
TILE_M = 6.0  # tile width (m): one to three window bays
TILE_TOP = 40.0  # tile height (m)
FLOOR = 3.2  # m per storey
GROUND_FLOOR = 3.6  # m
SHADE_LEVELS = 9  # sun incidence cos(theta) = 0, 1/8, ..., 1
TW, TH = int(TILE_M * PPM), int(TILE_TOP * PPM)


@dataclass
class Atlas:
    image: np.ndarray  # (n_tiles * TH, TW + 1, 4) uint8 RGBA
    n_facades: int

    def facade(self, i: int, shade: float, far: bool = False) -> int:
        """Tile of facade ``i`` lit at sun incidence ``shade`` (cos, 0-1), near or far copy."""
        q = int(round(float(np.clip(shade, 0, 1)) * (SHADE_LEVELS - 1)))
        return ((i % self.n_facades) * 2 + int(far)) * SHADE_LEVELS + q

    @property
    def foliage(self) -> int:
        return 2 * self.n_facades * SHADE_LEVELS

    @property
    def bark(self) -> int:
        return self.foliage + 1

    @property
    def pole(self) -> int:
        return self.foliage + 2

    @property
    def lamp(self) -> int:
        return self.foliage + 3

    @staticmethod
    def row0(tile: int) -> float:
        """Atlas row (pixel-centre coordinates) of height TILE_TOP (the top) of ``tile``."""
        return tile * TH - 0.5


def _facade_tile(colour: tuple, variant: int, weather: Weather, rng: np.random.Generator) -> np.ndarray:
    """(TH, TW, 3) float32 albedo in 0-1: a wall with windows; ``variant`` picks the window layout."""
    wall = np.asarray(colour, np.float32) / 255
    z = TILE_TOP - (np.arange(TH, dtype=np.float32) + 0.5) / PPM  # height of each row (m)
    s = (np.arange(TW, dtype=np.float32) + 0.5) / PPM
    zz, ss = np.meshgrid(z, s, indexing="ij")
    tex = wall * (1 + 0.06 * smooth_noise((TH, TW), 6, rng)
                  + 0.04 * rng.standard_normal((TH, TW), np.float32))[..., None]
    # a thin darker band at every floor slab and a plinth
    floor_z = np.mod(zz - GROUND_FLOOR, FLOOR)
    band = ((floor_z < 0.18) & (zz > GROUND_FLOOR - 0.1)) | (zz < 0.35)
    tex[band] *= 0.82
    n_win = (2, 3, 2, 1, 3)[variant % 5]
    win_w = (1.3, 1.0, 1.5, 2.4, 0.9)[variant % 5]
    win_h = (1.6, 1.8, 1.4, 1.5, 1.9)[variant % 5]
    bay = TILE_M / n_win
    sb = np.mod(ss, bay) - (bay - win_w) / 2
    fz = floor_z - 0.9  # sill 0.9 m above each floor
    sky = np.asarray(weather.sky_horizon, np.float32)
    glass_base = np.array([0.16, 0.19, 0.23], np.float32) + 0.35 * sky
    upper = (zz > GROUND_FLOOR) & (sb > 0) & (sb < win_w) & (fz > 0) & (fz < win_h)
    frame = (zz > GROUND_FLOOR) & (sb > -0.12) & (sb < win_w + 0.12) & (fz > -0.12) & (fz < win_h + 0.1) & ~upper
    g = np.clip(fz / win_h, 0, 1)[..., None]  # glass: darker low in the pane, sky reflection on top
    glass = glass_base * (0.6 + 0.5 * g)
    tex[frame] = np.minimum(wall * 1.2 + 0.1, 1.0)
    tex[upper] = glass[upper]
    if variant % 2 == 0:  # a shop front with an awning
        shop = (zz > 0.5) & (zz < GROUND_FLOOR - 0.6) & (np.mod(ss, 3.0) > 0.25) & (np.mod(ss, 3.0) < 2.75)
        tex[shop] = glass_base * 0.8
        awning = (zz > GROUND_FLOOR - 0.6) & (zz < GROUND_FLOOR - 0.2)
        tex[awning] = wall * 0.55
    else:  # a plain ground floor with a door
        door = (zz > 0.2) & (zz < 2.3) & (np.abs(ss - TILE_M / 2) < 0.55)
        tex[door] = wall * 0.35
        low = (zz > 1.0) & (zz < 2.4) & (np.abs(np.mod(ss, 3.0) - 0.9) < 0.45) & ~door
        tex[low] = glass_base * 0.9
    return np.clip(tex, 0, 1)


def _saturate(t: np.ndarray, sat: float) -> np.ndarray:
    if sat == 1.0:
        return t
    grey = t.mean(-1, keepdims=True)
    return grey + sat * (t - grey)


def build_atlas(style, weather: Weather) -> Atlas:
    """The lit atlas for a town style under ``weather``."""
    rng = np.random.default_rng(stable_seed("atlas", tuple(map(tuple, style.facades))))
    amb = np.asarray(weather.ambient, np.float32)
    sun = np.asarray(weather.sun, np.float32)
    up = max(np.sin(np.radians(weather.sun_elevation)), 0.3)
    tiles = []
    for i, c in enumerate(style.facades):
        near = _facade_tile(c, i, weather, rng)
        far = cv2.GaussianBlur(near, (0, 0), 0.9 * PPM)  # window detail blurred away: no shimmer far off
        for t in (near, far):
            for q in range(SHADE_LEVELS):
                tiles.append(t * (0.85 * amb + (q / (SHADE_LEVELS - 1)) * sun))
    veg = np.asarray(style.vegetation, np.float32) / 255
    leaf = smooth_noise((TH, TW), 3, rng) + 0.7 * rng.standard_normal((TH, TW), np.float32)
    tiles.append(veg * (1 + 0.22 * leaf)[..., None] * (0.9 * amb + 0.5 * up * sun))
    bark = np.array([0.36, 0.27, 0.20], np.float32) * (1 + 0.15 * smooth_noise((TH, TW), 2, rng))[..., None]
    tiles.append(bark * (0.75 * amb + 0.3 * sun))
    pole = np.asarray(style.pole, np.float32) / 255 * (1 + 0.05 * rng.standard_normal((TH, TW), np.float32))[..., None]
    tiles.append(pole * (0.85 * amb + 0.35 * sun))
    tiles.append(pole * 0.8 * (0.85 * amb + 0.35 * sun))
    img = np.concatenate([_saturate(t, weather.saturation) for t in tiles], axis=0)
    rgba = np.zeros((img.shape[0], TW + 1, 4), np.uint8)
    rgba[:, :TW, :3] = np.clip(img * 255 + 0.5, 0, 255)
    rgba[:, TW] = rgba[:, 0]
    return Atlas(image=rgba, n_facades=len(style.facades))
