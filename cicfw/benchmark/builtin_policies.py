"""The built-in policies: ``checkpoint`` (a trained CICModule), ``expert`` (the reference) and
``constant`` (a scripted fixed steering, for sanity checks: ``policy=constant policy.steer=-1``)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from cicfw.benchmark.checkpoint_policy import CheckpointPolicy
from cicfw.benchmark.policy import POLICIES, Observations, Policy
from cicfw.core.errors import CicfwError
from cicfw.sim.expert import Expert, ExpertParams
from cicfw.sim.vehicle import VehicleState

POLICIES.register("checkpoint")(CheckpointPolicy)


@POLICIES.register("expert")
class ExpertPolicy(Policy):
    """The simulator's expert (pure pursuit on the planned route's lane centre, no noise).

    It reads the privileged pose and route, never an image, so it renders nothing; it is the
    suite's reference and should score close to 100% in every cell.
    """

    cameras = ()

    def __init__(self, label: str = "Expert", **expert_params) -> None:
        self.label = label
        self.params = ExpertParams(**expert_params)
        self._experts: dict[int, object] = {}

    def reset(self, episodes: Sequence[int]) -> None:
        for e in episodes:
            self._experts.pop(int(e), None)

    def act(self, obs: Observations) -> np.ndarray:
        out = np.empty(len(obs))
        for b, e in enumerate(obs.episode):
            ex = self._experts.get(int(e))
            if ex is None or ex.route is not obs.routes[b]:
                ex = self._experts[int(e)] = Expert(obs.routes[b], self.params)
            x, y, yaw = obs.pose[b]
            out[b] = ex.act(VehicleState(float(x), float(y), float(yaw), speed=float(obs.speed_kmh[b]) / 3.6))[0]
        return out


@POLICIES.register("constant")
class ConstantPolicy(Policy):
    """Always the same steering (e.g. -1: hard left); renders nothing. A baseline and a test fixture."""

    cameras = ()

    def __init__(self, steer: float = 0.0, label: str | None = None) -> None:
        if not -1.0 <= float(steer) <= 1.0:
            raise CicfwError(f"policy.steer must be in [-1, 1] (negative = left), got {steer}", key="policy.steer",
                             value=steer)
        self.steer = float(steer)
        self.label = label or f"constant steer {self.steer:+.2f}"

    def act(self, obs: Observations) -> np.ndarray:
        return np.full(len(obs), self.steer)
