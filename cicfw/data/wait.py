"""How long the training step waits for data: the gap between one batch's end and the next one's start.

A disk slower than the loader shows up here, said once per epoch in the log (a warning when the wait is
at least ``WARN_SHARE`` of the time) and logged as ``perf/data_wait_share``, instead of as a silently
slow run.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import lightning as L
from lightning.pytorch.callbacks import Callback

log = logging.getLogger(__name__)

WARN_SHARE = 0.10
WARMUP_BATCHES = 3  # the first batches wait for the workers to start: not the loader's pace


def batch_size(batch: Any) -> int:
    """The samples in a batch: the length of its first tensor (a dict's first value, a tuple's first item);
    0 when it has none."""
    while isinstance(batch, (Mapping, list, tuple)) and len(batch):
        batch = next(iter(batch.values())) if isinstance(batch, Mapping) else batch[0]
    shape = getattr(batch, "shape", None)
    return int(shape[0]) if shape else 0


@dataclass
class RunTotals:
    """Wait and step seconds, batches and samples of the measured batches: an epoch's, or the whole run's."""

    wait: float = 0.0
    step: float = 0.0
    batches: int = 0
    samples: int = 0

    @property
    def share(self) -> float:
        """The wait's share of wait + step (0 before any measured batch)."""
        total = self.wait + self.step
        return self.wait / total if total > 0 else 0.0


class DataWait(Callback):
    """Accumulates wait and step time per epoch; reports the wait's share of the whole. ``run`` holds the
    same over every epoch so far, with the samples of the measured batches (``bench/gpu_check.py``'s
    throughput): the first ``WARMUP_BATCHES`` of each epoch are left out of both."""

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self.clock = clock
        self.epoch, self.run = RunTotals(), RunTotals()
        self._start = self._end = None

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.epoch, self._end = RunTotals(), None

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int) -> None:
        self._start = self.clock()
        if self._end is not None and batch_idx >= WARMUP_BATCHES:
            for totals in (self.epoch, self.run):
                totals.wait += self._start - self._end

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        self._end = self.clock()
        if batch_idx >= WARMUP_BATCHES:
            for totals in (self.epoch, self.run):
                totals.step += self._end - self._start
                totals.batches += 1
                totals.samples += batch_size(batch)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        e = self.epoch
        if not e.batches:
            return
        pl_module.log("perf/data_wait_share", e.share, rank_zero_only=True)
        if trainer.global_rank:
            return
        line = (f"data: the step waited for data {e.share:.0%} of the time over {e.batches} batches "
                f"({1000 * e.wait / e.batches:.1f} ms wait, {1000 * e.step / e.batches:.1f} ms step per batch)")
        if e.share >= WARN_SHARE:
            log.warning("%s; the loader is slower than training: more data.num_workers, data.in_memory, or "
                        "faster storage", line)
        else:
            log.info(line)
