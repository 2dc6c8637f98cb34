"""Samples seen (a reproduction cell's ``samples_seen``, its learning curve's ``samples``): every training batch
counts, whether its optimizer step came with it or after accumulating (``accumulate_grad_batches``), once per
process that trained on batches of its own (DDP's world size)."""
from __future__ import annotations

import pytest
import torch

from cicfw.model.checkpoint import WORLD_SIZE_KEY, samples_seen
from conftest import TINY_TRAIN, train_tiny_run


def _progress(processed: int) -> dict:
    """Lightning's fit-loop progress as a checkpoint holds it, ``processed`` training batches in all."""
    total = {"ready": processed, "started": processed, "processed": processed, "completed": processed}
    return {"fit_loop": {"epoch_loop.batch_progress": {"total": total, "current": dict(total)}}}


@pytest.mark.parametrize("ck, batch, accumulate, want", [
    # 10 batches of 8 on each of 2 processes, 6 optimizer steps (accumulating 2, one step at each epoch's end)
    ({"global_step": 6, "loops": _progress(10), WORLD_SIZE_KEY: 2}, 8, 2, 10 * 8 * 2),
    ({"global_step": 6, "loops": _progress(10)}, 8, 2, 10 * 8),  # no world size recorded: one process
    ({"global_step": 4, "loops": _progress(4), WORLD_SIZE_KEY: 1}, 8, 1, 4 * 8),
    ({"global_step": 3}, 8, 2, 3 * 2 * 8),  # no loop progress: each step took `accumulate` batches
    ({"global_step": 3}, 8, 1, 3 * 8),
])
def test_samples_seen_by_hand(ck, batch, accumulate, want):
    assert samples_seen(ck, batch, accumulate) == want


@pytest.mark.slow  # trains
def test_a_curve_point_counts_every_accumulated_batch(tmp_path):
    """3 batches of 8 accumulated by 2 take 2 optimizer steps (the last at the epoch's end): 24 samples, not
    the 16 that steps x batch size gave."""
    from cicfw.reproduction.app import _curve_point

    run = train_tiny_run(tmp_path, *TINY_TRAIN, "trainer.limit_train_batches=3", "trainer.accumulate_grad_batches=2")
    ck = torch.load(run["last"], map_location="cpu", weights_only=True)
    assert ck["global_step"] == 2 and ck[WORLD_SIZE_KEY] == 1
    point = _curve_point(run["last"], {"cells": {}}, batch=8, accumulate=2)
    assert point["samples"] == 3 * 8 and point["epoch"] == 1
