"""Rendering speed of the embedded simulator, one process on one core.

    python bench/sim_speed.py [--poses 300] [--weathers ...] [--towns ...] [--repeat 1]

For every weather: centre-camera frames per second and three-camera steps per second, medians over
poses sampled along the roads of the towns (right lane, either direction), buildings and props on.
Both wall-clock and CPU-time (this process) medians are printed: the machine may be shared, and
CPU time is what one core spends per frame. Also prints the one-off bake times (ground textures).
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)


def sample_poses(town, n: int, rng: np.random.Generator) -> list[tuple[float, float, float]]:
    """``n`` vehicle poses in the right lane of random roads, heading either way."""
    out = []
    lengths = np.array([len(r.centreline) for r in town.roads], float)
    for _ in range(n):
        road = town.roads[int(rng.choice(len(town.roads), p=lengths / lengths.sum()))]
        c = road.centreline
        i = int(rng.integers(1, len(c) - 1))
        d = c[i + 1] - c[i - 1]
        yaw = math.atan2(d[1], d[0]) + (math.pi if rng.random() < 0.5 else 0.0)
        right = np.array([math.sin(yaw), -math.cos(yaw)])
        p = c[i] + right * town.lane_width / 2
        out.append((float(p[0]), float(p[1]), yaw))
    return out


def time_renders(renderer, poses, warm: int = 20) -> tuple[np.ndarray, np.ndarray]:
    for i, p in enumerate(poses[:warm]):
        renderer.render(*p, t=0.1 * i)
    wall, cpu = [], []
    for i, p in enumerate(poses):
        w0, c0 = time.perf_counter(), time.process_time()
        renderer.render(*p, t=0.1 * i)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return np.array(wall), np.array(cpu)


def mean_items(renderers: dict, wx: str, towns: list, poses: dict, n: int = 50) -> float:
    """Mean number of items (walls, trunks, canopies, poles) drawn in the centre camera."""
    counts = []
    for t in towns:
        r = renderers[(wx, t.name, ("centre",))]
        for p in poses[t.name][:n]:
            r.render(*p)
            counts.append(r.last_items["centre"])
    return float(np.mean(counts))


def main() -> None:
    from cicfw.sim.render import WEATHERS, Renderer
    from cicfw.sim.render.ground import bake_base, bake_ground
    from cicfw.sim.town import load_town, town_names

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=300, help="poses per town (default: %(default)s)")
    ap.add_argument("--weathers", nargs="+", default=list(WEATHERS))
    ap.add_argument("--towns", nargs="+", default=None)
    ap.add_argument("--repeat", type=int, default=1, help="passes over the poses (default: %(default)s)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()

    towns = [load_town(n) for n in (a.towns or town_names())]
    rng = np.random.default_rng(a.seed)
    poses = {t.name: sample_poses(t, a.poses, rng) for t in towns}
    print(f"cicfw renderer speed | {platform.processor() or platform.machine()} | python {platform.python_version()}"
          f" | numpy {np.__version__} | opencv {cv2.__version__} | 1 thread")
    print(f"load average at start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"poses: {a.poses} per town along the roads of {', '.join(poses)}; repeat {a.repeat}")

    for t in towns:  # one-off costs, cached per process afterwards
        c0 = time.perf_counter()
        base = bake_base(t)
        c1 = time.perf_counter()
        bake_ground(t, WEATHERS["MidRainyNoon"], base)
        c2 = time.perf_counter()
        print(f"bake {t.name}: ground base {c1 - c0:.2f} s ({base.shape[1]}x{base.shape[0]} texels), "
              f"one weather {c2 - c1:.2f} s")

    # renderers first (bakes are cached per process), then passes that cycle through all weathers,
    # so a burst of load from other jobs is spread over the weathers instead of hitting one
    cam_sets = (("centre",), ("centre", "left", "right"))
    renderers = {(wx, town.name, cams): Renderer(town, wx, seed=a.seed, cameras=cams)
                 for wx in a.weathers for town in towns for cams in cam_sets}
    times: dict = {}
    for rep in range(a.repeat):
        for wx in a.weathers:
            for cams in cam_sets:
                for town in towns:
                    w, c = time_renders(renderers[(wx, town.name, cams)], poses[town.name])
                    times.setdefault((wx, len(cams)), []).append((rep, w, c))
    items = {wx: mean_items(renderers, wx, towns, poses) for wx in a.weathers}

    def med(wx, ncam, k):
        return float(np.median(np.concatenate([x[k] for x in times[(wx, ncam)]])))

    print()
    print(f"{'weather':<16} {'centre fps':>11} {'(cpu)':>8} {'ms':>6} {'3-cam steps/s':>14} {'(cpu)':>8} {'ms':>6}"
          f" {'items/cam':>9}")
    rows = []
    for wx in a.weathers:
        w1, c1, w3, c3 = med(wx, 1, 1), med(wx, 1, 2), med(wx, 3, 1), med(wx, 3, 2)
        rows.append((wx, 1 / w1, 1 / c1, 1 / w3, 1 / c3))
        print(f"{wx:<16} {1 / w1:>11.0f} {1 / c1:>8.0f} {w1 * 1e3:>6.2f} {1 / w3:>14.0f} {1 / c3:>8.0f}"
              f" {w3 * 1e3:>6.2f} {items[wx]:>9.1f}")
    if a.repeat > 1:
        print()
        print("per pass (wall clock, all weathers): " + ", ".join(
            f"pass {r}: centre {1 / np.median(np.concatenate([x[1] for k, v in times.items() if k[1] == 1 for x in v if x[0] == r])):.0f}"
            f" fps, 3-cam {1 / np.median(np.concatenate([x[1] for k, v in times.items() if k[1] == 3 for x in v if x[0] == r])):.0f}"
            " steps/s" for r in range(a.repeat)))
    print()
    print(f"slowest weather: centre {min(r[1] for r in rows):.0f} frames/s wall ({min(r[2] for r in rows):.0f} cpu), "
          f"3-camera {min(r[3] for r in rows):.0f} steps/s wall ({min(r[4] for r in rows):.0f} cpu)")
    print(f"load average at end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
