"""What a config collects: every episode's id, town, weather and seed, its steps, and its size on disk."""
from __future__ import annotations

import numpy as np

from cicfw.collect.config import town_key
from cicfw.data.cil_hdf5 import IMAGE_SHAPE, N_TARGETS, SAMPLES_PER_FILE

SAMPLE_BYTES = int(np.prod(IMAGE_SHAPE)) + 4 * N_TARGETS  # one sample in a CIL file, before HDF5's overhead


def episode_plan(cfg: dict) -> list[dict]:
    """Every episode's id, town, weather and seed: a pure function of the config."""
    combos = [(t, w) for t in cfg["towns"] for w in cfg["weathers"]]
    plan = []
    for i in range(cfg["episodes"]):
        town, weather = combos[i % len(combos)]
        plan.append({"id": f"ep{i:04d}_{town_key(town)}_{weather}", "index": i, "town": town, "weather": weather,
                     "seed": int(np.random.SeedSequence([int(cfg["seed"]), i]).generate_state(1)[0])})
    return plan


def steps_per_episode(cfg: dict) -> int:
    return int(round(float(cfg["seconds"]) * 10))


def episode_bytes(cfg: dict) -> int:
    """About what one episode's files take on disk (HDF5 overhead included, rounded up)."""
    n = steps_per_episode(cfg) * len(cfg["cameras"])
    parts = -(-n // SAMPLES_PER_FILE)
    return int(n * SAMPLE_BYTES * 1.01) + parts * 64 * 1024 + 64 * 1024
