"""bench/gpu_check.py: its checks' rules, and the whole script on the CPU (--dry-run)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import load_bench_script, run_app_in_process

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "gpu_check.py"


def test_loss_falls_rule():
    check = load_bench_script("gpu_check").loss_falls
    falling = [1.0 - 0.04 * i for i in range(20)]
    assert check(falling)[0]
    assert not check(falling[::-1])[0]                 # a rising loss fails
    assert not check([0.5] * 20)[0]                    # a flat one too
    assert not check([*falling[:-1], float("nan")])[0]  # a NaN anywhere fails
    assert not check([1.0])[0]                         # one step proves nothing


def test_steering_and_throughput_rules():
    m = load_bench_script("gpu_check")
    assert m.steering_ok([0.1, -0.9, 1.0], 3)[0]
    assert not m.steering_ok([0.1, 1.2, 0.0], 3)[0]
    assert not m.steering_ok([0.1, float("inf"), 0.0], 3)[0]
    assert not m.steering_ok([0.1, 0.2], 3)[0]
    rate, wait, n = m.throughput(20, 1.0, 3.0, 2)
    assert (rate, wait, n) == (5.0, 0.25, 2)  # 20 samples in 4 s, 1 s of it waiting
    assert m.throughput(0, 0.0, 0.0, 0)[2] == 0


def test_the_steps_are_timed_by_the_trainings_own_data_wait():
    """One implementation of the wait timing: the script reads cicfw.data.wait.DataWait's run totals (the
    callback every training has), it does not time the steps itself."""
    from types import SimpleNamespace

    import torch

    from cicfw.data.wait import WARMUP_BATCHES, DataWait

    timer = load_bench_script("gpu_check").step_timer()
    assert not hasattr(timer, "waits") and type(timer).on_train_batch_start is type(timer).__mro__[1].on_train_batch_start
    clock = iter(float(t) for t in range(100))
    wait = DataWait(clock=lambda: next(clock))
    trainer = SimpleNamespace(callbacks=[object(), wait], train_dataloader=None, precision="32-true", global_rank=0)
    timer.on_train_start(trainer, SimpleNamespace(device="cpu"))
    assert timer.data_wait is wait
    batch = {"rgb": torch.zeros(8, 3, 2, 2), "steer": torch.zeros(8)}
    module = SimpleNamespace(log=lambda *a, **k: None)
    for _ in range(2):  # two epochs: the first WARMUP_BATCHES of each are left out
        wait.on_train_epoch_start(trainer, module)
        for i in range(WARMUP_BATCHES + 2):
            wait.on_train_batch_start(trainer, module, batch, i)
            wait.on_train_batch_end(trainer, module, None, batch, i)
        wait.on_train_epoch_end(trainer, module)
    run = wait.run
    assert (run.batches, run.samples) == (4, 32) and run.wait == run.step == 4.0  # clock ticks of 1 s each
    assert load_bench_script("gpu_check").throughput(run.samples, run.wait, run.step, run.batches) == (4.0, 0.5, 4)


def test_without_cuda_it_says_so_and_exits_2():
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    proc = subprocess.run([sys.executable, str(SCRIPT)], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stdout.strip().splitlines() == [proc.stdout.strip()] and "--dry-run" in proc.stdout


def test_a_workdir_holding_data_or_a_run_is_refused_before_writing(tmp_path):
    """Its data_00000.h5 ... are CoRL-2017's own names: another folder's files are neither overwritten nor
    trained on."""
    for sub in ("data", "run"):
        (tmp_path / sub).mkdir(exist_ok=True)
        (tmp_path / sub / "data_00000.h5").write_bytes(b"theirs")
        proc = subprocess.run([sys.executable, str(SCRIPT), "--dry-run", "--workdir", str(tmp_path)],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2 and str(tmp_path / sub) in proc.stderr, proc.stderr
        assert (tmp_path / sub / "data_00000.h5").read_bytes() == b"theirs"
        (tmp_path / sub / "data_00000.h5").unlink()


@pytest.mark.slow
def test_dry_run_passes_every_check(monkeypatch):
    """The script run in this interpreter, as ``python bench/gpu_check.py --dry-run`` runs it (the test
    above starts it in a process of its own); its checkpoint check starts the fresh process it needs.
    Batches of 8, not the dry run's 32: every check passes at that size too (the loss falls by a quarter
    over the 20 steps), for a fraction of the training's compute."""
    import torch

    monkeypatch.syspath_prepend(str(SCRIPT.parent))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # what CUDA_VISIBLE_DEVICES="" gives
    proc = run_app_in_process("gpu_check", "--dry-run", "--batch-size", "8", env={"CUDA_VISIBLE_DEVICES": ""})
    out = proc.stdout
    assert proc.returncode == 0, out + proc.stderr[-3000:]
    for name in ("loss falls", "checkpoint on the CPU", "throughput measured"):
        assert any(line.startswith(f"PASS {name}: ") for line in out.splitlines()), out
    assert "FAIL" not in out
    assert "samples/s" in out and "waiting for data" in out
