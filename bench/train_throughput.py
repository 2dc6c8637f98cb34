"""Training throughput: the real loop (data, augmentation, forward, backward, step) next to the
model alone on the same batches, for eager / channels_last / torch.compile / bf16 autocast; plus
inference latency at batch 1 and 128 for the closed-loop runner.

    python bench/train_throughput.py [--steps 30] [--variants eager,channels_last,compile,bf16]

Prints samples/s; the figure of merit is loop / model-alone (target >= 90%).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import lightning as L
import numpy as np
import torch

from cicfw.data.cil_hdf5 import N_TARGETS, T, write_file
from cicfw.data.datamodule import CILDataModule
from cicfw.model.module import CICModule

VARIANTS = {  # name -> (channels_last, compile, Trainer precision)
    "eager": (False, False, "32-true"),
    "channels_last": (True, False, "32-true"),
    "compile": (False, True, "32-true"),
    "bf16": (False, False, "bf16-mixed"),
}


def write_dataset(folder: Path, files: int, rng: np.random.Generator) -> None:
    for i in range(files):
        t = np.zeros((200, N_TARGETS), np.float32)
        t[:, T.STEER] = rng.uniform(-0.7, 0.7, 200)
        t[:, T.SPEED] = rng.uniform(0, 30, 200)
        t[:, T.COMMAND] = rng.integers(2, 6, 200)
        t[:, T.CAMERA_ID] = np.resize([0, 1, 2], 200)
        t[:, T.CAMERA_YAW] = np.resize([0, -30, 30], 200)
        write_file(folder / f"data_{i:05d}.h5", rng.integers(0, 255, (200, 88, 200, 3), dtype=np.uint8), t)


def make_model(channels_last: bool, compile_: bool) -> CICModule:
    model = CICModule()
    if channels_last:
        model.use_channels_last()
    if compile_:
        model.compile()
    return model


class StepTimer(L.Callback):
    """Wall time of training batches after ``warmup`` (data fetch included: it happens between batches)."""

    def __init__(self, warmup: int) -> None:
        self.warmup, self.t0, self.n = warmup, None, 0

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if batch_idx == self.warmup:
            self.t0 = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if batch_idx >= self.warmup:
            self.n += batch["steer"].shape[0]
            self.t1 = time.perf_counter()


def loop_rate(dm: CILDataModule, variant: str, steps: int, warmup: int) -> float:
    cl, comp, precision = VARIANTS[variant]
    torch.manual_seed(0)
    model = make_model(cl, comp)
    timer = StepTimer(warmup)
    trainer = L.Trainer(max_steps=warmup + steps, limit_val_batches=0, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, precision=precision,
                        callbacks=[timer], use_distributed_sampler=False)
    trainer.fit(model, datamodule=dm)
    return timer.n / (timer.t1 - timer.t0)


def model_alone_rate(batches: list[dict], variant: str, warmup: int) -> float:
    cl, comp, precision = VARIANTS[variant]
    torch.manual_seed(0)
    model = make_model(cl, comp)
    model.train()
    opt = model.configure_optimizers()
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16-mixed")
    n, t0 = 0, None
    for i, b in enumerate(batches):
        if i == warmup:
            t0 = time.perf_counter()
        with autocast:
            _, loss, _ = model._losses(b)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if i >= warmup:
            n += b["steer"].shape[0]
    return n / (time.perf_counter() - t0)


def inference_latency(variant: str, batch: int, repeats: int = 20) -> float:
    cl, comp, precision = VARIANTS[variant]
    model = make_model(cl, comp).eval()
    image = torch.randint(0, 256, (batch, 3, 88, 200), dtype=torch.uint8)
    speed, cmd = torch.full((batch,), 20.0), torch.zeros(batch, dtype=torch.long)
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16-mixed")
    times = []
    with torch.inference_mode(), autocast:
        for i in range(repeats + 3):
            t0 = time.perf_counter()
            model.predict_steer(image, speed, cmd)
            if i >= 3:
                times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=30, help="timed steps per measurement")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--variants", default="eager,channels_last,compile,bf16")
    ap.add_argument("--files", type=int, default=40, help="synthetic CIL files of 200 samples")
    args = ap.parse_args()
    variants = args.variants.split(",")
    torch.set_num_threads(os.cpu_count() or 2)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, load {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as tmp:
        write_dataset(Path(tmp), args.files, np.random.default_rng(0))
        dm = CILDataModule(tmp, batch_size=120, val_batch_size=256)
        dm.setup("fit")
        it = iter(dm.train_dataloader())
        batches = [next(it) for _ in range(args.warmup + args.steps)]
        t0 = time.perf_counter()
        for _ in range(20):
            next(it)
        data_rate = 20 * 120 / (time.perf_counter() - t0)
        print(f"data pipeline alone (in-memory, augmented, balanced): {data_rate:,.0f} samples/s")
        print(f"{'variant':<14}{'model alone':>14}{'full loop':>12}{'loop/model':>12}")
        for v in variants:
            alone = model_alone_rate(batches, v, args.warmup)
            loop = loop_rate(dm, v, args.steps, args.warmup)
            print(f"{v:<14}{alone:>11.1f}/s{loop:>10.1f}/s{loop / alone:>11.0%}", flush=True)
    print("inference latency (eval, no grad), median ms:")
    for v in variants:
        print(f"  {v:<14} batch 1: {inference_latency(v, 1):6.1f} ms   batch 128: {inference_latency(v, 128):7.1f} ms", flush=True)


if __name__ == "__main__":
    sys.exit(main())
