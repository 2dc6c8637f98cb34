"""The expert driver (pure pursuit on the route's lane centre, speed profile slowing for turns) and
CIL's steering-noise injection.

The expert never looks at images, so weather does not change what it does. Its steering is the label;
the noise is added on top of it only for what the car actually does (``Noiser``).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from cicfw.core.errors import CicfwError, ConfigError
from cicfw.sim.roadgraph import Route
from cicfw.sim.vehicle import DT, TOP_SPEED_KMH, VehicleParams, VehicleState


#: what each value must be: key -> (lowest, whether the lowest itself is allowed, unit)
_BOUNDS = {"cruise_kmh": (0.0, False, "km/h"), "lateral_accel": (0.0, False, "m/s^2"), "min_kmh": (0.0, False, "km/h"),
           "decel": (0.0, False, "m/s^2"), "lookahead_min": (0.0, False, "m"), "lookahead_base": (0.0, True, "m"),
           "lookahead_gain": (0.0, True, "s"), "lookahead_max": (0.0, False, "m")}


@dataclass
class ExpertParams:
    """The expert's driving values; a value it cannot drive with (a negative speed, a look-ahead of 0 that
    steers +-1 bang-bang) is a ValueError naming ``expert.<key>`` and what is accepted."""

    cruise_kmh: float = 27.0  # target speed on straight roads
    lateral_accel: float = 1.6  # m/s^2 allowed in curves: ~13 km/h in right turns, ~17 in left
    min_kmh: float = 10.0  # never plan slower than this (except to stop)
    decel: float = 1.5  # m/s^2 used to slow down before curves
    lookahead_min: float = 3.5  # m, pure pursuit look-ahead = clip(base + gain * v, min, max)
    lookahead_base: float = 1.5
    lookahead_gain: float = 0.55  # s
    lookahead_max: float = 9.0

    def __post_init__(self) -> None:
        for key, (low, inclusive, unit) in _BOUNDS.items():
            v = getattr(self, key)
            if not isinstance(v, numbers.Real) or isinstance(v, bool) or not math.isfinite(v):
                raise CicfwError(f"expert.{key} must be a number ({unit}), got {v!r}")
            if v < low or (v == low and not inclusive):
                raise CicfwError(f"expert.{key} must be {'>=' if inclusive else '>'} {low:g} {unit}, got {v!r}")
        if self.cruise_kmh > TOP_SPEED_KMH:  # the data would not hold the speed asked for
            raise ConfigError("expert.cruise_kmh", self.cruise_kmh, f"at most {TOP_SPEED_KMH} km/h, the car's top speed")
        if self.min_kmh > self.cruise_kmh:
            raise CicfwError(f"expert.min_kmh={self.min_kmh!r} is above expert.cruise_kmh={self.cruise_kmh!r}; the "
                             f"slowest planned speed must be at most the cruise speed")
        if self.lookahead_max < self.lookahead_min:
            raise CicfwError(f"expert.lookahead_max={self.lookahead_max!r} is below expert.lookahead_min="
                             f"{self.lookahead_min!r}; the look-ahead is clip(base + gain * speed, min, max)")


def speed_profile(route: Route, p: ExpertParams) -> np.ndarray:
    """Target speed (m/s) at every route point: curvature-limited, then decel-limited backwards so the
    car slows before a turn rather than in it."""
    kappa = np.abs(route.curvature)
    # the worst curvature within a car length ahead/behind
    k = np.maximum.reduce([np.roll(kappa, i) for i in range(-6, 7)])
    v2 = np.minimum((p.cruise_kmh / 3.6) ** 2, p.lateral_accel / np.maximum(k, 1e-6))
    v2 = np.maximum(v2, (p.min_kmh / 3.6) ** 2)
    # v2[i] = min_j>=i (v2[j] + 2 a (s_j - s_i))
    w = v2 + 2 * p.decel * route.s
    w = np.minimum.accumulate(w[::-1])[::-1]
    return np.sqrt(np.maximum(w - 2 * p.decel * route.s, 0.0))


class Expert:
    """Pure pursuit on a route. ``act(state) -> (steer, target_speed m/s)``; tracks progress itself."""

    def __init__(self, route: Route, params: ExpertParams | None = None,
                 vehicle: VehicleParams | None = None) -> None:
        self.route = route
        self.p = params or ExpertParams()
        self.v = vehicle or VehicleParams()
        self.profile = speed_profile(route, self.p)
        self._max_wheel = math.radians(self.v.max_wheel_angle_deg)
        self._pts = route.points
        self._i = 0

    def locate(self, x: float, y: float) -> int:
        """Index of the nearest route point, searched in a window around the last one (monotone-ish)."""
        lo = max(self._i - 10, 0)
        hi = min(self._i + 60, len(self._pts))
        seg = self._pts[lo:hi]
        d2 = (seg[:, 0] - x) ** 2 + (seg[:, 1] - y) ** 2
        self._i = lo + int(np.argmin(d2))
        return self._i

    def act(self, state: VehicleState) -> tuple[float, float]:
        """Steering in [-1, 1] (positive right) and target speed (m/s) for the current state."""
        p = self.p
        i = self.locate(state.x, state.y)
        ld = min(max(p.lookahead_base + p.lookahead_gain * state.speed, p.lookahead_min), p.lookahead_max)
        s_target = self.route.s[i] + ld
        j = min(int(np.searchsorted(self.route.s, s_target)), len(self._pts) - 1)
        tx, ty = self._pts[j]
        if j == len(self._pts) - 1:  # past the end: extend the last heading
            extra = s_target - self.route.s[-1]
            h = self.route.heading[-1]
            tx, ty = tx + extra * math.cos(h), ty + extra * math.sin(h)
        dx, dy = tx - state.x, ty - state.y
        alpha = math.atan2(dy, dx) - state.yaw
        dist = max(math.hypot(dx, dy), 1e-3)
        curv = 2.0 * math.sin(alpha) / dist  # pure pursuit, positive = left
        steer = -math.atan(curv * self.v.wheelbase) / self._max_wheel
        # speed: the profile a little ahead (the car needs time to slow down)
        k = min(i + 4, len(self.profile) - 1)
        return min(max(steer, -1.0), 1.0), float(self.profile[k])


class Noiser:
    """CIL's steering noise ("Spike"), in simulation time.

    Each second without noise, a spike starts with probability 15/61. It lasts 2 s + U(0.5, 2) s,
    growing by 0.03 * intensity per second (intensity 10 +- 2, drawn per episode; sign random),
    capped at +-0.55, then is removed at the same rate (we stop at zero; the original overshoots).
    The value added to the steering is scaled by 25 / (2.3 * speed_kmh + 5).
    """

    def __init__(self, rng: np.random.Generator, frequency: int = 15, intensity: float = 10.0,
                 min_duration: float = 2.0, cap: float = 0.55, enabled: bool = True, dt: float = DT) -> None:
        self.rng = rng
        self.frequency = frequency
        self.intensity = intensity + int(rng.integers(-2, 3))
        self.min_duration = min_duration
        self.cap = cap
        self.enabled = enabled
        self.dt = dt
        self.t = 0.0
        self._next_check = 1.0
        self._phase = "off"  # off | on | removing
        self._sign = 1.0
        self._elapsed = 0.0
        self._duration = 0.0
        self._value = 0.0

    def step(self, steer: float, speed_kmh: float) -> tuple[float, bool]:
        """Advance one step; return (applied steering = steer + scaled noise, noise flag)."""
        self.t += self.dt
        if not self.enabled:
            return steer, False
        rate = 0.03 * self.intensity
        if self._phase == "off":
            if self.t >= self._next_check - 1e-9:
                self._next_check += 1.0
                if int(self.rng.integers(0, 61)) < self.frequency:
                    self._phase, self._elapsed, self._value = "on", 0.0, 0.0
                    self._sign = 1.0 if self.rng.integers(0, 2) else -1.0
                    self._duration = self.min_duration + float(self.rng.integers(50, 201)) / 100.0
        if self._phase == "on":
            self._elapsed += self.dt
            self._value = min(self.cap, self._elapsed * rate)
            if self._elapsed >= self._duration:
                self._phase = "removing"
        elif self._phase == "removing":
            self._value = max(self._value - rate * self.dt, 0.0)
            if self._value <= 0.0:
                self._phase = "off"
                self._next_check = self.t + 1.0
        if self._phase == "off" and self._value <= 0.0:
            return steer, False
        noise = self._sign * self._value * 25.0 / (2.3 * max(speed_kmh, 0.0) + 5.0)
        return min(max(steer + noise, -1.0), 1.0), True
