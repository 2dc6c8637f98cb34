"""Named weather presets: light (colour, direction), sky and clouds, fog, wet road and rain.

The paper trains under ClearNoon and ClearSunset and tests under MidRainyNoon and WetCloudySunset
(CARLA's names); CloudyNoon and HardRainNoon are two more for wider tests. Colours are linear-ish
RGB in 0-1; ``light`` values multiply the surface albedo.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Colour = tuple[float, float, float]


@dataclass(frozen=True)
class Weather:
    """One preset. Directions: azimuth CCW from east (x), elevation above the horizon, degrees."""

    name: str
    sun_elevation: float
    sun_azimuth: float
    sun: Colour  # direct light on a surface facing the sun
    ambient: Colour  # sky light on an upward surface
    sky_zenith: Colour
    sky_horizon: Colour
    sun_glow: float = 0.0  # strength of the bright halo around the sun near the horizon
    clouds: float = 0.0  # cloud cover 0-1
    cloud_lit: Colour = (1.0, 1.0, 1.0)  # colour of cloud tops facing the sun
    cloud_dark: Colour = (0.6, 0.62, 0.66)  # colour of thick cloud bases
    fog_distance: float = 800.0  # m: fog fraction = 1 - exp(-distance / fog_distance)
    wetness: float = 0.0  # 0 dry .. 1 soaked (darker, reflective road)
    puddles: float = 0.0  # 0-1 extra standing water
    rain: float = 0.0  # 0-1 rain streak density and brightness
    saturation: float = 1.0
    shadow_softness: float = 0.3  # m of penumbra on baked shadows

    @property
    def sun_direction(self) -> np.ndarray:
        """Unit world vector pointing at the sun."""
        el, az = math.radians(self.sun_elevation), math.radians(self.sun_azimuth)
        return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])

    @property
    def fog_colour(self) -> np.ndarray:
        return np.asarray(self.sky_horizon, np.float32)


WEATHERS: dict[str, Weather] = {w.name: w for w in (
    Weather("ClearNoon", sun_elevation=62, sun_azimuth=140, sun=(0.62, 0.60, 0.54),
            ambient=(0.50, 0.53, 0.60), sky_zenith=(0.26, 0.46, 0.82), sky_horizon=(0.72, 0.81, 0.93),
            clouds=0.18, cloud_lit=(1.0, 1.0, 0.98), cloud_dark=(0.80, 0.83, 0.88), fog_distance=700.0),
    Weather("ClearSunset", sun_elevation=7, sun_azimuth=200, sun=(1.05, 0.62, 0.32),
            ambient=(0.40, 0.36, 0.44), sky_zenith=(0.20, 0.26, 0.52), sky_horizon=(0.98, 0.62, 0.40),
            sun_glow=1.0, clouds=0.15, cloud_lit=(1.0, 0.62, 0.40), cloud_dark=(0.45, 0.35, 0.42),
            fog_distance=380.0, saturation=1.1),
    Weather("CloudyNoon", sun_elevation=62, sun_azimuth=140, sun=(0.10, 0.10, 0.10),
            ambient=(0.78, 0.80, 0.84), sky_zenith=(0.52, 0.57, 0.64), sky_horizon=(0.78, 0.80, 0.83),
            clouds=0.85, cloud_lit=(0.93, 0.93, 0.94), cloud_dark=(0.55, 0.57, 0.61), fog_distance=320.0,
            saturation=0.85, shadow_softness=2.0),
    Weather("MidRainyNoon", sun_elevation=62, sun_azimuth=140, sun=(0.0, 0.0, 0.0),
            ambient=(0.62, 0.64, 0.68), sky_zenith=(0.42, 0.44, 0.48), sky_horizon=(0.62, 0.64, 0.67),
            clouds=1.0, cloud_lit=(0.70, 0.71, 0.74), cloud_dark=(0.38, 0.40, 0.44), fog_distance=70.0,
            wetness=0.9, puddles=0.6, rain=0.45, saturation=0.65),
    Weather("HardRainNoon", sun_elevation=62, sun_azimuth=140, sun=(0.0, 0.0, 0.0),
            ambient=(0.50, 0.52, 0.56), sky_zenith=(0.34, 0.36, 0.40), sky_horizon=(0.52, 0.54, 0.57),
            clouds=1.0, cloud_lit=(0.58, 0.59, 0.62), cloud_dark=(0.30, 0.31, 0.35), fog_distance=42.0,
            wetness=1.0, puddles=1.0, rain=1.0, saturation=0.55),
    Weather("WetCloudySunset", sun_elevation=7, sun_azimuth=200, sun=(0.55, 0.34, 0.20),
            ambient=(0.52, 0.45, 0.47), sky_zenith=(0.33, 0.32, 0.39), sky_horizon=(0.86, 0.58, 0.44),
            sun_glow=0.6, clouds=0.75, cloud_lit=(0.95, 0.60, 0.42), cloud_dark=(0.36, 0.31, 0.36),
            fog_distance=160.0, wetness=1.0, puddles=0.8, saturation=0.9, shadow_softness=1.0),
)}

TRAINING_WEATHERS = ("ClearNoon", "ClearSunset")
NEW_WEATHERS = ("MidRainyNoon", "WetCloudySunset")


def get_weather(name: str) -> Weather:
    """The preset called ``name``; an unknown name raises a ValueError listing the known ones."""
    if name not in WEATHERS:
        raise ValueError(f"unknown weather {name!r}; known weathers: {', '.join(WEATHERS)}")
    return WEATHERS[name]
