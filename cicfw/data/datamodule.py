"""CILDataModule: the paper's data choices on CIL HDF5 files.

70/30 split by episode (seeded), |steer| <= 0.8, command-balanced batches of 120 (30 per
command), side cameras with a steering correction, CIL augmentation for training only.
"""
from __future__ import annotations

import logging
from typing import Any, Mapping, Sequence

import lightning as L
import numpy as np
import torch
from lightning.pytorch.accelerators import CUDAAccelerator
from torch.utils.data import BatchSampler, DataLoader, Dataset, DistributedSampler, RandomSampler

from cicfw import COMMANDS
from cicfw.core.errors import ConfigError
from cicfw.data.augment import AugmentConfig, augment_batch
from cicfw.data.frames import Frames
from cicfw.data.images import ImageStore
from cicfw.data.residency import decide, in_memory_setting
from cicfw.data.sampler import CommandBalancedBatchSampler, SeededBatches, batch_rng
from cicfw.data.split import check_split_settings, split_frames

log = logging.getLogger(__name__)


class FrameDataset(Dataset):
    """Batches as dicts of tensors, fetched whole through ``__getitems__`` (one vectorised pass).

    Augmentation draws from the batch's own stream when the batch carries one (``SeededBatches``), so
    workers and ranks never repeat each other; a plain list of indices draws from the dataset's generator.
    """

    def __init__(self, frames: Frames, store: ImageStore, augment: AugmentConfig | None, seed: int) -> None:
        self.frames, self.store, self.augment = frames, store, augment
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitems__(self, indices: Sequence[int]) -> dict[str, torch.Tensor]:
        idx = np.asarray(indices)
        images = self.store.get(idx)
        if self.augment is not None:
            augment_batch(images, self.augment, batch_rng(indices, self.rng))
        fr = self.frames
        return {
            "image": torch.from_numpy(images).permute(0, 3, 1, 2).contiguous(),
            "speed": torch.from_numpy(fr.speed[idx]),
            "command": torch.from_numpy(fr.command[idx]),
            "steer": torch.from_numpy(fr.steer[idx]),
        }

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {k: v[0] for k, v in self.__getitems__([i]).items()}


def _as_batch(batch: Any) -> Any:
    """``__getitems__`` already returns the collated batch."""
    return batch


class CILDataModule(L.LightningDataModule):
    def __init__(
        self,
        path: str,
        batch_size: int = 120,
        val_batch_size: int = 256,
        val_fraction: float = 0.3,
        seed: int = 0,
        max_abs_steer: float = 0.8,
        side_camera_correction: float = 0.15,
        cameras: Sequence[int] | None = (0, 1, 2),
        val_cameras: Sequence[int] | None = (0,),
        balanced: bool = True,
        batches_per_epoch: int | None = None,
        augment: dict | bool | None = True,
        in_memory: bool | str = "auto",
        num_workers: int = 0,
    ) -> None:
        super().__init__()
        for key, size in (("batch_size", batch_size), ("val_batch_size", val_batch_size)):
            if size < 1:
                raise ConfigError(f"data.{key}", size, ">= 1")
        # checked here, before any file is read (the sampler checks the batch size again)
        if balanced and batch_size % len(COMMANDS):
            raise ConfigError("data.batch_size", batch_size, f"a multiple of {len(COMMANDS)} for balanced batches",
                              f"data.batch_size must be a multiple of {len(COMMANDS)} for balanced batches "
                              f"({len(COMMANDS)} commands), got {batch_size}; or set data.balanced=false")
        if batches_per_epoch is not None and batches_per_epoch < 1:  # 0 read as null, -1 failed in the sampler
            raise ConfigError("data.batches_per_epoch", batches_per_epoch,
                              "null (training samples / batch size) or an integer >= 1")
        if batches_per_epoch is not None and not balanced:  # the plain shuffled sampler makes one pass per epoch
            raise ConfigError("data.batches_per_epoch", batches_per_epoch,
                              "null with data.balanced=false (an epoch is one pass over the training samples); "
                              "data.balanced=true sets the epoch's length")
        self.path = str(path)
        self.batch_size, self.val_batch_size = batch_size, val_batch_size
        self.val_fraction, self.seed = val_fraction, seed
        self.max_abs_steer, self.side_camera_correction = max_abs_steer, side_camera_correction
        self.cameras, self.val_cameras = check_split_settings(val_fraction, max_abs_steer, side_camera_correction,
                                                              cameras, val_cameras)
        self.balanced, self.batches_per_epoch = balanced, batches_per_epoch
        if augment is True or augment is None:
            self.augment = AugmentConfig()
        elif augment is False:
            self.augment = None
        elif isinstance(augment, Mapping):
            self.augment = AugmentConfig.from_dict(augment)
        else:  # 0, '' or [] would read as "the defaults", 1 or 'off' as nothing a user means
            raise ConfigError("data.augment", augment, "true, false or a dict of overrides",
                              f"data.augment must be true (CIL's augmentation), false (none) or a dict of "
                              f"overrides such as {{p_blur: 0.2}}, got {augment!r}")
        if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 0:
            # the DataLoader refuses it only when it is built, after the files were read, as a traceback
            raise ConfigError("data.num_workers", num_workers, "an integer >= 0 (0: batches in the main process)")
        self.in_memory, self.num_workers = in_memory_setting(in_memory), num_workers
        self.train_set: FrameDataset | None = None
        self.val_set: FrameDataset | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        frames, train, val = split_frames(self.path, self.val_fraction, self.seed, self.max_abs_steer,
                                          self.side_camera_correction, self.cameras, self.val_cameras)
        rank, world = self._rank()
        if not self.balanced and len(train) < self.batch_size * world:
            # drop_last batches of more samples than the split holds: an epoch of no step, a run that trains nothing
            raise ConfigError("data.batch_size", self.batch_size,
                              f"at most the {len(train) // world} training samples per rank with data.balanced=false")
        counts = dict(zip(COMMANDS, np.bincount(train.command, minlength=4).tolist()))
        log.info("data: %d train / %d val samples from %d files; train per command %s",
                 len(train), len(val), len(frames.files), counts)
        residency = self._residency(len(train) + len(val))
        log.info(residency.reason())
        self.train_set = FrameDataset(train, ImageStore(train, residency.in_memory), self.augment, self.seed)
        self.val_set = FrameDataset(val, ImageStore(val, residency.in_memory), None, self.seed)

    def _residency(self, frames: int):
        """RAM or streamed, counting a copy per rank on this node; once the ranks' process group is up,
        rank 0's decision holds for all (before it, as when train sets up the data ahead of fit, each
        rank decides from its own reading of the memory)."""
        trainer = getattr(self, "trainer", None)
        copies = 1
        if trainer is not None and trainer.world_size > 1:
            copies = max(1, trainer.world_size // max(1, trainer.num_nodes))
        residency = decide(frames, self.in_memory, copies)
        if copies > 1 and torch.distributed.is_available() and torch.distributed.is_initialized():
            residency = trainer.strategy.broadcast(residency, src=0)
        return residency

    def _pin_memory(self) -> bool:
        """Page-locked batches when training on a CUDA GPU: the copy to the device overlaps the step."""
        trainer = getattr(self, "trainer", None)
        return trainer is not None and isinstance(getattr(trainer, "accelerator", None), CUDAAccelerator)

    def _rank(self) -> tuple[int, int]:
        trainer = getattr(self, "trainer", None)
        return (trainer.global_rank, trainer.world_size) if trainer is not None else (0, 1)

    def train_dataloader(self) -> DataLoader:
        assert self.train_set is not None, "call setup() first"
        rank, world = self._rank()
        trainer = getattr(self, "trainer", None)
        start_epoch = int(trainer.current_epoch) if trainer is not None else 0  # a resumed run's epoch
        if self.balanced:
            batches = CommandBalancedBatchSampler(
                self.train_set.frames.command, self.batch_size, self.batches_per_epoch, self.seed, rank, world)
        elif world > 1:  # each rank its own share of one shuffled pass, as the balanced sampler shards
            shard = DistributedSampler(self.train_set, num_replicas=world, rank=rank, shuffle=True, seed=self.seed,
                                       drop_last=True)
            batches = BatchSampler(shard, self.batch_size, drop_last=True)
        else:
            gen = torch.Generator().manual_seed(self.seed)
            batches = BatchSampler(RandomSampler(self.train_set, generator=gen), self.batch_size, drop_last=True)
        # one process draws from the dataset's generator; workers and ranks need a stream per batch
        keyed = self.num_workers > 0 or world > 1
        return DataLoader(self.train_set, batch_sampler=SeededBatches(batches, self.seed, rank, start_epoch, keyed),
                          collate_fn=_as_batch, num_workers=self.num_workers,
                          persistent_workers=self.num_workers > 0, pin_memory=self._pin_memory())

    def val_dataloader(self) -> DataLoader:
        assert self.val_set is not None, "call setup() first"
        return DataLoader(self.val_set, batch_size=self.val_batch_size, shuffle=False,
                          collate_fn=_as_batch, num_workers=self.num_workers, pin_memory=self._pin_memory())
