"""trainer=ddp: two CPU processes (gloo) train, and the command-balanced sampler gives each rank its
own samples with every command in every batch."""
from __future__ import annotations

import json
from pathlib import Path

import lightning as L
import pytest
from lightning.pytorch.strategies import DDPStrategy

from cicfw import N_COMMANDS
from cicfw.train.app import build_model, build_trainer, make_datamodule
from conftest import compose_train

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)


class BatchRecorder(L.Callback):
    """Appends each training batch's (speed, command) pairs to ``rank<r>.jsonl``: speeds are
    random per sample in the tiny dataset, so they identify samples."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        with open(self.folder / f"rank{trainer.global_rank}.jsonl", "a") as f:
            f.write(json.dumps({"speed": batch["speed"].tolist(), "command": batch["command"].tolist(),
                                "world_size": trainer.world_size}) + "\n")


def _ddp_cfg(tiny_data: Path, *extra: str):
    return compose_train(
        "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2", "trainer.precision=32-true",
        "data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "data.val_batch_size=8",
        "debug=fast", "trainer.fast_dev_run=2", "progress_bar=false", *extra,
    )


def test_ddp_config_is_lightning_ddp_with_selectable_precision(tiny_data, tmp_path):
    cfg = compose_train("trainer=ddp")
    assert cfg.trainer.strategy == "ddp" and cfg.trainer.accelerator == "gpu"
    assert cfg.trainer.precision == "32-true" and cfg.trainer.use_distributed_sampler is False  # the licensed precision
    assert cfg.trainer.max_epochs == compose_train().trainer.max_epochs  # inherits trainer/default
    trainer = build_trainer(_ddp_cfg(tiny_data, "trainer.precision=bf16-mixed"), tmp_path)
    assert isinstance(trainer.strategy, DDPStrategy) and trainer.world_size == 2
    assert trainer.precision == "bf16-mixed"


class ImageRecorder(L.Callback):
    """Appends a digest of each training batch's images to ``images<r>.txt``."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        import hashlib

        with open(self.folder / f"images{trainer.global_rank}.txt", "a") as f:
            f.write(hashlib.sha256(batch["image"].cpu().numpy().tobytes()).hexdigest() + "\n")


def test_two_cpu_processes_each_see_their_own_balanced_batches_and_augmentation(tmp_path):
    """One two-rank training checked two ways. Every image is one grey, so the ranks' batches can differ
    only by their augmentation; the speeds are random per sample, so they identify the samples."""
    import numpy as np

    from cicfw.data.cil_hdf5 import write_file
    from cicfw.testing import make_targets

    rng = np.random.default_rng(0)
    for i in range(6):
        write_file(tmp_path / "grey" / f"data_{i:05d}.h5", np.full((24, 88, 200, 3), 128, np.uint8), make_targets(24, rng))
    # ddp_spawn: the same DDP over gloo, but started from this process (plain `ddp` re-runs the
    # command line, here pytest's); the sampler and the ddp config are what is under test.
    cfg = _ddp_cfg(tmp_path / "grey", "trainer.strategy=ddp_spawn")
    trainer = build_trainer(cfg, tmp_path / "run")
    trainer.callbacks += [BatchRecorder(tmp_path), ImageRecorder(tmp_path)]
    trainer.fit(build_model(cfg), datamodule=make_datamodule(cfg))

    seen = {}
    for rank in (0, 1):
        batches = [json.loads(line) for line in (tmp_path / f"rank{rank}.jsonl").read_text().splitlines()]
        assert len(batches) == 2 and all(b["world_size"] == 2 for b in batches)
        for b in batches:
            assert len(b["speed"]) == 8
            assert sorted(b["command"]) == sorted(list(range(N_COMMANDS)) * 2)  # 2 per command, every command
        seen[rank] = {s for b in batches for s in b["speed"]}
        assert len(seen[rank]) == 16  # no sample twice within a rank's two batches
    assert not seen[0] & seen[1], "the two ranks drew the same samples"

    digests = [(tmp_path / f"images{rank}.txt").read_text().split() for rank in (0, 1)]
    assert len(digests[0]) == len(digests[1]) == 2
    assert not set(digests[0]) & set(digests[1]), "the two ranks drew the same augmentation"


@pytest.mark.parametrize("rank_zero", [True, False])
def test_only_global_rank_0_says_the_runs_last_line(tmp_path, monkeypatch, caplog, rank_zero):
    """Every DDP rank re-runs the app: the last line (metric and checkpoints) is rank 0's alone."""
    import logging

    from cicfw.testing import fast_dev_run

    monkeypatch.setattr(L.Trainer, "is_global_zero", property(lambda self: rank_zero))
    with caplog.at_level(logging.INFO, logger="cicfw.train"):
        fast_dev_run(tmp_path)
    said = [r for r in caplog.records if "no checkpoint written" in r.getMessage()]
    assert len(said) == int(rank_zero), [r.getMessage() for r in said]
