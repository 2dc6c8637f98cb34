"""``ckpt_path=last`` and ``ckpt_path=hpc``, the names Lightning resolves in the run's own folder, turned into
the file they name before anything is checked: Lightning would load that file unchecked, so a resume by name
would skip every check a resume by path gets (the optimizer settings, the split, the schedule's run length,
the weight averaging). ``best`` never resumes (a fresh Trainer knows no best checkpoint): refused. No
``ckpt_path`` under SLURM, where Lightning itself resumes from the run's newest HPC checkpoint (a requeued
job), is ``hpc`` too."""
from __future__ import annotations

import copy
import logging
from pathlib import Path

from lightning.fabric.plugins.environments import SLURMEnvironment
from omegaconf import DictConfig, open_dict

from cicfw.core.errors import CicfwError
from cicfw.core.slurm_requeue import newest_hpc_checkpoint
from cicfw.model.checkpoint import UnloadableCheckpoint, load_weights_only

log = logging.getLogger("cicfw.train")


def recorded_step(path: Path) -> int:
    """The ``global_step`` the checkpoint at ``path`` records; -1 when it records none or cannot be read
    (the file chosen is checked in full afterwards)."""
    try:
        step = load_weights_only(path).get("global_step")
    except (UnloadableCheckpoint, AttributeError):
        return -1
    return step if isinstance(step, int) else -1


def own_checkpoint(name: str, run_dir: Path) -> Path | None:
    """The file ``name`` resumes from in ``run_dir``: for ``last`` ``checkpoints/last.ckpt`` (the only name
    cicfw writes it under), or an HPC checkpoint that records a later step; for ``hpc`` the highest
    ``hpc_ckpt_<n>.ckpt``; None when there is none. Never by modification time, which a copy or a touch
    changes. Other ``*last*.ckpt`` files without a ``last.ckpt`` are refused: which one is meant is unknown."""
    hpc = newest_hpc_checkpoint(run_dir)
    if name == "hpc":
        return hpc
    last = run_dir / "checkpoints" / "last.ckpt"
    if not last.is_file():
        others = sorted(p.name for p in (run_dir / "checkpoints").glob("*last*.ckpt")
                        if not p.name.startswith(".") and p.is_file())
        if others:
            raise CicfwError(f"ckpt_path=last: no checkpoints/last.ckpt in {str(run_dir)!r}, but {', '.join(others)}"
                             f"; give the checkpoint file to resume from", key="ckpt_path", value=name)
        return hpc
    if hpc is not None and hpc.is_file() and recorded_step(hpc) > recorded_step(last):
        return hpc
    return last


def lightning_resume_name(ckpt_path: object, run_dir: Path) -> str | None:
    """``ckpt_path`` as the name Lightning resolves: ``hpc`` for none under SLURM with an HPC checkpoint in
    ``run_dir`` (Lightning's ``_parse_ckpt_path`` resumes from it by itself), else ``ckpt_path`` as given."""
    if ckpt_path is not None and str(ckpt_path) != "":
        return str(ckpt_path)
    if SLURMEnvironment.detect() and own_checkpoint("hpc", run_dir) is not None:
        log.info("no ckpt_path under SLURM: resuming from the run's newest HPC checkpoint, as Lightning does "
                 "(ckpt_path=hpc)")
        return "hpc"
    return None


def with_checkpoint_file(cfg: DictConfig, run_dir: Path) -> DictConfig:
    """``cfg`` with a ``ckpt_path`` of ``last`` or ``hpc`` (``lightning_resume_name``) replaced by the file it
    names in ``run_dir`` (a copy; ``last`` with none there starts afresh, as Lightning does, and says so);
    ``best`` and ``hpc`` without a checkpoint are one ``CicfwError`` naming ``ckpt_path``. Any other value is
    returned as it is."""
    name = lightning_resume_name(cfg.get("ckpt_path"), run_dir)
    if name is None or name not in ("last", "hpc", "best"):
        return cfg
    if name == "best":
        raise CicfwError("ckpt_path=best: a run resumes from its latest state, not its best checkpoint; resume with "
                         "ckpt_path=last (or the file, <run>/checkpoints/last.ckpt), or evaluate the best one with "
                         "cicfw evaluate checkpoint=<run>", key="ckpt_path", value=name)
    found = own_checkpoint(name, run_dir)
    if found is None and name == "hpc":
        raise CicfwError(f"ckpt_path=hpc: no HPC checkpoint (hpc_ckpt_<n>.ckpt) in {str(run_dir)!r}; give the "
                         f"checkpoint file to resume from", key="ckpt_path", value=name)
    if found is None:
        log.info("ckpt_path=last: no checkpoint in %s yet, so training starts afresh", run_dir / "checkpoints")
    else:
        log.info("ckpt_path=%s: resuming from %s", name, found)
    cfg = copy.deepcopy(cfg)
    with open_dict(cfg):
        cfg.ckpt_path = None if found is None else str(found)
    return cfg
