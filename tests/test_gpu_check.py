"""bench/gpu_check.py: its checks' rules, and the whole script on the CPU (--dry-run)."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "gpu_check.py"


def load_script():
    spec = importlib.util.spec_from_file_location("gpu_check", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_loss_falls_rule():
    check = load_script().loss_falls
    falling = [1.0 - 0.04 * i for i in range(20)]
    assert check(falling)[0]
    assert not check(falling[::-1])[0]                 # a rising loss fails
    assert not check([0.5] * 20)[0]                    # a flat one too
    assert not check([*falling[:-1], float("nan")])[0]  # a NaN anywhere fails
    assert not check([1.0])[0]                         # one step proves nothing


def test_steering_and_throughput_rules():
    m = load_script()
    assert m.steering_ok([0.1, -0.9, 1.0], 3)[0]
    assert not m.steering_ok([0.1, 1.2, 0.0], 3)[0]
    assert not m.steering_ok([0.1, float("inf"), 0.0], 3)[0]
    assert not m.steering_ok([0.1, 0.2], 3)[0]
    rate, wait, n = m.throughput([10, 10, 10], [5.0, 0.5, 0.5], [5.0, 1.5, 1.5], skip=1)
    assert (rate, wait, n) == (5.0, 0.25, 2)  # 20 samples in 4 s, 1 s of it waiting; the first step skipped
    assert m.throughput([10], [1.0], [1.0], skip=1)[2] == 0


def test_without_cuda_it_says_so_and_exits_2():
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    proc = subprocess.run([sys.executable, str(SCRIPT)], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stdout.strip().splitlines() == [proc.stdout.strip()] and "--dry-run" in proc.stdout


@pytest.mark.slow
def test_dry_run_passes_every_check():
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    proc = subprocess.run([sys.executable, str(SCRIPT), "--dry-run"], env=env, capture_output=True, text=True,
                          timeout=900)
    out = proc.stdout
    assert proc.returncode == 0, out + proc.stderr[-3000:]
    for name in ("loss falls", "checkpoint on the CPU", "throughput measured"):
        assert any(line.startswith(f"PASS {name}: ") for line in out.splitlines()), out
    assert "FAIL" not in out
    assert "samples/s" in out and "waiting for data" in out
