"""The runner drives no frame twice: an episode is decided by the step that ends it (the goal within the
success radius, far off the route, too long off the road, the timeout) and leaves the lockstep batch at
once, and the frame after its last step is not rendered. A policy that reads a camera costs exactly one
rendered frame per observation it is served; the results are those of rendering every frame."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from cicfw.benchmark import runner as runner_module
from cicfw.benchmark.builtin_policies import ExpertPolicy
from cicfw.benchmark.policy import Observations, Policy
from cicfw.benchmark.runner import RunnerConfig, run
from cicfw.benchmark.suite import build_suite, make_backend

pytestmark = pytest.mark.slow  # drives the suite (pytest -m "not slow" skips it)

pytest.importorskip("cicfw.sim.render")

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
FAST = RunnerConfig(batch_size=4, progress_bar=False)


class CameraPolicy(Policy):
    """Reads the centre camera of every observation (a digest of each image, kept per episode) and steers
    like the expert, or holds ``steer`` (e.g. -1: circles off the road)."""

    cameras = ("centre",)

    def __init__(self, steer: float | None = None) -> None:
        self.expert, self.steer = ExpertPolicy(), steer
        self.label = "camera"
        self.served: dict[int, list[str]] = {}

    def reset(self, episodes):
        self.expert.reset(episodes)

    def act(self, obs: Observations) -> np.ndarray:
        images = obs.images["centre"]
        assert images.shape == (len(obs), 88, 200, 3) and images.dtype == np.uint8
        for e, img in zip(obs.episode, images):
            self.served.setdefault(int(e), []).append(hashlib.sha1(img.tobytes()).hexdigest())
        return self.expert.act(obs) if self.steer is None else np.full(len(obs), self.steer)


@pytest.fixture
def renders(monkeypatch):
    """Counts every frame the renderer draws."""
    from cicfw.sim.render import Renderer

    count = {"frames": 0}
    original = Renderer.render

    def counting(self, *args, **kwargs):
        count["frames"] += 1
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Renderer, "render", counting)
    return count


def drive(episodes, policy, renders, on_demand=True, monkeypatch=None):
    if not on_demand:  # the runner as it was: every step renders the next frame, served or not
        monkeypatch.setattr(runner_module, "renders_on_demand", lambda env: False)
    before = renders["frames"]
    res = run(episodes, policy, make_backend({"name": "embedded"}), FAST)
    return res, renders["frames"] - before


@pytest.mark.parametrize("steer, reasons", [(None, {"success"}), (-1.0, {"off_road"}), (0.0, {"success", "off_route"})])
def test_an_episode_decided_at_step_k_renders_k_frames_and_results_are_unchanged(steer, reasons, renders, monkeypatch):
    episodes = build_suite(make_backend({"name": "embedded"}), [TOWN], ["ClearNoon"], pairs=[0, 7, 20])
    policy = CameraPolicy(steer)
    res, frames = drive(episodes, policy, renders)
    steps = [r["steps"] for r in res.rows]
    assert {r["reason"] for r in res.rows} == reasons  # decided by the env (goal, route) or the runner (off road)
    # k steps = k observations served = k frames: the first from reset, one after each step but the last
    assert [len(policy.served[e.index]) for e in episodes] == steps
    assert frames == sum(steps) == res.steps

    every = CameraPolicy(steer)
    res_every, frames_every = drive(episodes, every, renders, on_demand=False, monkeypatch=monkeypatch)
    assert frames_every == sum(steps) + len(episodes)  # rendering every step drew one unseen frame each
    assert res_every.rows == res.rows and every.served == policy.served  # the same frames, the same drive
    for k in res.trajectories:
        assert all(np.array_equal(res.trajectories[k][c], res_every.trajectories[k][c]) for c in res.trajectories[k])


def test_step_without_rendering_then_render_gives_the_frame_step_would_have():
    backend = make_backend({"name": "embedded"})
    ep = build_suite(backend, [TOWN], ["ClearNoon"], pairs=[0])[0]
    from cicfw.benchmark.suite import suite_routes

    route = suite_routes(backend, ep.town)[ep.pair]
    a, b = (backend.make_env(ep.town, route, ep.weather, cameras=("centre",)) for _ in range(2))
    a.reset(), b.reset()
    for _ in range(5):
        steer, v = a.expert_action()
        oa, _, _ = a.step(steer, target_speed_kmh=v)
        ob, _, _ = b.step(steer, target_speed_kmh=v, render=False)
        assert ob["images"] == {} and ob["pose"] == oa["pose"]
        assert np.array_equal(b.render()["centre"], oa["images"]["centre"])
    assert runner_module.renders_on_demand(a)
