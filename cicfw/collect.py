"""Collect a CIL HDF5 dataset: ``python -m cicfw.collect [sim=embedded|carla] [key=value ...]``.

A thin Hydra app over the collection engine ``cicfw.sim.collection`` (episodes, workers, files,
metadata, resume, the folder lock and the other guarantees are documented there and in
docs/simulator.md). Every config error, a locked or unwritable folder and a full disk print one line
(``cicfw: error: ...``, exit status 2); Ctrl-C prints one line too (rerun the same command to resume).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from cicfw.sim.collection import (  # noqa: F401  (the engine's API, re-exported for callers of cicfw.collect)
    CAMERA_IDS, DEFAULTS, SIM_VERSION, CollectConfigError, CollectError, DiskFullError, FolderLockedError,
    collect_dataset, episode_plan, resolve_config, run_episode)


def run(cfg) -> str:
    """Collect into ``cfg.out_dir``; the one-line summary."""
    from cicfw.errors import report_user_errors

    @report_user_errors
    def go() -> str:
        out_dir = Path(str(cfg.out_dir)).expanduser()
        meta = collect_dataset(cfg, out_dir)
        m = json.loads(meta.read_text())
        return (f"dataset: {out_dir} ({m['counts']['samples']} samples, {m['counts']['episodes']} episodes, "
                f"sim={m.get('sim', 'embedded')}, complete={m['complete']})")

    try:
        return go()
    except KeyboardInterrupt:
        print(f"cicfw: interrupted; finished episodes are kept in {cfg.out_dir}: rerun the same command to resume",
              file=sys.stderr)
        sys.exit(130)


def _main() -> None:
    import hydra
    from omegaconf import DictConfig

    @hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="collect")
    def main(cfg: DictConfig) -> None:
        print(run(cfg))

    main()


if __name__ == "__main__":
    from cicfw.registry import guard_hydra_plugins

    guard_hydra_plugins()  # a plugin whose Hydra module fails to import: one warning, not a stopped app
    _main()
