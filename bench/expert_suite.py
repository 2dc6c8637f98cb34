"""Expert success on the closed-loop suite: every single-turn route of every town, without and with
CIL's steering noise. Prints a table.

The expert drives from the route (it never looks at the camera images), so its results are the same
under every weather: the suite runs without rendering. Success = within 2 m of the goal before the
timeout (route length at 10 km/h + 10 s), as in the CoRL-2017 benchmark.

    python bench/expert_suite.py [--towns town_a town_b] [--seeds 3]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from cicfw.sim.env import DrivingEnv, run_expert
from cicfw.sim.roadgraph import COMMAND_NAMES, single_turn_routes
from cicfw.sim.town import load_town, town_names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--towns", nargs="+", default=town_names())
    ap.add_argument("--seeds", type=int, default=3, help="noise seeds per route")
    args = ap.parse_args()
    if args.seeds < 1:  # the noisy share would be out of no episode
        ap.error(f"--seeds must be >= 1 (noise seeds per route), got {args.seeds}")
    print("expert on all single-turn routes (no rendering: the expert ignores images, so weather "
          "does not change these figures)")
    print(f"{'town':<8} {'routes':>6} {'no noise':>10} {'noise':>16} {'worst dev m':>12} "
          f"{'mean time/timeout':>18} {'sim steps/s':>12}")
    for name in args.towns:
        town = load_town(name)
        routes = single_turn_routes(town)
        t0, steps = time.perf_counter(), 0
        clean = [run_expert(DrivingEnv(town, r, renderer=False)) for r in routes]
        noisy = [run_expert(DrivingEnv(town, r, renderer=False), np.random.default_rng([seed, k]))
                 for seed in range(args.seeds) for k, r in enumerate(routes)]
        steps = sum(i["steps"] for i in clean + noisy)
        rate = steps / (time.perf_counter() - t0)
        ok_c = sum(i["success"] for i in clean)
        ok_n = sum(i["success"] for i in noisy)
        ratio = np.mean([i["t"] / r.timeout() for i, r in zip(clean, routes)])
        print(f"{name:<8} {len(routes):>6} {ok_c:>4}/{len(routes):<3}{100 * ok_c / len(routes):4.0f}% "
              f"{ok_n:>6}/{len(noisy):<4}{100 * ok_n / len(noisy):5.1f}% "
              f"{max(i['max_route_deviation'] for i in clean):5.2f}/{max(i['max_route_deviation'] for i in noisy):<5.2f} "
              f"{ratio:>18.2f} {rate:>12.0f}")
        for i, r in zip(clean, routes):
            if not i["success"]:
                print(f"   failed (no noise): {r.name} ({i['reason']}, {i['distance_to_goal']:.1f} m from goal)")
        for i, r in zip(noisy, routes * args.seeds):
            if not i["success"]:
                print(f"   failed (noise): {r.name} ({i['reason']}, {i['distance_to_goal']:.1f} m from goal)")
        by_cmd = {}
        for r in routes:
            by_cmd[COMMAND_NAMES[r.meta["command"]]] = by_cmd.get(COMMAND_NAMES[r.meta["command"]], 0) + 1
        print(f"   routes by command: {by_cmd}; worst dev = no noise / noise; with noise the car had a wheel "
              f"over the centre line in {np.mean([i['max_opposite_lane'] > 0 for i in noisy]):.0%} and over the "
              f"kerb in {np.mean([i['max_off_road'] > 0 for i in noisy]):.0%} of the episodes")


if __name__ == "__main__":
    main()
