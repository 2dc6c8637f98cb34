"""Parameters and training-step cost of every mixer x head, relative to CIL (independent + regression).

    python bench/models.py [--batch 120] [--repeats 5] [--threads 2]

Each model is built exactly as ``python -m cicfw.train mixer=M head=H`` builds it (Hydra compose +
``build_model``, so the configs' defaults are what is measured). The timed step is forward + loss
(+ the mixer's regularizer) + backward on a batch of 120 random images (CPU, fp32, 30 per command).
Every model is timed right after a CIL model in each round (paired), in a shuffled order, and its
ratio is the median of those paired ratios, so load from other processes hits both sides alike.
"branches" times the mixer + head alone on fixed features h (median of 5), which isolates what the
mixers add from the encoder, which dominates.
Figure to reach: no mixer costs more than 1.5x the CIL training step.
"""
from __future__ import annotations

import argparse
import os
import platform
import random
import statistics
import sys
import time

import torch

MIXERS = ["independent", "gtu", "re", "moe", "soft_sharing", "cross_stitch", "sluice"]
HEADS = ["regression", "softmax", "hybrid", "coexistence", "sine"]
LIMIT = 1.5


def build(mixer: str, head: str):
    from hydra import compose, initialize_config_module

    from cicfw.train.app import build_model

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("train", overrides=[f"mixer={mixer}", f"head={head}"])
    return build_model(cfg)


def make_batch(n: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return {
        "image": torch.randint(0, 256, (n, 3, 88, 200), dtype=torch.uint8, generator=g),
        "speed": torch.rand(n, generator=g) * 40,
        "command": torch.arange(n) % 4,
        "steer": torch.rand(n, generator=g) * 1.6 - 0.8,
    }


def step(model, batch) -> float:
    """Seconds for one forward + loss + backward, as a training step computes them."""
    model.zero_grad(set_to_none=True)
    t = time.perf_counter()
    out = model(batch["image"], batch["speed"], batch["command"])
    loss = model.head.loss(out, batch["steer"]) + model.mixer.regularizer()
    loss.backward()
    return time.perf_counter() - t


def branches_step(model, h, batch) -> float:
    """Seconds for mixer + head forward/backward on fixed features h (no encoder)."""
    model.zero_grad(set_to_none=True)
    t = time.perf_counter()
    out = model.mixer(h)[torch.arange(h.shape[0]), batch["command"]]
    loss = model.head.loss(out, batch["steer"]) + model.mixer.regularizer()
    loss.backward()
    return time.perf_counter() - t


def n_params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def load() -> str:
    return "load average %.2f %.2f %.2f" % os.getloadavg()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=120)
    ap.add_argument("--repeats", type=int, default=5, help="timed rounds (after one warm-up round)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    print(f"bench/models.py: batch {args.batch}, CPU fp32, torch {torch.__version__}, {args.threads} threads, "
          f"{args.repeats} rounds (medians); {platform.machine()}, {os.cpu_count()} cores")
    print(f"start: {load()}")
    t0 = time.perf_counter()
    pairs = [(m, h) for m in MIXERS for h in HEADS]
    base_pair = ("independent", "regression")
    models = {p: build(*p).train() for p in pairs}
    base_model = build(*base_pair).train()  # a second CIL, timed next to every model (paired ratios)
    batch = make_batch(args.batch)
    h = torch.randn(args.batch, 512, requires_grad=True)
    times = {p: [] for p in pairs}
    ratios = {p: [] for p in pairs}
    btimes = {p: [] for p in pairs}
    order = list(pairs)
    rng = random.Random(0)
    paired_base = {p: [] for p in pairs}
    for r in range(args.repeats + 1):
        rng.shuffle(order)  # no model always runs right after the same one
        for p in order:
            tb, tp = step(base_model, batch), step(models[p], batch)
            bt = min(branches_step(models[p], h, batch) for _ in range(5))
            if r:  # round 0 warms up allocators and kernels
                paired_base[p].append(tb)
                times[p].append(tp)
                ratios[p].append(tp / tb)
                btimes[p].append(bt)
        print(f"round {r}/{args.repeats} done, {load()}", file=sys.stderr, flush=True)
    print(f"end:   {load()}  ({time.perf_counter() - t0:.0f} s)")
    base = statistics.median(times[base_pair])
    print()
    print("x CIL: median over rounds of (this model's step / a CIL step timed just before it); the row "
          "independent+regression against itself shows the noise. x CIL (min): fastest step of the model / "
          "fastest of the CIL steps paired with it (the least disturbed by other processes). "
          "branches ms: mixer + head alone on fixed h (fastest of 5, median over rounds).")
    print(f"{'mixer':<13} {'head':<12} {'params':>10} {'mixer+head':>11} {'step ms':>8} {'x CIL':>6} "
          f"{'ratio range':>12} {'x CIL (min)':>11} {'branches ms':>12}")
    worst: dict[str, float] = {}
    for m, hd in pairs:
        model, rs = models[(m, hd)], ratios[(m, hd)]
        ratio = statistics.median(rs)
        worst[m] = max(worst.get(m, 0.0), ratio)
        print(f"{m:<13} {hd:<12} {n_params(model):>10,} {n_params(model.mixer) + n_params(model.head):>11,} "
              f"{statistics.median(times[(m, hd)]) * 1e3:>8.0f} {ratio:>6.2f} {min(rs):>5.2f}-{max(rs):<6.2f} "
              f"{min(times[(m, hd)]) / min(paired_base[(m, hd)]):>11.2f} {statistics.median(btimes[(m, hd)]) * 1e3:>12.1f}")
    print()
    base_min = min(min(ts) for ts in paired_base.values())
    print(f"CIL baseline (independent + regression): median {base * 1e3:.0f} ms, fastest {base_min * 1e3:.0f} ms "
          f"per forward+backward of {args.batch}")
    print("worst head per mixer, x CIL: " + ", ".join(f"{m} {r:.2f}" for m, r in worst.items()))
    bad = [m for m, r in worst.items() if r > LIMIT]
    print(f"figure: every mixer <= {LIMIT}x CIL: " + ("yes" if not bad else f"NO ({', '.join(bad)})"))


if __name__ == "__main__":
    main()
