"""GPU readiness in one command: train a few hundred steps with docs/scaling.md's one-GPU recipe on a
dataset this script writes itself, then check the run. One line per check, PASS or FAIL:

  loss falls            the mean training loss of the last tenth of the steps is below the first tenth's
                        (every loss finite). The images carry their label (a bright bar whose column is the
                        steering), so a model that learns anything shows it within a few hundred steps.
  checkpoint on the CPU the run's last.ckpt loads with Agent.load(path, device="cpu") in a process that sees
                        no GPU (CUDA_VISIBLE_DEVICES=""), and acting on a few frames gives finite steering
                        in [-1, 1].
  throughput measured   training samples/s, the share of step time spent waiting for the next batch (from
                        the end of one batch to the start of the next, timed by the training's own
                        cicfw.data.wait.DataWait, the first batches of each epoch left out) and, on a GPU,
                        the peak GPU memory (torch.cuda.max_memory_allocated); it passes when the steps
                        were timed, on the device the recipe asks for.

    python bench/gpu_check.py                        # a CUDA GPU: fp32 (32-true), 4 loader workers, compile, 300 steps
    python bench/gpu_check.py data.in_memory=false   # extra Hydra overrides go to the training (streamed images)
    python bench/gpu_check.py --dry-run              # no GPU: the same path on the CPU, fp32, eager, 0 workers, 20 steps
    python bench/gpu_check.py --license-study        # only print the bf16 license study's commands and rule

Training is the project's own ``cicfw.train.train`` on a config composed as ``python -m cicfw.train``
composes it (data=cil_hdf5 on the written files; docs/scaling.md section 2's overrides:
trainer.accelerator=gpu trainer.precision=32-true data.num_workers=4, plus speed.compile=true and
the default speed.channels_last).

Last it prints the commands of the bf16 license study on this GPU (``license_study``): the catalogue rows
``cil`` and ``cil_bf16`` at ``budget=converged6`` trained and driven on the GPU, eight paired seeds, and the
rule that decides it, fixed before its first cell, as docs/results/bf16_license_xeon/ was run on a CPU.
Until that study says otherwise the GPU recipes train in 32-true with TF32 off (docs/training.md). The only addition is a callback recording each step's loss and the
recipe the run got, appended to the callbacks ``cicfw.train.build_callbacks`` returns; the timing is the
training's own ``DataWait`` (the data-wait line every training logs).

Exit status: 0 when every check passes, 1 when one fails, 2 without a CUDA GPU and without --dry-run.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

#: docs/scaling.md, "2. One GPU", plus compile (speed.compile=auto would choose it at >= 200 steps); fp32, the
#: precision the evidence licenses (docs/training.md): bf16 autocast waits for its license study on a GPU
GPU_RECIPE = ("trainer.accelerator=gpu", "trainer.precision=32-true", "data.num_workers=4", "speed.compile=true")
#: the same run on a CPU, kept short: fp32, eager, the main process loads the data
DRY_RUN_RECIPE = ("trainer.accelerator=cpu", "trainer.precision=32-true", "data.num_workers=0", "speed.compile=false")


# ---- the checks (pure: unit-tested without training) -------------------------------------------------
def loss_falls(losses: Sequence[float], fraction: float = 0.1) -> tuple[bool, str]:
    """Whether the mean loss of the last ``fraction`` of the steps is below that of the first (every
    loss finite, at least two steps), and the line's detail."""
    values = [float(v) for v in losses]
    if len(values) < 2:
        return False, f"{len(values)} training step(s) recorded, need at least 2"
    bad = [i for i, v in enumerate(values) if not math.isfinite(v)]
    if bad:
        return False, f"{len(bad)} non-finite loss(es), the first at step {bad[0]}"
    k = max(1, int(round(len(values) * fraction)))
    first, last = float(np.mean(values[:k])), float(np.mean(values[-k:]))
    return last < first, f"mean of the first {k} steps {first:.4f} -> last {k} steps {last:.4f} ({len(values)} steps)"


def steering_ok(steer: Any, n_frames: int) -> tuple[bool, str]:
    """One finite steering value in [-1, 1] per frame, and the line's detail."""
    s = np.asarray(steer, dtype=np.float64).reshape(-1)
    if len(s) != n_frames:
        return False, f"{len(s)} steering value(s) for {n_frames} frames"
    if not np.all(np.isfinite(s)):
        return False, f"non-finite steering {s.tolist()}"
    if np.any(np.abs(s) > 1.0):
        return False, f"steering outside [-1, 1]: {s.min():.3f} .. {s.max():.3f}"
    return True, f"{n_frames} frames, steering {s.min():+.3f} .. {s.max():+.3f}"


def throughput(samples: int, wait: float, step: float, steps: int) -> tuple[float, float, int]:
    """(samples/s, the share of step time spent waiting for data, steps measured) from the measured steps'
    totals (``DataWait.run``: each epoch's first batches, the workers' start, left out); a step's time is
    its wait plus its work."""
    total = float(wait + step)
    if steps <= 0 or total <= 0:
        return float("nan"), float("nan"), 0
    return samples / total, float(wait) / total, int(steps)


def line(ok: bool, name: str, detail: str) -> bool:
    print(f"{'PASS' if ok else 'FAIL'} {name}: {detail}", flush=True)
    return ok


# ---- the bf16 license study on a GPU -----------------------------------------------------------------
#: the design, fixed before the study's first cell (docs/results/bf16_license_xeon/README.md's, on a GPU):
#: eight pairs, a fixed number (no early stop), judged once by the paired TOST at +-5 points overall
LICENSE_ROWS = ("cil", "cil_bf16")  # conf/reproduce.yaml: cil_bf16 is cil plus trainer.precision=bf16-mixed
LICENSE_SEEDS = tuple(range(8))
LICENSE_MARGIN = 5
LICENSE_BUDGET = "converged6"
#: what moves the budget's training onto the GPU (its suite drives there too: policy.device=auto)
LICENSE_GPU_TRAIN = ("trainer.accelerator=gpu", "data.num_workers=4")


def gpu_slug(name: str) -> str:
    """A folder-name part for a GPU kind: "NVIDIA H100 80GB HBM3" -> "h100_80gb_hbm3"."""
    words = [w for w in "".join(c if c.isalnum() else " " for c in name.lower()).split() if w not in ("nvidia", "geforce")]
    return "_".join(words) or "gpu"


def budget_train(budget: str = LICENSE_BUDGET) -> list[str]:
    """The training overrides of a reproduction budget (conf/budget/<budget>.yaml's ``train``)."""
    from importlib.resources import files

    from omegaconf import OmegaConf

    return [str(o) for o in OmegaConf.load(str(files("cicfw.conf") / "budget" / f"{budget}.yaml")).train]


def license_study(gpu_name: str, budget_train: Sequence[str]) -> dict[str, Any]:
    """The bf16 license study on the GPU ``gpu_name``: its results folder, one ``cicfw.reproduce`` command per
    seed (both rows of the pair, the order alternating from seed to seed: fp32 first on even seeds) and the
    test that decides it. ``budget_train``: the converged6 budget's training overrides (conf/budget), to
    which the GPU's are added, so the cells train on the GPU what the published budget trains on a CPU."""
    slug = gpu_slug(gpu_name)
    folder = f"docs/results/bf16_license_{slug}"
    train = "[" + ",".join(f'"{o}"' for o in (*budget_train, *LICENSE_GPU_TRAIN)) + "]"
    commands = []
    for seed in LICENSE_SEEDS:
        rows = LICENSE_ROWS if seed % 2 == 0 else LICENSE_ROWS[::-1]
        commands.append(f"python -m cicfw.reproduce budget={LICENSE_BUDGET} 'rows=[{','.join(rows)}]' "
                        f"'seeds=[{seed}]' 'budget.train={train}' results_dir=outputs/reproduce/bf16_license_{slug} "
                        f"publish_dir={folder}")
    test = (f"python -m cicfw.reproduction.paired_switch {folder}/cells/{LICENSE_ROWS[1]} "
            f"{folder}/cells/{LICENSE_ROWS[0]} --margin {LICENSE_MARGIN}")
    return {"folder": folder, "commands": commands, "test": test}


#: the GPU a run without one prints the study's commands for (a GPU run prints them with its own name)
EXAMPLE_GPU = "NVIDIA H100 80GB HBM3"


def print_license_study(gpu_name: str, wait_share: float | None = None, example: bool = False) -> dict[str, Any]:
    """Print the bf16 license study's design, commands and rule for ``gpu_name`` (and, after a GPU run, the
    most a faster precision could save there: the share of step time not spent waiting for data);
    ``example``: no GPU here, the commands are shown for ``gpu_name``."""
    study = license_study(gpu_name, budget_train())
    seeds = f"{LICENSE_SEEDS[0]}-{LICENSE_SEEDS[-1]}"
    print(f"\nbf16 license study on {gpu_name} (the GPU recipes stay 32-true, TF32 off, until it licenses bf16)"
          + (" -- no GPU here: shown for that GPU; a run on a GPU prints them with its own name" if example else "")
          + ":", flush=True)
    print(f"  design, fixed before its first cell: write it into {study['folder']}/README.md and commit it first.\n"
          f"  Rows {LICENSE_ROWS[0]} (fp32) and {LICENSE_ROWS[1]} (trainer.precision=bf16-mixed, nothing else), "
          f"budget={LICENSE_BUDGET} trained and driven on this GPU, seeds {seeds}: {len(LICENSE_SEEDS)} pairs, a fixed "
          f"number (no early stop, nothing pooled with the CPU studies); within a pair the order alternates "
          f"(even seeds fp32 first); every cell on this one kind of GPU, one cell at a time, from one commit.\n"
          f"  Rule: licensed iff the overall row of the test below reads \"equivalent within ±{LICENSE_MARGIN}\" "
          f"(paired TOST p < 0.05 by seed, the 90% t-interval of the {len(LICENSE_SEEDS)} per-seed differences inside "
          f"±{LICENSE_MARGIN} points); the columns are reported, not required. A license holds for this GPU kind only.",
          flush=True)
    if wait_share is not None and math.isfinite(wait_share):
        print(f"  What it could buy here: this run's step waited for data {100 * wait_share:.0f}% of the time, so a "
              f"faster precision can shorten at most the other {100 * (1 - wait_share):.0f}%.", flush=True)
    print("  No TF32 arm: TF32 stays off (cicfw.model.speed.keep_fp32); licensing it needs a switch for it and a "
          "study of its own with the same design.", flush=True)
    print("  The cells, one command per seed:", flush=True)
    for c in study["commands"]:
        print(f"    {c}", flush=True)
    print(f"  The test, once all {len(LICENSE_SEEDS)} pairs are in, run once:\n    {study['test']}", flush=True)
    return study


# ---- the data ----------------------------------------------------------------------------------------
def write_dataset(folder: Path, frames: int, files: int, seed: int = 0) -> Path:
    """``files`` CIL HDF5 files, ``frames`` in all: noise images with a bright vertical bar whose column
    is the steering (-1 left edge, +1 right edge), every command, the centre camera, random speeds."""
    from cicfw.data.cil_hdf5 import T, write_file
    from cicfw.testing import make_targets

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    per_file = max(4, frames // files)
    cols = np.arange(200)
    for i in range(files):
        t = make_targets(per_file, rng)
        t[:, T.CAMERA_ID] = 0  # the centre camera: the label is the steering itself
        t[:, T.CAMERA_YAW] = 0
        rgb = rng.integers(0, 90, (per_file, 88, 200, 3), dtype=np.uint8)
        centre = (t[:, T.STEER] + 1.0) * 99.5
        bar = np.abs(cols[None, :] - centre[:, None]) <= 6  # (n, 200)
        rgb[bar[:, None, :, None].repeat(88, 1).repeat(3, 3)] = 230
        write_file(folder / f"data_{i:05d}.h5", rgb, t)
    return folder


# ---- timing ------------------------------------------------------------------------------------------
def step_timer():
    """A Lightning callback recording each training step's loss and the recipe the run got; its ``data_wait``
    is the training's own ``DataWait`` (the steps' wait and work), found among the trainer's callbacks."""
    import lightning as L

    from cicfw.data.wait import DataWait

    class StepTimer(L.Callback):
        def __init__(self) -> None:
            self.losses: list = []
            self.recipe: dict[str, Any] = {}
            self.data_wait: DataWait | None = None

        def on_train_start(self, trainer, pl_module) -> None:
            loader = trainer.train_dataloader
            self.recipe = {"device": str(pl_module.device), "precision": str(trainer.precision),
                           "workers": getattr(loader, "num_workers", None),
                           "pin_memory": bool(getattr(loader, "pin_memory", False)),
                           "channels_last": bool(getattr(pl_module, "channels_last", False)),
                           "compiled": getattr(pl_module, "_compiled_step", None) is not None}
            self.data_wait = next((c for c in trainer.callbacks if isinstance(c, DataWait)), None)

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
            loss = outputs["loss"] if isinstance(outputs, dict) else outputs
            self.losses.append(loss.detach().float())  # read after training: no device sync per step

    return StepTimer()


@contextlib.contextmanager
def with_callback(callback):
    """``cicfw.train.build_callbacks`` returning its callbacks plus ``callback``, while the block runs."""
    import cicfw.train.app as train_module

    original = train_module.build_callbacks
    train_module.build_callbacks = lambda cfg, run_dir: [*original(cfg, run_dir), callback]
    try:
        yield
    finally:
        train_module.build_callbacks = original


# ---- the run -----------------------------------------------------------------------------------------
def train_run(data: Path, run_dir: Path, overrides: Sequence[str]):
    """Compose the train config with ``overrides`` on ``data`` and train with ``cicfw.train.train``;
    returns the timing callback."""
    from hydra import compose, initialize_config_module

    from cicfw.train.app import train

    timer = step_timer()
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("train", overrides=["data=cil_hdf5", f"data.path={data}", *overrides])
    with with_callback(timer):
        train(cfg, run_dir)
    return timer


def act_on_cpu(checkpoint: Path, frames: Path) -> dict[str, Any]:
    """Load ``checkpoint`` with ``Agent.load(device="cpu")`` and act on the frames of ``frames`` (.npz:
    rgb, speed, command); run in a process that sees no GPU."""
    from cicfw.export.agent import Agent

    agent = Agent.load(checkpoint, device="cpu")
    f = np.load(frames)
    steer = agent.act(f["rgb"], f["speed"], f["command"])
    devices = sorted({str(p.device) for p in agent.model.parameters()}) if agent.model is not None else []
    return {"steer": np.asarray(steer, float).tolist(), "label": f["steer"].astype(float).tolist(),
            "devices": devices, "agent_device": str(agent.device)}


def check_checkpoint(run_dir: Path, data: Path, n_frames: int = 8) -> bool:
    """Check 2: last.ckpt acts on the CPU in a fresh process that sees no GPU."""
    from cicfw.data.cil_hdf5 import T, read_rgb, read_targets

    ckpt = run_dir / "checkpoints" / "last.ckpt"
    if not ckpt.is_file():
        return line(False, "checkpoint on the CPU", f"no {ckpt}")
    last_file = sorted(data.glob("*.h5"))[-1]
    rgb, targets = read_rgb(last_file), read_targets(last_file)
    frames = run_dir / "frames.npz"
    np.savez(frames, rgb=rgb[:n_frames], speed=targets[:n_frames, T.SPEED],
             command=targets[:n_frames, T.COMMAND].astype(np.int64), steer=targets[:n_frames, T.STEER])
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    proc = subprocess.run([sys.executable, __file__, "--act-on-cpu", str(ckpt), str(frames)], env=env,
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        return line(False, "checkpoint on the CPU", f"Agent.load({ckpt.name}, device='cpu') failed: {last}")
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    ok, detail = steering_ok(got["steer"], n_frames)
    if ok and (got["agent_device"] != "cpu" or got["devices"] != ["cpu"]):
        ok, detail = False, f"the agent runs on {got['agent_device']}, its weights on {got['devices']}"
    mae = float(np.mean(np.abs(np.asarray(got["steer"]) - np.asarray(got["label"])))) if ok else float("nan")
    return line(ok, "checkpoint on the CPU", f"{ckpt.name}: {detail}" + (f", MAE to the labels {mae:.3f}" if ok else ""))


def run_checks(args: argparse.Namespace, cuda: bool) -> bool:
    recipe = DRY_RUN_RECIPE if args.dry_run else GPU_RECIPE
    steps, epochs = args.steps, args.epochs
    per_epoch = max(1, steps // epochs)
    overrides = [*recipe, f"trainer.max_epochs={epochs}", f"data.batches_per_epoch={per_epoch}",
                 f"data.batch_size={args.batch_size}", f"seed={args.seed}",
                 *([f"model.lr={args.lr}"] if args.lr is not None else []),
                 "progress_bar=false", "trainer.enable_model_summary=false", *args.overrides]
    with contextlib.ExitStack() as stack:
        work = Path(args.workdir) if args.workdir else Path(stack.enter_context(
            tempfile.TemporaryDirectory(prefix="cicfw-gpu-check-")))
        t0 = time.perf_counter()
        data = write_dataset(work / "data", args.frames, args.files, args.seed)
        print(f"dataset: {args.frames} frames in {args.files} CIL HDF5 files, written in "
              f"{time.perf_counter() - t0:.1f} s ({data})", flush=True)
        print(f"training: {' '.join(overrides)}", flush=True)
        run_dir = work / "run"
        if cuda:
            import torch

            torch.cuda.reset_peak_memory_stats()
        t0 = time.perf_counter()
        try:
            timer = train_run(data, run_dir, overrides)
        except Exception as err:  # noqa: BLE001 - a readiness check reports, it does not crash
            why = f"training failed: {type(err).__name__}: {str(err).strip().splitlines()[0] if str(err).strip() else ''}"
            for name in ("loss falls", "checkpoint on the CPU", "throughput measured"):
                line(False, name, why)
            return False
        wall = time.perf_counter() - t0
        r = timer.recipe
        print(f"recipe: {r.get('device')}, precision {r.get('precision')}, {r.get('workers')} loader workers, "
              f"pinned memory {'yes' if r.get('pin_memory') else 'no'}, channels_last "
              f"{'yes' if r.get('channels_last') else 'no'}, torch.compile {'yes' if r.get('compiled') else 'no'}; "
              f"{len(timer.losses)} steps in {wall:.1f} s (with the warm-up and validation)", flush=True)
        ok, detail = loss_falls([float(v) for v in timer.losses])
        results = [line(ok, "loss falls", detail)]
        results.append(check_checkpoint(run_dir, data))
        from cicfw.data.wait import WARMUP_BATCHES

        run = timer.data_wait.run if timer.data_wait is not None else None
        rate, wait, measured = throughput(run.samples, run.wait, run.step, run.batches) if run else (0.0, 0.0, 0)
        if cuda and not args.dry_run:
            import torch

            memory = f"peak GPU memory {torch.cuda.max_memory_allocated() / 2**30:.2f} GiB"
            want = "cuda"
        else:
            import resource

            memory = f"peak GPU memory n/a (CPU run; peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB)"
            want = "cpu"
        ok = measured > 0 and math.isfinite(rate) and rate > 0 and str(r.get("device", "")).startswith(want)
        where = "" if ok or measured == 0 else f" (trained on {r.get('device')}, expected {want})"
        if run is None:
            where = " (the training has no cicfw.data.wait.DataWait callback to time its steps)"
        results.append(line(ok, "throughput measured",
                            f"{rate:.1f} samples/s, waiting for data {100 * wait:.1f}% of step time over "
                            f"{measured} steps (the first {WARMUP_BATCHES} of each epoch skipped), {memory}{where}"))
    if cuda and not args.dry_run:
        import torch

        print_license_study(torch.cuda.get_device_name(0), wait if measured else None)
    else:
        print_license_study(EXAMPLE_GPU, example=True)
    return all(results)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("overrides", nargs="*", help="more Hydra overrides for the training (data.in_memory=false ...)")
    p.add_argument("--dry-run", action="store_true",
                   help="no GPU needed: the same path on the CPU, fp32, no compile, 0 workers, 20 steps")
    p.add_argument("--steps", type=int, help="training steps (300; --dry-run 20)")
    p.add_argument("--epochs", type=int, help="epochs the steps are split into, a validation and checkpoint each (3; --dry-run 2)")
    p.add_argument("--frames", type=int, help="frames written (4000; --dry-run 480)")
    p.add_argument("--files", type=int, default=20, help="CIL HDF5 files they are written into (20)")
    p.add_argument("--batch-size", type=int, help="per step, a multiple of 4 (the paper's 120; --dry-run 32)")
    p.add_argument("--lr", type=float, help="Adam's learning rate (default: the paper's, model.lr in conf/train.yaml)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workdir", help="write the data and the run here and keep them (default: a temporary folder)")
    p.add_argument("--license-study", action="store_true",
                   help="only print the bf16 license study's design, commands and rule for this GPU (no training)")
    p.add_argument("--act-on-cpu", nargs=2, metavar=("CKPT", "FRAMES"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    # its data files are named as CoRL-2017's are, and its run would resume or overwrite another's: a folder
    # already holding either is refused before anything is written
    held = [Path(args.workdir, d) for d in ("data", "run") if args.workdir and any(Path(args.workdir, d).glob("*"))]
    if held:
        p.error(f"--workdir {args.workdir}: {held[0]} already holds files, which the check would overwrite or "
                f"train on; give an empty or new folder")
    dry = args.dry_run
    for key, gpu, cpu in (("steps", 300, 20), ("epochs", 3, 2), ("frames", 4000, 480), ("batch_size", 120, 32)):
        if getattr(args, key) is None:
            setattr(args, key, cpu if dry else gpu)
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.act_on_cpu:
        print(json.dumps(act_on_cpu(Path(args.act_on_cpu[0]), Path(args.act_on_cpu[1]))))
        return 0
    import torch

    cuda = torch.cuda.is_available()
    if args.license_study:
        print_license_study(torch.cuda.get_device_name(0) if cuda else EXAMPLE_GPU, example=not cuda)
        return 0
    if not cuda and not args.dry_run:
        print("gpu_check needs a CUDA GPU (torch sees none); run it with --dry-run to check the script on the CPU",
              flush=True)
        return 2
    return 0 if run_checks(args, cuda) else 1


if __name__ == "__main__":
    sys.exit(main())
