"""The training batches: command-balanced (the paper: 120 samples, 30 per command), sharded across ranks,
each carrying its own augmentation seed.

A random generator held by the dataset is copied into every DataLoader worker and every DDP rank, so
they would all draw the same augmentation. Seeding each batch from where it stands in the run instead
(``SeededBatches``: seed, rank, epoch, batch number) gives distinct draws per batch, worker, rank and
epoch, and the same batches for the same seed whatever the number of workers. A single process keeps the
dataset's one generator (``keyed=False``): its draws never repeat, and a run keeps the augmentation it
always had.
"""
from __future__ import annotations

from typing import Iterable, Iterator

import numpy as np
from torch.utils.data import DistributedSampler, Sampler

from cicfw import COMMANDS, N_COMMANDS
from cicfw.core.errors import CicfwError, ConfigError


class CommandBalancedBatchSampler(Sampler[list[int]]):
    """Yields batches with ``batch_size / 4`` samples of each command.

    Each command's indices are shuffled once per epoch (seed + epoch, the same on every rank) and
    split into disjoint per-rank shards, then cycled, so rarer commands repeat within an epoch
    rather than shrinking their share. An epoch is ``num_batches`` batches (default: the number
    of samples / batch size / world size).
    """

    def __init__(
        self,
        commands: np.ndarray,
        batch_size: int = 120,
        num_batches: int | None = None,
        seed: int = 0,
        rank: int = 0,
        world_size: int = 1,
    ) -> None:
        if batch_size % N_COMMANDS:
            raise ConfigError("data.batch_size", batch_size, f"a multiple of {N_COMMANDS} for balanced batches")
        self.per_command = batch_size // N_COMMANDS
        self.batch_size = batch_size
        self.pools = [np.flatnonzero(commands == c) for c in range(N_COMMANDS)]
        for name, pool in zip(COMMANDS, self.pools):
            if len(pool) < world_size:
                raise CicfwError(
                    f"command {name!r} has {len(pool)} training samples, fewer than the {world_size} "
                    f"rank(s) that each need one; collect more data or use data.balanced=false"
                )
        self.seed, self.rank, self.world_size = seed, rank, world_size
        self.num_batches = num_batches or max(1, len(commands) // (batch_size * world_size))
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.num_batches

    def __iter__(self) -> Iterator[list[int]]:
        rng = np.random.default_rng((self.seed, self.epoch))
        shards = [rng.permutation(pool)[self.rank :: self.world_size] for pool in self.pools]
        self.epoch += 1  # a fresh order next epoch even if nobody calls set_epoch
        need = self.num_batches * self.per_command
        streams = [np.resize(s, need) for s in shards]  # cycle each shard to the length needed
        for i in range(self.num_batches):
            sl = slice(i * self.per_command, (i + 1) * self.per_command)
            yield np.concatenate([s[sl] for s in streams]).tolist()


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
        shard = getattr(self.batches, "sampler", None)
        if isinstance(shard, DistributedSampler):  # a rank's share of the shuffled pass: reshuffled each epoch
            shard.set_epoch(epoch)
        for i, indices in enumerate(self.batches):
            yield _seeded_batch(list(indices), (self.seed, self.rank, epoch, i) if self.keyed else ())
