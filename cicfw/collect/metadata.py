"""``dataset_metadata.json``: what a dataset holds (config, counts, episodes, files and their checksums)."""
from __future__ import annotations

import time
from pathlib import Path

from cicfw import __version__
from cicfw.collect.config import CAMERA_IDS
from cicfw.data.frames import META_NAME  # noqa: F401  (the collector's modules import it from here)

SIM_VERSION = "embedded-1"  # bump when the embedded simulator's output changes for the same config


def planned_sets(cfg: dict, plan: list[dict]) -> tuple[list[str], list[str]]:
    """The listed towns and weathers the plan gives an episode: episodes go round-robin over the town x weather
    pairs, town by town, so fewer episodes than pairs leave the last ones out of the data (an evaluation reads
    the dataset's towns and weathers as the ones its model was trained in)."""
    return ([t for t in cfg["towns"] if any(ep["town"] == t for ep in plan)],
            [w for w in cfg["weathers"] if any(ep["weather"] == w for ep in plan)])


def dataset_metadata(cfg: dict, out_dir: Path, plan: list[dict], markers: dict, started: float,
                     sim_version: str, complete: bool) -> dict:
    """The metadata of the dataset as far as ``markers`` (finished episodes) go."""
    counts = {"episodes": len(markers), "samples": sum(m["samples"] for m in markers.values()),
              "steps": sum(m["steps"] for m in markers.values()),
              "files": sum(len(m["files"]) for m in markers.values()),
              "noisy_steps": sum(m["noisy_steps"] for m in markers.values())}
    cmd = {c: sum(m["commands"][c] for m in markers.values()) for c in ("2", "3", "4", "5")}
    return {
        "format": "CIL HDF5 (CoRL-2017 layout), written by cicfw.collect",
        "complete": complete, "planned_episodes": len(plan),
        "cicfw_version": __version__, "sim": cfg["sim"].get("name", "embedded"), "sim_version": sim_version,
        "config_hash": cfg["_hash"], "config": {k: v for k, v in cfg.items() if k != "_hash"},
        **dict(zip(("towns", "weathers"), planned_sets(cfg, plan))), "seed": cfg["seed"],
        "cameras": {c: {"id": CAMERA_IDS[c][0], "yaw_deg": CAMERA_IDS[c][1]} for c in cfg["cameras"]},
        "counts": counts, "step_commands": cmd,
        "units": {"speed": "km/h", "position": "m (rear axle)", "time": "ms of game time",
                  "steer": "[-1, 1], positive right; targets[5] = steering applied (expert + noise)"},
        "episodes": {k: {x: m[x] for x in ("town", "weather", "seed", "samples", "noisy_episode",
                                            "noisy_steps", "route_length_m", "distance_driven_m", "commands")}
                     for k, m in sorted(markers.items())},
        # a file's SHA-256 with its size and mtime when it was hashed: a reader reuses it only while both match
        "files": {f["name"]: {"episode": k, "samples": f["samples"],
                              **{x: f[x] for x in ("sha256", "bytes", "mtime_ns") if x in f}}
                  for k, m in sorted(markers.items()) for f in m["files"]},
        "collection_seconds": round(time.time() - started, 1),
    }
