"""Training-step cost of Table-4 rows as a reproduction cell trains them, relative to CIL.

    python bench/row_cost.py --rows cil,moe,gtu [--rounds 3] [--steps 10]

bench/models.py times every mixer x head eagerly; a cell of ``budget=converged`` trains with
``speed.compile=true speed.channels_last=true``, where a mixer can cost more (or less) than its
eager figure says. Here each row's model is built from its ``paper_*`` experiment (conf/reproduce.yaml's
catalogue), given the converged budget's speed switches (``apply_speed``: compile + channels_last,
Adam's for-loop step), and timed on the same random batch (``dummy_batch``) for the whole optimizer
step (forward, loss, backward, Adam; ``time_steps``, as bench/train_throughput.py's model-alone figure). Rows are interleaved round by round, CIL first in each, so a change of load hits
them alike; the figure is the median over rounds of (row's samples/s / CIL's samples/s in that round).
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import torch
from hydra import compose, initialize_config_module

from cicfw.model.speed import SpeedConfig, apply_speed, dummy_batch, time_steps
from cicfw.reproduction.claims import shipped_config
from cicfw.train.app import build_model

BATCH = 120


def build(row: str, keep_memory: bool = False):
    """The row's model as its cell builds it, with the speed switches applied (compiled, warmed up);
    ``keep_memory`` as ``speed.keep_memory`` (bench/allocator.py compares it)."""
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        spec = compose("reproduce").catalogue[row]
        cfg = compose("train", overrides=[f"experiment={spec['experiment']}", *spec.get("overrides", [])])
    torch.manual_seed(0)
    model = build_model(cfg).train()
    t0 = time.perf_counter()
    variant = apply_speed(model, SpeedConfig(channels_last=True, compile=True, adam="for-loop", keep_memory=keep_memory), BATCH)
    opt = model.configure_optimizers()
    opt = opt["optimizer"] if isinstance(opt, dict) else opt
    return model, opt, variant, time.perf_counter() - t0


def check_args(ap: argparse.ArgumentParser, args: argparse.Namespace, rows: list[str]) -> None:
    """One line (exit status 2) before anything is compiled: a row that is not in conf/reproduce.yaml's
    catalogue (naming the known ones), fewer than one round or step, a negative warm-up."""
    known = list(shipped_config()["catalogue"])
    unknown = [r for r in rows if r not in known]
    if unknown:
        ap.error(f"--rows: unknown row(s) {', '.join(unknown)}; known rows: {', '.join(known)}")
    if args.rounds < 1 or args.steps < 1:
        ap.error(f"--rounds and --steps must be >= 1 (got {args.rounds} and {args.steps}): the figure is a median "
                 f"over rounds of timed steps")
    if args.warmup < 0:
        ap.error(f"--warmup must be >= 0, got {args.warmup}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", default="cil,moe", help="comma-separated catalogue rows (CIL is always timed)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=10, help="timed optimizer steps per row and round")
    ap.add_argument("--warmup", type=int, default=2)
    args = ap.parse_args()
    rows = ["cil"] + [r for r in args.rows.split(",") if r and r != "cil"]
    check_args(ap, args, rows)
    print(f"bench/row_cost.py: batch {BATCH}, {torch.get_num_threads()} threads, torch {torch.__version__}, "
          f"{args.rounds} rounds x {args.steps} steps; load {os.getloadavg()[0]:.2f}", flush=True)
    models = {}
    for r in rows:
        model, opt, variant, warm = build(r)
        models[r] = (model, opt)
        print(f"  {r:<14} {variant}; compiled + warmed in {warm:.0f} s", flush=True)
    batches = [dummy_batch(None, BATCH)] * (args.warmup + args.steps)
    speed: dict[str, list[float]] = {r: [] for r in rows}
    cores: dict[str, list[float]] = {r: [] for r in rows}
    for k in range(args.rounds):
        for r in rows:
            s, c = time_steps(*models[r], batches, args.warmup)
            speed[r].append(s)
            cores[r].append(c)
        print(f"  round {k + 1}/{args.rounds}: " + ", ".join(f"{r} {speed[r][-1]:.0f}" for r in rows)
              + f" samples/s; load {os.getloadavg()[0]:.2f}", flush=True)
    print(f"\n{'row':<14} {'samples/s':>10} {'x CIL':>6} {'cores':>6}")
    for r in rows:
        ratio = statistics.median(a / b for a, b in zip(speed[r], speed["cil"]))
        print(f"{r:<14} {statistics.median(speed[r]):>10.0f} {ratio:>6.2f} {statistics.median(cores[r]):>6.2f}")


if __name__ == "__main__":
    main()
