"""``collect sim=carla`` offline: the collection engine (``cicfw.collect``) drives the CARLA backend
against the recording stand-in server (real Town01/Town02 maps, autospecs of the real classes).

The same CIL files as the embedded collector (three cameras, CIL noise, metadata, resume, the lock),
one tick per step, each sample's image the ticked frame's, each episode's own town and weather, and
nothing left in the world after success or Ctrl-C."""
from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

carla = pytest.importorskip("carla", reason="the CARLA client is not installed: pip install -e '.[carla]'")

from cicfw.carla_client import backend as carla_backend  # noqa: E402
from cicfw.carla_client.backend import CarlaBackend  # noqa: E402
from carla_standin import StandIn, maps_dir  # noqa: E402
from cicfw.collect import collect_dataset, episode_plan, resolve_config  # noqa: E402
from cicfw.data.cil_hdf5 import T, check_file  # noqa: E402

MAPS = maps_dir()
pytestmark = [pytest.mark.slow,  # drives whole episodes (pytest -m "not slow" skips it)
              pytest.mark.skipif(MAPS is None, reason="CARLA's Town01/Town02 OpenDRIVE files are not in "
                                                      "../shared/carla-maps (or $CICFW_CARLA_MAPS)")]
SETTLE = 2
STEPS = 30
CFG = {"towns": ["town_a", "town_b"], "weathers": ["ClearNoon", "WetCloudySunset"], "episodes": 3,
       "seconds": STEPS / 10, "workers": 0, "seed": 3, "noise": {"episode_fraction": 1.0},
       "sim": {"name": "carla", "settle_ticks": SETTLE, "sensor_timeout_s": 0.5}}


@pytest.fixture
def standin(monkeypatch):
    si = StandIn(MAPS, image_size_override=(200, 150))
    monkeypatch.setattr(carla_backend, "connect", lambda *a, **k: si.client)  # every backend reaches it
    return si


def _read(path):
    with h5py.File(path, "r") as f:
        return f["rgb"][()], f["targets"][()]


def test_collect_sim_carla_writes_cil_episodes_with_one_tick_per_step(standin, tmp_path):
    si = standin
    si.backlog, si.delay_s = True, 0.005  # older frames around each image, delivered late from a thread
    meta = json.loads(collect_dataset(CFG, tmp_path, progress=False).read_text())
    assert meta["complete"] and meta["sim_version"] == CarlaBackend.data_version
    assert meta["counts"]["samples"] == 3 * STEPS * 3
    plan = episode_plan(resolve_config(CFG))
    logged = si.episodes()
    assert len(logged) == 3
    for ep, got in zip(plan, logged):
        ticks = got["ticks"]
        assert len(ticks) == SETTLE + 1 + STEPS  # reset's ticks, then one per step
        assert {t[2] for t in ticks} == {ep["weather"]}
        assert {t[5] for t in ticks} == {"Town01" if ep["town"] == "town_a" else "Town02"}
        files = sorted(tmp_path.glob(f"{ep['id']}_*.h5"))
        assert [f.name for f in files] == [f["name"] for f in meta_files(meta, ep["id"])]
        rgb, tg = map(np.concatenate, zip(*(_read(f) for f in files)))
        assert sum(check_file(f).n for f in files) == len(rgb) == STEPS * 3
        assert np.all(np.isfinite(tg))
        assert list(tg[:, T.CAMERA_ID][:6]) == [0, 1, 2, 0, 1, 2]
        assert list(tg[:6, T.CAMERA_YAW]) == [0.0, -30.0, 30.0, 0.0, -30.0, 30.0]
        # each sample: the image of the frame whose state it labels (reset's last tick, then each step's)
        frames = [StandIn.decode_frame(img) for img in rgb]
        want = [t[1] for t in ticks[SETTLE:SETTLE + STEPS]]
        for cam in range(3):
            assert frames[cam::3] == want
            assert set(rgb[cam::3, 44, 100, 0]) == {cam}  # each camera's own image
        assert set(np.unique(tg[:, T.COMMAND])) <= {2.0, 3.0, 4.0, 5.0}
        assert np.abs(tg[:, T.STEER]).max() <= 1.0 and tg[:, T.SPEED].min() >= 0.0
        assert np.all(tg[:, T.SIDEWALK] == 0.0) and np.all(tg[:, T.OPPOSITE_LANE] == 0.0)
        # the game time advances 100 ms per step
        assert np.all(np.diff(tg[::3, T.GAME_TIME]) == 100.0)
    assert meta["episodes"] and all(m["noisy_episode"] for m in meta["episodes"].values())
    assert si.leftovers() == []
    # a rerun resumes: everything is there, nothing is simulated
    n = len(si.ticks())
    assert json.loads(collect_dataset(CFG, tmp_path, progress=False).read_text())["complete"]
    assert len(si.ticks()) == n


def meta_files(meta: dict, ep_id: str) -> list[dict]:
    return sorted(({"name": k} for k, v in meta["files"].items() if v["episode"] == ep_id), key=lambda f: f["name"])


def test_ctrl_c_in_a_carla_collection_leaves_nothing_and_the_rerun_finishes(standin, tmp_path):
    si = standin
    stop_at = si.frame + 2 * (SETTLE + 1 + STEPS) + 10  # in the third episode

    def interrupt(frame: int) -> None:
        if frame == stop_at:
            raise KeyboardInterrupt

    si.on_tick = interrupt
    with pytest.raises(KeyboardInterrupt):
        collect_dataset(CFG, tmp_path, progress=False)
    assert si.leftovers() == []
    meta = json.loads((tmp_path / "dataset_metadata.json").read_text())
    assert not meta["complete"] and meta["counts"]["episodes"] == 2
    assert not list(tmp_path.glob("ep0002_*.h5")) and not list(tmp_path.glob(".*.part"))
    si.on_tick = None
    before = len(si.episodes())
    meta = json.loads(collect_dataset(CFG, tmp_path, progress=False).read_text())
    assert meta["complete"] and len(si.episodes()) == before + 1  # only the unfinished episode
    assert si.leftovers() == []


def test_no_server_is_one_line_before_the_folder_is_touched(tmp_path):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = {**CFG, "sim": {"name": "carla", "host": "127.0.0.1", "port": port, "connect_timeout_s": 1.0}}
    with pytest.raises(ValueError, match=rf"no CARLA server answered at 127.0.0.1:{port} within 1 s") as err:
        collect_dataset(cfg, tmp_path / "out", progress=False)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "out").exists()


def test_a_collection_env_never_ends_by_itself(standin):
    be = CarlaBackend(client=standin.client, settle_ticks=SETTLE)
    route = be.single_turn_routes("town_a")[0]  # ~70 m: the expert reaches its goal in ~12 s
    with be.make_env("town_a", route, "ClearNoon", renderer=False, endless=True) as env:
        env.reset()
        for _ in range(200):
            steer, v = env.expert_action()
            _, done, info = env.step(steer, target_speed_kmh=v)
            assert not done and info["reason"] is None
        assert info["distance_to_goal"] > 0  # it drove on past the goal (the route's last point)
    assert standin.leftovers() == []
