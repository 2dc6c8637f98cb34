"""Data at the public set's size: where the images live (data.in_memory=auto), augmentation streams per
worker/rank/epoch, and streamed files that change under a running job."""
from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from cicfw.data import images as images_module
from cicfw.data.cil_hdf5 import write_file
from cicfw.data.datamodule import CILDataModule
from cicfw.data.images import DataChangedError, ImageStore
from cicfw.data.residency import RAM_SHARE, decide, in_memory_setting
from cicfw.testing import make_targets, write_tiny_dataset

FRAME = 88 * 200 * 3  # bytes of one decoded uint8 RGB image, written out here, not taken from the module


def fake_trainer(rank: int, world: int) -> SimpleNamespace:
    """What the datamodule reads of a Trainer: its rank, world, epoch, and a broadcast that keeps rank 0's."""
    return SimpleNamespace(global_rank=rank, world_size=world, num_nodes=1, current_epoch=0,
                           strategy=SimpleNamespace(broadcast=lambda obj, src=0: obj))


# --- where the images live -------------------------------------------------------------------------

def test_auto_keeps_in_ram_what_fits_half_the_memory_and_streams_the_rest():
    avail = 10_000_000_000
    fits = int(0.5 * avail) // FRAME  # the largest frame count within half of the memory
    assert decide(fits, "auto", available=avail).in_memory
    assert not decide(fits + 1, "auto", available=avail).in_memory
    assert RAM_SHARE == 0.5


def test_each_rank_on_a_node_counts_its_own_copy():
    avail = 10_000_000_000
    n = int(0.5 * avail) // FRAME // 2 + 1  # fits one copy, not two
    assert decide(n, "auto", copies=1, available=avail).in_memory
    assert not decide(n, "auto", copies=2, available=avail).in_memory


def test_the_public_set_streams_and_the_main_jobs_data_stays_in_ram_on_24_gb():
    avail = 19_400_000_000  # MemAvailable of an idle 24 GB machine
    public = decide(462_000 + 66_330, "auto", available=avail)
    main = decide(29_995 + 4_400, "auto", available=avail)
    assert not public.in_memory and main.in_memory
    assert "27.9 GB" in public.reason() and "streamed" in public.reason()  # 528,330 x 52,800 bytes
    assert "in RAM" in main.reason() and "auto" in main.reason()


def test_in_memory_true_on_images_that_cannot_fit_is_refused_with_the_arithmetic():
    with pytest.raises(ValueError) as err:
        decide(528_330, True, available=19_400_000_000)
    assert (err.value.key, err.value.value) == ("data.in_memory", True)
    assert all(n in str(err.value) for n in ("528,330", "52,800", "27.9 GB", "19.4 GB")), err.value  # the arithmetic
    assert decide(528_330, False, available=19_400_000_000).in_memory is False


@pytest.mark.parametrize("bad", ["yes", 1, None, "Auto"])
def test_in_memory_accepts_true_false_auto_only(bad):
    with pytest.raises(ValueError) as err:
        in_memory_setting(bad)
    assert (err.value.key, err.value.value) == ("data.in_memory", bad)


def test_in_memory_true_is_refused_before_any_image_is_read(tmp_path, monkeypatch):
    write_tiny_dataset(tmp_path, n_files=4, n=8)
    monkeypatch.setattr("cicfw.data.residency.available_bytes", lambda: 1000)  # a machine with 1 kB free
    opened = []
    monkeypatch.setattr(ImageStore, "__init__", lambda *a, **k: opened.append(a))
    dm = CILDataModule(str(tmp_path), batch_size=8, in_memory=True, augment=False)
    with pytest.raises(ValueError) as err:
        dm.setup()
    assert err.value.key == "data.in_memory"
    assert not opened


# --- augmentation streams ------------------------------------------------------------------------

def constant_dataset(folder: Path, n_files: int = 4, n: int = 40) -> Path:
    """Every image the same grey: batches can differ only by their augmentation."""
    rng = np.random.default_rng(0)
    for i in range(n_files):
        write_file(folder / f"data_{i:05d}.h5", np.full((n, 88, 200, 3), 128, np.uint8), make_targets(n, rng))
    return folder


def first_batches(folder: Path, workers: int, k: int = 4, rank: int = 0, world: int = 1) -> list[np.ndarray]:
    dm = CILDataModule(str(folder), batch_size=8, seed=3, in_memory=False, num_workers=workers)
    dm.trainer = fake_trainer(rank, world)
    dm.setup()
    out = []
    for i, batch in enumerate(dm.train_dataloader()):
        out.append(batch["image"].numpy())
        if i + 1 == k:
            break
    return out


@pytest.mark.slow  # DataLoader worker processes
def test_two_workers_draw_different_augmentation(tmp_path):
    a = first_batches(constant_dataset(tmp_path), workers=2)
    assert not np.array_equal(a[0], a[1])  # batch 0 comes from worker 0, batch 1 from worker 1


@pytest.mark.slow  # DataLoader worker processes
def test_the_same_seed_gives_the_same_batches_through_workers(tmp_path):
    folder = constant_dataset(tmp_path)
    a, b = first_batches(folder, workers=2), first_batches(folder, workers=2)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


def test_two_ranks_draw_different_augmentation(tmp_path):
    folder = constant_dataset(tmp_path)
    r0, r1 = first_batches(folder, 0, rank=0, world=2), first_batches(folder, 0, rank=1, world=2)
    assert not np.array_equal(r0[0], r1[0])


@pytest.mark.slow  # DataLoader worker processes
def test_epochs_draw_different_augmentation(tmp_path):
    dm = CILDataModule(str(constant_dataset(tmp_path)), batch_size=8, seed=3, in_memory=False, num_workers=2,
                       batches_per_epoch=1)
    dm.setup()
    loader = dm.train_dataloader()
    e0, e1 = (next(iter(loader))["image"].numpy() for _ in range(2))
    assert not np.array_equal(e0, e1)


def test_a_single_process_keeps_the_datasets_own_generator(tmp_path):
    """One process, no ranks: the augmentation the run always had (the main job's table stands)."""
    from cicfw.data.augment import AugmentConfig, augment_batch

    folder = constant_dataset(tmp_path)
    dm = CILDataModule(str(folder), batch_size=8, seed=3, in_memory=True, num_workers=0, balanced=False)
    dm.setup()
    got = next(iter(dm.train_dataloader()))["image"].permute(0, 2, 3, 1).numpy()
    want = augment_batch(np.full((8, 88, 200, 3), 128, np.uint8), AugmentConfig(), np.random.default_rng(3))
    assert np.array_equal(got, want)


def test_rank_shards_stay_disjoint_through_the_wrapper(tmp_path):
    dm = CILDataModule(str(write_tiny_dataset(tmp_path, n_files=6, n=40)), batch_size=8, seed=1, in_memory=False)
    dm.setup()
    shards = []
    for rank in (0, 1):
        dm.trainer = fake_trainer(rank, 2)
        shards.append({i for batch in dm.train_dataloader().batch_sampler for i in batch})
    assert shards[0] and shards[1] and not shards[0] & shards[1]


def test_unbalanced_batches_give_each_rank_its_share_of_one_shuffled_pass(tmp_path):
    """data.balanced=false under several ranks: each rank drew a whole pass of its own (two ranks, two passes
    an epoch). Now the ranks split one pass, disjoint and covering it but the remainder, reshuffled each epoch."""
    dm = CILDataModule(str(write_tiny_dataset(tmp_path, n_files=6, n=40)), batch_size=8, seed=1, in_memory=False,
                       balanced=False)
    dm.setup()
    n = len(dm.train_set)
    epochs = []
    for rank in (0, 1):
        dm.trainer = fake_trainer(rank, 2)
        loader = dm.train_dataloader()
        epochs.append([[i for batch in loader.batch_sampler for i in batch] for _ in range(2)])
    for e in (0, 1):
        a, b = set(epochs[0][e]), set(epochs[1][e])
        assert not a & b and len(a) == len(b) == (n // 2) // 8 * 8  # per rank: its half, in whole batches
    assert epochs[0][0] != epochs[0][1]  # the next epoch is another shuffle


# --- streamed files that change under a running job ----------------------------------------------

def streamed(tmp_path: Path) -> tuple[ImageStore, list[Path]]:
    folder = write_tiny_dataset(tmp_path / "d", n_files=4, n=8)
    dm = CILDataModule(str(folder), batch_size=8, in_memory=False, augment=False)
    dm.setup()
    return dm.train_set.store, sorted(folder.glob("*.h5"))


def test_a_file_replaced_after_setup_is_named_not_paired_with_old_labels(tmp_path):
    store, files = streamed(tmp_path)
    victim = store.frames.files[int(store.frames.file_idx[0])]
    rng = np.random.default_rng(9)
    write_file(victim, rng.integers(0, 255, (8, 88, 200, 3), dtype=np.uint8), make_targets(8, rng))
    with pytest.raises(DataChangedError) as err:
        store.get(np.arange(len(store.frames)))
    assert str(victim) in str(err.value)


def test_a_file_removed_after_setup_is_named(tmp_path):
    store, _ = streamed(tmp_path)
    victim = store.frames.files[int(store.frames.file_idx[0])]
    victim.unlink()
    with pytest.raises(DataChangedError) as err:
        store.get(np.arange(len(store.frames)))
    assert str(victim) in str(err.value)


def test_a_file_truncated_while_open_is_named(tmp_path):
    store, _ = streamed(tmp_path)
    idx = np.arange(len(store.frames))
    store.get(idx)  # every file now open
    victim = store.frames.files[int(store.frames.file_idx[0])]
    with open(victim, "r+b") as f:
        f.truncate(4096)
    with pytest.raises(DataChangedError) as err:
        store.get(idx)
    assert str(victim) in str(err.value)


@pytest.mark.slow  # DataLoader worker processes
def test_a_workers_error_arrives_as_one_line(tmp_path):
    folder = constant_dataset(tmp_path / "d")
    dm = CILDataModule(str(folder), batch_size=8, in_memory=False, num_workers=1)
    dm.setup()
    files = sorted(folder.glob("*.h5"))
    for f in files:
        f.unlink()
    with pytest.raises(DataChangedError) as err:
        next(iter(dm.train_dataloader()))
    assert "\n" not in str(err.value) and any(str(f) in str(err.value) for f in files)  # names the file


def test_streaming_keeps_a_bounded_number_of_files_open(tmp_path, monkeypatch):
    monkeypatch.setattr(images_module, "MAX_OPEN_FILES", 2)
    store, files = streamed(tmp_path)
    store.get(np.arange(len(store.frames)))
    assert len(store._handles) == 2
    open_fds = {os.path.realpath(f"/proc/self/fd/{fd}") for fd in os.listdir("/proc/self/fd")}
    assert sum(str(f.resolve()) in open_fds for f in files) <= 2


# --- the step waiting for data -------------------------------------------------------------------

def test_the_wait_share_is_the_gaps_between_batches_over_the_whole(caplog):
    from cicfw.data.wait import WARMUP_BATCHES, DataWait

    # batch i starts at starts[i] and ends at ends[i] (seconds); the gaps before the warm-up batches
    # are the workers starting and do not count
    starts = [0.0, 5.0, 5.5, 6.0, 6.3, 7.0, 7.4]
    ends = [4.0, 5.2, 5.7, 6.1, 6.5, 7.1, 7.6]
    clock = iter(t for pair in zip(starts, ends) for t in pair)
    cb = DataWait(clock=lambda: next(clock))
    trainer = SimpleNamespace(global_rank=0)
    logged = {}
    module = SimpleNamespace(log=lambda k, v, **_: logged.update({k: v}))
    cb.on_train_epoch_start(trainer, module)
    for i in range(len(starts)):
        cb.on_train_batch_start(trainer, module, None, i)
        cb.on_train_batch_end(trainer, module, None, None, i)
    wait = sum(starts[i] - ends[i - 1] for i in range(WARMUP_BATCHES, len(starts)))  # 0.3 + 0.2 + 0.5 + 0.3
    step = sum(ends[i] - starts[i] for i in range(WARMUP_BATCHES, len(starts)))  # 0.1 + 0.2 + 0.1 + 0.2
    with caplog.at_level("INFO"):
        cb.on_train_epoch_end(trainer, module)
    assert logged["perf/data_wait_share"] == pytest.approx(wait / (wait + step)) == pytest.approx(1.3 / 1.9)
    assert "waited for data 68%" in caplog.text and "slower than training" in caplog.text


# --- where the bytes are read from ---------------------------------------------------------------

@pytest.mark.parametrize("layout", [dict(chunks=(1, 88, 200, 3)), dict(), dict(chunks=(1, 88, 200, 3), compression="gzip"),
                                    dict(chunks=(2, 88, 200, 3))])
def test_every_storage_layout_reads_the_images_h5py_reads(tmp_path, layout):
    """Raw reads (one chunk per image, or contiguous) and the h5py fallback (compressed, other chunks)
    give the very bytes h5py gives, duplicated rows included."""
    from cicfw.data.frames import load_frames

    rng = np.random.default_rng(4)
    for i in range(3):
        with h5py.File(tmp_path / f"f{i}.h5", "w") as f:
            f.create_dataset("rgb", data=rng.integers(0, 255, (10, 88, 200, 3), dtype=np.uint8), **layout)
            f["targets"] = make_targets(10, rng)
    frames = load_frames(str(tmp_path))
    idx = np.array([0, 3, 3, 7, 12, 25, 29, 12])
    want = np.stack([h5py.File(frames.files[frames.file_idx[i]], "r")["rgb"][frames.row[i]] for i in idx])
    assert np.array_equal(ImageStore(frames, in_memory=False).get(idx), want)
    raw = layout.get("compression") is None and layout.get("chunks", (1,))[0] == 1
    assert (images_module.raw_offsets(h5py.File(frames.files[0], "r")["rgb"]) is not None) == raw


def test_train_counts_a_copy_per_rank_before_the_ranks_start(tmp_path, monkeypatch):
    """train sets the data up before fit starts the ranks: the trainer's world size must count already."""
    import cicfw.data.datamodule as dm_module
    from hydra import compose, initialize_config_module

    from cicfw.train import app as train_module

    seen = []
    real = dm_module.decide
    monkeypatch.setattr(dm_module, "decide", lambda frames, setting, copies=1: seen.append(copies) or real(frames, setting, copies))
    monkeypatch.setattr(train_module, "fit", lambda *a, **k: (_ for _ in ()).throw(SystemExit("stop before fit")))
    data = write_tiny_dataset(tmp_path / "d", n_files=4, n=24)
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("train", overrides=["data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "trainer=ddp",
                                          "trainer.accelerator=cpu", "trainer.devices=2", "trainer.precision=32-true",
                                          "speed.compile=false", "progress_bar=false"])
    with pytest.raises(SystemExit, match="stop before fit"):
        train_module.train(cfg, tmp_path / "run")
    assert seen == [2]


def test_batches_are_pinned_for_a_cuda_gpu_only(tmp_path):
    from lightning.pytorch.accelerators import CPUAccelerator, CUDAAccelerator

    dm = CILDataModule(str(write_tiny_dataset(tmp_path, n_files=4, n=24)), batch_size=8, in_memory=False)
    dm.setup()
    pinned = {}
    for name, accelerator in (("cuda", CUDAAccelerator()), ("cpu", CPUAccelerator())):
        dm.trainer = SimpleNamespace(**vars(fake_trainer(0, 1)), accelerator=accelerator)
        pinned[name] = (dm.train_dataloader().pin_memory, dm.val_dataloader().pin_memory)
    assert pinned == {"cuda": (True, True), "cpu": (False, False)}


@pytest.mark.parametrize("augment", [0, 1, "", "off", [], [1]])
def test_data_augment_takes_true_false_or_a_dict_only(augment):
    """0, '' and [] used to switch CIL's full augmentation on; 1 was a TypeError deep in from_dict."""
    with pytest.raises(ValueError) as err:
        CILDataModule("unused", augment=augment)
    assert (err.value.key, err.value.value) == ("data.augment", augment)
    assert CILDataModule("unused", augment=False).augment is None
    assert CILDataModule("unused", augment={"p_blur": 0.2}).augment.p_blur == 0.2


def test_a_dangling_link_in_the_data_folder_is_named(tmp_path, caplog):
    from cicfw.data.cil_hdf5 import find_files

    write_tiny_dataset(tmp_path, n_files=2, n=8)
    (tmp_path / "data_00099.h5").symlink_to(tmp_path / "gone.h5")
    with caplog.at_level("WARNING"):
        assert len(find_files(tmp_path)) == 2
    assert "data_00099.h5" in caplog.text and "point at nothing" in caplog.text
