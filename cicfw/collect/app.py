"""Collect a CIL HDF5 dataset: ``python -m cicfw.collect [sim=embedded|carla] [key=value ...]``.

``verify=true`` (or ``--verify``) checks a collected folder instead, changing nothing: every file against
its recorded size and SHA-256, one line per missing or corrupt file and per HDF5 file the collection did not
write, exit status 2 if any.

A thin Hydra app over the collection engine, its package ``cicfw.collect`` (episodes, workers, files,
metadata, resume, the folder lock and the other guarantees are documented there and in
docs/simulator.md). Every config error, a locked or unwritable folder and a full disk print one line
(``cicfw: error: ...``, exit status 2); Ctrl-C and SIGTERM print one line too (rerun the same command to
resume; exit status 130, 143 for SIGTERM), after the workers are ended and half-written files removed.
"""
from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from cicfw.collect.config import check_lock_wait
from cicfw.collect.dataset import collect_dataset
from cicfw.collect.errors import CollectError
from cicfw.collect.integrity import verify_dataset
from cicfw.core.errors import USER_ERRORS, on_interrupt, report_user_errors
from cicfw.core.json_files import read_json
from cicfw.core.run_folder import claim_folder, release_folder_locks, undo_run_folder

log = logging.getLogger("cicfw.collect")


def _run(cfg, on_start=None) -> str:
    """Collect into ``cfg.out_dir``; the one-line summary. Ctrl-C or SIGTERM: one line saying what is kept.
    ``on_start``: called as the first episode is about to be collected (``collect_dataset``)."""
    raw = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    verify = raw.pop("verify", False)  # a bool: the app's schema (cicfw/collect/schema.py) checks it
    out_dir = Path(str(raw["out_dir"])).expanduser()
    if verify:
        return _verify(raw, out_dir)
    # another app's run (a training or evaluation folder), or a folder inside one (<run>/checkpoints), is not a
    # dataset: its episodes would join that run's files, and the folder would then read as a dataset to every
    # app; other files the engine checks
    claim_folder(out_dir, "collect", "out_dir", foreign_ok=True)
    with on_interrupt(f"finished episodes are kept in {raw['out_dir']}: rerun the same command to resume"):
        meta = collect_dataset(raw, out_dir, on_start=on_start)
    m = read_json(meta)
    return (f"dataset: {out_dir} ({m['counts']['samples']} samples, {m['counts']['episodes']} episodes, "
            f"sim={m.get('sim', 'embedded')}, complete={m['complete']})")


#: ``_run`` with its user errors as one line (exit status 2): the Python entry point
run = report_user_errors(_run)


def _verify(raw: dict, out_dir: Path) -> str:
    """``verify=true``: every file of ``out_dir`` against its record, one line per problem; the summary."""
    lock_wait = raw.get("lock_wait")  # CollectConfig's default: wait while a collection is under way
    check_lock_wait(lock_wait)
    report = verify_dataset(out_dir, lock_wait)
    for line in report.lines():
        print(f"cicfw: {line}", file=sys.stderr)
    if not report.ok:
        raise CollectError(report.summary())
    return report.summary()


def _to_job_log(line: str) -> None:
    """``line`` into the run's job log too (collect.log: Hydra's file handler), and only there: stdout, which
    a closed pipe may have gone, gets it as it is; the run folder keeps how the collection ended."""
    record = log.makeRecord(log.name, logging.INFO, __file__, 0, "%s", (line,), None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


def _main() -> None:
    sys.argv = ["verify=true" if a == "--verify" else a for a in sys.argv]  # `cicfw collect --verify`

    @hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="collect")
    @report_user_errors
    def main(cfg: DictConfig) -> None:
        out, started = Path(HydraConfig.get().runtime.output_dir), []
        try:
            line = _run(cfg, on_start=lambda: started.append(True))
            _to_job_log(line)
            print(line)
        except USER_ERRORS:  # refused before collecting: the run folder as CollectRunFolderCheck found it (a
            if not started:  # multirun job's keeps its log); once collecting, its log and episodes stay
                undo_run_folder(out)
            raise
        finally:  # a check writes nothing, so it leaves no run folder either (a file written beside it stays)
            try:
                if cfg.verify:
                    undo_run_folder(out, hydra_only=True)
            finally:
                release_folder_locks(out)  # CollectRunFolderCheck's, held while the folder was put back

    main()

