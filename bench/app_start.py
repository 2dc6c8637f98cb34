"""How long each app takes to start: a fresh interpreter importing what the app runs (its module, or an
evaluation worker's), wall time, median of ``--repeat`` runs.

Every command, test subprocess and evaluation worker pays this before its first step (``--help`` imports
less and is not timed here). Give ``--tree`` more
than once to compare source trees (each on PYTHONPATH in turn); their runs are interleaved so that a busy
moment hits both alike. Prints one line per app and tree.

    python bench/app_start.py --repeat 5 --tree . --tree ../other-checkout
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

#: each app's name and the module its run imports
APPS = {"train": "cicfw.train.app", "evaluate": "cicfw.benchmark.app", "evaluation-worker": "cicfw.benchmark.runner",
        "export": "cicfw.export.app", "collect": "cicfw.collect.app", "diagnose": "cicfw.diagnose.app",
        "reproduce": "cicfw.reproduction.app"}


def start_seconds(app: str, tree: Path) -> float:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", f"import {APPS[app]}"], env=env, check=True, cwd=tree,  # -c: cwd first
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", action="append", type=Path, help="a source tree (default: this one)")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--apps", nargs="+", default=list(APPS), choices=APPS)
    args = parser.parse_args()
    trees = [t.resolve() for t in (args.tree or [Path(__file__).resolve().parents[1]])]
    times: dict[tuple[str, Path], list[float]] = {(a, t): [] for a in args.apps for t in trees}
    for _ in range(args.repeat):
        for app in args.apps:
            for tree in trees:
                times[app, tree].append(start_seconds(app, tree))
    print(f"load average {os.getloadavg()[0]:.2f}; {args.repeat} runs each, interleaved; median [min, max] seconds")
    for (app, tree), got in times.items():
        print(f"{app:18s} {str(tree):30s} {statistics.median(got):6.2f} [{min(got):.2f}, {max(got):.2f}]")


if __name__ == "__main__":
    main()
