"""Batches that carry their own augmentation seed: (seed, rank, epoch, batch number).

A random generator held by the dataset is copied into every DataLoader worker and every DDP rank, so
they would all draw the same augmentation. Seeding each batch from where it stands in the run instead
gives distinct draws per batch, worker, rank and epoch, and the same batches for the same seed whatever
the number of workers. A single process keeps the dataset's one generator (``keyed=False``): its draws
never repeat, and a run keeps the augmentation it always had.
"""
from __future__ import annotations

from typing import Iterable, Iterator

import numpy as np
from torch.utils.data import Sampler


class SeededBatch(list):
    """A batch of indices with the key of its augmentation stream."""

    key: tuple[int, ...] = ()

    def __reduce__(self):  # crosses into worker processes with its key
        return (_seeded_batch, (list(self), self.key))


def _seeded_batch(indices: list[int], key: tuple[int, ...]) -> SeededBatch:
    batch = SeededBatch(indices)
    batch.key = key
    return batch


def batch_rng(indices: Iterable[int], fallback: np.random.Generator) -> np.random.Generator:
    """The generator for a batch: its own stream when it carries a key, else ``fallback``."""
    key = getattr(indices, "key", ())
    return np.random.default_rng(key) if key else fallback


class SeededBatches(Sampler[list[int]]):
    """Wraps a batch sampler; tags its i-th batch of the e-th pass with the key (seed, rank, e, i)."""

    def __init__(self, batches: Sampler[list[int]], seed: int, rank: int = 0, start_epoch: int = 0,
                 keyed: bool = True) -> None:
        self.batches, self.seed, self.rank, self.keyed = batches, seed, rank, keyed
        self._passes = start_epoch  # each pass is an epoch; a resumed run starts at its own
        if start_epoch and hasattr(batches, "set_epoch"):
            batches.set_epoch(start_epoch)

    def __len__(self) -> int:
        return len(self.batches)

    def __iter__(self) -> Iterator[SeededBatch]:
        epoch = self._passes
        self._passes += 1
        for i, indices in enumerate(self.batches):
            yield _seeded_batch(list(indices), (self.seed, self.rank, epoch, i) if self.keyed else ())
