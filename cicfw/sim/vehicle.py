"""Kinematic bicycle vehicle at 10 Hz with a simple longitudinal model and a speed controller.

The pose (x, y, yaw) is the centre of the REAR AXLE (the bicycle model's reference point); yaw is
CCW from +x. Steering is in [-1, 1], positive = right (CARLA's convention), mapped linearly to a wheel
angle of up to ``max_wheel_angle_deg`` (40 deg by default: the tightest junction connector, radius
~7.5 m, needs ~0.5 at the wheelbase of 2.7 m, leaving room for noise and correction).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

DT = 0.1  # seconds per step (10 Hz, as CIL's data)


@dataclass
class VehicleParams:
    wheelbase: float = 2.7  # m
    max_wheel_angle_deg: float = 40.0  # |steer| = 1
    length: float = 4.5  # m (for footprint queries)
    width: float = 1.8  # m
    rear_overhang: float = 0.9  # m from the rear bumper to the rear axle
    max_accel: float = 4.0  # m/s^2 at full throttle from standstill
    top_speed: float = 30.0  # m/s where full throttle gives no more acceleration
    max_brake: float = 8.0  # m/s^2 at full brake
    rolling: float = 0.1  # m/s^2 of constant resistance while moving
    drag: float = 0.0008  # 1/m (deceleration = drag * v^2)
    steer_tau: float = 0.0  # s, first-order lag of the wheel angle (0 = instantaneous)


@dataclass
class VehicleState:
    x: float
    y: float
    yaw: float  # rad, CCW from +x
    speed: float = 0.0  # m/s, forward
    steer: float = 0.0  # actual steering in [-1, 1] (after the lag)

    @property
    def speed_kmh(self) -> float:
        return self.speed * 3.6


class Vehicle:
    """``step(steer, throttle, brake)`` advances the state by ``dt`` seconds (exact arc integration)."""

    def __init__(self, state: VehicleState, params: VehicleParams | None = None, dt: float = DT) -> None:
        self.p = params or VehicleParams()
        self.s = state
        self.dt = dt
        self._max_wheel = math.radians(self.p.max_wheel_angle_deg)

    def step(self, steer: float, throttle: float, brake: float) -> VehicleState:
        p, s, dt = self.p, self.s, self.dt
        steer = min(max(float(steer), -1.0), 1.0)
        throttle = min(max(float(throttle), 0.0), 1.0)
        brake = min(max(float(brake), 0.0), 1.0)
        if p.steer_tau > 0:
            s.steer += (steer - s.steer) * (1.0 - math.exp(-dt / p.steer_tau))
        else:
            s.steer = steer
        v0 = s.speed
        a = throttle * p.max_accel * max(1.0 - v0 / p.top_speed, 0.0) - p.drag * v0 * v0
        if v0 > 0.0:
            a -= brake * p.max_brake + p.rolling
        v1 = max(v0 + a * dt, 0.0)
        s.speed = v1
        dist = 0.5 * (v0 + v1) * dt
        # positive steer turns right: yaw decreases
        curv = -math.tan(s.steer * self._max_wheel) / p.wheelbase
        dyaw = curv * dist
        if abs(dyaw) < 1e-9:
            s.x += dist * math.cos(s.yaw)
            s.y += dist * math.sin(s.yaw)
        else:
            r = 1.0 / curv
            s.x += r * (math.sin(s.yaw + dyaw) - math.sin(s.yaw))
            s.y -= r * (math.cos(s.yaw + dyaw) - math.cos(s.yaw))
        s.yaw = (s.yaw + dyaw + math.pi) % (2 * math.pi) - math.pi
        return s

    def centre(self) -> tuple[float, float]:
        """The car's geometric centre (rear axle + half length - rear overhang, forward)."""
        off = self.p.length / 2 - self.p.rear_overhang
        return self.s.x + off * math.cos(self.s.yaw), self.s.y + off * math.sin(self.s.yaw)


class SpeedController:
    """Target speed -> (throttle, brake): a PI controller on throttle, proportional braking."""

    def __init__(self, kp: float = 0.5, ki: float = 0.1, kb: float = 0.4, dt: float = DT,
                 params: VehicleParams | None = None) -> None:
        self.kp, self.ki, self.kb, self.dt = kp, ki, kb, dt
        self.p = params or VehicleParams()
        self._i = 0.0

    def reset(self) -> None:
        self._i = 0.0

    def __call__(self, speed: float, target: float) -> tuple[float, float]:
        if target <= 0.05:  # stop and hold
            self._i = 0.0
            return 0.0, 1.0 if speed > 0.0 else 0.3
        err = target - speed
        if err < -0.6:  # well over the target: brake, no throttle
            self._i = 0.0
            return 0.0, min(self.kb * -err, 1.0)
        # feed-forward for resistance at the target speed, then PI
        ff = (self.p.rolling + self.p.drag * target * target) / (
            self.p.max_accel * max(1.0 - target / self.p.top_speed, 0.1))
        self._i = min(max(self._i + err * self.dt, -2.0), 2.0)
        throttle = ff + self.kp * err + self.ki * self._i
        return min(max(throttle, 0.0), 1.0), 0.0


def _level_speed(p: VehicleParams) -> float:
    """m/s where full throttle only balances drag and rolling resistance: how fast the car really gets."""
    a, b, c = p.drag, p.max_accel / p.top_speed, p.max_accel - p.rolling
    return (-b + math.sqrt(b * b + 4 * a * c)) / (2 * a)


#: the embedded car's top speed in km/h (rounded down): a target speed above it is never reached
TOP_SPEED_KMH = math.floor(_level_speed(VehicleParams()) * 3.6)
