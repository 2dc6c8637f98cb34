"""``speed.keep_memory`` on the training step: samples/s and page faults per step, with and without.

    python bench/allocator.py [--rounds 3] [--steps 12]

The switch is process-wide (glibc's malloc thresholds, cicfw/model/memory.py), so each measurement is a
fresh process: CIL as bench/row_cost.py builds it (``paper_cil``) with the converged budget's speed switches (compile +
channels_last, Adam's for-loop step), batch 120, ``--warmup`` steps, then ``--steps`` timed optimizer
steps on one random batch (``time_steps``, the model-alone figure of bench/train_throughput.py). Each
round runs both variants, in alternating order, so a change of load hits both; the figure is the median
over rounds of (kept / plain). Every line carries the load average and the cores the process got.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys

BATCH = 120


def child(keep: bool, warmup: int, steps: int) -> None:
    from row_cost import build  # bench/ is this script's folder: CIL as its reproduction cell builds it

    from cicfw.model.speed import dummy_batch, time_steps

    model, opt, variant, _ = build("cil", keep_memory=keep)
    batch = dummy_batch(None, BATCH)
    time_steps(model, opt, [batch] * warmup, warmup)
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    rate, cores = time_steps(model, opt, [batch] * steps, 0)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / steps
    print(json.dumps({"variant": variant, "rate": rate, "cores": cores, "faults": faults,
                      "load": os.getloadavg()[0]}))


def measure(keep: bool, args) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", "kept" if keep else "plain", "--warmup",
                          str(args.warmup), "--steps", str(args.steps)], capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"bench/allocator.py: the {'kept' if keep else 'plain'} process failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=12, help="timed optimizer steps per process")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--child", choices=["plain", "kept"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args.child == "kept", args.warmup, args.steps)
    import torch

    print(f"bench/allocator.py: CIL, batch {BATCH}, compile + channels_last, {args.rounds} rounds x {args.steps} "
          f"steps after {args.warmup}; torch {torch.__version__}; load {os.getloadavg()[0]:.2f} before", flush=True)
    got: dict[bool, list[dict]] = {False: [], True: []}
    for k in range(args.rounds):
        for keep in ((False, True) if k % 2 == 0 else (True, False)):
            m = measure(keep, args)
            got[keep].append(m)
            print(f"  round {k + 1}: {'kept ' if keep else 'plain'} {m['rate']:6.1f} samples/s, "
                  f"{m['faults']:8.0f} page faults/step, {m['cores']:.2f} cores, load {m['load']:.2f}", flush=True)
    ratio = statistics.median(b["rate"] / a["rate"] for a, b in zip(got[False], got[True]))
    print(f"SUMMARY plain {statistics.median(m['rate'] for m in got[False]):.1f} samples/s "
          f"({statistics.median(m['faults'] for m in got[False]):.0f} faults/step), kept "
          f"{statistics.median(m['rate'] for m in got[True]):.1f} samples/s "
          f"({statistics.median(m['faults'] for m in got[True]):.0f} faults/step): kept/plain {ratio:.2f}x "
          f"(median of {args.rounds} paired rounds)")


if __name__ == "__main__":
    main()
