"""Command-balanced minibatches (the paper: 120 samples, 30 per command), sharded across ranks."""
from __future__ import annotations

from typing import Iterator

import numpy as np
from torch.utils.data import Sampler

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
