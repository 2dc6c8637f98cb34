"""``python -m cicfw.diagnose``: why a model misses turns, measured on its validation frames.

    python -m cicfw.diagnose checkpoint=outputs/<run>/checkpoints/<best>.ckpt
    python -m cicfw.diagnose checkpoint=outputs/reproduce/<budget>/cells/cil/seed0/train/checkpoints/epoch004.ckpt
    python -m cicfw.diagnose checkpoint=x.ckpt data.path=/data/SeqVal split=all     # your own frames
    python -m cicfw.diagnose -m checkpoint=a.ckpt,b.ckpt                            # one folder each

Per command and per junction phase (approach / inside / exit), how the predicted steering follows the
expert's (slope, offset, MAE), and how far swapping the command on the same image moves it
(``cicfw.diagnose.steer_diagnostic`` does the measuring; docs/evaluation.md reads the report). The frames
are the training run's validation episodes: the split's settings (data path, seed, fraction, filters)
come from the training run's saved config beside the checkpoint (``<run>/.hydra/config.yaml`` of a
``cicfw train`` run, or a ``cicfw reproduce`` cell's), and any ``data.*`` given here overrides them.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any, Mapping

import hydra
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from cicfw.core.config_checks import is_number, same_value
from cicfw.core.errors import USER_ERRORS, CicfwError, ConfigError, report_user_errors
from cicfw.core.json_files import read_json
from cicfw.core.run_folder import release_folder_locks, undo_run_folder
from cicfw.data.provenance import data_root, recorded_files, same_place
from cicfw.diagnose import steer_diagnostic as sd
from cicfw.diagnose.steer_diagnostic import DataSettings
from cicfw.export.agent import torch_device
from cicfw.model.checkpoint import (RUN_CONFIG_LEVELS, checkpoint_hyper_parameters, checkpoint_record,
                                    checkpoint_split, config_parts_differ, describe, load_model, prepare_for_inference,
                                    read_checkpoint, resolve_checkpoint, run_config_files, where_it_ran)
from cicfw.reproduction.catalogue import row_overrides

log = logging.getLogger("cicfw.diagnose")

#: the datamodule arguments that decide which frames are the validation frames
SPLIT_KEYS = ("path", "seed", "val_fraction", "max_abs_steer", "side_camera_correction", "cameras", "val_cameras")


#: option -> (is the value accepted, what is accepted): checked before the checkpoint or data is read; their
#: types are the schema's (cicfw/diagnose/schema.py), refused while composing
OPTION_RULES = {
    "batch_size": (lambda v: v >= 1, "a positive integer (frames per network call)"),
    "max_frames": (lambda v: v is None or v >= 1, "null (every frame) or a positive integer (an evenly spaced subset)"),
    "threads": (lambda v: v is None or v >= 1, "null (torch's default) or a positive integer"),
    "phases.approach_m": (lambda v: v is None or (is_number(v) and v > 0),
                          "null (the dataset's command_distance) or a number of metres > 0"),
    "phases.exit_s": (lambda v: is_number(v) and v >= 0, "a number of seconds >= 0"),
    "phases.dt_s": (lambda v: is_number(v) and v > 0,
                    "a number of seconds > 0 (the time step when the game time does not increase)"),
}


def check_options(cfg: DictConfig) -> None:
    """One ``ValueError`` line for a number option outside its domain (``batch_size=0``, ``phases.dt_s=0``),
    before anything is loaded: such a value would fail deep inside (or silently skew the phases)."""
    for key, (ok, accepted) in OPTION_RULES.items():
        value = OmegaConf.select(cfg, key)
        if not ok(value):
            raise CicfwError(f"{key}={value!r} is not valid; use {accepted}", key=key, value=value)


def run_device(name: Any) -> str:
    """The device to run on: the agent's own check (``auto``, a torch device this machine has), limited to
    the CPU and CUDA GPUs."""
    device = torch_device(str(name or "auto"))
    if device.type not in ("cpu", "cuda"):
        raise CicfwError(f"device={str(name)!r} is not supported here; use auto, cpu, cuda or cuda:N", key="device",
                         value=str(name))
    return str(device)


def _compose_train(overrides: list[str]) -> DictConfig:
    if GlobalHydra.instance().is_initialized():
        return compose("train", overrides=overrides)
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("train", overrides=overrides)


def _data_values(node: DictConfig, where: str) -> dict[str, Any]:
    """The split's keys of a training config's ``data`` node, resolved one by one."""
    out: dict[str, Any] = {}
    for key in SPLIT_KEYS:
        if key in node:
            try:
                value = OmegaConf.select(node, key, throw_on_resolution_failure=True)
            except Exception as err:
                raise CicfwError(f"{where}: data.{key} cannot be resolved here ({err}); give data.{key}=...") from None
            out[key] = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
    return out


def training_data(checkpoint: Path) -> tuple[dict[str, Any], str] | None:
    """The split settings of the run that wrote ``checkpoint``, and where they came from: the nearest
    ``.hydra/config.yaml`` at most RUN_CONFIG_LEVELS folders above it, either a ``cicfw train`` run's (its
    ``data`` node) or a ``cicfw reproduce`` cell's (the cell's training config composed again from its
    row, seed and budget). None when there is neither, or when the config names other parts than the
    checkpoint (a checkpoint copied into another run's folder: that run's split is not its own)."""
    for path in run_config_files(checkpoint):
        try:
            cfg = OmegaConf.load(path)
        except Exception as err:  # a truncated or hand-broken file: its split settings are unknown
            raise CicfwError(f"cannot read the saved config {path} of the run that wrote {checkpoint} ({err}); "
                             "its split settings come from there: mend or remove that file") from err
        differ = config_parts_differ(OmegaConf.to_container(cfg, resolve=False), checkpoint_hyper_parameters(checkpoint))
        if differ:
            log.warning("%s is not the config of %s (%s), so its split settings are not used", path, checkpoint,
                        differ)
            return None
        if "data" in cfg and "path" in cfg.data:
            values = _data_values(cfg.data, str(path))
            values["path"] = where_it_ran(values.get("path"), path)
            return values, f"{path} (the training run's config)"
        if "cell" in cfg and "budget" in cfg and "catalogue" in cfg:
            row, seed = str(cfg.cell.row), int(cfg.cell.seed)
            tcfg = _compose_train(row_overrides(cfg, row, seed))
            return _data_values(tcfg.data, str(path)), f"{path} (reproduce cell {row} seed {seed}, its training config)"
    return None


def data_settings(cfg: DictConfig, checkpoint: Path, record: Mapping[str, Any] | None = None):
    """The frames' settings: the datamodule's defaults, then the training run's, then ``data.*`` given here.
    ``record``: the checkpoint's record of its data, whose absolute path replaces the saved config's."""
    values = {f.name: f.default for f in dataclasses.fields(DataSettings) if f.name in SPLIT_KEYS and f.name != "path"}
    found = training_data(checkpoint)
    source = "the datamodule's defaults"
    if found is not None:
        values.update(found[0])
        source = found[1]
    # the checkpoint's own record of its split wins over a config beside it, which may be another run's (a
    # checkpoint copied into a run folder of the same parts, trained with another seed)
    own = {k: v for k, v in checkpoint_split(checkpoint).items() if k in SPLIT_KEYS and k != "path"}
    if own:
        other = sorted(k for k in own if found is not None and k in found[0] and found[0][k] != own[k])
        if other:
            log.warning("%s gives data.%s otherwise than the checkpoint recorded (%s), so the checkpoint's are used",
                        found[1], ", data.".join(other), ", ".join(f"{k}={own[k]}" for k in other))
        values.update(own)
        source += "; split settings as the checkpoint recorded them"
    if record is not None:
        values["path"] = record["path"]
        source += "; data.path as the run recorded it"
    given = {k: v for k, v in (OmegaConf.to_container(cfg.data, resolve=True) or {}).items() if v is not None}
    if str(cfg.split) != "all":  # another seed or fraction than the checkpoint's own draws another split: its
        for key in ("seed", "val_fraction"):  # "val" would hold episodes the model trained on, and say val
            if key in given and key in own and not same_value(given[key], own[key]):
                raise ConfigError(f"data.{key}", given[key], f"the checkpoint's own {own[key]!r}, which drew the "
                                  f"split it trained on (or leave it out); split=all measures every frame")
    values.update(given)
    if given:
        source += f"; given here: {', '.join(sorted(given))}"
    searched = f"no training config found beside {str(checkpoint)!r} (searched .hydra/config.yaml up to " \
               f"{RUN_CONFIG_LEVELS} folders above it)"
    if not values.get("path"):
        raise CicfwError(f"{searched}; give data.path=<the CIL HDF5 folder it trained on> and data.seed=<its seed>",
                         key="data.path")
    if found is None and "seed" not in given and "seed" not in own and cfg.split != "all":
        raise CicfwError(f"{searched}, so its train/validation split is unknown; give data.seed=<the training "
                         f"run's seed> (and data.val_fraction if not 0.3), or split=all to measure every frame",
                         key="data.seed")
    values["path"] = str(Path(str(values["path"])).expanduser())
    return DataSettings(**values), source


def recorded_split_files(cfg: DictConfig, data: Any, record: Mapping[str, Any] | None,
                         checkpoint: Path) -> tuple[list[Path] | None, list[str]]:
    """The files the split is drawn from: those the checkpoint recorded (None without a record, and for
    ``split=all`` over a ``data.path`` given here: every frame of the user's own folder), each checked; a
    recorded file missing or changed, or a ``data.path`` given here that does not hold them, is one
    ``OtherData`` line naming both folders. Also returns the HDF5 files added to the folder since."""
    given = cfg.data.get("path") is not None
    if record is None or (given and str(cfg.split) == "all"):
        return None, []
    instead = ("leave data.path out to read the folder the run recorded, or give split=all to measure every frame "
               "of data.path" if given else
               "put the recorded files back, or give data.path=<a folder holding them>")
    return recorded_files(record, data_root(data.path) if given else None, "data.path",
                          f"the checkpoint {str(checkpoint)!r}", instead)


def check_earlier_diagnosis(out_dir: Path, checkpoint: Path, split: str, data_path: str) -> None:
    """A folder holding the diagnosis of another checkpoint, split or data folder is refused: writing there
    would replace that report and its frames. The same diagnosis again (other phases, a fresh plot) may."""
    earlier = read_json(out_dir / "steer_diagnostic.json", default=None)
    data = earlier.get("data") if isinstance(earlier, dict) else None
    if not isinstance(data, dict):
        return
    for what, there, here in (("checkpoint", earlier.get("checkpoint"), str(checkpoint)),
                              ("split", data.get("split"), split), ("data.path", data.get("path"), data_path)):
        same = there == here or (what != "split" and same_place(str(there), here))
        if there is not None and not same:
            raise ConfigError("hydra.run.dir", str(out_dir), "a new folder or this diagnosis's own",
                              f"hydra.run.dir={str(out_dir)!r} holds the diagnosis of another {what} ({there!r} "
                              f"there, {here!r} now), which this run would replace; give a new folder "
                              f"(hydra.run.dir=<new folder>)")


def diagnose(cfg: DictConfig, out_dir: Path) -> dict[str, Path]:
    """Load the checkpoint, pick its frames, measure, write the report into ``out_dir``; returns the paths."""
    if not cfg.get("checkpoint"):
        raise CicfwError("no checkpoint to diagnose: give checkpoint=path/to.ckpt (written by cicfw train)",
                         key="checkpoint")
    if cfg.split not in sd.SPLITS:
        raise CicfwError(f"split={cfg.split!r} is not known; use one of {', '.join(sd.SPLITS)}", key="split",
                         value=cfg.split)
    check_options(cfg)
    device = run_device(cfg.get("device"))
    ckpt_path = resolve_checkpoint(cfg.checkpoint)  # a missing file: one line
    ckpt = read_checkpoint(ckpt_path)  # not a checkpoint, not cicfw's, a part not installed: one line
    model = load_model(ckpt_path)  # hyper-parameters its parts refuse, weights that do not fit: before the data

    record = checkpoint_record(ckpt_path)  # the absolute data path and the files the run trained on
    data, source = data_settings(cfg, ckpt_path, record)
    files, added = recorded_split_files(cfg, data, record, ckpt_path)
    check_earlier_diagnosis(out_dir, ckpt_path, str(cfg.split), str(data.path))
    if added:
        log.info("%d HDF5 file(s) added to %s since the run trained are left out of the split: %s", len(added),
                 data.path, ", ".join(added[:5]) + (" ..." if len(added) > 5 else ""))
    if cfg.get("threads"):
        torch.set_num_threads(cfg.threads)
    model = prepare_for_inference(model, bool(cfg.get("fuse", True))).to(device)
    approach_m = cfg.phases.approach_m
    approach_from = "phases.approach_m"
    if approach_m is None:
        approach_m = sd.dataset_command_distance(data.path) if Path(data.path).is_dir() else None
        approach_from = "the dataset's command_distance (dataset_metadata.json)"
        if approach_m is None:
            approach_m, approach_from = 12.0, "the embedded simulator's default command_distance"
    frames, store = sd.load_split(data, str(cfg.split), files)
    if len(frames) == 0:
        raise sd.DiagnosticError(f"the {cfg.split} split of {data.path} holds no frame of camera(s) "
                                 f"{data.val_cameras}; check data.val_cameras / split")
    hp = ckpt["hyper_parameters"]
    label = describe(hp)
    log.info("diagnosing %s (%s) on %d %s frames of %s; split settings from %s", label, ckpt_path, len(frames),
             cfg.split, data.path, source)
    d, arrays = sd.measure(frames, store.get, sd.model_steer_all(model, device), approach_m=float(approach_m),
                           exit_s=float(cfg.phases.exit_s), dt_s=float(cfg.phases.dt_s),
                           batch_size=int(cfg.batch_size), max_frames=cfg.get("max_frames"))
    meta = {"model": label, "checkpoint": str(ckpt_path), "epoch": int(ckpt.get("epoch", -1)) + 1,
            "global_step": int(ckpt.get("global_step", 0)), "head": hp.get("head"), "mixer": hp.get("mixer"),
            "decoder": (hp.get("head_kwargs") or {}).get("decode"),
            "data": {**{k: getattr(data, k) for k in SPLIT_KEYS}, "split": str(cfg.split), "source": source,
                     "frames": int(len(d.expert)), "episodes": int(len(set(arrays["episode"].tolist()))),
                     "files": None if files is None else len(files), "files_left_out": added,
                     "data_hash": None if record is None else record.get("hash")},
            "phases": {"approach_m": float(approach_m), "approach_m_from": approach_from,
                       "exit_s": float(cfg.phases.exit_s), "dt_s": float(cfg.phases.dt_s),
                       "counts": {p: int((d.phase == p).sum()) for p in (*sd.PHASES, "unknown")}}}
    try:
        paths = sd.write_report(out_dir, d, meta, arrays, plot=bool(cfg.get("plot", True)))
    except OSError as err:  # a full disk: no file of the report was written
        raise CicfwError(f"could not write {err.filename} ({err.strerror or err}); nothing of the report was "
                         f"written: free some space, then run the same command") from None
    log.info("\n%s", sd.markdown(d, f"Steering diagnostic: {label}", sd.measured_line(meta)))
    log.info("report in %s", out_dir)
    return paths


@hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="diagnose")
@report_user_errors
def main(cfg: DictConfig) -> None:
    out = Path(HydraConfig.get().runtime.output_dir)
    try:
        diagnose(cfg, out)
    except USER_ERRORS:  # refused before its report: the folder as it was, no .hydra or log of a run that never was
        undo_run_folder(out)  # (a multirun job's folder is not noted: it keeps the log its failure line names)
        raise
    finally:
        release_folder_locks(out)  # LockedRunFolderCheck's, held while the folder was put back

