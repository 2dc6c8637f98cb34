"""Collection speed, end to end: samples (camera images + targets) written per second by
cicfw.collection.collect_dataset into a temporary folder, cold (renderers baked in every run, worker
processes started), in-process (workers=1) and with worker processes. ``--default`` times the
default dataset (43,200 samples, ~2.2 GB in the temporary folder) instead.

    python bench/collect_speed.py [--episodes 12] [--seconds 40] [--workers 1 2] [--default]
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cicfw.sim.env as sim_env
from cicfw.collect import DEFAULTS, collect_dataset, episode_plan, make_backend, resolve_config, run_episode


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--episodes", type=int, default=12)
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--default", action="store_true", help="time the default dataset (workers=2)")
    args = ap.parse_args()
    if args.default:
        args.episodes, args.seconds, args.workers = DEFAULTS["episodes"], DEFAULTS["seconds"], [DEFAULTS["workers"]]
    print(f"collect: {args.episodes} episodes x {args.seconds:.0f} s, towns {DEFAULTS['towns']}, weathers "
          f"{DEFAULTS['weathers']}, cameras {DEFAULTS['cameras']} (median of {args.repeats} runs)")
    for w in args.workers:
        rates = []
        for _ in range(args.repeats):
            with tempfile.TemporaryDirectory() as d:
                cfg = {"episodes": args.episodes, "seconds": args.seconds, "workers": w}
                sim_env._RENDERERS.clear()  # cold: every run bakes its renderers
                t0 = time.perf_counter()
                meta = json.loads(collect_dataset(cfg, Path(d), progress=False).read_text())
                dt = time.perf_counter() - t0
                rates.append(meta["counts"]["samples"] / dt)
        rates.sort()
        n = args.episodes * args.seconds * 10 * len(DEFAULTS["cameras"])
        print(f"  workers={w}: {rates[len(rates) // 2]:8.0f} samples/s  ({rates[len(rates) // 2] / 3:6.0f} "
              f"three-camera steps/s; {n / rates[len(rates) // 2]:.0f} s for {n:.0f} samples; all runs: "
              f"{', '.join(f'{r:.0f}' for r in rates)})")
    # where one episode's time goes (in-process, warm caches)
    cfg = resolve_config({"episodes": 1, "seconds": args.seconds, "workers": 0})
    ep = episode_plan(cfg)[0]
    backend = make_backend(cfg["sim"])
    with tempfile.TemporaryDirectory() as d:
        run_episode(cfg, ep, Path(d), backend)  # warm: towns, renderer textures
        t0 = time.perf_counter()
        m = run_episode(cfg, ep, Path(d), backend)
        dt = time.perf_counter() - t0
    print(f"  one episode in-process, warm renderers: {m['samples'] / dt:.0f} samples/s")
    full = resolve_config({})
    n = full["episodes"] * full["seconds"] * 10 * len(full["cameras"])
    print(f"  the default dataset ({full['episodes']} episodes x {full['seconds']:.0f} s = {n:.0f} samples) "
          f"would take ~{n / max(rates) / 60:.1f} min at the best rate above")


if __name__ == "__main__":
    main()
