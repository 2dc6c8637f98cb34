"""A SLURM job requeued into its own run folder, recognised so that its training goes on there.

Pre-empted under SLURM (SIGUSR1), Lightning saves ``hpc_ckpt_<n>.ckpt`` in the run folder and SLURM runs the
same command again, with the same job id and so the same folder (docs/scaling.md). That folder holds the
run's outputs, which any other run would be refused over: this module says when they are this run's own.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

HPC_PREFIX = "hpc_ckpt_"


def newest_hpc_checkpoint(folder: str | Path) -> Path | None:
    """The ``hpc_ckpt_<n>.ckpt`` with the highest ``n`` in ``folder`` (the one Lightning resumes from);
    None when there is none."""
    found = [(int(p.stem[len(HPC_PREFIX):]), p) for p in Path(folder).glob(f"{HPC_PREFIX}*.ckpt")
             if p.stem[len(HPC_PREFIX):].isdigit()]
    return max(found, key=lambda vp: vp[0])[1] if found else None


def saved_values(config: Any) -> dict:
    """``config``'s values as Hydra records them in ``.hydra/config.yaml`` (unresolved, without the ``hydra``
    node) and as they read back from there, so that a saved config and a composed one compare equal."""
    values = OmegaConf.to_container(config, resolve=False, enum_to_str=True)
    values.pop("hydra", None)
    return OmegaConf.to_container(OmegaConf.create(OmegaConf.to_yaml(OmegaConf.create(values))), resolve=False)


def saved_config(folder: str | Path, name: str = "config.yaml") -> DictConfig | None:
    """The config the Hydra run in ``folder`` saved (``.hydra/config.yaml``, or an earlier segment's ``name``),
    unresolved; None when there is none, it cannot be read or it holds no mapping."""
    try:
        saved = OmegaConf.load(Path(folder) / ".hydra" / name)
    except Exception:  # missing or unreadable: nothing says which run is there
        return None
    return saved if isinstance(saved, DictConfig) else None


def is_requeued_run(folder: str | Path, config: Any) -> bool:
    """Whether this process is a SLURM job requeued into ``folder``, its own run folder: SLURM detected
    (Lightning's ``SLURMEnvironment.detect``), an HPC checkpoint there and the same composed config as
    ``config``. Lightning then resumes from that checkpoint by itself (``ckpt_path=hpc``)."""
    if config is None or newest_hpc_checkpoint(folder) is None:
        return False
    from lightning.fabric.plugins.environments import SLURMEnvironment  # only here: Lightning is slow to import

    saved = saved_config(folder) if SLURMEnvironment.detect() else None
    return saved is not None and saved_values(saved) == saved_values(config)  # this command's run: the same values
