"""The steering diagnostic (``cicfw diagnose``, ``cicfw.diagnose.steer_diagnostic``) on models with a known answer.

The frames are tiny episodes whose image carries its own expert steering in one pixel, so a plain
``steer_fn`` can be a model with an exact, known relation to the expert: half the expert's steering
(slope 0.5, offset 0), one that ignores the command (swap effect 0), one whose branches are constants
(known shifts). Expected values are written by hand or recomputed here with other formulas (numpy).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hydra import compose, initialize_config_module

from cicfw.diagnose import steer_diagnostic as sd
from cicfw.data.cil_hdf5 import N_TARGETS, T, write_file
from cicfw.data.frames import load_frames, split_by_episode
from conftest import assert_refused, fill_the_disk_for_pictures, run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

REPO = Path(__file__).resolve().parents[1]


def all_commands(steer_fn):
    """A ``steer_all_fn`` from a plain ``steer_fn(images, speed, branch) -> steer``: the frames under each command."""
    def steer_all(images, speed):
        branch = [torch.full((len(speed),), c, dtype=torch.long) for c in range(4)]
        return np.stack([torch.as_tensor(steer_fn(images, speed, b)).detach().double().numpy() for b in branch], 1)

    return steer_all


# ------------------------------------------------------------------------------------------------
# tiny episodes: commands over time, steering written into pixel (0, 0) of the red channel

# one episode of 40 frames: follow 6, left 12, follow 8, right (or straight) 10, follow 4
PLAN = [(2, 6), (3, 12), (2, 8), (4, 10), (2, 4)]
PLAN_STRAIGHT = [(2, 6), (3, 12), (2, 8), (5, 10), (2, 4)]
STEER_RANGE = {2: (-0.05, 0.05), 3: (-0.5, -0.1), 4: (0.1, 0.5), 5: (-0.05, 0.05)}


def encode(steer: np.ndarray) -> np.ndarray:
    return (np.rint(np.asarray(steer) * 100) + 100).astype(np.uint8)


def decode_pixel(images: torch.Tensor) -> torch.Tensor:
    """The expert steering a tiny frame carries (images (B, 3, 88, 200) uint8), in float32 as the file holds it."""
    return (images[:, 0, 0, 0].float() - 100.0) / 100.0


def episode_targets(plan, rng: np.random.Generator, speed_kmh: float = 36.0) -> np.ndarray:
    codes = np.concatenate([np.full(n, c) for c, n in plan])
    n = len(codes)
    t = np.zeros((n, N_TARGETS), np.float32)
    lo = np.array([STEER_RANGE[c][0] for c in codes])
    hi = np.array([STEER_RANGE[c][1] for c in codes])
    t[:, T.STEER] = np.rint(rng.uniform(lo, hi) * 100) / 100  # exactly what the pixel can carry
    t[:, T.SPEED] = speed_kmh  # 36 km/h at 10 Hz: 1 m a frame
    t[:, T.COMMAND] = codes
    t[:, T.GAME_TIME] = np.arange(n) * 100.0  # ms
    return t


def write_episodes(folder: Path, n_files: int = 8, plan_of=lambda i: PLAN_STRAIGHT if i in (1, 4, 7) else PLAN,
                   seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    for i in range(n_files):
        t = episode_targets(plan_of(i), rng)
        rgb = np.zeros((len(t), 88, 200, 3), np.uint8)
        rgb[:, 0, 0, 0] = encode(t[:, T.STEER])
        rgb[:, 10:20, 10:20, 1] = rng.integers(0, 255, (len(t), 1, 1))  # something for a real network to see
        write_file(folder / f"ep{i:03d}.h5", rgb, t)
    return folder


@pytest.fixture
def episodes(tmp_path: Path) -> Path:
    return write_episodes(tmp_path / "episodes")


def measure_with(folder: Path, steer_fn, approach_m: float = 3.0, exit_s: float = 0.5, seed: int = 0,
                 split: str = "val"):
    frames, store = sd.load_split(sd.DataSettings(str(folder), seed=seed), split)
    return sd.measure(frames, store.get, all_commands(steer_fn), approach_m=approach_m, exit_s=exit_s,
                      batch_size=16)


# ------------------------------------------------------------------------------------------------
# phases


def test_phases_of_a_hand_written_sequence():
    codes = [5, 5, 2, 2, 3, 3, 3, 3, 3, 2, 2, 2, 2, 4, 4, 4, 3, 3, 2, 2]
    phase, turn = sd.assign_phases(codes, np.full(20, 36.0), np.arange(20) * 0.1, approach_m=2.5, exit_s=0.25)
    expected = (["unknown"] * 2                          # straight already on at the first frame: no onset seen
                + ["exit"] * 2                           # 0.0 and 0.1 s after it ended
                + ["approach"] * 3 + ["inside"] * 2      # left: 0, 1, 2 m driven < 2.5 m; then 3, 4 m
                + ["exit"] * 3 + ["lane"]                # 0.0, 0.1, 0.2 s < 0.25 s; then 0.3 s
                + ["approach"] * 3                       # right: 0, 1, 2 m
                + ["approach"] * 2                       # left right after right: a new onset
                + ["exit"] * 2)
    assert phase.tolist() == expected
    assert turn.tolist() == [5, 5, 5, 5, 3, 3, 3, 3, 3, 3, 3, 3, 2, 4, 4, 4, 3, 3, 3, 3]


def test_phases_follow_distance_and_time_not_frame_counts():
    codes = [2, 3, 3, 3, 3, 3, 2, 2, 2, 2]
    # half the speed: 0.5 m a frame, so 2.5 m of approach is five frames (0, .5, 1, 1.5, 2 m)
    phase, _ = sd.assign_phases(codes, np.full(10, 18.0), np.arange(10) * 0.1, approach_m=2.5, exit_s=0.25)
    assert phase.tolist() == ["lane"] + ["approach"] * 5 + ["exit"] * 3 + ["lane"]
    # frames 0.2 s apart: 2 m a frame at 36 km/h, and the exit is two frames (0, 0.2 s)
    phase, _ = sd.assign_phases(codes, np.full(10, 36.0), np.arange(10) * 0.2, approach_m=2.5, exit_s=0.25)
    assert phase.tolist() == ["lane", "approach", "approach", "inside", "inside", "inside", "exit", "exit", "lane", "lane"]
    # no usable time (all zero, as in files without game time): dt_s apart
    phase, _ = sd.assign_phases(codes, np.full(10, 36.0), np.zeros(10), approach_m=2.5, exit_s=0.25, dt_s=0.1)
    assert phase.tolist() == ["lane"] + ["approach"] * 3 + ["inside"] * 2 + ["exit"] * 3 + ["lane"]


def test_phases_are_computed_on_whole_episodes_per_camera(tmp_path: Path):
    """Two cameras interleaved, one episode split over two files (dataset_metadata.json), and a frame
    dropped by the loader's |steer| <= 0.8 filter: phases are those of each camera's whole sequence."""
    rng = np.random.default_rng(1)
    one = episode_targets(PLAN, rng)
    one[8, T.STEER] = 0.95  # an approach frame the loader drops
    both = np.repeat(one, 2, axis=0)
    both[:, T.CAMERA_ID] = np.tile([0, 1], len(one))
    folder = tmp_path / "d"
    for p in range(2):
        part = both[p * 40:(p + 1) * 40]
        write_file(folder / f"epA_{p:03d}.h5", np.zeros((len(part), 88, 200, 3), np.uint8), part)
    (folder / "dataset_metadata.json").write_text(json.dumps(
        {"files": {"epA_000.h5": {"episode": "epA"}, "epA_001.h5": {"episode": "epA"}}}))
    frames = load_frames(str(folder))
    assert len(frames) == 2 * 40 - 2  # the 0.95 frame of both cameras dropped
    phase, turn = sd.frame_phases(frames, approach_m=3.0, exit_s=0.5)
    want_phase, want_turn = sd.assign_phases(one[:, T.COMMAND], one[:, T.SPEED], one[:, T.GAME_TIME] / 1000,
                                             approach_m=3.0, exit_s=0.5)
    step = (frames.file_idx * 40 + frames.row) // 2  # the time step of each kept frame
    assert phase.tolist() == want_phase[step].tolist()
    assert turn.tolist() == want_turn[step].tolist()
    assert want_phase[6:9].tolist() == ["approach"] * 3 and want_phase[9] == "inside"


# ------------------------------------------------------------------------------------------------
# the measures, recomputed independently


def test_fit_line_matches_numpy_polyfit():
    rng = np.random.default_rng(3)
    expert = rng.uniform(-0.6, 0.6, 200)
    pred = 0.37 * expert - 0.02 + rng.normal(0, 0.05, 200)
    fit = sd.fit_line(expert, pred)
    slope, offset = np.polyfit(expert, pred, 1)
    assert fit["slope"] == pytest.approx(slope, abs=1e-10) and fit["offset"] == pytest.approx(offset, abs=1e-10)
    assert fit["mae"] == pytest.approx(np.abs(pred - expert).mean())
    assert fit["r"] == pytest.approx(np.corrcoef(expert, pred)[0, 1])
    assert fit["n"] == 200
    flat = sd.fit_line(np.full(5, 0.1), np.arange(5.0))  # the expert's steering does not vary: no line
    assert flat["slope"] is None and flat["offset"] is None and flat["mae"] == pytest.approx(np.mean(np.abs(np.arange(5.0) - 0.1)))


def test_half_the_expert_has_slope_half_and_offset_zero(episodes: Path):
    d, arrays = measure_with(episodes, lambda images, speed, command: 0.5 * decode_pixel(images))
    assert len(d.expert) == 80  # the seeded split keeps 2 of the 8 episodes for validation (centre camera)
    assert np.allclose(d.pred, 0.5 * d.expert, atol=1e-12)
    assert {(r["by"], r["command"], r["phase"]) for r in d.rows} >= {
        ("command", "left", "all"), ("phase", "all", "inside"), ("junction", "left", "approach"),
        ("junction", "left", "inside"), ("junction", "left", "exit"), ("junction", "right", "inside"),
        ("junction", "straight", "inside"), ("junction", "follow", "lane")}
    for r in d.rows:
        assert r["slope"] == pytest.approx(0.5, abs=1e-9), r
        assert r["offset"] == pytest.approx(0.0, abs=1e-9), r
    left = next(r for r in d.rows if (r["by"], r["command"]) == ("command", "left"))
    mask = d.command == 1
    assert left["n"] == int(mask.sum()) == 24  # 12 left frames in each of the 2 validation episodes
    assert left["mae"] == pytest.approx(np.mean(np.abs(0.5 * d.expert[mask] - d.expert[mask])))


def test_a_model_that_ignores_the_command_has_no_swap_effect(episodes: Path):
    d, _ = measure_with(episodes, lambda images, speed, command: 0.8 * decode_pixel(images) + 0.01 * speed / 36)
    assert d.pairs and {p["frames"] for p in d.pairs} == {"all", "junction", "lane"}
    for p in d.pairs:
        assert all(v == 0.0 for k, v in p.items() if k not in ("frames", "n")), p
    for r in d.rows:
        assert r["shift_left"] == r["shift_right"] == r["shift_straight"] == 0.0


def test_a_model_with_constant_branches_has_the_known_swap_effect(episodes: Path):
    values = torch.tensor([0.0, -0.3, 0.3, 0.1], dtype=torch.float64)  # follow, left, right, straight
    d, _ = measure_with(episodes, lambda images, speed, command: values[command])
    for p in d.pairs:
        assert p["follow-left"] == pytest.approx(0.3) and p["left-right"] == pytest.approx(0.6)
        assert p["right-straight"] == pytest.approx(0.2) and p["follow-straight"] == pytest.approx(0.1)
    inside_left = next(r for r in d.rows if (r["by"], r["command"], r["phase"]) == ("junction", "left", "inside"))
    assert inside_left["shift_left"] == pytest.approx(-0.3) and inside_left["shift_right"] == pytest.approx(0.3)
    mask = (d.turn == 3) & (d.phase == "inside")
    assert inside_left["needed"] == pytest.approx(d.expert[mask].mean() - 0.0)
    assert inside_left["pred_mean"] == pytest.approx(-0.3)


def test_no_junction_frames_is_one_clear_error(tmp_path: Path):
    folder = write_episodes(tmp_path / "lane", plan_of=lambda i: [(2, 40)])
    with pytest.raises(sd.DiagnosticError) as err:
        measure_with(folder, lambda images, speed, command: decode_pixel(images), split="all")
    assert "\n" not in str(err.value)


# ------------------------------------------------------------------------------------------------
# a real network: every head through its own decoder


@pytest.mark.parametrize("head,head_kwargs,mixer", [
    ("regression", {}, "independent"), ("softmax", {}, "independent"), ("hybrid", {"decode": "expectation"}, "gtu"),
    ("coexistence", {}, "independent"), ("sine", {"n_units": 21}, "independent")])
def test_the_fast_path_decodes_every_head_like_predict_steer(head, head_kwargs, mixer):
    from cicfw.model.module import CICModule

    torch.manual_seed(0)
    model = CICModule(head=head, head_kwargs=head_kwargs, mixer=mixer).eval()
    images = torch.randint(0, 255, (3, 3, 88, 200), dtype=torch.uint8)
    speed = torch.tensor([0.0, 12.0, 30.0])
    fast = sd.model_steer_all(model)(images, speed)
    slow = all_commands(model.predict_steer)(images, speed)
    assert fast.shape == (3, 4)
    assert np.allclose(fast, slow, atol=1e-6)


def test_a_head_without_a_decoder_is_one_clear_error():
    from cicfw.model.module import CICModule

    model = CICModule().eval()
    model.head.decode = lambda out: (_ for _ in ()).throw(NotImplementedError())
    with pytest.raises(sd.DiagnosticError) as err:
        sd.model_steer_all(model)(torch.zeros(2, 3, 88, 200, dtype=torch.uint8), torch.zeros(2))
    assert type(model.head).__name__ in str(err.value)  # names the head


# ------------------------------------------------------------------------------------------------
# the app


def save_checkpoint(run: Path, **hp) -> Path:
    from cicfw.model.module import CICModule

    torch.manual_seed(0)
    model = CICModule(**hp)
    path = run / "checkpoints" / "epoch001.ckpt"
    path.parent.mkdir(parents=True)
    torch.save({"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams), "epoch": 0,
                "global_step": 5}, path)
    return path


def write_run_config(run: Path, data: Path, seed: int) -> None:
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(
        f"seed: {seed}\ndata:\n  path: {data}\n  seed: ${{seed}}\n  val_fraction: 0.3\n  batch_size: 120\n")


def diagnose_cfg(*overrides: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("diagnose", overrides=list(overrides))


def test_the_app_end_to_end(tmp_path: Path, episodes: Path):
    """``python -m cicfw.diagnose checkpoint=...`` finds the run's split in its saved config and writes
    the report; the frames are exactly the validation episodes of that split (recomputed here)."""
    run = tmp_path / "run"
    ckpt = save_checkpoint(run, head="softmax")
    write_run_config(run, episodes, seed=3)
    out = tmp_path / "out"
    res = run_app_in_process("cicfw.diagnose", f"checkpoint={ckpt}", f"hydra.run.dir={out}", "phases.approach_m=3",
                             "threads=1", cwd=REPO, env={"OMP_NUM_THREADS": "1"})
    assert res.returncode == 0, res.stderr[-3000:]
    doc = json.loads((out / "steer_diagnostic.json").read_text())
    _, val = split_by_episode(load_frames(str(episodes)), 0.3, 3)
    assert doc["data"]["seed"] == 3 and doc["data"]["frames"] == len(val) == 80
    assert doc["data"]["source"].endswith("(the training run's config)")
    assert doc["model"] == "independent+softmax" and doc["epoch"] == 1 and doc["phases"]["approach_m"] == 3.0
    frames = np.load(out / "steer_frames.npz")
    assert sorted(set(frames["episode"].tolist())) == sorted(set(val.group.tolist()))
    assert all((out / f).stat().st_size > 0 for f in ("steer_diagnostic.md", "steer_diagnostic.csv", "steer_scatter.png"))
    md = (out / "steer_diagnostic.md").read_text()
    assert "| junction | left | inside |" in md
    measured = md.splitlines()[2]  # under the title: which frames of which checkpoint
    assert "val split" in measured and "80 frames" in measured and str(ckpt) in measured, measured


def test_an_unreadable_saved_config_is_one_line_naming_it(tmp_path: Path, episodes: Path):
    """A run config beside the checkpoint that YAML cannot read: one line naming that file, nothing written."""
    run = tmp_path / "run"
    ckpt = save_checkpoint(run, head="softmax")
    write_run_config(run, episodes, seed=3)
    config = run / ".hydra" / "config.yaml"
    config.write_text("data: {path: [unclosed\n")
    out = tmp_path / "out"
    res = run_app_in_process("cicfw.diagnose", f"checkpoint={ckpt}", f"hydra.run.dir={out}", "threads=1", cwd=REPO,
                             env={"OMP_NUM_THREADS": "1"})
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-3000:]
    line = [ln for ln in res.stderr.splitlines() if ln.startswith("cicfw: error:")]
    assert len(line) == 1 and str(config) in line[0], res.stderr
    assert not (out / "steer_diagnostic.json").exists()


@pytest.mark.parametrize("split, said", [("train", "train split"), ("val", "val split"), ("all", "every frame")])
def test_the_markdown_report_says_which_frames_it_measured(split, said):
    from cicfw.diagnose.steer_diagnostic import measured_line

    meta = {"checkpoint": "run/checkpoints/last.ckpt", "epoch": 2, "global_step": 6,
            "data": {"split": split, "path": "/data/x", "frames": 32, "episodes": 4}}
    line = measured_line(meta)
    assert said in line and "/data/x" in line and "32 frames" in line and "last.ckpt" in line
    assert measured_line({"model": "m"}) is None


def test_the_cli_lists_diagnose_and_a_missing_checkpoint_is_one_line(tmp_path: Path):
    from cicfw.cli import COMMANDS

    assert COMMANDS["diagnose"][0] == "cicfw.diagnose"
    res = run_app_in_process("cicfw.cli", "diagnose", f"checkpoint={tmp_path / 'nope.ckpt'}",
                             f"hydra.run.dir={tmp_path / 'out'}", cwd=REPO)
    assert_refused(res, "checkpoint", tmp_path / "nope.ckpt")


def test_bad_inputs_are_one_clear_line(tmp_path: Path, episodes: Path):
    from cicfw.model.checkpoint import CheckpointError
    from cicfw.diagnose.app import diagnose

    out = tmp_path / "out"
    with pytest.raises(ValueError) as err:
        diagnose(diagnose_cfg(), out)
    assert err.value.key == "checkpoint"
    foreign = tmp_path / "foreign.ckpt"
    torch.save({"weights": torch.zeros(2)}, foreign)
    with pytest.raises(CheckpointError) as err:
        diagnose(diagnose_cfg(f"checkpoint={foreign}"), out)
    assert str(foreign) in str(err.value)
    ckpt = save_checkpoint(tmp_path / "bare")  # no saved training config beside it
    with pytest.raises(ValueError) as err:
        diagnose(diagnose_cfg(f"checkpoint={ckpt}"), out)
    assert err.value.key == "data.path" and "\n" not in str(err.value)
    with pytest.raises(ValueError) as err:
        diagnose(diagnose_cfg(f"checkpoint={ckpt}", f"data.path={episodes}"), out)
    assert err.value.key == "data.seed"
    lane = write_episodes(tmp_path / "lane", plan_of=lambda i: [(2, 40)])
    with pytest.raises(sd.DiagnosticError):
        diagnose(diagnose_cfg(f"checkpoint={ckpt}", f"data.path={lane}", "split=all"), out)
    with pytest.raises(ValueError) as err:
        diagnose(diagnose_cfg(f"checkpoint={ckpt}", "split=nope"), out)
    assert (err.value.key, err.value.value) == ("split", "nope")
    assert not out.exists()  # nothing written for a refused input


def test_a_reproduce_cell_gives_its_training_split(tmp_path: Path, episodes: Path):
    """A cicfw reproduce cell saves the reproduction's config, not the training one: the cell's training
    config is composed again from its row, seed and budget."""
    from cicfw.diagnose.app import training_data

    cell = tmp_path / "cells" / "cil" / "seed2"
    ckpt = save_checkpoint(cell / "train")
    (cell / ".hydra").mkdir(parents=True)
    (cell / ".hydra" / "config.yaml").write_text(
        "progress_bar: false\ncatalogue:\n  cil:\n    experiment: paper_cil\ncell:\n  row: cil\n  seed: 2\n"
        f"budget:\n  name: tiny\n  train:\n  - data=cil_hdf5\n  - data.path={episodes}\n  - data.val_fraction=0.25\n")
    values, source = training_data(ckpt)
    assert values["path"] == str(episodes) and values["seed"] == 2 and values["val_fraction"] == 0.25
    assert "reproduce cell cil seed 2" in source


BAD_OPTIONS = [  # override, the key its one line names (each refused before the checkpoint is even looked for;
    # a value of the wrong type, threads=abc, is the schema's refusal while composing: tests/test_app_schemas.py)
    ("batch_size=0", "batch_size"),
    ("max_frames=-5", "max_frames"),
    ("max_frames=0", "max_frames"),
    ("threads=-2", "threads"),
    ("phases.exit_s=-1", "phases.exit_s"),
    ("phases.dt_s=0", "phases.dt_s"),
    ("phases.approach_m=-3", "phases.approach_m"),
    ("device=gpu", "device"),
    ("device=mps", "device"),
]


@pytest.mark.parametrize("override,key", BAD_OPTIONS, ids=[o for o, _ in BAD_OPTIONS])
def test_bad_numbers_and_devices_are_refused_before_anything_loads(tmp_path: Path, override: str, key: str):
    """A value outside its domain is one line naming the key and what is accepted, before the checkpoint
    (here a missing one, which would otherwise be the error) or the data is read; nothing is written."""
    from cicfw.diagnose.app import diagnose

    out = tmp_path / "out"
    with pytest.raises(ValueError) as err:
        diagnose(diagnose_cfg(f"checkpoint={tmp_path / 'nope.ckpt'}", override), out)
    assert err.value.key == key and err.value.value == yaml.safe_load(override.split("=", 1)[1]), err.value
    assert "\n" not in str(err.value) and "nope.ckpt" not in str(err.value)
    assert not out.exists()


def test_a_cuda_device_this_machine_lacks_is_one_line(tmp_path: Path, monkeypatch):
    """device=cuda without CUDA, or a GPU index past the machine's: one line offering cpu / auto / the GPUs there."""
    from cicfw.diagnose.app import diagnose

    nope = f"checkpoint={tmp_path / 'nope.ckpt'}"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError) as err:
        diagnose(diagnose_cfg(nope, "device=cuda"), tmp_path / "out")
    assert (err.value.key, err.value.value) == ("device", "cuda") and "device=cpu" in str(err.value)  # the way out
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError) as err:
        diagnose(diagnose_cfg(nope, "device=cuda:3"), tmp_path / "out")
    assert (err.value.key, err.value.value) == ("device", "cuda:3") and "cuda:0" in str(err.value)  # what there is


def test_the_cli_refuses_a_bad_thread_count_in_one_line(tmp_path: Path):
    """``threads=-2`` was a torch RuntimeError traceback: now status 2 and one line."""
    res = run_app_in_process("cicfw.diagnose", f"checkpoint={tmp_path / 'nope.ckpt'}", "threads=-2",
                             f"hydra.run.dir={tmp_path / 'out'}", cwd=REPO)
    assert len([x for x in res.stderr.splitlines() if x.strip()]) == 1, res.stderr
    assert_refused(res, "threads", -2)


def test_a_run_refused_after_hydra_starts_leaves_no_folder_behind(tmp_path: Path):
    """A checkpoint that is missing is found only once Hydra has written ``.hydra`` and diagnose.log: the
    refused run takes them back, so no folder of a run that never was is left."""
    out = tmp_path / "day" / "out"
    res = run_app_in_process("cicfw.diagnose", f"checkpoint={tmp_path / 'nope.ckpt'}", f"hydra.run.dir={out}",
                             cwd=REPO)
    assert_refused(res, "checkpoint", tmp_path / "nope.ckpt")
    assert not (tmp_path / "day").exists()


def test_a_refused_run_in_an_earlier_diagnose_folder_leaves_it_as_it_was(tmp_path: Path):
    out = tmp_path / "out"
    (out / ".hydra").mkdir(parents=True)
    (out / ".hydra" / "hydra.yaml").write_text("hydra:\n  job:\n    name: diagnose\n")
    (out / ".hydra" / "config.yaml").write_text("checkpoint: earlier.ckpt\n")
    (out / "diagnose.log").write_text("the earlier run's log\n")
    (out / "steer_diagnostic.json").write_text("{}")
    before = {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    res = run_app_in_process("cicfw.diagnose", f"checkpoint={tmp_path / 'nope.ckpt'}", f"hydra.run.dir={out}",
                             cwd=REPO)
    assert_refused(res, "checkpoint", tmp_path / "nope.ckpt")
    assert {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_a_failed_job_of_a_diagnose_sweep_is_one_line(tmp_path: Path):
    """``-m checkpoint=a.ckpt,b.ckpt`` with a missing one: the job's error in one line, as evaluate's, not
    Hydra's traceback."""
    missing = tmp_path / "nope.ckpt"
    res = run_app_in_process("cicfw.diagnose", "-m", f"checkpoint={missing}", f"hydra.sweep.dir={tmp_path / 'sweep'}",
                             "plot=false", cwd=REPO)
    assert res.returncode != 0 and "Traceback" not in res.stderr, res.stderr[-3000:]
    line = next(x for x in res.stderr.splitlines() if x.startswith("cicfw: error: job 0"))
    assert str(missing) in line


@pytest.mark.parametrize("beside", ["another run's config", "no config"])
def test_the_split_is_the_one_the_checkpoint_recorded(tmp_path: Path, episodes: Path, beside: str):
    """A checkpoint trained with seed 3, copied into the folder of a run of the same parts trained with seed 0,
    was measured on seed 0's validation episodes, among them episodes it trained on; alone in a folder it was
    refused for want of a data.seed that it records itself."""
    from cicfw.diagnose.app import data_settings

    run = tmp_path / "run"
    ckpt = save_checkpoint(run, head="softmax")
    torch.save({**torch.load(ckpt, weights_only=True), "cicfw_split": {"seed": 3, "val_fraction": 0.3}}, ckpt)
    if beside == "another run's config":
        write_run_config(run, episodes, seed=0)
        overrides = []
    else:
        overrides = [f"data.path={episodes}"]
    settings, source = data_settings(diagnose_cfg(f"checkpoint={ckpt}", *overrides), ckpt)
    assert settings.seed == 3
    assert "as the checkpoint recorded them" in source


@pytest.mark.parametrize("given", ["data.seed=0", "data.val_fraction=0.5"])
def test_another_split_than_the_checkpoint_recorded_is_refused(tmp_path: Path, episodes: Path, given: str):
    """data.val_fraction=0.5 (or another seed) beside a checkpoint that recorded its split drew another
    split: the report said "the val split" over episodes the model trained on. Refused for val and train;
    split=all, which measures every frame, and the recorded value itself are fine."""
    from cicfw.core.errors import ConfigError
    from cicfw.diagnose.app import data_settings

    ckpt = save_checkpoint(tmp_path / "run", head="softmax")
    torch.save({**torch.load(ckpt, weights_only=True), "cicfw_split": {"seed": 3, "val_fraction": 0.3}}, ckpt)
    key, value = given.split("=")
    for split in ("val", "train"):
        with pytest.raises(ConfigError) as err:
            data_settings(diagnose_cfg(f"checkpoint={ckpt}", f"data.path={episodes}", given, f"split={split}"), ckpt)
        assert err.value.key == key and float(err.value.value) == float(value)
    data_settings(diagnose_cfg(f"checkpoint={ckpt}", f"data.path={episodes}", given, "split=all"), ckpt)
    data_settings(diagnose_cfg(f"checkpoint={ckpt}", f"data.path={episodes}", "data.seed=3", "data.val_fraction=0.3"),
                  ckpt)


def test_a_folder_holding_another_checkpoints_diagnosis_is_refused_and_kept(tmp_path: Path, episodes: Path):
    """Diagnosing checkpoint B into the folder of A's diagnosis would replace A's report: refused, the folder
    as it was. A's own diagnosis again (other options) rewrites it."""
    runs = [tmp_path / "a", tmp_path / "b"]
    ckpts = [save_checkpoint(run, head="softmax") for run in runs]
    for run in runs:
        write_run_config(run, episodes, seed=3)
    out = tmp_path / "out"
    common = [f"hydra.run.dir={out}", "phases.approach_m=3", "threads=1", "plot=false"]
    first = run_app_in_process("cicfw.diagnose", f"checkpoint={ckpts[0]}", *common, cwd=REPO)
    assert first.returncode == 0, first.stderr[-3000:]
    before = {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    res = run_app_in_process("cicfw.diagnose", f"checkpoint={ckpts[1]}", *common, cwd=REPO)
    assert_refused(res, "hydra.run.dir", out)
    assert {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    again = run_app_in_process("cicfw.diagnose", f"checkpoint={ckpts[0]}", *common, "phases.exit_s=1", cwd=REPO)
    assert again.returncode == 0, again.stderr[-3000:]


def test_a_full_disk_while_writing_the_report_is_one_line_and_writes_none_of_it(tmp_path: Path, episodes: Path,
                                                                                 monkeypatch):
    """The disk fills as the last file of the report (the scatter plot) is written: one CicfwError line, and
    no file of the report under its name (not a table beside no plot, nor an earlier run's plot beside it)."""
    from cicfw.core.errors import CicfwError
    from cicfw.diagnose.app import diagnose

    run = tmp_path / "run"
    ckpt = save_checkpoint(run, head="softmax")
    write_run_config(run, episodes, seed=3)
    out = tmp_path / "out"
    out.mkdir()
    fill_the_disk_for_pictures(monkeypatch)
    with pytest.raises(CicfwError) as err:
        diagnose(diagnose_cfg(f"checkpoint={ckpt}", "phases.approach_m=3", "threads=1"), out)
    assert "steer_scatter.png" in str(err.value) and "\n" not in str(err.value)
    assert list(out.iterdir()) == []


def test_the_same_diagnosis_again_without_its_plot_leaves_no_earlier_plot(tmp_path: Path, episodes: Path):
    """A rerun with plot=false (and other phases) rewrites the tables: the earlier scatter plot, drawn with the
    other phases, is not left beside them as if it were this diagnosis's."""
    from cicfw.diagnose.app import diagnose

    run = tmp_path / "run"
    ckpt = save_checkpoint(run, head="softmax")
    write_run_config(run, episodes, seed=3)
    out = tmp_path / "out"
    diagnose(diagnose_cfg(f"checkpoint={ckpt}", "phases.approach_m=3", "threads=1"), out)
    assert (out / "steer_scatter.png").is_file()
    diagnose(diagnose_cfg(f"checkpoint={ckpt}", "phases.approach_m=2", "threads=1", "plot=false"), out)
    assert json.loads((out / "steer_diagnostic.json").read_text())["phases"]["approach_m"] == 2
    assert not (out / "steer_scatter.png").exists()
