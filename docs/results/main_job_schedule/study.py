"""The main-job schedule study's cells and verdicts, from its run folders and cells.csv.

    python docs/results/main_job_schedule/study.py add ARM SEED RUN_DIR   # one cell into cells.csv
    python docs/results/main_job_schedule/study.py verdict ARM            # ARM against the main job

``add`` reads a finished ``python -m cicfw.train experiment=main ...`` run folder: its overrides
(.hydra/overrides.yaml), the best validation error (csv/metrics.csv), the optimizer steps, and, where the run
drove the suite, the success per column (evaluate/summary.json). ``verdict`` applies the rule fixed before the cells
(README.md): val MAE no worse than the main job's (the paired mean difference <= 0) and overall success
equivalent within ±5 points, both paired by seed over the seeds both arms ran, with the project's own interval
(``cicfw.reproduction.seed_stats.difference``: a t-interval over the per-seed differences, 95%, so TOST at
2.5% each side).
"""
from __future__ import annotations

import csv
import json
import platform
import sys
from pathlib import Path

import yaml

from cicfw.reproduction.seed_stats import difference, word

HERE = Path(__file__).parent
CELLS = HERE / "cells.csv"
COLUMNS = ("training_town/training_weathers", "training_town/new_weathers", "new_town/training_weathers",
           "new_town/new_weathers")
FIELDS = ("arm", "seed", "cpu", "commit", "overrides", "steps", "val_steer_mae", "success", *COLUMNS)
MARGIN = 5.0


def cpu_name() -> str:
    """The CPU's model name (/proc/cpuinfo), the kind a cell is recorded with."""
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def cell(arm: str, seed: int, run: Path, commit: str) -> dict[str, str]:
    """One row of cells.csv from a finished run folder."""
    overrides = yaml.safe_load((run / ".hydra" / "overrides.yaml").read_text())
    rows = list(csv.DictReader((run / "csv" / "metrics.csv").open()))
    val = [float(r["val/steer_mae"]) for r in rows if r.get("val/steer_mae")]
    steps = max(int(r["step"]) for r in rows if r.get("val/steer_mae")) + 1  # validation ends each epoch
    summary = run / "evaluate" / "summary.json"  # evaluate_after's, or `cicfw.evaluate hydra.run.dir=<run>/evaluate`
    suite = json.loads(summary.read_text()) if summary.exists() else None
    if suite is not None and not (suite.get("complete") and suite["episodes"] == 480):
        sys.exit(f"{summary}: the suite is not complete (480 episodes)")
    out = {"arm": arm, "seed": str(seed), "cpu": cpu_name(), "commit": commit,
           "overrides": " ".join(o for o in overrides
                                 if not o.startswith(("seed=", "hydra.", "progress_bar=", "evaluate_after="))),
           "steps": str(steps), "val_steer_mae": f"{min(val):.4f}",
           "success": f"{suite['success']:.2f}" if suite else ""}
    out.update({c: f"{suite['cells'][c]['rate']:.2f}" if suite else "" for c in COLUMNS})
    return out


def read_cells() -> list[dict[str, str]]:
    return list(csv.DictReader(CELLS.open())) if CELLS.exists() else []


def add(arm: str, seed: int, run: Path, commit: str) -> None:
    """Put the cell into cells.csv, replacing an earlier row of the same arm and seed."""
    new = cell(arm, seed, run, commit)
    rows = [r for r in read_cells() if (r["arm"], r["seed"]) != (arm, str(seed))] + [new]
    with CELLS.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows({k: r.get(k, "") for k in FIELDS} for r in rows)
    print(new)


def per_seed(arm: str, key: str) -> dict[int, float]:
    return {int(r["seed"]): float(r[key]) for r in read_cells() if r["arm"] == arm and r[key]}


def verdict(arm: str, base: str = "main") -> None:
    """Print the arm's paired differences from the main job and what the rule makes of them."""
    kinds = {r["cpu"] for r in read_cells() if r["arm"] in (arm, base)}
    if len(kinds) > 1:
        sys.exit(f"cells of {arm} and {base} ran on {len(kinds)} CPU kinds ({', '.join(sorted(kinds))}): "
                 "not paired here")
    mae = difference(per_seed(arm, "val_steer_mae"), per_seed(base, "val_steer_mae"))
    mae_ok = mae.estimate.mean <= 0
    print(f"{arm} - {base}, {mae.method}: val MAE {mae.estimate.mean:+.4f} "
          f"[{mae.estimate.lo}, {mae.estimate.hi}] -> {'no worse' if mae_ok else 'worse'}")
    driven = per_seed(arm, "success")
    if not driven:
        print(f"{arm}: not driven (the suite is driven once an arm passes the validation gate)")
        print("rule: fails" if not mae_ok else "rule: open (drive the arm)")
        return
    success = difference(driven, per_seed(base, "success"))
    reading = word(success.estimate.lo, success.estimate.hi, MARGIN)
    print(f"{arm} - {base}, {success.method}: success {success.estimate.mean:+.2f} points "
          f"[{success.estimate.lo}, {success.estimate.hi}] -> {reading}")
    passes = mae_ok and reading == f"equivalent within ±{MARGIN:g}" and success.enough_seeds
    print(f"rule: {'passes' if passes else 'fails'}")


if __name__ == "__main__":
    if sys.argv[1:2] == ["add"] and len(sys.argv) in (5, 6):
        add(sys.argv[2], int(sys.argv[3]), Path(sys.argv[4]), sys.argv[5] if len(sys.argv) == 6 else "")
    elif sys.argv[1:2] == ["verdict"] and len(sys.argv) == 3:
        verdict(sys.argv[2])
    else:
        sys.exit(__doc__)
