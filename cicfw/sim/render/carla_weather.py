"""CARLA's weather presets, and the fixed rule that derives the embedded simulator's presets from them.

``CARLA_PRESETS`` copies every field of ``carla.WeatherParameters.<name>`` (carla 0.9.16) for the six
presets we render; a test compares it with the installed library. ``derive_presets`` turns them into
our ``Weather`` presets: each moves from its *anchor* (our ClearNoon or ClearSunset, same CARLA sun
altitude) by what CARLA changes, through one rule per parameter fixed by its physical meaning (never by
driving results). docs/simulator.md#weathers gives the rule, parameter by parameter, and its sources
(Kasten & Czeplak 1980 for the light under cloud cover; UE4's exponential height fog for the fog).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

#: every field of carla.WeatherParameters.<name> in the carla 0.9.16 client (floats as the library returns them)
CARLA_PRESETS: dict[str, dict[str, float]] = {
    name: {"cloudiness": cloud, "precipitation": rain, "precipitation_deposits": deposits, "wind_intensity": wind,
           "sun_azimuth_angle": -1.0, "sun_altitude_angle": altitude, "fog_density": fog,
           "fog_distance": 0.75, "fog_falloff": 0.10000000149011612, "wetness": 0.0, "scattering_intensity": 1.0,
           "mie_scattering_scale": 0.029999999329447746, "rayleigh_scattering_scale": 0.03310000151395798,
           "dust_storm": 0.0}
    for name, cloud, rain, deposits, wind, altitude, fog in (
        ("ClearNoon", 5.0, 0.0, 0.0, 10.0, 45.0, 2.0),
        ("ClearSunset", 5.0, 0.0, 0.0, 10.0, 15.0, 2.0),
        ("CloudyNoon", 60.0, 0.0, 0.0, 10.0, 45.0, 3.0),
        ("MidRainyNoon", 60.0, 60.0, 60.0, 60.0, 45.0, 3.0),
        ("HardRainNoon", 100.0, 100.0, 90.0, 100.0, 45.0, 7.0),
        ("WetCloudySunset", 60.0, 0.0, 50.0, 10.0, 15.0, 2.0),
    )
}
#: our hand-set clear presets: the rule's fixed points (each derives to itself)
ANCHORS = ("ClearNoon", "ClearSunset")
#: CARLA fields our renderer has no counterpart for: the rule needs them equal to the anchor's
MUST_MATCH = ("fog_distance", "fog_falloff", "scattering_intensity", "mie_scattering_scale",
              "rayleigh_scattering_scale", "dust_storm")
#: Kasten & Czeplak (1980): g(n) = 1 - KC_GLOBAL n^KC_POWER, diffuse fraction f(n) = KC_DIFFUSE0 + KC_DIFFUSE2 n^2
KC_GLOBAL, KC_POWER, KC_DIFFUSE0, KC_DIFFUSE2 = 0.75, 3.4, 0.3, 0.7
#: extinction per metre per unit of CARLA fog_density (UE4 exponential height fog, horizontal ray)
FOG_EXTINCTION = math.log(2.0) ** 2 / 1000.0
LUMA = (0.2126, 0.7152, 0.0722)  # Rec. 709


def global_light(n: float) -> float:
    """Global horizontal irradiance under cloud cover ``n`` (0-1), relative to a clear sky."""
    return 1.0 - KC_GLOBAL * n ** KC_POWER


def diffuse_fraction(n: float) -> float:
    """The diffuse share of the global irradiance under cloud cover ``n``."""
    return KC_DIFFUSE0 + KC_DIFFUSE2 * n * n


def beam_light(n: float) -> float:
    """The direct (beam) horizontal irradiance under cloud cover ``n``, relative to a clear sky's global."""
    return global_light(n) * (1.0 - diffuse_fraction(n))


def luminance(colour: tuple[float, float, float]) -> float:
    return sum(w * c for w, c in zip(LUMA, colour))


def grey(colour: tuple[float, float, float], s: float) -> tuple[float, float, float]:
    """``colour`` moved toward its own luminance by ``s`` (0: unchanged, 1: grey)."""
    lum = luminance(colour)
    return tuple(lum + (c - lum) * (1.0 - s) for c in colour)


def scaled(colour: tuple[float, float, float], k: float, clip: bool = False) -> tuple[float, float, float]:
    """``colour`` x ``k``, clipped to 0-1 when it is a displayed colour (sky, clouds), not a light."""
    out = tuple(c * k for c in colour)
    return tuple(min(max(c, 0.0), 1.0) for c in out) if clip else out


def anchor_of(name: str, anchors: Mapping[str, Any] | tuple = ANCHORS) -> str:
    """The anchor with the CARLA sun altitude of preset ``name`` (one, or a ValueError)."""
    alt = CARLA_PRESETS[name]["sun_altitude_angle"]
    found = [a for a in anchors if CARLA_PRESETS[a]["sun_altitude_angle"] == alt]
    if len(found) != 1:
        raise ValueError(f"weather {name!r}: the rule needs exactly one anchor with CARLA's sun altitude {alt}, "
                         f"found {found or 'none'} among {', '.join(anchors)}")
    return found[0]


def light_factors(anchor: Any, n: float, n0: float) -> tuple[float, float]:
    """(r_sun, r_amb): how cloud cover ``n`` scales the anchor's (cover ``n0``) direct and ambient light."""
    r_sun = beam_light(n) / beam_light(n0)
    a_amb = luminance(anchor.ambient)
    a_sun = luminance(anchor.sun) * max(math.sin(math.radians(anchor.sun_elevation)), 0.0)
    total = (a_amb + a_sun) * global_light(n) / global_light(n0)
    return r_sun, (total - a_sun * r_sun) / a_amb


def fog_distance(anchor_distance: float, rho: float, rho0: float) -> float:
    """Our fog distance (m) for CARLA fog density ``rho``, from the anchor's distance at ``rho0``."""
    return 1.0 / (1.0 / anchor_distance + FOG_EXTINCTION * (rho - rho0))


def check_comparable(name: str, target: Mapping[str, float], base: Mapping[str, float]) -> None:
    """A ValueError when a CARLA field the renderer has no counterpart for differs from the anchor's."""
    for k in MUST_MATCH:
        if target[k] != base[k]:
            raise ValueError(f"weather {name!r}: CARLA's {k} is {target[k]}, the anchor's {base[k]}; the rule "
                             f"has no counterpart for it and needs them equal")


def derive(name: str, anchor: Any, target: Mapping[str, float], base: Mapping[str, float]) -> Any:
    """Preset ``name`` from ``anchor`` (our Weather) and CARLA's ``target`` and anchor (``base``) fields."""
    check_comparable(name, target, base)
    n, n0 = target["cloudiness"] / 100.0, base["cloudiness"] / 100.0
    s = (n - n0) / (1.0 - n0)
    r_sun, r_amb = light_factors(anchor, n, n0)
    dark = scaled(grey(anchor.cloud_dark, s), r_amb, clip=True)
    lit = tuple(min(max(d + (lt - dk) * r_sun, 0.0), 1.0)
                for d, lt, dk in zip(dark, anchor.cloud_lit, anchor.cloud_dark))
    deposits, wet = target["precipitation_deposits"] / 100.0, target["wetness"] / 100.0
    return dataclasses.replace(
        anchor, name=name,
        sun_elevation=anchor.sun_elevation + target["sun_altitude_angle"] - base["sun_altitude_angle"],
        sun_azimuth=anchor.sun_azimuth + target["sun_azimuth_angle"] - base["sun_azimuth_angle"],
        clouds=anchor.clouds + (n - n0) * (1.0 - anchor.clouds) / (1.0 - n0),
        sun=scaled(anchor.sun, r_sun), ambient=scaled(grey(anchor.ambient, s), r_amb),
        sky_zenith=scaled(grey(anchor.sky_zenith, s), r_amb, clip=True),
        sky_horizon=scaled(grey(anchor.sky_horizon, s), r_amb, clip=True),
        cloud_dark=dark, cloud_lit=lit, sun_glow=anchor.sun_glow * r_sun,
        fog_distance=fog_distance(anchor.fog_distance, target["fog_density"], base["fog_density"]),
        rain=target["precipitation"] / 100.0, wetness=max(deposits, wet), puddles=deposits)


def derive_presets(anchors: Mapping[str, Any], names: tuple[str, ...] | list[str]) -> dict[str, Any]:
    """Our preset for each of ``names``: an anchor as it is, every other derived from its anchor."""
    out = {}
    for name in names:
        if name in anchors:
            out[name] = anchors[name]
            continue
        a = anchor_of(name, tuple(anchors))
        out[name] = derive(name, anchors[a], CARLA_PRESETS[name], CARLA_PRESETS[a])
    return out
