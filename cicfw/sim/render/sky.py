"""Sky panoramas (gradient, sun and glow, a distant tree line, clouds on a flat layer seen in
perspective) and animated rain streaks, both deterministic from a seed.

The panorama is indexed by world azimuth (columns, 0-360 deg, CCW from east) and elevation (rows,
top = ``SKY_TOP`` deg); cameras sample it with a per-pixel map plus their heading, so clouds stay
put in the world while the car turns.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from cicfw.sim.render.noise import smooth_noise
from cicfw.sim.render.weather import Weather

PANO_W = 1024  # 0.35 deg per column (the cameras resolve 0.3-0.7 deg per pixel)
PANO_PAD = 340  # columns repeated on each side, so camera lookups never need wrapping
SKY_TOP, SKY_BOTTOM = 15.0, -1.0  # elevation range of the panorama rows (the cameras see 0.3-13.6 deg)
PANO_H = int((SKY_TOP - SKY_BOTTOM) * 4)  # 0.25 deg per row
CLOUD_HEIGHT = 1500.0  # m
RAIN_PERIOD = 4  # rain texture height in image heights


def _elev_az() -> tuple[np.ndarray, np.ndarray]:
    el = SKY_TOP - (np.arange(PANO_H, dtype=np.float32) + 0.5) * (SKY_TOP - SKY_BOTTOM) / PANO_H
    az = (np.arange(PANO_W, dtype=np.float32) + 0.5) * 360.0 / PANO_W
    return np.meshgrid(el, az, indexing="ij")


def sky_panorama(weather: Weather, vegetation: tuple, seed: int = 0) -> np.ndarray:
    """(PANO_H, PANO_W, 3) float32 RGB in 0-1 for ``weather``, with a distant tree line at the horizon."""
    rng = np.random.default_rng(seed)
    el, az = _elev_az()
    e = np.abs(el)
    zen, hor = np.asarray(weather.sky_zenith, np.float32), np.asarray(weather.sky_horizon, np.float32)
    t = np.clip(e / 35.0, 0, 1) ** 0.55
    sky = hor + t[..., None] * (zen - hor)

    # sun halo (strong at sunset) and the sun disc
    sd = weather.sun_direction
    elr, azr = np.radians(e), np.radians(az)
    dirs = np.stack([np.cos(elr) * np.cos(azr), np.cos(elr) * np.sin(azr), np.sin(elr)], -1)
    cosang = np.clip(dirs @ sd.astype(np.float32), -1, 1)
    ang = np.degrees(np.arccos(cosang))
    sun_col = np.asarray(weather.sun, np.float32)
    sun_rgb = sun_col / max(float(sun_col.max()), 1e-6)
    if weather.sun_glow > 0:
        glow = weather.sun_glow * (0.55 * np.exp(-ang / 25.0) + 0.35 * np.exp(-ang / 6.0)) * np.exp(-e / 18.0)
        sky = sky + glow[..., None] * (np.array([1.0, 0.85, 0.6], np.float32) * sun_rgb - 0.3 * sky)

    # clouds: a noise layer at CLOUD_HEIGHT seen in perspective, hazy towards the horizon
    if weather.clouds > 0:
        n = 512
        cell = 1.0 + 6.0 * (1 - 0.5 * weather.clouds)
        field = smooth_noise((n, n), 8 * cell, rng) + 0.5 * smooth_noise((n, n), 3 * cell, rng) + \
            0.25 * smooth_noise((n, n), cell, rng)
        dist = CLOUD_HEIGHT / np.tan(np.radians(np.maximum(e, 1.5)))
        span = 60000.0  # m covered by the noise image
        mx = (dist * np.cos(azr) / span + 0.5) * n
        my = (dist * np.sin(azr) / span + 0.5) * n
        val = cv2.remap(field, mx.astype(np.float32), my.astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT)
        thr = 1.1 - 2.0 * weather.clouds
        dens = np.clip((val - thr) * 1.3, 0, 1) ** 0.8
        thick = np.clip((val - thr - 0.6) * 0.8, 0, 1)
        lit = np.asarray(weather.cloud_lit, np.float32)
        dark = np.asarray(weather.cloud_dark, np.float32)
        ccol = lit + thick[..., None] * (dark - lit)
        if weather.sun_glow > 0:  # clouds near the sun glow
            ccol = ccol + (0.5 * weather.sun_glow * np.exp(-ang / 20.0))[..., None] * (sun_rgb - 0.5 * ccol)
        haze = np.exp(-e / 4.0)
        a = (dens * (1 - 0.7 * haze))[..., None]
        sky = sky + a * (ccol - sky)

    if weather.sun_elevation > 0 and weather.clouds < 0.7:
        disc = np.clip((0.9 - ang) * 2.0, 0, 1) * (1 - weather.clouds)
        sky = sky + disc[..., None] * (np.array([1.0, 0.97, 0.9], np.float32) - sky)

    # a distant tree line, 0.5-2.2 deg tall, hazed towards the horizon colour
    prof = 1.2 + 0.7 * smooth_noise((1, PANO_W * 3), 10, rng)[0, PANO_W:2 * PANO_W] + \
        0.3 * smooth_noise((1, PANO_W * 3), 2, rng)[0, PANO_W:2 * PANO_W]
    tree = np.clip((np.maximum(prof, 0.4)[None, :] - el) * 4.0, 0, 1)
    veg = np.asarray(vegetation, np.float32) / 255 * np.asarray(weather.ambient, np.float32)
    far = veg + 0.6 * (hor - veg)
    sky = sky + tree[..., None] * (far - sky)
    return np.clip(sky, 0, 1).astype(np.float32)


def rain_streaks(weather: Weather, seed: int, height: int, width: int) -> np.ndarray | None:
    """(RAIN_PERIOD * height, width, 3) uint8 additive streak texture that tiles vertically, or None
    when it does not rain. Cameras slide a window down it with time."""
    if weather.rain <= 0:
        return None
    rng = np.random.default_rng(seed)
    th = RAIN_PERIOD * height
    ss = 2  # draw at twice the resolution, then shrink (soft, anti-aliased streaks)
    img = np.zeros((th * ss, width * ss), np.float32)
    count = int(1000 * weather.rain)
    slant = 0.18
    for _ in range(count):
        x, y = rng.uniform(0, width * ss), rng.uniform(0, th * ss)
        near = rng.random() ** 4  # few big near drops, many thin far ones
        length = (4 + 16 * near) * ss
        bright = (0.2 + 0.4 * rng.random()) * (0.6 + 0.4 * near)
        thick = 1 + int(near * 2.2)
        for dy in (0, -th * ss, th * ss):  # draw wrapped copies so the texture tiles
            p0 = (int((x) * 16), int((y + dy) * 16))
            p1 = (int((x + slant * length) * 16), int((y + dy + length) * 16))
            cv2.line(img, p0, p1, bright, thick, cv2.LINE_AA, 4)
    img = cv2.resize(img, (width, th), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    streak = np.clip(img * (100 * (0.4 + 0.6 * weather.rain)), 0, 255)
    tint = np.array([0.95, 0.97, 1.0], np.float32)
    return np.ascontiguousarray(np.clip(streak[..., None] * tint, 0, 255).astype(np.uint8))


def pano_maps(rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel panorama (column at heading 0, row) for vehicle-local ray directions (H, W, 3)."""
    az = np.degrees(np.arctan2(rays[..., 1], rays[..., 0]))  # CCW, relative to the heading
    el = np.degrees(np.arctan2(rays[..., 2], np.hypot(rays[..., 0], rays[..., 1])))
    mx = az * PANO_W / 360.0 - 0.5
    my = (SKY_TOP - el) * PANO_H / (SKY_TOP - SKY_BOTTOM) - 0.5
    return mx.astype(np.float32), my.astype(np.float32)


def heading_shift(yaw: float) -> float:
    """Panorama columns to add for a vehicle heading ``yaw`` (rad, CCW from east), for a panorama
    padded by ``pad_panorama``."""
    return (math.degrees(yaw) % 360.0) * PANO_W / 360.0 + PANO_PAD


def pad_panorama(pano: np.ndarray) -> np.ndarray:
    """Repeat PANO_PAD columns of the panorama on both sides (lookups stay inside it)."""
    return np.ascontiguousarray(np.concatenate([pano[:, -PANO_PAD:], pano, pano[:, :PANO_PAD]], axis=1))
