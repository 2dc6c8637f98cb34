"""Training throughput of each speed variant: the model alone (forward, loss, backward, Adam step on
batches already in memory) and the full Lightning loop (data, augmentation, the same step, logging),
interleaved over several rounds so a change of load cannot pass for a loop overhead; medians.

    python bench/train_throughput.py                       # all variants, 3 rounds (~10 min on 2 cores)
    python bench/train_throughput.py --variants eager,default --rounds 2

Variants (``--variants``, comma-separated; ``default`` = conf/speed/default.yaml's switches):
  eager                      NCHW, Adam's for-loop step (torch's CPU default)
  channels_last              NHWC layout for the convolutions
  channels_last+fused        ... and Adam's fused step (the fallback when compile is not usable)
  compile                    torch.compile'd training step (forward + loss + its backward)
  compile+cl                 ... and channels_last
  compile+cl+foreach         ... and Adam's foreach step
  compile+cl+fused           ... and Adam's fused step
  compile+cl+fused+f32in     ... with the uint8 -> float conversion done before the compiled graph
                             (every other compile variant converts inside it)
  compile+cl+fused+bf16      ... under bf16 autocast (only where the CPU has avx512_bf16 / amx_bf16)

Every figure is printed with the 1-minute load average at the moment it was taken and the CPU this
process got while measuring it (CPU seconds per wall second: near the thread count on an idle
machine; well below it means another process took the cores, whatever the load average says: a
process at a higher priority (negative nice) holds them at a low load average). The ``mean loss``
column is each variant's loss over all its model-alone steps (same initial weights, same batches):
the variants must agree within dropout's noise. Closes with one summary line for the default.
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
from lightning.pytorch.loggers import CSVLogger
from omegaconf import OmegaConf

from cicfw.data.cil_hdf5 import N_TARGETS, T, write_file
from cicfw.data.datamodule import CILDataModule
from cicfw.model.module import CICModule
from cicfw.model.speed import SpeedConfig, apply_speed, time_steps, use_inductor_cache, warm_up

ROOT = Path(__file__).resolve().parents[1]
BATCH = 120

# name -> (channels_last, compile, adam, precision, convert the image to float before the model)
VARIANTS = {
    "eager": (False, False, "for-loop", "32-true", False),
    "channels_last": (True, False, "for-loop", "32-true", False),
    "channels_last+fused": (True, False, "fused", "32-true", False),
    "compile": (False, True, "for-loop", "32-true", False),
    "compile+cl": (True, True, "for-loop", "32-true", False),
    "compile+cl+foreach": (True, True, "foreach", "32-true", False),
    "compile+cl+fused": (True, True, "fused", "32-true", False),
    "compile+cl+fused+f32in": (True, True, "fused", "32-true", True),
    "compile+cl+fused+bf16": (True, True, "fused", "bf16-mixed", False),
}


def cpu_has_native_bf16() -> bool:
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def default_variant() -> str:
    """The variant conf/speed/default.yaml selects (its precision: conf/trainer/default.yaml's)."""
    cfg = OmegaConf.load(ROOT / "conf" / "trainer" / "default.yaml")
    s = SpeedConfig(**OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "speed" / "default.yaml")))
    key = (s.channels_last, s.compile in (True, "auto"), s.adam, str(cfg.get("precision", "32-true")), False)
    for name, spec in VARIANTS.items():
        if spec == key:
            return name
    VARIANTS["default"] = key
    return "default"


def load1() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


def write_dataset(folder: Path, files: int, rng: np.random.Generator) -> None:
    for i in range(files):
        t = np.zeros((200, N_TARGETS), np.float32)
        t[:, T.STEER] = rng.uniform(-0.7, 0.7, 200)
        t[:, T.SPEED] = rng.uniform(0, 30, 200)
        t[:, T.COMMAND] = rng.integers(2, 6, 200)
        t[:, T.CAMERA_ID] = np.resize([0, 1, 2], 200)
        t[:, T.CAMERA_YAW] = np.resize([0, -30, 30], 200)
        write_file(folder / f"data_{i:05d}.h5", rng.integers(0, 255, (200, 88, 200, 3), dtype=np.uint8), t)


class FloatInput(CICModule):
    """Converts the uint8 image to float (NHWC when channels_last) before the compiled step."""

    def on_after_batch_transfer(self, batch, dataloader_idx=0):
        fmt = torch.channels_last if self.channels_last else torch.contiguous_format
        return {**batch, "image": batch["image"].contiguous(memory_format=fmt).float()}


class Variant:
    def __init__(self, name: str) -> None:
        cl, comp, adam, self.precision, f32in = VARIANTS[name]
        self.name = name
        torch.manual_seed(0)  # the same initial weights for every variant
        self.model = (FloatInput if f32in else CICModule)()
        t0 = time.perf_counter()
        speed = SpeedConfig(channels_last=cl, compile=comp, adam=adam, keep_memory=False)  # bench/allocator.py's
        self.applied = apply_speed(self.model, speed, BATCH)
        if comp and self.precision == "bf16-mixed" and self.model._compiled_step is not None:
            with self.autocast():  # the autocast graph is another compilation
                warm_up(self.model, BATCH)
        self.warmup_s = time.perf_counter() - t0
        self.opt = self.model.configure_optimizers()
        self.alone: list[tuple[float, float]] = []  # (samples/s, load)
        self.loop: list[tuple[float, float]] = []
        self.losses: list[float] = []
        self.cores: list[float] = []  # CPU seconds of this process per wall second, per measurement

    def autocast(self):
        return torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.precision == "bf16-mixed")

    def model_alone(self, batches: list[dict], warmup: int) -> tuple[float, float]:
        """(samples/s, CPU cores this process got) over the steps after ``warmup``."""
        return time_steps(self.model, self.opt, batches, warmup, self.autocast, self.losses)

    def full_loop(self, dm: CILDataModule, steps: int, warmup: int, log_dir: str) -> tuple[float, float]:
        """(samples/s, CPU cores this process got) of the Lightning loop after ``warmup`` steps."""
        timer = StepTimer(warmup)
        trainer = L.Trainer(max_steps=warmup + steps, limit_val_batches=0, enable_checkpointing=False,
                            logger=CSVLogger(log_dir, name=self.name.replace("+", "_")), log_every_n_steps=10,
                            enable_progress_bar=False, enable_model_summary=False, precision=self.precision,
                            callbacks=[timer], use_distributed_sampler=False, accelerator="cpu", devices=1)
        trainer.fit(self.model, datamodule=dm)
        wall = timer.t1 - timer.t0
        return timer.n / wall, (timer.c1 - timer.c0) / wall


class StepTimer(L.Callback):
    """Wall time from the end of batch ``warmup - 1`` to the end of the last batch: each counted batch's
    fetch, augmentation, step and logging are inside the window."""

    def __init__(self, warmup: int) -> None:
        self.warmup, self.n, self.t0, self.t1 = warmup, 0, None, None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        now, cpu = time.perf_counter(), time.process_time()
        if batch_idx == self.warmup - 1:
            self.t0, self.c0 = now, cpu
        elif batch_idx >= self.warmup:
            self.n += batch["steer"].shape[0]
            self.t1, self.c1 = now, cpu


def inference_ms(model, batch: int, repeats: int) -> float:
    image = torch.randint(0, 256, (batch, 3, 88, 200), dtype=torch.uint8)
    speed, cmd = torch.full((batch,), 20.0), torch.arange(batch) % 4
    times = []
    with torch.inference_mode():
        for i in range(repeats + 3):
            t0 = time.perf_counter()
            model.predict_steer(image, speed, cmd)
            if i >= 3:
                times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1000


def inference_section(repeats: int) -> None:
    from cicfw.model.checkpoint import prepare_for_inference

    print(f"\ninference (eval, no grad), median ms per call; load {load1():.2f}")
    torch.manual_seed(0)
    base = CICModule().eval()
    ref = {"eager": base}
    cl = CICModule().eval()
    cl.load_state_dict(base.state_dict())
    ref["channels_last"] = cl.use_channels_last()
    folded = CICModule().eval()
    folded.load_state_dict(base.state_dict())
    ref["BN folded + cl (closed-loop policy)"] = prepare_for_inference(folded)
    for name, m in ref.items():
        b1, b64 = inference_ms(m, 1, repeats * 4), inference_ms(m, 64, repeats)
        print(f"  {name:<36} batch 1: {b1:6.2f} ms   batch 64: {b64:7.1f} ms   (load {load1():.2f})", flush=True)


def profile_loop(dm: CILDataModule, name: str, steps: int, warmup: int, log_dir: str) -> None:
    """The default's full loop under torch.profiler: the ops that take the time, and the share of the
    loop spent outside the training step (data, augmentation, Lightning, logging)."""
    from torch.profiler import ProfilerActivity, profile, record_function

    v = Variant(name)
    v.full_loop(dm, 2, warmup, log_dir)  # warm: recompilations, first optimizer state

    class Marks(L.Callback):
        def on_train_batch_start(self, *a):
            self.rf = record_function("## step (forward+loss+backward+Adam)")
            self.rf.__enter__()

        def on_train_batch_end(self, *a):
            self.rf.__exit__(None, None, None)

    print(f"profiling {name}: {steps} steps after {warmup} warm-up steps; load {load1():.2f}")
    trainer = L.Trainer(max_steps=warmup + steps, limit_val_batches=0, enable_checkpointing=False,
                        logger=CSVLogger(log_dir, name="profile"), log_every_n_steps=10, enable_progress_bar=False,
                        enable_model_summary=False, precision=v.precision, callbacks=[Marks()],
                        use_distributed_sampler=False, accelerator="cpu", devices=1)
    t0 = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        trainer.fit(v.model, datamodule=dm)
    wall = time.perf_counter() - t0
    events = prof.key_averages()
    step = next((e for e in events if e.key.startswith("## step")), None)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    if step is not None:
        print(f"wall {wall:.1f} s for {warmup + steps} steps; inside the training step (forward, loss, backward, "
              f"Adam, logging hooks) {step.cpu_time_total / 1e6:.1f} s = {step.cpu_time_total / 1e6 / wall:.0%}; "
              f"load {load1():.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", default=None, help="comma-separated (default: all; bf16 only with native support)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds (figures are medians over them)")
    ap.add_argument("--steps", type=int, default=10, help="timed steps per measurement")
    ap.add_argument("--warmup", type=int, default=2, help="untimed steps before each measurement")
    ap.add_argument("--files", type=int, default=40, help="synthetic CIL files of 200 samples")
    ap.add_argument("--inference-repeats", type=int, default=10, help="0 skips the inference section")
    ap.add_argument("--profile", action="store_true",
                    help="only profile the default's full loop (torch.profiler, after a warm-up) and print where time goes")
    args = ap.parse_args()
    if args.steps < 1 or args.warmup < 1 or args.rounds < 1:
        ap.error("--steps, --warmup and --rounds must be >= 1")
    default = default_variant()
    bf16 = cpu_has_native_bf16()
    if args.variants:
        names = [v.strip() for v in args.variants.split(",") if v.strip()]
        names = [default if v == "default" else v for v in names]
        unknown = [v for v in names if v not in VARIANTS]
        if unknown:
            ap.error(f"unknown variants {unknown}; known: default, {', '.join(VARIANTS)}")
    else:
        names = [v for v in VARIANTS if bf16 or "bf16" not in v]
    names = list(dict.fromkeys(["eager", *names, default]))  # eager and the default always run
    torch.set_num_threads(os.cpu_count() or 2)
    cache = use_inductor_cache()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, native bf16: {bf16}, "
          f"inductor cache {cache}, load {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"default (conf/speed/default.yaml): {default}")

    with tempfile.TemporaryDirectory() as tmp:
        write_dataset(Path(tmp) / "data", args.files, np.random.default_rng(0))
        # an epoch long enough that no measurement ever reaches its end
        dm = CILDataModule(str(Path(tmp) / "data"), batch_size=BATCH, batches_per_epoch=100_000)
        dm.setup("fit")
        it = iter(dm.train_dataloader())
        batches = [next(it) for _ in range(args.warmup + args.steps)]
        t0 = time.perf_counter()
        for _ in range(30):
            next(it)
        print(f"data pipeline alone (in-memory, augmented, balanced): {30 * BATCH / (time.perf_counter() - t0):,.0f} "
              f"samples/s (load {load1():.2f})")

        if args.profile:
            return profile_loop(dm, default, args.steps, args.warmup, str(Path(tmp) / "logs"))
        variants = []
        for name in names:
            v = Variant(name)
            variants.append(v)
            print(f"  built {name:<24} -> {v.applied}; set-up incl. compile warm-up {v.warmup_s:5.1f} s "
                  f"(load {load1():.2f})", flush=True)
        for r in range(args.rounds):
            for v in variants:
                a, ca = v.model_alone(batches, args.warmup)
                la = load1()
                v.alone.append((a, la))
                f, cf = v.full_loop(dm, args.steps, args.warmup, str(Path(tmp) / "logs"))
                lf = load1()
                v.loop.append((f, lf))
                v.cores += [ca, cf]
                print(f"round {r + 1}  {v.name:<24} model alone {a:6.1f}/s (load {la:.2f}, got {ca:.2f} cores)   "
                      f"full loop {f:6.1f}/s (load {lf:.2f}, got {cf:.2f} cores)", flush=True)

    def med(xs):
        return statistics.median(x for x, _ in xs)

    loads = [ld for v in variants for _, ld in v.alone + v.loop]
    print(f"\nmedians over {args.rounds} rounds of {args.steps} steps x {BATCH} samples; "
          f"load during the rounds {min(loads):.2f}-{max(loads):.2f}")
    print(f"| {'variant':<24} | {'model alone':>11} | {'full loop':>9} | {'loop/model':>10} | {'vs eager':>8} "
          f"| {'mean loss':>9} | {'load':>9} | {'cores got':>9} |")
    print(f"|{'-' * 26}|{'-' * 12}:|{'-' * 10}:|{'-' * 11}:|{'-' * 9}:|{'-' * 10}:|{'-' * 11}|{'-' * 10}:|")
    eager = med(variants[0].loop)
    for v in variants:
        a, f = med(v.alone), med(v.loop)
        ls = [ld for _, ld in v.alone + v.loop]
        label = v.name + (" (default)" if v.name == default else "")
        print(f"| {label:<24} | {a:9.1f}/s | {f:7.1f}/s | {f / a:10.0%} | {f / eager:7.2f}x "
              f"| {statistics.mean(v.losses):9.4f} | {min(ls):.2f}-{max(ls):.2f} | {min(v.cores):.2f}-{max(v.cores):.2f} |")
    if args.inference_repeats:
        inference_section(args.inference_repeats)
    d = next(v for v in variants if v.name == default)
    a, f = med(d.alone), med(d.loop)
    print(f"\nSUMMARY default {default}: full loop {f:.1f} samples/s = {f / a:.0%} of its model-alone "
          f"{a:.1f}/s, {f / eager:.2f}x eager's full loop ({eager:.1f}/s) in the same run; "
          f"load {min(loads):.2f}-{max(loads):.2f} (now {load1():.2f})")


if __name__ == "__main__":
    sys.exit(main())
