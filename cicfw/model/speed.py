"""Training speed switches (the ``speed`` node, ``conf/speed/default.yaml``): memory layout, torch.compile,
Adam's step, malloc.

None of them changes what is computed, only how fast (float rounding aside; the tolerance is tested
in ``tests/test_speed.py``). ``bench/train_throughput.py`` measures each one; the fastest correct
combination is the default.

torch.compile is applied to the training step only (forward + loss; backward comes with it through
AOTAutograd); validation and inference stay eager, so they pay no compilation for their own batch
sizes. Its generated code is cached on disk in the cicfw cache folder (``$CICFW_CACHE/inductor``,
default ``~/.cache/cicfw/inductor``), so the warm-up is paid once per machine. The warm-up runs
before training, on a dummy batch, without touching the model's weights, statistics or the random
streams; if it fails (no C compiler, an unsupported platform, a plugin part that cannot be traced)
training goes on eager with one warning line.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from cicfw.core.config_checks import SchemaError
from cicfw.model.encoders import IMAGE_HW
from cicfw.model.memory import keep_freed_memory

log = logging.getLogger("cicfw.speed")


def keep_fp32() -> None:
    """fp32 stays fp32 on a GPU: TensorFloat-32 off for matrix multiplies and cuDNN convolutions.

    On Ampere and newer GPUs TF32 runs an fp32 matmul or convolution with 10-bit mantissas in its
    products (fp32 has 23), and PyTorch's defaults already use it for cuDNN convolutions, which are most
    of the CIL encoder's arithmetic. That is another numerical recipe, as bf16 autocast is, and it has no
    license from driving (docs/training.md: the same paired test would license it), so ``32-true``
    means IEEE fp32 here: every training and every checkpoint loaded to drive calls this. It changes
    nothing on a CPU (the flags are CUDA's; oneDNN's fp32 stays fp32 by default)."""
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    torch.set_float32_matmul_precision("highest")

ADAM_IMPLS = ("for-loop", "foreach", "fused")


def cicfw_cache_dir() -> Path:
    """The cicfw cache folder: ``$CICFW_CACHE``, else ``~/.cache/cicfw`` (as in ``conf/data/sim_default.yaml``)."""
    return Path(os.environ.get("CICFW_CACHE") or Path.home() / ".cache" / "cicfw").expanduser()


def use_inductor_cache() -> Path:
    """Point inductor's on-disk cache into the cicfw cache folder (``<cache>/inductor``) unless the user
    set TORCHINDUCTOR_CACHE_DIR to somewhere else than torch's default (``/tmp/torchinductor_<user>``,
    which torch writes into the environment itself once it has looked). Call before compiling.
    Returns the folder used."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    current = os.environ.get("TORCHINDUCTOR_CACHE_DIR")
    if not current or os.path.abspath(current) == os.path.abspath(default_cache_dir()):
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(cicfw_cache_dir() / "inductor")
        if current:  # torch already resolved the default: drop what it memoised from it
            from torch._inductor.utils import clear_caches

            clear_caches()
    return Path(os.environ["TORCHINDUCTOR_CACHE_DIR"])


#: ``compile: auto`` compiles when training runs at least this many steps: below it, a compilation
#: with an empty cache (~15-45 s on 2 cores) costs more than it saves (tests, fast_dev_run, debugging)
AUTO_COMPILE_MIN_STEPS = 200


@dataclass
class SpeedConfig:
    """The ``speed`` node: its schema (cicfw/train/schema.py) and its defaults, which conf/speed/default.yaml
    states. The defaults are the fastest variant that computes what eager does (docs/training.md#speed)."""

    channels_last: bool = True   # NHWC memory layout for the encoder's convolutions
    compile: bool | str = "auto"  # true | false | auto: compile the training step when it runs >= 200 steps
    adam: str = "for-loop"       # for-loop | foreach | fused: how Adam's step is computed
    keep_memory: bool = True     # malloc keeps freed memory (cicfw/model/memory.py): no page faults per step

    def __post_init__(self) -> None:
        if self.adam not in ADAM_IMPLS:
            raise SchemaError(f"speed.adam must be one of {', '.join(ADAM_IMPLS)}, got {self.adam!r}",
                              "speed.adam", "wrong type")
        if not any(type(self.compile) is type(c) and self.compile == c for c in (True, False, "auto")):
            raise SchemaError(f"speed.compile must be true, false or auto, got {self.compile!r}",
                              "speed.compile", "wrong type")


#: the speed switches' names: the keys of the ``speed`` node
SPEED_SWITCHES = tuple(f.name for f in dataclasses.fields(SpeedConfig))


def dummy_batch(model, batch_size: int) -> dict[str, torch.Tensor]:
    """A batch of the training shapes (the encoder's input is uint8 (B, 3, 88, 200))."""
    g = torch.Generator().manual_seed(0)
    return {"image": torch.randint(0, 256, (batch_size, 3, *IMAGE_HW), dtype=torch.uint8, generator=g),
            "speed": torch.rand(batch_size, generator=g) * 30,
            "command": torch.arange(batch_size) % 4,
            "steer": torch.rand(batch_size, generator=g) * 1.6 - 0.8}


def warm_up(model, batch_size: int) -> None:
    """One forward + backward of the training step on a dummy batch, leaving no trace: the weights,
    the BatchNorm statistics, the gradients and the random streams are as before."""
    saved = {k: v.detach().clone() for k, v in model.state_dict().items()}
    was_training = model.training
    grads = {p: p.grad for p in model.parameters()}
    model.train()
    try:
        with torch.random.fork_rng(devices=[]):
            _, loss, _ = model._losses(dummy_batch(model, batch_size))
            loss.backward()
    finally:
        with torch.no_grad():
            for k, v in model.state_dict().items():
                v.copy_(saved[k])
        for p, g in grads.items():
            p.grad = g
        model.train(was_training)


def apply_speed(model, speed: SpeedConfig, batch_size: int = 120, warm: bool = True) -> str:
    """Apply ``speed`` to ``model`` (a CICModule) and return the name of the variant it runs
    (``compile: auto`` must have been resolved to true/false by the caller).

    With ``compile``, compiles the training step now on a dummy CPU batch (timed, logged) and falls
    back to the variant without compile, with one warning line, if that fails. ``warm=False`` (a model
    that will train on a GPU) compiles lazily on the first step instead, with dynamo told to fall back
    to eager on a failure.
    """
    model.adam_impl = speed.adam
    if speed.channels_last:
        model.use_channels_last()
    name = ("channels_last" if speed.channels_last else "eager") + f", Adam {speed.adam}"
    if speed.keep_memory:
        why = keep_freed_memory()
        if why is None:
            name += ", freed memory kept"
        else:
            log.warning("speed.keep_memory: %s; freed memory goes back to the kernel as usual", why)
    if not speed.compile:
        return name
    cache = use_inductor_cache()
    t0 = time.perf_counter()
    try:
        model.enable_compile()
        if not warm:
            import torch._dynamo

            torch._dynamo.config.suppress_errors = True  # a failure at the first step: eager, not a crash
            log.info("torch.compile: the training step compiles at its first step (inductor cache %s)", cache)
            return "compile+" + name
        warm_up(model, batch_size)
    except Exception as err:  # noqa: BLE001 - any failure of the compiler stack means: run eager
        model.disable_compile()
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        log.warning("torch.compile is not usable here (%s: %s); training runs %s without compile",
                    type(err).__name__, first[:200], name)
        return name
    log.info("torch.compile: training step compiled in %.1f s (inductor cache %s)", time.perf_counter() - t0, cache)
    return "compile+" + name


def time_steps(model, opt, batches: list[dict], warmup: int, autocast=contextlib.nullcontext,
               losses: list[float] | None = None) -> tuple[float, float]:
    """Run one optimizer step (forward, loss, backward, ``opt.step``) per batch, as training does, and
    return (samples/s, CPU cores this process got) over the steps after ``warmup`` (bench/ scripts).
    Each step's loss is appended to ``losses`` when given."""
    model.train()
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    for i, b in enumerate(batches):
        if i == warmup:
            n, t0, c0 = 0, time.perf_counter(), time.process_time()
        b = model.on_after_batch_transfer(b, 0)
        with autocast():
            _, loss, _ = model._losses(b)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if losses is not None:
            losses.append(float(loss.detach()))
        n += b["steer"].shape[0]
    wall = time.perf_counter() - t0
    return n / wall, (time.process_time() - c0) / wall


def planned_steps(trainer_cfg, batches_per_epoch: int) -> float:
    """Training steps a run with this trainer config will take (inf when unbounded or time-limited)."""
    if trainer_cfg.get("fast_dev_run"):
        return 1
    max_steps = trainer_cfg.get("max_steps")
    if max_steps is not None and max_steps >= 0:
        return max_steps
    epochs = trainer_cfg.get("max_epochs")
    if epochs is None or epochs < 0:
        return float("inf")
    limit = trainer_cfg.get("limit_train_batches")
    if isinstance(limit, int) and not isinstance(limit, bool):
        batches_per_epoch = min(batches_per_epoch, limit)
    elif isinstance(limit, float):
        batches_per_epoch = int(batches_per_epoch * limit)
    return epochs * batches_per_epoch


def apply_speed_from_config(model, speed: SpeedConfig, trainer_cfg, batch_size: int, batches_per_epoch: int) -> str:
    """``apply_speed`` with ``speed`` (the ``speed`` node's switches), ``compile: auto`` resolved from the run's
    length and device in ``trainer_cfg`` (``cfg.trainer``); logs and returns the variant."""
    speed = dataclasses.replace(speed)
    if speed.compile == "auto":
        steps = planned_steps(trainer_cfg, batches_per_epoch)
        speed.compile = steps >= AUTO_COMPILE_MIN_STEPS
        if not speed.compile:
            log.info("speed.compile=auto: %d training steps, too few to pay for compiling; running eager", steps)
    on_cpu = str(trainer_cfg.get("accelerator", "cpu")) == "cpu" or (
        str(trainer_cfg.get("accelerator")) == "auto" and not torch.cuda.is_available())
    keep_fp32()
    variant = apply_speed(model, speed, batch_size, warm=on_cpu)
    log.info("training speed variant: %s", variant)
    return variant
