"""The policy interface the runner drives: a batch of observations in, a batch of steering out.

Plain Python (no Lightning). The runner does longitudinal control itself (a speed controller), so a
policy only steers and the suite measures steering. A policy names the cameras it needs; the runner
renders only those. Third-party policies register by name in ``POLICIES`` (entry-point group
``cicfw.policies``) and are then selectable as ``policy=<name>``.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from cicfw.core.errors import CicfwError
from cicfw.registry import Registry


@dataclass
class Observations:
    """One lockstep step for a batch of B episodes.

    ``images``, ``speed_kmh`` and ``command`` are what a learned policy may use. ``pose`` and ``routes``
    are privileged (the planner's truth) and exist for reference policies such as the
    expert; a learned policy must ignore them.
    """

    images: Mapping[str, np.ndarray]  # camera name -> (B, 88, 200, 3) uint8 RGB (the policy's cameras)
    speed_kmh: np.ndarray  # (B,) float
    command: np.ndarray  # (B,) int CIL codes 2 follow, 3 left, 4 right, 5 straight
    pose: np.ndarray  # (B, 3) x, y, yaw of the vehicle reference point (rear axle), privileged
    routes: Sequence[Any]  # (B,) each episode's planned cicfw.sim.roadgraph.Route, privileged
    episode: np.ndarray  # (B,) the episodes' indices in the run (for stateful policies)

    def __len__(self) -> int:
        return len(self.speed_kmh)


class Policy(abc.ABC):
    """Maps observations to steering in [-1, 1] (positive = right, CARLA's convention)."""

    #: the cameras ``act`` reads ("centre", "left", "right"); () = render nothing
    cameras: tuple[str, ...] = ()
    #: the row label in reports
    label: str = "policy"

    def reset(self, episodes: Sequence[int]) -> None:
        """New episodes start (stateful policies clear their per-episode state)."""

    @abc.abstractmethod
    def act(self, obs: Observations) -> np.ndarray:
        """Steering (B,) in [-1, 1] for the batch; called once per step per chunk of episodes."""


POLICIES: Registry = Registry("policy", "cicfw.policies", "cicfw.benchmark.builtin_policies")


def make_policy(spec: Mapping[str, Any]) -> Policy:
    """Build a policy from its config node: ``{name: <registered policy>, **kwargs}``.

    The spec is plain data so worker processes can each build their own copy.
    """
    kwargs = dict(spec)
    name = kwargs.pop("name", None)
    if not name:
        raise CicfwError(f"policy config {dict(spec)} has no 'name:'; registered policies: "
                         f"{', '.join(POLICIES.names())}")
    return POLICIES.get(str(name))(**kwargs)
