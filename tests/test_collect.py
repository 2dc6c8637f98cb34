"""The collector: CIL files that read back through cicfw.data.cil_hdf5, determinism, resume, the app's
one-line errors (collect and preview), and the engine over the backend interface (sim=...).

The integrity guarantees under faults (lock, killed parent, full disk ...) are in test_collect_integrity.py."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module

import cicfw.collect.app as collect_mod
import cicfw.collect.dataset as dataset_mod
import cicfw.core.files as files_mod
from cicfw.collect import DEFAULTS, CollectConfigError, collect_dataset, resolve_config
from cicfw.collect import LOCK_NAME
from cicfw.data.cil_hdf5 import T, check_file, find_files, read_rgb, read_targets
from cicfw.registry import SIM_BACKENDS
from cicfw.sim.backends import EmbeddedBackend
from conftest import assert_refused, run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

SMALL = {"episodes": 2, "seconds": 8, "workers": 0}  # 80 steps x 3 cameras = 240 samples = 2 files each


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("collected")
    collect_dataset(SMALL, out, progress=False)
    return out


def test_files_read_back_with_cil_values(small_dataset: Path):
    files = find_files(small_dataset)
    assert [f.name for f in files] == [f"ep0000_town_a_ClearNoon_00{i}.h5" for i in range(2)] + \
        [f"ep0001_town_a_ClearSunset_00{i}.h5" for i in range(2)]
    assert [check_file(f).n for f in files] == [200, 40, 200, 40]
    t = np.vstack([read_targets(f) for f in files[:2]])
    rgb = np.concatenate([read_rgb(f) for f in files[:2]])
    assert t.shape == (240, 28) and rgb.shape == (240, 88, 200, 3) and rgb.dtype == np.uint8
    assert set(np.unique(t[:, T.COMMAND])) <= {2, 3, 4, 5}
    assert np.array_equal(t[:, T.CAMERA_ID], np.tile([0, 1, 2], 80))
    assert np.array_equal(t[:, T.CAMERA_YAW], np.tile([0, -30, 30], 80))
    step = t[::3]
    assert np.all((step[:, T.SPEED] >= 0) & (step[:, T.SPEED] < 40)) and step[-1, T.SPEED] > 10
    assert np.all(np.diff(step[:, T.GAME_TIME]) == 100)  # ms, 10 Hz
    assert np.allclose(np.hypot(step[:, T.ORIENT_X], step[:, T.ORIENT_Y]), 1.0, atol=1e-5)
    moved = np.hypot(np.diff(step[:, T.POS_X]), np.diff(step[:, T.POS_Y]))
    assert np.allclose(moved, step[:-1, T.SPEED] / 3.6 * 0.1, atol=0.08)  # positions follow the speed
    assert np.all(np.abs(step[:, T.STEER]) <= 1) and np.all(step[:, T.GAS] >= 0)
    clean = step[:, T.NOISE_FLAG] == 0
    assert np.array_equal(step[clean, T.STEER_NOISE], step[clean, T.STEER])
    # the three cameras of a step see different images, and each step's rows agree but for the camera
    assert not np.array_equal(rgb[0], rgb[1]) and not np.array_equal(rgb[0], rgb[2])
    assert np.array_equal(np.delete(t[0], [T.CAMERA_ID, T.CAMERA_YAW]), np.delete(t[2], [T.CAMERA_ID, T.CAMERA_YAW]))
    meta = json.loads((small_dataset / "dataset_metadata.json").read_text())
    assert meta["complete"] and meta["counts"]["samples"] == 480 and meta["towns"] == ["town_a"]
    assert meta["sim_version"] and meta["weathers"] == ["ClearNoon", "ClearSunset"]
    last = small_dataset / "ep0001_town_a_ClearSunset_001.h5"
    # the SHA-256 with the size and mtime of the file it was taken of: a reader reuses it while both still match
    assert meta["files"][last.name] == {"episode": "ep0001_town_a_ClearSunset", "samples": 40,
                                        "sha256": hashlib.sha256(last.read_bytes()).hexdigest(),
                                        "bytes": last.stat().st_size, "mtime_ns": last.stat().st_mtime_ns}


def test_a_town_that_gets_no_episode_is_not_listed_as_collected(tmp_path: Path, caplog):
    """episodes=1 over towns [town_a, town_b] collects town_a alone, but the metadata listed both, so an evaluation
    of a model trained on it labelled town_b its training town."""
    from omegaconf import OmegaConf

    from cicfw.benchmark.trained_sets import training_set_overrides

    collect_dataset({"episodes": 1, "seconds": 0.5, "workers": 0, "cameras": ["centre"], "towns": ["town_a", "town_b"],
                     "weathers": ["ClearNoon"]}, tmp_path, progress=False)
    meta = json.loads((tmp_path / "dataset_metadata.json").read_text())
    assert meta["towns"] == ["town_a"] and meta["config"]["towns"] == ["town_a", "town_b"]
    assert "suite.training_towns=[town_a]" in training_set_overrides(OmegaConf.create({"path": str(tmp_path)}), [])
    assert "town_b" in caplog.text  # said while collecting


def test_noise_label_is_the_experts_steer_not_the_noisy_one(tmp_path: Path):
    collect_dataset({"episodes": 1, "seconds": 20, "workers": 0, "cameras": ["centre"],
                     "noise": {"episode_fraction": 1.0}}, tmp_path, progress=False)
    t = np.vstack([read_targets(f) for f in find_files(tmp_path)])
    noisy = t[:, T.NOISE_FLAG] == 1
    assert noisy.mean() > 0.2
    assert np.abs(t[noisy, T.STEER_NOISE] - t[noisy, T.STEER]).max() > 0.1


def test_same_seed_same_bytes_and_resume_after_an_interrupted_run(tmp_path: Path, small_dataset: Path,
                                                                   monkeypatch):
    real_write = files_mod.temp_beside
    calls = {"n": 0}
    seen = []

    def dying_write(path, suffix=".tmp"):  # episode 0 finishes, episode 1 dies writing its 2nd file
        calls["n"] += suffix == ".part"  # the HDF5 files (JSON files are written with ".tmp")
        if calls["n"] == 4:
            seen.extend(p.name for p in out.glob(".*.part"))
            raise KeyboardInterrupt("killed")
        return real_write(path, suffix)

    out = tmp_path / "resumed"
    monkeypatch.setattr(files_mod, "temp_beside", dying_write)
    with pytest.raises(KeyboardInterrupt):
        collect_dataset(SMALL, out, progress=False)
    visible = sorted(p.name for p in out.glob("*.h5"))
    assert visible == ["ep0000_town_a_ClearNoon_000.h5", "ep0000_town_a_ClearNoon_001.h5"]
    # the dead episode's first file existed under a temporary name only, and is gone now
    assert len(seen) == 1 and seen[0].startswith(".ep0001_town_a_ClearSunset_000.h5.")
    assert not list(out.glob(".*.part"))
    meta = json.loads((out / "dataset_metadata.json").read_text())
    assert not meta["complete"] and meta["counts"]["episodes"] == 1
    monkeypatch.setattr(files_mod, "temp_beside", real_write)
    collect_dataset(SMALL, out, progress=False)
    # no temporary files left, nor the lock file (it exists while a collector holds the folder)
    assert [p.name for p in out.rglob(".*") if p.is_file() and p.parent == out] == []
    assert not (out / LOCK_NAME).exists()
    assert json.loads((out / "dataset_metadata.json").read_text())["complete"]
    for f in find_files(small_dataset):  # same seed, same bytes, whether interrupted or not
        assert (out / f.name).read_bytes() == f.read_bytes(), f.name
    # a third run has nothing to do and does not touch the files
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5")}
    collect_dataset(SMALL, out, progress=False)
    assert before == {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5")}


def test_another_seed_gives_other_data(tmp_path: Path, small_dataset: Path):
    collect_dataset({**SMALL, "episodes": 1, "seed": 1}, tmp_path, progress=False)
    a = read_targets(tmp_path / "ep0000_town_a_ClearNoon_000.h5")
    b = read_targets(small_dataset / "ep0000_town_a_ClearNoon_000.h5")
    assert not np.array_equal(a[:, T.POS_X], b[:, T.POS_X])


def test_bad_config_values_give_one_clear_error(tmp_path: Path, small_dataset: Path):
    with pytest.raises(CollectConfigError) as err:  # the schema (CollectConfig): kind and key
        resolve_config({"episode": 3})
    assert (err.value.kind, err.value.key) == ("unknown key", "collect.episode") and "'episodes'" in str(err.value)
    with pytest.raises(CollectConfigError) as err:
        resolve_config({"episodes": "many"})
    assert (err.value.kind, err.value.key) == ("wrong type", "collect.episodes")
    with pytest.raises(CollectConfigError) as err:
        resolve_config({"cameras": ["top"]})
    assert (err.value.key, err.value.value) == ("collect.cameras", "top")
    with pytest.raises(ValueError) as err:
        resolve_config({"towns": ["town_q"]})
    assert (err.value.key, err.value.value) == ("collect.towns", "town_q")
    for key, name in (("towns", "town_a"), ("weathers", "ClearNoon")):  # a name listed twice
        with pytest.raises(CollectConfigError) as err:
            resolve_config({key: [name, name]})
        assert (err.value.key, err.value.value) == (f"collect.{key}", name)
    with pytest.raises(CollectConfigError) as err:
        resolve_config({"expert": {"speed": 3}})
    assert (err.value.kind, err.value.key) == ("unknown key", "collect.expert.speed")
    with pytest.raises(CollectConfigError) as err:
        collect_dataset({**SMALL, "seconds": 9}, small_dataset, progress=False)
    assert (err.value.key, err.value.value) == ("out_dir", small_dataset.resolve())


BAD_TOWN = "name: broken\nroads: [1\n"  # not YAML


@pytest.mark.parametrize("override, key, value", [  # the key and the value its one line names
    ("towns=[town_q]", "collect.towns", "town_q"),
    ("weathers=[Foggy]", "collect.weathers", "Foggy"),
    ("episodes=0", "collect.episodes", "0"),
    ("episodes=-3", "collect.episodes", "-3"),
    ("seconds=0", "collect.seconds", "0"),
    ("seconds=-2.5", "collect.seconds", "-2.5"),
    ("towns=[/no/such/my_town.yaml]", "collect.towns", "/no/such/my_town.yaml"),
    ("towns=[BAD]", "collect.towns", "BAD"),
    ("cameras=[top]", "collect.cameras", "top"),
    ("workers=-1", "collect.workers", "-1"),
    ("noise.episode_fraction=2", "collect.noise.episode_fraction", "2"),
    ("lock_wait=-1", "collect.lock_wait", "-1"),
    ("sim.name=nosuch", "sim", "nosuch"),
    ("+frames=3", "collect.frames", None),  # added with +: the schema refuses it in the app
])
def test_the_app_prints_one_line_for_every_config_error(tmp_path: Path, capsys, override: str, key: str,
                                                        value: str | None, monkeypatch):
    bad = tmp_path / "broken_town.yaml"
    bad.write_text(BAD_TOWN)
    override = override.replace("BAD", str(bad))
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("collect", overrides=[f"out_dir={tmp_path / 'out'}", override])
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("simulated despite a bad config"))
    with pytest.raises(SystemExit) as exc:
        collect_mod.run(cfg)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cicfw: error: "), err
    assert key in lines[0] and (value is None or value.replace("BAD", str(bad)) in lines[0]), lines[0]
    assert not (tmp_path / "out").exists()  # reported before the folder was touched


@pytest.mark.parametrize("override, kind, key", [
    ("expert.cruise_kmh=abc", "wrong type", "expert.cruise_kmh"),
    ("episodes=many", "wrong type", "episodes"),
    ("lock_wait=soon", "wrong type", "lock_wait"),
    ("verify=maybe", "wrong type", "verify"),
    ("expert.cruise=30", "unknown key", "expert.cruise"),
    ("noise.intensty=3", "unknown key", "noise.intensty"),
    ("episods=3", "unknown key", "episods"),
])
def test_the_schema_refuses_a_type_or_key_while_composing(override: str, kind: str, key: str):
    """conf/collect.yaml's schema is CollectAppConfig: OmegaConf refuses these before the app runs."""
    from hydra.errors import HydraException

    from cicfw.core.config_checks import config_error

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        with pytest.raises(HydraException) as err:
            compose("collect", overrides=[override])
    refused = config_error(err.value)
    assert (refused.kind, refused.key) == (kind, key), refused


def test_the_real_command_line_prints_one_line(tmp_path: Path):
    r = run_app_in_process("cicfw.collect", f"out_dir={tmp_path / 'out'}", "weathers=[Foggy]", cwd=tmp_path)
    assert_refused(r, "collect.weathers", "Foggy")


@pytest.mark.parametrize("override, key, value", [
    ("weathers=[Foggy]", "collect.weathers", "Foggy"), ("weathers=[ClearNoon,ClearNoon]", "collect.weathers",
                                                        "ClearNoon"), ("towns=[nowhere]", "collect.towns", "nowhere")])
def test_a_refused_collect_leaves_no_run_folder_it_made(tmp_path: Path, override: str, key: str, value: str):
    made, kept = tmp_path / "outputs" / "run", tmp_path / "mine"  # one made for the run, one that was there
    kept.mkdir()
    for folder in (made, kept):
        r = run_app_in_process("cicfw.collect", f"out_dir={tmp_path / 'out'}", override, f"hydra.run.dir={folder}",
                               cwd=tmp_path)
        assert_refused(r, key, value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]  # no outputs/, no out/
    assert kept.is_dir() and list(kept.iterdir()) == []


@pytest.mark.parametrize("args", [  # an option and the value its one line names
    ["--towns", "town_q"], ["--towns", "/no/such/my_town.yaml"], ["--towns", "BAD"], ["--weathers", "Foggy"],
    ["--scale", "0"], ["--colours", "1"], ["--seed", "-1"], ["--prefix", "sub/"],
])
def test_preview_prints_one_line_for_every_config_error(tmp_path: Path, capsys, args: list):
    from cicfw.sim import preview

    bad = tmp_path / "broken_town.yaml"
    bad.write_text(BAD_TOWN)
    args = [str(bad) if a == "BAD" else a for a in args]
    with pytest.raises(SystemExit) as exc:
        preview.main(["--out", str(tmp_path / "out"), *args])
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cicfw: error: "), lines
    assert args[1] in lines[0], lines[0]  # the value refused, and the option (a town's line is the town loader's)
    assert args[0] == "--towns" or args[0] in lines[0], lines[0]
    assert not (tmp_path / "out").exists()  # refused before anything was written


# ------------------------------------------------------------------------------------------------
# the engine over the backend interface


class RecordingBackend:
    """Only the documented interface (no resolve_town: names only), over the embedded simulator; its
    envs have no ``info()`` and a ``close()``, and stop (done) after ``stop_after`` steps."""

    calls: list = []

    def __init__(self, stop_after: int = 10**9, **kwargs) -> None:
        self.inner = EmbeddedBackend(**kwargs)
        self.stop_after = stop_after
        self.data_version = "recording-7"
        RecordingBackend.calls.append(("init", kwargs))

    def towns(self):
        return ["town_a"]

    def weathers(self):
        return ["ClearNoon"]

    def random_route(self, town, rng, min_length, name="random", command_distance=None):
        RecordingBackend.calls.append(("route", town, name))
        return self.inner.random_route(town, rng, min_length, name, command_distance)

    def make_env(self, town, route, weather, seed=0, cameras=("centre",), renderer=True, expert=None,
                 time_offset=0.0, endless=False):
        RecordingBackend.calls.append(("make_env", town, weather, endless))
        return RecordingEnv(self.inner.make_env(town, route, weather, seed, cameras, renderer, expert, time_offset,
                                                endless), self.stop_after)


class RecordingEnv:
    def __init__(self, env, stop_after: int) -> None:
        self.env, self.stop_after, self.n = env, stop_after, 0
        self.speed_ctl = env.speed_ctl

    def reset(self):
        return self.env.reset()

    def expert_action(self):
        return self.env.expert_action()

    def step(self, steer, throttle=None, brake=None):
        obs, done, info = self.env.step(steer, throttle=throttle, brake=brake)
        self.n += 1
        return obs, done or self.n >= self.stop_after, info

    def close(self):
        RecordingBackend.calls.append(("close", self.n))


@pytest.fixture
def recording(monkeypatch):
    SIM_BACKENDS.names()  # load the registry before replacing an entry
    monkeypatch.setitem(SIM_BACKENDS._entries, "recording", RecordingBackend)
    RecordingBackend.calls = []
    return RecordingBackend


def test_the_engine_drives_any_backend_through_its_interface(tmp_path: Path, recording):
    cfg = {"episodes": 2, "seconds": 1.5, "weathers": ["ClearNoon"], "cameras": ["centre", "right"], "workers": 0,
           "command_distance": 9.0, "sim": {"name": "recording", "stop_after": 12, "command_distance": 9.0}}
    meta = json.loads(collect_dataset(cfg, tmp_path, progress=False).read_text())
    assert meta["complete"] and meta["sim"] == "recording" and meta["sim_version"] == "recording-7"
    # an env that is done after 12 steps ends its episode there: 12 steps x 2 cameras
    assert [check_file(f).n for f in find_files(tmp_path)] == [24, 24]
    assert meta["counts"] == {"episodes": 2, "samples": 48, "steps": 24, "files": 2, "noisy_steps":
                              meta["counts"]["noisy_steps"]}
    kinds = [c[0] for c in recording.calls]
    assert kinds.count("init") == 1  # one backend for the whole in-process run
    assert kinds.count("make_env") == 2 and ("make_env", "town_a", "ClearNoon", True) in recording.calls
    assert [c for c in recording.calls if c[0] == "close"] == [("close", 12), ("close", 12)]  # closed each time
    t = read_targets(find_files(tmp_path)[0])
    assert np.array_equal(t[:, T.CAMERA_ID], np.tile([0, 2], 12)) and np.all(t[:, T.OPPOSITE_LANE] >= 0)
    with pytest.raises(CollectConfigError) as err:
        resolve_config({**cfg, "towns": ["town_b"]})
    assert (err.value.key, err.value.value) == ("collect.towns", "town_b") and "town_a" in str(err.value)  # known
    # another simulator is another dataset: the same folder refuses the embedded one
    with pytest.raises(CollectConfigError) as err:
        collect_dataset({**cfg, "sim": {"name": "embedded"}}, tmp_path, progress=False)
    assert (err.value.key, err.value.value) == ("out_dir", tmp_path.resolve())


def test_sim_carla_routes_collect_to_the_carla_backend(tmp_path: Path, recording, monkeypatch):
    """``python -m cicfw.collect sim=carla`` builds SIM_BACKENDS['carla'] with conf/sim/carla.yaml's kwargs
    (a stand-in here: no server) and collects through it."""
    made = []

    class StandIn(RecordingBackend):
        def __init__(self, **kwargs):
            made.append(kwargs)
            super().__init__(stop_after=3)

    monkeypatch.setitem(SIM_BACKENDS._entries, "carla", StandIn)
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("collect", overrides=["sim=carla", f"out_dir={tmp_path}", "episodes=1", "workers=0",
                                            "weathers=[ClearNoon]", "cameras=[centre]"])
    line = collect_mod.run(cfg)
    assert "sim=carla" in line and "complete=True" in line
    from omegaconf import OmegaConf

    assert made and made[0] == {k: v for k, v in OmegaConf.to_container(cfg.sim).items() if k != "name"}
    assert [check_file(f).n for f in find_files(tmp_path)] == [3]


def test_hydra_collect_config_composes_and_resolves():
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("collect", overrides=["episodes=3", "towns=[town_a,town_b]"])
    resolved = resolve_config(cfg)
    assert resolved["episodes"] == 3 and resolved["towns"] == ["town_a", "town_b"]
    assert resolve_config({}) == resolve_config(None)  # data.collect: {} = the defaults
    assert set(resolve_config({})) == set(DEFAULTS)


def test_the_documented_expert_keys_are_set_without_plus():
    """``expert.cruise_kmh=30`` as conf/collect.yaml documents it (no ``+``); its spelled-out defaults are
    ExpertParams' own and hash as the engine's ``expert: {}``, so no collected dataset changes its hash."""
    from dataclasses import asdict

    from omegaconf import OmegaConf

    from cicfw.collect import config_hash
    from cicfw.sim.expert import ExpertParams

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        default = compose("collect")
        faster = compose("collect", overrides=["expert.cruise_kmh=30"])
    assert OmegaConf.to_container(default.expert) == asdict(ExpertParams())
    assert resolve_config(faster)["expert"] == {"cruise_kmh": 30}
    assert resolve_config(default)["expert"] == {}
    assert config_hash(resolve_config(default)) == config_hash(resolve_config({}))
    assert resolve_config({"expert": {"cruise_kmh": 27.0, "decel": 2}})["expert"] == {"decel": 2}


def test_a_collect_that_fails_while_collecting_keeps_its_episodes_and_log(tmp_path: Path, monkeypatch):
    # the run folder is the dataset folder (collect accepts it): the disk "fills" before the second episode
    import cicfw.collect.writing as writing
    calls, real = [], writing._free_bytes

    def free(path):
        calls.append(path)
        return real(path) if len(calls) <= 2 else 0  # the whole plan's check and episode 0: room; then none
    monkeypatch.setattr(writing, "_free_bytes", free)
    out = tmp_path / "data"
    r = run_app_in_process("cicfw.collect", f"out_dir={out}", f"hydra.run.dir={out}", "episodes=2", "seconds=2",
                           "workers=0", "weathers=[ClearNoon]", "cameras=[centre]", cwd=tmp_path)
    assert r.returncode == 2 and "free" in r.stderr, r.stderr[-500:]
    kept = sorted(p.name for p in out.iterdir())
    assert "collect.log" in kept and ".hydra" in kept, kept  # the failed run's log, which its line points to
    assert [n for n in kept if n.endswith(".h5")] == ["ep0000_town_a_ClearNoon_000.h5"], kept  # resumable


def test_a_finished_collect_is_never_undone_by_a_later_refusal_in_the_process(tmp_path: Path):
    out = tmp_path / "data"
    r = run_app_in_process("cicfw.collect", f"out_dir={out}", f"hydra.run.dir={out}", "episodes=1", "seconds=2",
                           "workers=0", "weathers=[ClearNoon]", "cameras=[centre]", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-500:]
    # the summary line on stdout is in the run folder's log too: a piped or nohup run keeps how it ended
    assert "dataset: " in r.stdout and "complete=True" in (out / "collect.log").read_text()
    before = sorted(p.name for p in out.iterdir())
    refused = run_app_in_process("cicfw.train", "mixer=nosuch", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert refused.returncode == 2 and "nosuch" in refused.stderr
    assert sorted(p.name for p in out.iterdir()) == before and "dataset_metadata.json" in before
