"""Checkpoints: loaded safely (weights_only), each bad input gives its one clear message, and a
checkpoint trained for a few steps drives a two-episode suite end to end."""
from __future__ import annotations

import collections
import json
import os
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Dataset

from cicfw.benchmark.checkpoint_policy import CheckpointPolicy
from cicfw.benchmark.policy import Observations
from cicfw.core.errors import CicfwError
from cicfw.model.checkpoint import CheckpointError, load_model, read_checkpoint
from cicfw.model.module import CICModule
from conftest import damaged_checkpoints, misfit_counts

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")


class Frames(Dataset):
    def __len__(self):
        return 8

    def __getitem__(self, i):
        return {"image": torch.full((3, 88, 200), i * 20, dtype=torch.uint8), "speed": torch.tensor(10.0 + i),
                "command": torch.tensor(i % 4), "steer": torch.tensor(0.1 * (i % 3) - 0.1)}


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    """A CIL-size checkpoint trained for two steps, saved by a Lightning Trainer."""
    L.seed_everything(0)
    model = CICModule(mixer="gtu", head="hybrid")
    trainer = L.Trainer(max_steps=2, limit_val_batches=0, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, accelerator="cpu")
    trainer.fit(model, DataLoader(Frames(), batch_size=4))
    path = tmp_path_factory.mktemp("ckpt") / "two_steps.ckpt"
    trainer.save_checkpoint(path)
    return path


def test_checkpoint_round_trip_and_policy_uses_the_commands_branch(ckpt: Path):
    model = load_model(ckpt)
    assert not model.training and model.hparams.mixer == "gtu" and model.hparams.head == "hybrid"
    ref = CICModule.load_from_checkpoint(ckpt, weights_only=True).eval()
    for a, b in zip(model.state_dict().values(), ref.state_dict().values()):
        assert torch.equal(a, b)
    pol = CheckpointPolicy(checkpoint=str(ckpt))
    assert pol.cameras == ("centre",) and pol.label == "gtu+hybrid"
    side = CheckpointPolicy(checkpoint=str(ckpt), camera="left")  # a table row must not read as the centre's
    assert side.cameras == ("left",) and side.label == "gtu+hybrid (left camera)"
    assert CheckpointPolicy(checkpoint=str(ckpt), camera="left", label="mine").label == "mine"
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (4, 88, 200, 3), dtype=np.uint8)
    speed = np.array([5.0, 10.0, 15.0, 20.0], np.float32)
    cmd = np.array([2, 3, 4, 5])
    obs = Observations(images={"centre": img}, speed_kmh=speed, command=cmd, pose=np.zeros((4, 3)),
                       routes=[None] * 4, episode=np.arange(4))
    steer = pol.act(obs)
    with torch.no_grad():
        want = ref.predict_steer(torch.from_numpy(img).permute(0, 3, 1, 2), torch.from_numpy(speed),
                                 torch.from_numpy(cmd - 2))
    assert steer.shape == (4,) and np.allclose(steer, want.numpy(), atol=1e-5)
    assert np.all(np.abs(steer) <= 1.0)
    # inference folds BatchNorm into the convolutions (and drops Dropout): same function, less work
    kinds = {type(m).__name__ for m in pol.model.modules()}
    assert "BatchNorm2d" not in kinds and "Dropout2d" not in kinds and "Conv2d" in kinds
    assert np.array_equal(CheckpointPolicy(checkpoint=str(ckpt), fuse=False).act(obs), want.numpy())


class Boom:
    def __reduce__(self):
        return (os.system, ("touch /tmp/cicfw_test_unpickled_me",))


def test_each_bad_checkpoint_gives_its_message(ckpt: Path, tmp_path: Path):
    def refused(name: str) -> CheckpointError:  # the error, after checking it names checkpoint= and the file
        with pytest.raises(CheckpointError) as err:
            read_checkpoint(tmp_path / name)
        assert err.value.key == "checkpoint" and str(err.value.value) == str((tmp_path / name).resolve())
        return err.value

    with pytest.raises(FileNotFoundError) as err:
        read_checkpoint(tmp_path / "missing.ckpt")
    assert "checkpoint" in str(err.value) and str(tmp_path / "missing.ckpt") in str(err.value)
    (tmp_path / "notes.ckpt").write_text("not a checkpoint")
    refused("notes.ckpt")
    torch.save(collections.OrderedDict(w=torch.zeros(2)), tmp_path / "state_dict.pt")
    assert "['w']" in str(refused("state_dict.pt"))  # the keys it found
    # a pickle that would run code is refused, and nothing ran
    marker = Path("/tmp/cicfw_test_unpickled_me")
    marker.unlink(missing_ok=True)
    torch.save({"state_dict": {}, "hyper_parameters": {"payload": Boom()}}, tmp_path / "evil.ckpt")
    refused("evil.ckpt")
    assert not marker.exists()
    # trained with parts that are not installed here
    data = torch.load(ckpt, weights_only=True)
    for key, registered in (("mixer", "gtu, independent"), ("head", "hybrid"), ("encoder", "cil")):
        bad = {**data, "hyper_parameters": {**data["hyper_parameters"], key: "their_plugin"}}
        torch.save(bad, tmp_path / f"no_{key}.ckpt")
        with pytest.raises(CheckpointError) as err:
            read_checkpoint(tmp_path / f"no_{key}.ckpt")
        assert (err.value.key, err.value.value) == (key, "their_plugin")
        assert all(n in str(err.value) for n in registered.split(", "))  # those installed
    # a diverged run's NaN weights: refused when loaded, not a NaN steer in the middle of a suite
    state = dict(data["state_dict"])
    name = next(k for k, v in state.items() if v.is_floating_point())
    state[name] = torch.full_like(state[name], float("nan"))
    torch.save({**data, "state_dict": state}, tmp_path / "diverged.ckpt")
    with pytest.raises(CheckpointError) as err:
        load_model(tmp_path / "diverged.ckpt")
    assert (err.value.key, err.value.value) == ("checkpoint", str(tmp_path / "diverged.ckpt"))
    assert name in str(err.value)
    # a folder: its single best checkpoint is taken; two are ambiguous
    run = tmp_path / "run" / "checkpoints"
    run.mkdir(parents=True)
    (run / "epoch001-mae0.3000.ckpt").write_bytes(ckpt.read_bytes())
    (run / "last.ckpt").write_bytes(ckpt.read_bytes())
    assert read_checkpoint(tmp_path / "run")["hyper_parameters"]["mixer"] == "gtu"
    (run / "epoch002-mae0.2000.ckpt").write_bytes(ckpt.read_bytes())
    with pytest.raises(CheckpointError) as err:
        read_checkpoint(tmp_path / "run")
    assert (err.value.key, err.value.value) == ("checkpoint", tmp_path / "run")


def test_weights_that_do_not_fit_their_model_name_the_key_and_the_counts(tmp_path: Path):
    """A deleted, added or reshaped weight, or another mixer's weights under the first's hyper_parameters:
    the loader evaluate, export and diagnose share names the weight and counts each kind, one line."""
    _, files = damaged_checkpoints(tmp_path)
    for name, (path, counts, key) in files.items():
        with pytest.raises(CheckpointError) as err:
            load_model(path)
        text = str(err.value)
        assert (err.value.key, err.value.value) == ("checkpoint", str(path)), name
        assert misfit_counts(text) == counts and repr(key) in text and "\n" not in text, text
    path, counts, key = files["missing"]
    with pytest.raises(CheckpointError) as err:  # evaluate's policy builds its model with the same loader
        CheckpointPolicy(checkpoint=str(path), device="cpu")
    assert err.value.key == "checkpoint" and misfit_counts(str(err.value)) == counts and repr(key) in str(err.value)


def test_evaluate_config_errors(tmp_path: Path):
    from cicfw.benchmark.app import compose_config, evaluate

    cases = [  # the overrides, the error kind, and the key and value it names (None: not one)
        ([f"checkpoint={tmp_path}/nope.ckpt"], FileNotFoundError, "checkpoint", f"{tmp_path}/nope.ckpt"),
        ([], ValueError, "checkpoint", None),
        (["policy=expert", f"checkpoint={tmp_path}/a.ckpt"], ValueError, "checkpoint", f"{tmp_path}/a.ckpt"),
        (["policy=expert", "suite.towns=[town_z]"], ValueError, None, "town_z"),
        (["policy=constant", "policy.steer=-3"], ValueError, "policy.steer", -3),
        (["policy=expert", "runner.batch_size=0"], ValueError, "runner.batch_size", 0),
        ([f"checkpoint={tmp_path}/a.ckpt", "policy.camera=bogus"], ValueError, "policy.camera", "bogus"),  # a typo
    ]
    for overrides, kind, key, value in cases:
        with pytest.raises(kind) as err:
            evaluate(compose_config(overrides + ["progress_bar=false"]), tmp_path / "run")
        if isinstance(err.value, CicfwError):
            assert (err.value.key, err.value.value) == (key, value), (overrides, str(err.value))
        else:
            assert key in str(err.value) and value in str(err.value), (overrides, str(err.value))
    assert not (tmp_path / "run").exists()  # nothing half-written


def test_multirun_joins_its_runs_into_one_table(tmp_path: Path):
    from conftest import run_app_in_process

    sweep = tmp_path / "sweep"
    proc = run_app_in_process(
        "cicfw.evaluate", "-m", "policy=expert,constant", f"suite.towns=[{TOWN}]", "suite.weathers=[ClearNoon]",
        "suite.pairs=[0,1,2]", "progress_bar=false", "maps=false", f"hydra.sweep.dir={sweep}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    md = (sweep / "table.md").read_text()
    assert "| Expert | – | – | 100.00 | – |" in md and "| constant steer +0.00 | – | – |" in md
    assert (sweep / "success_bars.png").is_file() and (sweep / "0" / "episodes.csv").is_file()


def test_a_two_step_checkpoint_runs_a_two_episode_suite_end_to_end(ckpt: Path, tmp_path: Path):
    from cicfw.benchmark.app import compose_config, evaluate
    from cicfw.benchmark.finished_run import load_trajectories

    cfg = compose_config([f"checkpoint={ckpt}", f"suite.towns=[{TOWN}]", "suite.weathers=[MidRainyNoon]",
                          "suite.training_towns=[]", "suite.pairs=[0,13]", "runner.batch_size=2", "runner.threads=1",
                          "progress_bar=false", "video=[1]", "name=two steps"])
    out = tmp_path / "eval"
    s = evaluate(cfg, out)
    assert s["model"] == "two steps" and s["episodes"] == 2
    assert list(s["cells"]) == ["new_town/new_weathers"]
    data = json.loads((out / "episodes.json").read_text())
    assert [r["key"] for r in data["episodes"]] == ["bench_town/MidRainyNoon/000", "bench_town/MidRainyNoon/013"]
    assert data["meta"]["checkpoint"] == str(ckpt) and data["meta"]["policy"] == "checkpoint"
    for r in data["episodes"]:
        assert r["reason"] in ("success", "timeout", "off_road", "off_route") and r["steps"] > 0
    assert "| two steps | – | – | – |" in (out / "table.md").read_text()
    trajs = load_trajectories(out)
    assert sorted(trajs) == ["bench_town/MidRainyNoon/000", "bench_town/MidRainyNoon/013"]
    assert len(trajs["bench_town/MidRainyNoon/000"]["x"]) == data["episodes"][0]["steps"]
    assert (out / "map_bench_town.png").stat().st_size > 10_000
    video = out / "videos" / "bench_town_MidRainyNoon_013.mp4"
    import cv2

    cap = cv2.VideoCapture(str(video))
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    ok, frame = cap.read()
    cap.release()
    assert ok and n == data["episodes"][1]["steps"] and frame.shape == (88 * 3 + 84, 600, 3)
    # any episode of a finished run can be filmed afterwards, with the same frames
    from cicfw.benchmark import video as video_cli

    assert video_cli.main([str(out), "bench_town/MidRainyNoon/013"]) == 0
    cap = cv2.VideoCapture(str(video))
    ok, again = cap.read()
    cap.release()
    assert ok and np.array_equal(again, frame)
    assert video_cli.main([str(out), "7"]) == 2  # no such episode: one error line


def test_the_summary_names_a_relative_checkpoint_by_its_absolute_file_too(ckpt: Path, tmp_path: Path, monkeypatch):
    """summary.json keeps the checkpoint as typed (relative to where the run started) and adds the file it named,
    absolute, so a summary read from another directory, or moved, still names it."""
    import shutil

    from cicfw.benchmark.app import evaluate_policy

    here = tmp_path / "work"
    (here / "runs").mkdir(parents=True)
    shutil.copy(ckpt, here / "runs" / "m.ckpt")
    monkeypatch.chdir(here)
    evaluate_policy({"name": "checkpoint", "checkpoint": "runs/m.ckpt"},
                    {"towns": [TOWN], "weathers": ["MidRainyNoon"], "training_towns": [], "pairs": [4]},
                    {"workers": 1, "threads": 1}, "eval", sim={"name": "embedded", "route_before": 6,
                                                             "max_deviation": 2}, maps=False)
    summary = json.loads((here / "eval" / "summary.json").read_text())
    assert summary["checkpoint"] == "runs/m.ckpt"
    assert summary["checkpoint_file"] == os.path.join(os.path.realpath(tmp_path), "work", "runs", "m.ckpt")


def test_train_can_end_with_the_suite(tiny_data: Path, tmp_path: Path):
    from cicfw.train.app import train
    from conftest import compose_train

    # an untrained model's episode, short: 6 m before its turn, ended 2 m off its route
    overrides = [f"suite.towns=[{TOWN}]", "suite.weathers=[MidRainyNoon]", "suite.pairs=[4]", "progress_bar=false",
                 "maps=false", "runner.threads=1", "sim.route_before=6", "sim.max_deviation=2"]
    cfg = compose_train("data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "data.val_batch_size=8",
                        "debug=fast", "progress_bar=false", "evaluate_after=true",
                        f"evaluate_overrides=[{','.join(repr(o) for o in overrides)}]")
    mae = train(cfg, tmp_path / "run")
    assert 0.0 <= mae < 2.0  # still the validation metric by default
    s = json.loads((tmp_path / "run" / "evaluate" / "summary.json").read_text())
    assert s["episodes"] == 1 and Path(s["checkpoint"]).parent == tmp_path / "run" / "checkpoints"
    assert Path(s["checkpoint"]).is_file()
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["closed_loop/success"] == s["success"]
    assert metrics["closed_loop/success/new_town/new_weathers"] == s["success"]  # not a training town
    cfg.return_closed_loop = True
    assert train(cfg, tmp_path / "run2") == json.loads((tmp_path / "run2" / "evaluate" / "summary.json")
                                                       .read_text())["success"]


def test_a_cuda_device_this_machine_lacks_is_one_line_before_driving(ckpt: Path, tmp_path: Path, monkeypatch):
    """``policy.device=cuda`` on a machine without CUDA ended in torch's "Torch not compiled with CUDA
    enabled" traceback; the agent's device check (shared with diagnose) refuses it in one line."""
    from cicfw.benchmark.journal import LOG_NAME
    from cicfw.benchmark.app import compose_config, evaluate

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = compose_config([f"checkpoint={ckpt}", "policy.device=cuda", f"suite.towns=[{TOWN}]",
                          "suite.weathers=[ClearNoon]", "suite.limit=1", "runner.workers=1", "progress_bar=false"])
    with pytest.raises(ValueError) as err:
        evaluate(cfg, tmp_path / "run")
    assert (err.value.key, err.value.value) == ("policy.device", "cuda") and "device=cpu" in str(err.value)  # way out
    assert "\n" not in str(err.value)
    assert not (tmp_path / "run" / LOG_NAME).exists()  # not one episode driven


def untrained_checkpoint(path: Path, seed: int) -> Path:
    """A CIL-size gtu+regression checkpoint of freshly initialised weights (``seed`` decides them)."""
    torch.manual_seed(seed)
    model = CICModule(mixer="gtu", head="regression")
    torch.save({"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams),
                "pytorch-lightning_version": L.__version__, "epoch": 0, "global_step": 0}, path)
    return path


def test_the_recorded_checkpoint_hash_is_of_the_weights_every_worker_drove(tmp_path: Path, monkeypatch):
    """A checkpoint file replaced right after the evaluation first read it (a training run rewrites its
    last.ckpt each epoch): the episode log records the SHA-256 of the bytes read, and worker processes drive
    those bytes' weights, never the file's new ones (which a rerun would otherwise reuse as the old's)."""
    import hashlib

    from cicfw.benchmark.app import evaluate_policy
    from cicfw.benchmark.journal import read_log
    from cicfw.model import checkpoint as checkpoint_module

    first = untrained_checkpoint(tmp_path / "first.ckpt", seed=0).read_bytes()
    second = untrained_checkpoint(tmp_path / "second.ckpt", seed=1).read_bytes()
    assert first != second
    live = tmp_path / "run" / "checkpoints" / "last.ckpt"
    live.parent.mkdir(parents=True)
    suite = {"towns": [TOWN], "weathers": ["MidRainyNoon"], "training_towns": [], "limit": 2}
    runner = {"batch_size": 1, "threads": 1}  # each episode alone, one thread: the same floats in any process

    def drive(out: Path, workers: int):
        return evaluate_policy({"name": "checkpoint", "checkpoint": str(live), "device": "cpu"}, suite,
                               {**runner, "workers": workers}, out, maps=False,
                               sim={"name": "embedded", "route_before": 6, "max_deviation": 2})  # short episodes

    live.write_bytes(first)
    drive(tmp_path / "ref", workers=1)  # the first file's episodes, nothing replaced
    _, ref_rows, ref_trajs, _ = read_log(tmp_path / "ref")

    read = checkpoint_module.load_weights_only
    replaced = []

    def then_replaced(source):  # the next training epoch lands just after the evaluation read the file
        ckpt = read(source)
        if not replaced:
            live.write_bytes(second)
            replaced.append(True)
        return ckpt

    live.write_bytes(first)
    monkeypatch.setattr(checkpoint_module, "load_weights_only", then_replaced)
    drive(tmp_path / "eval", workers=2)
    assert replaced and live.read_bytes() == second
    header, rows, trajs, _ = read_log(tmp_path / "eval")
    assert header["fingerprint"]["policy"]["checkpoint_sha256"] == hashlib.sha256(first).hexdigest()
    assert len(rows) == 2 and rows == ref_rows  # driven by the first file's weights, in both workers
    assert sorted(trajs) == sorted(ref_trajs)
    assert all(np.array_equal(trajs[k][c], ref_trajs[k][c]) for k in trajs for c in trajs[k])


def test_a_worker_keeps_no_checkpoint_bytes_once_its_policy_is_built(tmp_path: Path, monkeypatch):
    """A worker process is given the checkpoint's bytes (the whole file, optimizer state included: 3x the weights
    for Adam) to build its policy from; while it drives, neither the spec (held by its Process object) nor the
    policy holds them, so each of ``runner.workers`` processes carries its model only."""
    import gc
    import weakref

    from cicfw.benchmark import runner
    from cicfw.model.checkpoint import CheckpointBytes

    read = CheckpointBytes.read(untrained_checkpoint(tmp_path / "m.ckpt", seed=0))
    alive = weakref.ref(read)
    spec = {"name": "checkpoint", "checkpoint": read, "device": "cpu"}
    del read
    seen = []

    def drive(episodes, policy, backend, cfg, on_done):
        gc.collect()
        seen.append((alive() is not None, type(policy).__name__))
        return "driven"

    monkeypatch.setattr(runner, "drive", drive)
    monkeypatch.setattr(runner, "make_backend", lambda spec: None)
    monkeypatch.setattr(runner, "_exit_with_parent", lambda: None)  # in this process: no parent to watch
    sent = collections.deque()
    runner._worker(0, [], spec, {}, {"batch_size": 1, "threads": 1}, 1, SimpleQueue(sent))
    assert list(sent) == [("result", 0, "driven")], list(sent)
    assert seen == [(False, "CheckpointPolicy")]


class SimpleQueue:
    """What ``_worker`` puts, kept in order (a worker's queue to its parent)."""

    def __init__(self, items: collections.deque) -> None:
        self.items = items

    def put(self, item) -> None:
        self.items.append(item)
