"""Named weather presets: light (colour, direction), sky and clouds, fog, wet road and rain.

The paper trains under ClearNoon and ClearSunset and tests under MidRainyNoon and WetCloudySunset
(CARLA's names); CloudyNoon and HardRainNoon are two more for wider tests. Colours are linear-ish
RGB in 0-1; ``light`` values multiply the surface albedo.

The presets come in two families that share the two training presets. ``carla`` (the default) derives
every other preset from CARLA's own parameters for that name by a fixed rule (carla_weather.py).
``harsh`` keeps the hand-set presets every result before the families was driven under: far wetter,
foggier and darker than CARLA's (MidRainyNoon overcast with fog at 70 m, WetCloudySunset soaked with
fog at 160 m), so that those results stay reproducible.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cicfw.core.errors import CicfwError
from cicfw.sim.render.carla_weather import derive_presets

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


CLEAR_NOON = Weather("ClearNoon", sun_elevation=62, sun_azimuth=140, sun=(0.62, 0.60, 0.54),
                     ambient=(0.50, 0.53, 0.60), sky_zenith=(0.26, 0.46, 0.82), sky_horizon=(0.72, 0.81, 0.93),
                     clouds=0.18, cloud_lit=(1.0, 1.0, 0.98), cloud_dark=(0.80, 0.83, 0.88), fog_distance=700.0)
CLEAR_SUNSET = Weather("ClearSunset", sun_elevation=7, sun_azimuth=200, sun=(1.05, 0.62, 0.32),
                       ambient=(0.40, 0.36, 0.44), sky_zenith=(0.20, 0.26, 0.52), sky_horizon=(0.98, 0.62, 0.40),
                       sun_glow=1.0, clouds=0.15, cloud_lit=(1.0, 0.62, 0.40), cloud_dark=(0.45, 0.35, 0.42),
                       fog_distance=380.0, saturation=1.1)

#: the hand-set presets before calibration (every result before weather families was driven under them)
HARSH_WEATHERS: dict[str, Weather] = {w.name: w for w in (
    CLEAR_NOON, CLEAR_SUNSET,
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

#: the same names derived from CARLA's parameters (carla_weather.py); the training presets are shared
CARLA_WEATHERS: dict[str, Weather] = derive_presets({w.name: w for w in (CLEAR_NOON, CLEAR_SUNSET)},
                                                    tuple(HARSH_WEATHERS))
WEATHER_FAMILIES: dict[str, dict[str, Weather]] = {"carla": CARLA_WEATHERS, "harsh": HARSH_WEATHERS}
FAMILY_NOTES = {"carla": "derived from CARLA's presets", "harsh": "the hand-set presets before calibration"}
DEFAULT_FAMILY = "carla"
#: the family of every result driven before the families existed
LEGACY_FAMILY = "harsh"
WEATHERS = WEATHER_FAMILIES[DEFAULT_FAMILY]

TRAINING_WEATHERS = ("ClearNoon", "ClearSunset")
NEW_WEATHERS = ("MidRainyNoon", "WetCloudySunset")


def weather_family(family: str) -> dict[str, Weather]:
    """The presets of ``family``; an unknown family raises a ValueError listing the known ones."""
    if family not in WEATHER_FAMILIES:
        known = ", ".join(f"{k} ({v})" for k, v in FAMILY_NOTES.items())
        raise CicfwError(f"unknown weather family {family!r}; known weather families: {known}", key="weather_family",
                         value=family)
    return WEATHER_FAMILIES[family]


def get_weather(name: str, family: str = DEFAULT_FAMILY) -> Weather:
    """The preset called ``name`` in ``family``; an unknown name raises a ValueError listing the known ones."""
    presets = weather_family(family)
    if name not in presets:
        raise CicfwError(f"unknown weather {name!r}; known weathers: {', '.join(presets)}")
    return presets[name]


def family_data_tag(weathers: list[str] | tuple[str, ...], family: str) -> str | None:
    """``family`` when it renders one of ``weathers`` otherwise than the legacy family, else None: what a
    dataset's hash must add so that data collected before the families keeps its hash."""
    presets, legacy = weather_family(family), WEATHER_FAMILIES[LEGACY_FAMILY]
    changed = [w for w in weathers if w in presets and presets[w] != legacy.get(w)]
    return family if changed else None
