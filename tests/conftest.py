"""Shared fixtures: tiny datasets in the exact CIL HDF5 layout, composed configs, and the hand formulas
the statistics tests recompute with."""
from __future__ import annotations

import logging
import math
import os
import signal
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module

from cicfw.testing import make_targets, write_tiny_dataset  # noqa: F401  (tests import them from here)


def pytest_configure(config):
    """A suite started in the background (``nohup pytest ... &``) inherits SIGINT ignored, and so would the
    apps the Ctrl-C tests start, which would then never see their Ctrl-C: give them the default back.
    Under pytest-xdist, give each worker its share of the cores: two workers each running torch on
    every core (and the apps they start in subprocesses, which inherit OMP_NUM_THREADS) would fight."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT") or 0)
    if workers > 1:
        threads = max(1, (os.cpu_count() or 1) // workers)
        os.environ.setdefault("OMP_NUM_THREADS", str(threads))
        import torch

        torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


@pytest.fixture(autouse=True)
def _no_log_handler_outlives_its_test():
    """An app run in-process (Hydra's job logging) hangs a handler on the root logger that writes to this
    test's captured stream, which pytest closes after it; a later test's log line would then print
    "--- Logging error ---" into that test's stderr. Take such handlers off when the test ends."""
    root = logging.getLogger()
    before = list(root.handlers)
    yield
    for handler in [h for h in root.handlers if h not in before and not type(h).__module__.startswith("_pytest")]:
        root.removeHandler(handler)
        handler.close()


def wilson(k: int, n: int, z: float) -> tuple[float, float]:
    """Wilson's score interval for k of n at normal quantile z, from its closed form (no library)."""
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def at(row: str, seed: int, pct: int, n: int = 100):
    """A reproduction cell with ``pct`` successes of ``n`` episodes in every column: overall ``pct``%."""
    from cicfw.reproduction.cells import COLUMNS, CellResult

    eps = {f"{c}/{k:03d}": {"success": k < pct, "column": c, "command": "left"} for c in COLUMNS for k in range(n)}
    return CellResult(row=row, seed=seed, episodes=eps, meta={"decoder": None, "wall_s": {}})


def p_two_sided_2df(t: float) -> float:
    """Two-sided p of Student's t with 2 df, in closed form: 1 - |t| / sqrt(2 + t^2)."""
    return 1.0 - abs(t) / math.sqrt(2.0 + t * t)


@pytest.fixture
def tiny_data(tmp_path: Path) -> Path:
    return write_tiny_dataset(tmp_path / "data")


def compose_train(*overrides: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("train", overrides=list(overrides))


@pytest.fixture
def fast_cfg(tiny_data: Path):
    """A train config on the tiny data: one fast_dev_run step, batch 8, no progress bar."""
    return compose_train(
        "data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "data.val_batch_size=8",
        "debug=fast", "progress_bar=false",
    )


@pytest.fixture
def no_data(monkeypatch):
    """Fail loudly if training reaches the data (collecting or reading any file)."""
    import cicfw.train.app as train_mod
    from cicfw.data.datamodule import CILDataModule

    def touched(*_a, **_k):
        raise AssertionError("the data was touched before the config error was reported")

    monkeypatch.setattr(train_mod, "ensure_data", touched)
    monkeypatch.setattr(CILDataModule, "setup", touched)


def process_alive(pid: int) -> bool:
    """Running: not gone, and not a zombie waiting to be reaped (its new parent may not reap it at once)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")
