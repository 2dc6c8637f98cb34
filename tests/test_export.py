"""cicfw export and the agent: every mixer x head exports to ONNX and TorchScript with the checkpoint's
steering (``CICModule.predict_steer``) on real frames and random inputs at batch 1 and 64; a broken
decoder inside the graph fails the export's own parity check; bad inputs give one line each and
leave nothing behind; docs/deploy.md's numpy loop runs without torch and cicfw, its CARLA loop on the
stand-in server.

The mixer x head grid uses a tiny test encoder (registered for this module only) so that 40 models
train, export twice and run in seconds; one CIL-size model trained by a Lightning Trainer goes
through the command line.
"""
from __future__ import annotations

import hashlib
import inspect
import json
import subprocess
import sys
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torch import nn

import cicfw.export.app as export
from cicfw.export.agent import Agent, AgentInputError, DrivingFunction
from cicfw.benchmark.checkpoint_policy import CheckpointPolicy
from cicfw.benchmark.policy import Observations
from cicfw.data.cil_hdf5 import T, write_file
from cicfw.export.app import ExportError, export_model
from cicfw.model.checkpoint import CheckpointError, load_model
from cicfw.model.encoders import Encoder
from cicfw.model.module import CICModule
from cicfw.registry import ENCODERS, HEADS, MIXERS
from cicfw.testing import make_targets, write_tiny_dataset
from conftest import assert_refused, misfit_counts, run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

TINY = "export_test_tiny"
DEPLOY_DOC = Path(__file__).resolve().parents[1] / "docs" / "deploy.md"
FORMATS = ("onnx", "torchscript")
#: the tolerance the tests hold every runtime to (the export's default)
TOL = export.TOLERANCE


class TinyEncoder(Encoder):
    """A few-thousand-parameter stand-in for the CIL stack, same contract (uint8 (B, 3, 88, 200), speed)."""

    def __init__(self, out_dim: int = 32) -> None:
        super().__init__()
        self.convs = nn.Sequential(nn.Conv2d(3, 8, 5, 4, bias=False), nn.BatchNorm2d(8), nn.ReLU(inplace=True),
                                   nn.AvgPool2d(7, 7))  # 88x200 -> 21x49 -> 3x7
        self.join = nn.Sequential(nn.Linear(8 * 3 * 7 + 1, out_dim), nn.ReLU(inplace=True), nn.Dropout(0.5))
        self.out_dim = out_dim

    def forward(self, image: torch.Tensor, speed: torch.Tensor) -> torch.Tensor:
        x = self.convs(image.float() / 255.0).flatten(1)
        return self.join(torch.cat([x, speed[:, None]], dim=1))


@pytest.fixture(scope="module", autouse=True)
def tiny_encoder():
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(ENCODERS._entries, TINY, TinyEncoder)
        mp.setitem(ENCODERS._origin, TINY, "cicfw")
        yield


def small_kwargs(mixer: str) -> dict:
    """Small widths for whichever of them the mixer takes."""
    params = inspect.signature(MIXERS.get(mixer).__init__).parameters
    want = {"hidden": 16, "expert_dim": 16, "experts": 2, "coef_hidden": 8}
    return {k: v for k, v in want.items() if k in params}


def tiny_checkpoint(path: Path, mixer: str, head: str, steps: int = 3, seed: int = 0) -> Path:
    """A tiny model trained for a few Adam steps (weights and BatchNorm statistics moved off their
    initial values), saved as Lightning saves a checkpoint."""
    torch.manual_seed(seed)
    model = CICModule(encoder=TINY, mixer=mixer, mixer_kwargs=small_kwargs(mixer), head=head).train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(steps):
        img = torch.randint(0, 256, (8, 3, 88, 200), dtype=torch.uint8)
        speed, cmd = torch.rand(8) * 40, torch.arange(8) % 4
        loss = model.head.loss(model(img, speed, cmd), torch.rand(8) * 1.2 - 0.6) + model.mixer.regularizer()
        opt.zero_grad()
        loss.backward()
        opt.step()
    torch.save({"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams),
                "pytorch-lightning_version": L.__version__, "epoch": 0, "global_step": steps}, path)
    return path


@pytest.fixture(scope="module")
def episode(tmp_path_factory) -> tuple[export.CheckInputs, Path]:
    """64 real frames of an episode the embedded simulator's expert drives, and the same frames written
    as a collected CIL HDF5 file."""
    frames = export.rendered_frames(64)
    t = make_targets(64, np.random.default_rng(0))
    t[:, T.SPEED], t[:, T.COMMAND], t[:, T.CAMERA_ID] = frames.speed_kmh, frames.command, 0
    path = write_file(tmp_path_factory.mktemp("episode") / "episode_000.h5", frames.images, t)
    return frames, path


def reference(ckpt: Path, inputs: export.CheckInputs) -> np.ndarray:
    """The checkpoint's own steering: ``CICModule.predict_steer`` of the model it rebuilds."""
    model = load_model(ckpt)
    with torch.no_grad():
        return model.predict_steer(torch.from_numpy(inputs.images).permute(0, 3, 1, 2),
                                   torch.from_numpy(inputs.speed_kmh), torch.from_numpy(inputs.command - 2)).numpy()


#: every how many inputs one is also run alone (batch 1): real and random frames, of every command. Batch 1
#: is one code path whichever frame runs it, and the batch of 64 covers every input: 15 of the 128 alone
#: suffice. Not a multiple of 2: the random inputs cycle through the 4 commands, and every one must run alone.
ONE_EVERY = 9


def max_diff(agent: Agent, inputs: export.CheckInputs, want: np.ndarray) -> float:
    """The agent's largest steering difference from ``want`` at batch 64 (every input) and batch 1 (every
    ``ONE_EVERY``-th: the same code path per frame, in a fraction of the calls)."""
    alone = range(0, len(inputs), ONE_EVERY)
    one = np.array([agent.act(inputs.images[i], inputs.speed_kmh[i], inputs.command[i]) for i in alone])
    big = np.concatenate([agent.act(inputs.images[i:i + 64], inputs.speed_kmh[i:i + 64], inputs.command[i:i + 64])
                          for i in range(0, len(inputs), 64)])
    assert big.shape == want.shape and one.shape == want[::ONE_EVERY].shape and np.all(np.abs(big) <= 1)
    assert {int(c) for c in inputs.command[::ONE_EVERY]} == {int(c) for c in inputs.command}  # every command alone
    return float(max(np.abs(one - want[::ONE_EVERY]).max(), np.abs(big - want).max()))


#: every mixer and every head, each mixer with the next head in turn (8 mixers x 5 heads: 8 pairs, each head 1-2
#: times). The head decodes the mixer's per-branch output through one interface and is traced after it, so a
#: pair fails to export only where its mixer or its head does; every pair is built and trained by
#: tests/test_zoo_training.py.
GRID = [(m, sorted(HEADS.names())[i % len(HEADS.names())]) for i, m in enumerate(sorted(MIXERS.names()))]


@pytest.mark.parametrize("mixer,head", GRID, ids=[f"{m}-{h}" for m, h in GRID])
def test_every_mixer_and_head_exports_with_parity(mixer, head, episode, tmp_path):
    frames, episode_file = episode
    ckpt = tiny_checkpoint(tmp_path / f"{mixer}-{head}.ckpt", mixer, head)
    inputs = frames + export.random_inputs(64, seed=1)
    want = reference(ckpt, inputs)
    assert max_diff(Agent.load(ckpt), inputs, want) <= TOL  # the checkpoint's agent: predict_steer, BatchNorm folded
    for fmt in FORMATS:
        out = tmp_path / f"model{export.FORMATS[fmt]}"
        info = export_model(ckpt, fmt, out, frames=episode_file, n_frames=4)
        assert info["parity"]["max_abs_diff"] <= TOL and info["parity"]["inputs"] == 8
        agent = Agent.load(out)
        assert agent.runtime == {"onnx": "onnxruntime", "torchscript": "torchscript"}[fmt]
        assert agent.info["mixer"] == mixer and agent.info["head"] == head  # the description travels inside
        assert max_diff(agent, inputs, want) <= TOL, f"{mixer}+{head} {fmt}"
        side = json.loads(out.with_name(out.name + ".json").read_text())
        assert side["decoder"]["head"] == head and side["command_codes"] == {"2": "follow", "3": "left", "4": "right",
                                                                             "5": "straight"}
        assert side["inputs"][0]["shape"] == ["batch", 88, 200, 3] and side["cicfw_version"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [ckpt.name, "model.onnx", "model.onnx.json", "model.pt", "model.pt.json"])  # no temporary file left


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_broken_decoder_in_the_graph_fails_the_parity_check(fmt, episode, tmp_path, monkeypatch):
    _, episode_file = episode
    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "gtu", "hybrid")
    real = export.graph_module

    def with_argmax_decoder(model):  # the graph decodes the argmax bin instead of the expectation
        graph = real(model)
        head = graph.model.head
        head.decode = lambda out: head.midpoints.to(out.dtype)[out.argmax(dim=-1)]
        return graph

    monkeypatch.setattr(export, "graph_module", with_argmax_decoder)
    out = tmp_path / f"m{export.FORMATS[fmt]}"
    with pytest.raises(ExportError) as err:
        export_model(ckpt, fmt, out, frames=episode_file, n_frames=4)
    assert "tolerance" in str(err.value) and "0.0001" in str(err.value), err.value  # the key and the bound missed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ckpt"]  # nothing written, nothing half-written


@pytest.fixture(scope="module")
def cil_run(tmp_path_factory) -> Path:
    """A CIL-size gtu+hybrid checkpoint trained for two steps by a Lightning Trainer, in a run folder
    whose saved config names its (tiny) training dataset."""
    from torch.utils.data import DataLoader, TensorDataset

    run = tmp_path_factory.mktemp("run")
    data = write_tiny_dataset(run / "data", n_files=2, n=8)
    (run / ".hydra").mkdir()
    OmegaConf.save(OmegaConf.create({"mixer": {"name": "gtu"}, "head": {"name": "hybrid", "W": 10.0},
                                     "data": {"path": str(data)}, "seed": 0}), run / ".hydra" / "config.yaml")

    L.seed_everything(0)
    model = CICModule(mixer="gtu", head="hybrid")
    g = torch.Generator().manual_seed(0)
    ds = TensorDataset(torch.randint(0, 256, (8, 3, 88, 200), dtype=torch.uint8, generator=g),
                       torch.rand(8, generator=g) * 30, torch.arange(8) % 4, torch.rand(8, generator=g) - 0.5)
    loader = DataLoader(ds, batch_size=4, collate_fn=lambda b: dict(zip(("image", "speed", "command", "steer"),
                                                                          map(torch.stack, zip(*b)))))
    trainer = L.Trainer(max_steps=2, limit_val_batches=0, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, accelerator="cpu")
    trainer.fit(model, loader)
    ckpt = run / "checkpoints" / "epoch000-mae0.5000.ckpt"  # a best checkpoint's name: what a run folder resolves to
    trainer.save_checkpoint(ckpt)
    return ckpt


def test_the_suites_policy_drives_through_the_agent_unchanged(cil_run, episode):
    frames, _ = episode
    pol = CheckpointPolicy(checkpoint=str(cil_run))
    assert isinstance(pol.agent, Agent) and pol.agent.runtime == "torch" and pol.label == "gtu+hybrid"
    obs = Observations(images={"centre": frames.images}, speed_kmh=frames.speed_kmh.astype(np.float64),
                       command=frames.command, pose=np.zeros((64, 3)), routes=[None] * 64, episode=np.arange(64))

    def before(rows: slice) -> np.ndarray:
        """The policy's inference before the agent existed, verbatim (bit for bit only at the same batch
        size: the kernels round differently at batch 1 and 64)."""
        img = torch.from_numpy(np.ascontiguousarray(frames.images[rows])).permute(0, 3, 1, 2)
        with torch.inference_mode():
            return pol.model.predict_steer(img, torch.from_numpy(frames.speed_kmh[rows]),
                                           torch.from_numpy(frames.command[rows] - 2)).float().clamp(-1.0, 1.0).numpy()

    steer = pol.act(obs)
    assert steer.dtype == np.float32 and np.array_equal(steer, before(slice(None)))
    one = pol.agent.act(frames.images[3], float(frames.speed_kmh[3]), int(frames.command[3]))
    # one frame: the same function, but not bit for bit (which kernels run at batch 1 depends on the
    # threads torch has when the test runs: a full-suite run saw 16 float32 ulps)
    assert isinstance(one, float) and abs(one - float(before(slice(3, 4))[0])) < 1e-6
    assert np.abs(steer - reference(cil_run, frames)).max() < 1e-5  # fused BatchNorm: the same function


def test_command_line_exports_a_cil_model_with_its_sidecar(cil_run, episode, tmp_path):
    frames, episode_file = episode
    out = tmp_path / "cil.onnx"
    res = run_app_in_process("cicfw.export", f"checkpoint={cil_run.parent.parent}", f"out={out}",
                             f"frames={episode_file}", "n_frames=4", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert f"cicfw export: {out} (" in res.stdout and "gtu+hybrid, onnx" in res.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cil.onnx", "cil.onnx.json"]  # no outputs/ folder
    side = json.loads((tmp_path / "cil.onnx.json").read_text())
    data = cil_run.parent.parent / "data"
    files = sorted(data.rglob("*.h5"))
    assert side["training_dataset"]["hash"] == hashlib.sha256(
        "".join(f"{f.name}:{f.stat().st_size}" for f in files).encode()).hexdigest()[:16]
    assert side["row_config"]["mixer"] == {"name": "gtu"} and side["label"] == "gtu+hybrid"
    assert side["checkpoint"]["sha256"] == hashlib.sha256(cil_run.read_bytes()).hexdigest()
    assert side["decoder"]["decode"] == "expectation" and side["normalisation"]["speed"] == "speed_kmh / 40"
    assert (side["parity"]["real_frames"], side["parity"]["random_inputs"]) == (4, 4)  # what the check ran on
    inputs = frames + export.random_inputs(64, seed=2)
    assert max_diff(Agent.load(out, threads=1), inputs, reference(cil_run, inputs)) <= TOL

    # docs/deploy.md's numpy loop, verbatim, in a process where torch and cicfw cannot be imported
    np.savez(tmp_path / "episode.npz", rgb=frames.images, speed_kmh=frames.speed_kmh, command=frames.command)
    loop = DEPLOY_DOC.read_text().split("## Without cicfw", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    script = ('import sys\nsys.modules["torch"] = sys.modules["cicfw"] = None\n' + loop
              + 'print(info["label"], repr(float(steer)))\n')
    res = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    label, last = res.stdout.split()
    assert label == "gtu+hybrid" and abs(float(last) - reference(cil_run, frames)[-1]) <= TOL


def test_export_renders_its_own_frames_and_writes_torchscript_by_default_beside_the_checkpoint(tmp_path, episode):
    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "independent", "sine")
    info = export_model(ckpt, "torchscript", n_frames=3)
    assert info["out"] == str(tmp_path / "m.pt") and "embedded simulator" in info["parity"]["what"]
    assert info["decoder"]["decode"] == "phase" and info["training_dataset"]["hash"] is None


def test_the_carla_loop_in_the_docs_drives_against_the_carla_wheels_api(episode, tmp_path, monkeypatch):
    """docs/deploy.md's CARLA client loop, verbatim but for five ticks, on the recording stand-in server
    (autospecs of the installed wheel's classes, calls bound to its stubs)."""
    import enum
    import types

    pytest.importorskip("carla", reason="the CARLA client is not installed: pip install -e '.[carla]'")
    from carla_standin import StandIn, maps_dir

    if maps_dir() is None:
        pytest.skip("CARLA's Town01/Town02 OpenDRIVE files are not in ../shared/carla-maps (or $CICFW_CARLA_MAPS)")
    _, episode_file = episode
    export_model(tiny_checkpoint(tmp_path / "m.ckpt", "gtu", "hybrid"), "onnx", tmp_path / "cil.onnx",
                 frames=episode_file, n_frames=2)
    si = StandIn(maps_dir())
    world = si.client.get_world()
    settings = world.get_settings()
    settings.synchronous_mode, settings.fixed_delta_seconds = True, 0.1
    world.apply_settings(settings)
    start = world.get_map().generate_waypoints(10.0)[0].transform  # an OpenDRIVE map has no spawn points
    car = world.spawn_actor(world.get_blueprint_library().find("vehicle.lincoln.mkz_2020"), start)
    # CARLA's PythonAPI agents package is not in the wheel: its RoadOption, as local_planner.py defines it
    planner = types.ModuleType("agents.navigation.local_planner")
    planner.RoadOption = enum.IntEnum("RoadOption", {"VOID": -1, "LEFT": 1, "RIGHT": 2, "STRAIGHT": 3,
                                                     "LANEFOLLOW": 4, "CHANGELANELEFT": 5, "CHANGELANERIGHT": 6})
    for name in ("agents", "agents.navigation"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    monkeypatch.setitem(sys.modules, "agents.navigation.local_planner", planner)
    monkeypatch.chdir(tmp_path)
    loop = DEPLOY_DOC.read_text().split("## Driving in CARLA", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    assert loop.count("while not done:") == 1
    exec(loop.replace("while not done:", "for _ in range(5):"),
         {"world": world, "car": car, "throttle": 0.4, "next_option": planner.RoadOption.LEFT})
    controls = si.controls()
    assert len(controls) == 5 and all(c[3] == pytest.approx(0.4) and -1 <= c[2] <= 1 for c in controls)
    assert si.check_calls() == []


# ---- bad input: one line each, nothing written ------------------------------------------------
def test_each_bad_export_gives_one_line_and_writes_nothing(tmp_path, episode, monkeypatch):
    _, episode_file = episode
    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "independent", "regression")
    run = dict(frames=episode_file, n_frames=2)
    torch.save({"w": torch.zeros(2)}, tmp_path / "weights.pt")
    (tmp_path / "cut.ckpt").write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
    cases = [  # the arguments, the error kind, and the key and value it carries (a checkpoint's: its path named)
        (dict(checkpoint=tmp_path / "weights.pt"), CheckpointError, None, tmp_path / "weights.pt"),
        (dict(checkpoint=tmp_path / "cut.ckpt"), CheckpointError, None, tmp_path / "cut.ckpt"),
        (dict(fmt="tflite"), ExportError, "format", "tflite"),
        (dict(out=tmp_path / "nope" / "m.onnx"), ExportError, "out", tmp_path / "nope" / "m.onnx"),
        (dict(out=tmp_path), ExportError, "out", tmp_path),
        (dict(n_frames=0), ExportError, "n_frames", 0),
        (dict(n_frames=65), ExportError, "n_frames", 65),  # the episode holds 64: not padded with random inputs
        (dict(tolerance=float("inf")), ExportError, "tolerance", float("inf")),  # no check: a NaN model would pass
    ]
    for kwargs, kind, key, value in cases:
        args = {"checkpoint": ckpt, "fmt": "onnx", "out": tmp_path / "m.onnx", **run, **kwargs}
        with pytest.raises(kind) as err:
            export_model(**args)
        assert "\n" not in str(err.value)
        if key is None:
            assert str(value) in str(err.value), err.value
        else:
            assert (err.value.key, err.value.value) == (key, value), err.value
    edited = torch.load(ckpt, weights_only=True)  # a weight deleted: the loader names it, not torch's cut line
    gone = next(iter(edited["state_dict"]))
    del edited["state_dict"][gone]
    torch.save(edited, tmp_path / "edited.ckpt")
    with pytest.raises(CheckpointError) as err:
        export_model(**{"checkpoint": tmp_path / "edited.ckpt", "fmt": "onnx", "out": tmp_path / "m.onnx", **run})
    assert err.value.key == "checkpoint" and misfit_counts(str(err.value)) == (1, 0, 0) and repr(gone) in str(err.value)
    with monkeypatch.context() as mp:  # a read-only folder (faked: root writes through chmod)
        mp.setattr(export.os, "access", lambda path, mode: False)
        with pytest.raises(ExportError) as err:
            export_model(ckpt, "onnx", tmp_path / "m.onnx", **run)
        assert (err.value.key, err.value.value) == ("out", tmp_path / "m.onnx")
    # a folder that cannot take the file (a full disk here): the temporary files go, nothing stays
    monkeypatch.setattr(export.os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(28, "No space left on device")))
    with pytest.raises(ExportError) as err:
        export_model(ckpt, "onnx", tmp_path / "m.onnx", **run)
    assert err.value.key == "out" and str(err.value.value).endswith("m.onnx.json")  # the file that failed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.ckpt", "edited.ckpt", "m.ckpt", "weights.pt"]


def test_more_frames_than_the_rendered_episodes_hold_are_refused_before_the_model_loads(tmp_path, monkeypatch):
    from cicfw.sim.render import Renderer

    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "independent", "regression")
    monkeypatch.setattr(export, "load_model", lambda *a, **k: pytest.fail("the model loaded before n_frames was checked"))
    monkeypatch.setattr(Renderer, "render", lambda *a, **k: pytest.fail("a frame drawn before n_frames was checked"))
    with pytest.raises(ExportError) as err:
        export_model(ckpt, "torchscript", tmp_path / "m.pt", n_frames=100_000)
    assert (err.value.key, err.value.value) == ("n_frames", 100_000)


def test_the_cli_prints_one_line_for_a_bad_checkpoint(tmp_path):
    (tmp_path / "notes.ckpt").write_text("not a checkpoint")
    res = run_app_in_process("cicfw.cli", "export", f"checkpoint={tmp_path / 'notes.ckpt'}", f"out={tmp_path / 'm.onnx'}")
    assert res.stdout == "" and res.stderr.count("\n") == 1, res.stderr
    assert_refused(res, "checkpoint", tmp_path / "notes.ckpt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.ckpt"]


@torch.library.custom_op("cicfw_export_test::twist", mutates_args=())
def twist(x: torch.Tensor) -> torch.Tensor:
    """An operator a plugin might bring: it runs in torch, ONNX has no form for it."""
    return x.flip(-1).clone()


@twist.register_fake
def _(x):
    return torch.empty_like(x)


twist.register_autograd(lambda ctx, grad: grad.flip(-1))  # so the plugin's model trains


class TwistMixer(nn.Module):
    """A plugin's mixer built on ``twist``."""

    n_branches = 4

    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__()
        self.out = nn.Linear(in_dim, 4 * out_dim)
        self.out_dim = out_dim

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return twist(self.out(h)).view(h.shape[0], 4, self.out_dim)

    def regularizer(self) -> torch.Tensor:
        return self.out.weight.new_zeros(())


def test_a_plugin_operator_that_does_not_export_is_named(tmp_path, episode, monkeypatch):
    _, episode_file = episode
    monkeypatch.setitem(MIXERS._entries, "twist", TwistMixer)
    monkeypatch.setitem(MIXERS._origin, "twist", "cicfw-twist-mixer")
    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "twist", "regression")
    with pytest.raises(ExportError) as err:
        export_model(ckpt, "onnx", tmp_path / "m.onnx", frames=episode_file, n_frames=2)
    msg = str(err.value)  # names the operator, the part and the plugin it came from, and the way out
    assert all(s in msg for s in ("'cicfw_export_test::twist'", "'twist'", "'cicfw-twist-mixer'", "format=torchscript"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ckpt"]
    export_model(ckpt, "torchscript", tmp_path / "m.pt", frames=episode_file, n_frames=2)  # and this one does


def test_the_agent_names_the_checkpoint_file_it_loaded_from_a_run_folder(tmp_path):
    """Given a run folder, the agent's ``info["source"]`` is the checkpoint file it chose there, not the folder."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    ckpt = tiny_checkpoint(run / "checkpoints" / "epoch=1-step=3.ckpt", "independent", "softmax")
    agent = Agent.load(run)
    assert agent.info["source"] == str(ckpt)
    assert agent.info["decoder"]["decode"] == "argmax"  # as a sidecar gives it (docs/deploy.md)


# ---- the agent's inputs -------------------------------------------------------------------------
def test_the_agent_says_what_it_expects(tmp_path):
    agent = Agent.load(tiny_checkpoint(tmp_path / "m.ckpt", "independent", "softmax"))
    frame = np.zeros((88, 200, 3), np.uint8)
    cases = [
        ((np.zeros((3, 88, 200), np.uint8), 10, 2), r"channels-first \(C, H, W\).*use image.transpose\(1, 2, 0\)"),
        ((np.zeros((5, 3, 88, 200), np.uint8), [10] * 5, [2] * 5), r"use images.transpose\(0, 2, 3, 1\)"),
        ((np.zeros((88, 200, 4), np.uint8), 10, 2), r"4 channels \(BGRA.*image\[\.\.\., 2::-1\]"),
        ((np.zeros((600, 800, 3), np.uint8), 10, 2), r"\(600, 800, 3\): the agent expects uint8 RGB frames \(88, 200, 3\)"),
        ((frame.astype(np.float32) / 255, 10, 2), r"dtype float32: the agent expects uint8 pixels 0-255"),
        ((frame, 10, 1), r"^command code 1 is not a CIL command: the agent expects 2 follow, 3 left, 4 right, "
                         r"5 straight \(the branch is code - 2\)$"),
        ((np.stack([frame] * 2), [10, 10], [2, 6]), r"command code 6 is not a CIL command"),
        ((np.stack([frame] * 2), [10], [2, 3]), r"2 image\(s\) but 1 speed\(s\) and 2 command\(s\)"),
    ]
    for args, message in cases:
        with pytest.raises(AgentInputError, match=message) as err:
            agent.act(*args)
        assert "\n" not in str(err.value)
    assert isinstance(agent.act(frame, 10.0, np.float32(4.0)), float)  # CIL's targets store codes as floats


def test_driving_function_is_the_modules_predict_steer():
    torch.manual_seed(0)
    model = CICModule(encoder=TINY, mixer="independent", mixer_kwargs={"hidden": 8}, head="hybrid").eval()
    img = torch.randint(0, 256, (5, 88, 200, 3), dtype=torch.uint8)
    speed, code = torch.rand(5) * 30, torch.tensor([2, 3, 4, 5, 2])
    with torch.no_grad():
        got = DrivingFunction(model)(img, speed, code)
    assert torch.equal(got, model.predict_steer(img.permute(0, 3, 1, 2), speed, code - 2).clamp(-1, 1))


# ---- bad frames= and opset=: one line, up front -------------------------------------------------
def test_frames_that_are_not_cil_data_are_one_line_naming_frames(tmp_path, monkeypatch):
    """frames= of a text file, an empty file or a folder without HDF5 files: one line naming frames=
    (the h5py traceback and data.path= before), refused before the model loads; nothing written."""
    import h5py

    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "independent", "regression")
    (tmp_path / "notes.h5").write_text("hello\n")
    (tmp_path / "empty.h5").write_bytes(b"")
    (tmp_path / "nothing").mkdir()
    (tmp_path / "zero").mkdir()
    with h5py.File(tmp_path / "zero" / "data_00000.h5", "w") as f:  # the CIL layout, no sample
        f.create_dataset("rgb", (0, 88, 200, 3), np.uint8)
        f.create_dataset("targets", (0, 28), np.float32)
    monkeypatch.setattr(export, "load_model", lambda *a, **k: pytest.fail("the model loaded before frames= was checked"))
    before = sorted(p.name for p in tmp_path.iterdir())
    for name in ("notes.h5", "empty.h5", "nothing", "zero"):
        with pytest.raises(ExportError) as err:
            export_model(ckpt, "onnx", tmp_path / "m.onnx", frames=tmp_path / name, n_frames=2)
        assert (err.value.key, err.value.value) == ("frames", tmp_path / name) and "\n" not in str(err.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_frames_with_a_command_code_the_model_has_no_branch_for_are_one_line(tmp_path, monkeypatch):
    """Real frames whose command code is 7 went into the parity check and failed the tracing, which was then
    reported as an operator TorchScript cannot trace, to be reported as a cicfw bug."""
    from cicfw.testing import write_tiny_dataset

    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "independent", "regression")
    frames = write_tiny_dataset(tmp_path / "frames", n_files=1, n=8, commands=(7,))
    monkeypatch.setattr(export, "load_model", lambda *a, **k: pytest.fail("the model loaded before frames= was checked"))
    with pytest.raises(ExportError) as err:
        export_model(ckpt, "torchscript", tmp_path / "m.pt", frames=frames, n_frames=2)
    assert (err.value.key, err.value.value) == ("frames", frames) and "command code 7" in str(err.value)
    assert not (tmp_path / "m.pt").exists()


def test_the_cli_refuses_a_text_frames_file_in_one_line(tmp_path):
    (tmp_path / "notes.h5").write_text("hello\n")
    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "independent", "regression")
    res = run_app_in_process("cicfw.export", f"checkpoint={ckpt}", f"out={tmp_path / 'm.onnx'}",
                             f"frames={tmp_path / 'notes.h5'}")
    assert res.stdout == "" and res.stderr.count("\n") == 1, res.stderr
    assert_refused(res, "frames", tmp_path / "notes.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ckpt", "notes.h5"]


@pytest.mark.parametrize("opset", ["abc", 99, 6, True, 17.0])
def test_an_opset_torch_cannot_write_is_refused_up_front(tmp_path, monkeypatch, opset):
    """opset= outside the range torch.onnx states (its TorchScript-based exporter's) is one line with that
    range, before the checkpoint is read, not an export failure that asks to report a cicfw bug."""
    from torch.onnx import _constants

    monkeypatch.setattr(export, "resolve_checkpoint", lambda *a: pytest.fail("the checkpoint was read first"))
    low, high = _constants.ONNX_MIN_OPSET, _constants.ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET
    assert export.opset_range() == (low, high) and low <= export.DEFAULT_OPSET <= high
    with pytest.raises(ExportError) as err:
        export_model(tmp_path / "m.ckpt", "onnx", tmp_path / "m.onnx", opset=opset)
    assert err.value.key == "opset" and err.value.value is opset
    assert f"{low}" in str(err.value) and f"{high}" in str(err.value)  # the range there is
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("opset", ["5", "17"])
def test_an_opset_given_for_torchscript_is_refused_up_front(tmp_path, opset):
    """format=torchscript opset=5 exported and exit 0: the opset, ONNX's only, was silently ignored. Given
    explicitly it is refused, before the checkpoint is read; left out, torchscript exports as before."""
    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "independent", "regression")
    res = run_app_in_process("cicfw.export", f"checkpoint={ckpt}", "format=torchscript", f"opset={opset}",
                             f"out={tmp_path / 'm.pt'}")
    assert_refused(res, "opset", opset)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ckpt"]


def test_an_opset_too_old_for_an_operator_asks_for_a_newer_one(tmp_path):
    """opset 7 is torch's, but lacks an operator cicfw's own parts use: the line asks for a newer opset
    instead of calling it a cicfw bug."""
    ckpt = tiny_checkpoint(tmp_path / "m.ckpt", "independent", "regression")
    frames = write_tiny_dataset(tmp_path / "data", n_files=1, n=4)
    with pytest.raises(ExportError) as err:
        export_model(ckpt, "onnx", tmp_path / "m.onnx", frames=frames, n_frames=2, opset=7)
    assert "opset=17" in str(err.value) and "format=torchscript" in str(err.value)  # the overrides that work
    assert "please report" not in str(err.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "m.ckpt"]


def test_an_export_written_to_the_same_out_meanwhile_is_never_replaced(tmp_path, episode, monkeypatch):
    """Another export writes ``out`` after this one checked it (both found nothing there): this one is one
    line naming ``out`` and writes nothing, the other's model and sidecar stay byte for byte."""
    _, episode_file = episode
    ckpt = tiny_checkpoint(tmp_path / "a.ckpt", "gtu", "hybrid")
    out = tmp_path / "model.pt"
    theirs = {out: b"their model", out.with_name("model.pt.json"): b'{"theirs": true}\n'}
    original = export.parity

    def another_export_finishes(*args, **kwargs):
        for path, data in theirs.items():
            path.write_bytes(data)
        return original(*args, **kwargs)

    monkeypatch.setattr(export, "parity", another_export_finishes)
    with pytest.raises(ExportError) as err:
        export_model(ckpt, "torchscript", out, frames=episode_file, n_frames=2)
    assert err.value.key == "out" and str(out) in str(err.value), str(err.value)
    assert {p: p.read_bytes() for p in tmp_path.iterdir() if p != ckpt} == theirs


@pytest.mark.parametrize("fmt", FORMATS)
def test_the_sidecar_hash_is_of_the_checkpoint_bytes_exported(fmt, tmp_path, episode, monkeypatch):
    """A checkpoint replaced right after export first read it (a training run rewrites its last.ckpt each
    epoch): the sidecar's sha256 is of the bytes the exported model was built from, not of the new file;
    the exported model, read once as bytes, runs as it does from its file."""
    from cicfw.model import checkpoint as checkpoint_module
    from cicfw.model.checkpoint import CheckpointBytes

    inputs, episode_file = episode
    first = tiny_checkpoint(tmp_path / "first.ckpt", "gtu", "regression", seed=0)
    second = tiny_checkpoint(tmp_path / "second.ckpt", "gtu", "regression", seed=1)
    live = tmp_path / "run" / "checkpoints" / "last.ckpt"
    live.parent.mkdir(parents=True)
    live.write_bytes(first.read_bytes())
    read = checkpoint_module.load_weights_only
    replaced = []

    def then_replaced(source):  # the next training epoch lands just after the export read the file
        ckpt = read(source)
        if not replaced:
            live.write_bytes(second.read_bytes())
            replaced.append(True)
        return ckpt

    monkeypatch.setattr(checkpoint_module, "load_weights_only", then_replaced)
    res = export_model(live, fmt, tmp_path / f"model.{'onnx' if fmt == 'onnx' else 'pt'}", frames=episode_file,
                       n_frames=2)
    monkeypatch.undo()
    assert replaced and live.read_bytes() == second.read_bytes()
    side = json.loads(Path(res["sidecar"]).read_text())
    assert side["checkpoint"]["sha256"] == hashlib.sha256(first.read_bytes()).hexdigest()
    steer = Agent.load(res["out"]).act(inputs.images, inputs.speed_kmh, inputs.command)
    assert np.abs(steer - reference(first, inputs)).max() <= TOL  # the model exported is the hashed bytes'
    assert np.abs(steer - reference(second, inputs)).max() > 100 * TOL
    read = CheckpointBytes.read(res["out"])
    assert read.sha256 == hashlib.sha256(Path(res["out"]).read_bytes()).hexdigest()
    from_bytes = Agent.load(read)
    assert from_bytes.info["label"] == "gtu+regression"  # its description, from the model or its sidecar
    assert np.array_equal(from_bytes.act(inputs.images, inputs.speed_kmh, inputs.command), steer)
