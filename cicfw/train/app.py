"""``python -m cicfw.train``: compose encoder/mixer/head/data/trainer/speed from the config and fit.

Returns the validation metric (``optimized_metric``) so Hydra sweepers can optimise it.
"""
from __future__ import annotations

import errno
import inspect
import io
import logging
import math
import os
import shutil
from pathlib import Path
from typing import Any, Callable, Mapping

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from lightning.fabric.plugins.environments import SLURMEnvironment
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import Callback, Checkpoint, EMAWeightAveraging, ModelCheckpoint, RichProgressBar
from lightning.pytorch.loggers import CSVLogger, Logger, TensorBoardLogger
from lightning.pytorch.loggers.logger import rank_zero_experiment
from lightning.pytorch.plugins.io import CheckpointIO, TorchCheckpointIO
from omegaconf import DictConfig

from cicfw import COMMANDS
from cicfw.benchmark.app import check_evaluation_overrides, evaluate_after_training, saved_checkpoint
from cicfw.benchmark.trained_sets import recorded_sets
from cicfw.collect import collect_dataset
from cicfw.collect.config import CAMERA_IDS, DEFAULTS
from cicfw.core.command_line import command_line_keys
from cicfw.core.config_checks import did_you_mean as _did_you_mean
from cicfw.core.config_checks import (CACHE_VARIABLE, checked_seed, forget_empty_cache_setting, is_integer,
                                      same_value)
from cicfw.data.datamodule import CILDataModule
from cicfw.data.wait import DataWait
from cicfw.data.cil_hdf5 import find_files
from cicfw.data.frames import META_NAME, camera_names
from cicfw.core.errors import USER_ERRORS, CicfwError, ConfigError, Interrupted, on_interrupt, report_user_errors
from cicfw.core.files import atomic_write, writable_folder
from cicfw.model.checkpoint import (PART_KEYS, SUPERSEDED_KEY, TRAINING_DEFAULTS, WORLD_SIZE_KEY, UnloadableCheckpoint,
                                   checkpoint_record, load_weights_only, model_from_hparams, parts_label, saved_hparams,
                                   weights_misfit)
from cicfw.model.diagnostics import MixerDiagnostics
from cicfw.model.module import CICModule
from cicfw.model.speed import apply_speed_from_config
from cicfw.core.run_folder import (claim_folder, data_folders, enclosing_run, forget_failed_run, hold_train_folder,
                                  release_run_folder, undo_run_folder)
from cicfw.core.sweeps import is_worker_process
from cicfw.data.provenance import (CHECKPOINT_KEY, SETS_KEY, check_same_data, folder_record, record_data, same_files,
                                   same_place, summary, with_earlier, write_record)
from cicfw.train.schema import MODEL, checked_data, checked_node, checked_part, checked_speed, checked_trainer
from cicfw.train.schema import check_top_level
from cicfw.train.resumed_encoding import check_resumed_encoding
from cicfw.train.resume_names import with_checkpoint_file
from cicfw.train.schedule_record import SCHEDULE_KEY, check_resumed_horizon, horizon_settings
from cicfw.train.split_record import SPLIT_KEY, check_resumed_split, split_settings

log = logging.getLogger("cicfw.train")

def keep_earlier_metrics(log_dir: Path) -> None:
    """``<log_dir>/metrics.csv``, which Lightning's CSV logger deletes when it starts writing there (a run
    resumed in its own folder has one), kept as ``metrics.<n>.csv`` (the first free n), and the log says so."""
    metrics = Path(log_dir) / "metrics.csv"
    if metrics.is_file():
        n = 1
        while metrics.with_name(f"metrics.{n}.csv").exists():
            n += 1
        metrics.rename(metrics.with_name(f"metrics.{n}.csv"))
        log.info("the metrics logged before this resume are kept in %s", metrics.with_name(f"metrics.{n}.csv"))


class KeepingCSVLogger(CSVLogger):
    """Lightning's CSV logger that keeps the earlier metrics (``keep_earlier_metrics``) when it first writes,
    inside ``trainer.fit``, not when it is built: a run refused before then finds its folder as it was."""

    @property
    @rank_zero_experiment
    def experiment(self) -> Any:
        if self._experiment is None:
            keep_earlier_metrics(Path(self.log_dir))
        return super().experiment


def csv_logger(run_dir: Path) -> CSVLogger:
    """``<run dir>/csv/metrics.csv``, an earlier segment's kept as ``metrics.<n>.csv`` (``KeepingCSVLogger``)."""
    return KeepingCSVLogger(str(run_dir), name="csv", version="")


LOGGERS: dict[str, Callable[[Path], Logger]] = {
    "csv": csv_logger,
    "tensorboard": lambda run_dir: TensorBoardLogger(str(run_dir), name="tensorboard", version=""),
}


def build_model(cfg: DictConfig) -> CICModule:
    """The model from the encoder/mixer/head/model nodes, each checked against its schema
    (cicfw/train/schema.py): an unknown name or key fails here with one line naming what is accepted (before
    any data is read)."""
    enc, enc_kw = checked_part(cfg, "encoder")
    mix, mix_kw = checked_part(cfg, "mixer")
    head, head_kw = checked_part(cfg, "head")
    model_kw = checked_node(cfg, "model", MODEL)
    try:
        model = CICModule(encoder=enc, encoder_kwargs=enc_kw, mixer=mix, mixer_kwargs=mix_kw,
                          head=head, head_kwargs=head_kw, **model_kw)
    except CicfwError:
        raise
    except ValueError as err:  # a plugin's part refuses its settings with a plain ValueError (docs/plugins.md);
        raise CicfwError(str(err)) from err  # chained: CICFW_DEBUG=1 shows where the plugin raised it
    if cfg.speed.get("channels_last"):
        model.use_channels_last()
    return model


#: metrics where higher is better: the best checkpoint is the one with the lowest ``optimized_metric``
HIGHER_IS_BETTER = ("val/bin_acc",)


def logged_metrics(model: CICModule) -> list[str]:
    """The metrics ``CICModule`` logs while training (its training step and validation epochs)."""
    val = ["val/loss", "val/steer_mae", *(f"val/steer_mae/{c}" for c in COMMANDS)]
    if model.head.bins is not None:
        val.append("val/bin_acc")
    return [*val, "train/loss", "train/task_loss", "train/steer_mae"]


def check_optimized_metric(metric: Any, model: CICModule) -> None:
    """``optimized_metric`` must be a lower-is-better metric the model logs while training (the best
    checkpoint's monitor); Lightning refused any other only after the first epoch."""
    logged = logged_metrics(model)
    accepted = [m for m in logged if m not in HIGHER_IS_BETTER]
    if metric in accepted:
        return
    names = ", ".join(accepted)
    if metric in logged:
        raise CicfwError(f"optimized_metric={metric} is higher-is-better, but the best checkpoint is the one with the "
                         f"lowest optimized_metric; choose one of {names}")
    if str(metric).startswith("closed_loop/"):
        raise CicfwError(f"optimized_metric={metric} is measured after training, but optimized_metric picks the best "
                         f"checkpoint while training; choose one of {names} (evaluate_after=true "
                         f"return_closed_loop=true returns the closed-loop success rate to sweepers)")
    raise CicfwError(f"optimized_metric={metric} is not a metric the model logs; "
                     f"{_did_you_mean(str(metric), accepted)}choose one of {names}")


def ensure_data(data_cfg: DictConfig) -> None:
    """Collect (or finish collecting) the default simulator dataset; a complete one returns at once.

    Asking the collector every time, rather than testing for files, means a collection that was
    killed half-way is finished instead of silently training on part of the data.
    """
    if data_cfg.get("collect") is None:
        return
    path = Path(data_cfg.path).expanduser()
    check_not_your_own_data(path)
    make_collect_folder(path)

    with on_interrupt(f"while collecting the dataset: finished episodes are kept in {path}; run the same "
                      f"command to go on"):
        collect_dataset(data_cfg.collect, path)


def make_collect_folder(path: Path) -> None:
    """``data=sim_default`` collects into ``data.path``, by default under the cicfw cache folder
    (``$CICFW_CACHE``, else ``~/.cache/cicfw``): claimed as collect claims its ``out_dir`` (``claim_folder``:
    another app's run or a folder inside one is refused, naming ``data.path``, or ``CICFW_CACHE`` when the
    cache itself lies in one), then made here (``writable_folder``), and a folder that cannot be
    made or written is one line naming what the user of train changes, ``CICFW_CACHE`` for a folder under it,
    else ``data.path`` (the collector's own error names collect's ``out_dir``)."""
    cache = os.environ.get(CACHE_VARIABLE)
    root = Path(os.path.abspath(os.path.expanduser(cache))) if cache else None
    if root is not None and (root == path.absolute() or root in path.absolute().parents):
        key, value, instead = CACHE_VARIABLE, cache, "give data.path=<a writable folder>"
        check_cache_outside_runs(cache, root)
    else:
        key, value, instead = "data.path", None, f"set the environment variable {CACHE_VARIABLE} to one for the default"
    # the rule collect applies to its out_dir: not another app's run nor a folder inside one (an existing
    # dataset there, which collecting finishes or reads, passes)
    claim_folder(path, "collect", "data.path", foreign_ok=True)
    writable_folder(path, key, f"a folder you can write, where data=sim_default collects its dataset (or {instead})",
                    "the dataset folder", value=value)


def check_cache_outside_runs(cache: str, root: Path) -> None:
    """The cache folder (``$CICFW_CACHE``) is no cicfw run or results folder, nor inside one: the dataset
    collected into it would lie among that run's files (``<results>/datasets/smoke``)."""
    found = enclosing_run(root, include_self=True)
    if found is not None:
        run, owner = found
        where = "is" if str(run) == os.path.realpath(root) else "lies inside"
        raise ConfigError(CACHE_VARIABLE, cache, "", message=(
            f"the environment variable {CACHE_VARIABLE}={cache!r} {where} {str(run)!r}, a run of cicfw "
            f"{owner}, where data=sim_default would collect its dataset among that run's files; set "
            f"{CACHE_VARIABLE} to a folder outside any run or results folder (or give data.path=<a folder outside them>)"))


def check_not_your_own_data(path: Path) -> None:
    """``data=sim_default`` (the default) collects into ``data.path``; a folder of CIL files it did not
    collect is the user's own data, which ``data=cil_hdf5`` reads: say so instead of the collector's
    "collect into an empty folder"."""
    if not path.is_dir() or (path / META_NAME).exists():
        return
    files = [f for f in path.rglob("*") if f.suffix in (".h5", ".hdf5") and f.is_file()]
    if files:
        raise CicfwError(f"data.path={path} holds {len(files)} CIL HDF5 file(s) that cicfw did not collect, and "
                         f"the default data=sim_default collects its own dataset into data.path; add data=cil_hdf5 "
                         f"to train on them: python -m cicfw.train data=cil_hdf5 data.path={path}")


def make_datamodule(cfg: DictConfig) -> CILDataModule:
    """The datamodule from ``cfg.data``: its arguments are checked (batch size a multiple of 4 for
    balanced batches, ...) but no file is read or collected yet."""
    kwargs = checked_data(cfg)
    kwargs.pop("collect", None)
    kwargs["path"] = str(Path(kwargs["path"]).expanduser())
    datamodule = CILDataModule(**kwargs)
    check_collected_cameras(cfg.data, datamodule)
    return datamodule


def check_collected_cameras(data_cfg: DictConfig, datamodule: CILDataModule) -> None:
    """The default data (``data.collect``) records the cameras of ``collect.cameras``: ``data.cameras``
    or ``data.val_cameras`` choosing none of their ids is refused now, not after the collection."""
    if data_cfg.get("collect") is None:
        return

    names = data_cfg.collect.get("cameras") or DEFAULTS["cameras"]
    recorded = {CAMERA_IDS[n][0]: n for n in names if n in CAMERA_IDS}  # unknown names: the collector says so
    for key, chosen in (("cameras", datamodule.cameras), ("val_cameras", datamodule.val_cameras)):
        if chosen is not None and recorded and not set(chosen) & set(recorded):
            held = camera_names(dict(sorted(recorded.items())))
            raise CicfwError(f"data.{key}={list(chosen)} chooses none of the cameras the default data records "
                             f"({held}; collect.cameras); choose among those, or train on your own files with "
                             f"data=cil_hdf5 data.path=...")


class EpochCheckpoints(Checkpoint):
    """``checkpoints/epochNNN.ckpt`` after each listed epoch (1-based), kept: a learning curve's points. A
    ``Checkpoint``, so that Lightning runs it after the best checkpoint has taken that epoch's validation
    (listed after it): a run resumed from the file still knows that epoch's score and its best file."""

    def __init__(self, dirpath: Path, epochs, max_epochs: int | None = None) -> None:
        """``epochs``: ``keep_epoch_checkpoints`` (whole numbers: the schema); one below 1 or beyond
        ``max_epochs`` (the run's ``trainer.max_epochs``) is a ``ConfigError`` (it would never be saved)."""
        wrong = [int(e) for e in epochs if e < 1 or (max_epochs is not None and e > max_epochs)]
        if wrong:
            within = f"within trainer.max_epochs={max_epochs} (1 to {max_epochs})" if max_epochs is not None else ">= 1"
            raise ConfigError("keep_epoch_checkpoints", wrong[0], f"a list of epochs {within}, e.g. [1,2] (each "
                              f"keeps checkpoints/epochNNN.ckpt)")
        self.dirpath, self.epochs = Path(dirpath), {int(e) for e in epochs}

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        epoch = trainer.current_epoch + 1
        if epoch not in self.epochs:
            return
        done, planned = trainer.fit_loop.epoch_loop.batch_progress.current.completed, trainer.num_training_batches
        if math.isfinite(planned) and done < planned:  # stopped inside it (trainer.max_steps, max_time)
            log.info("epoch %d stopped after %d of its %s batches: no epoch%03d.ckpt (keep_epoch_checkpoints keeps "
                     "the weights after whole epochs)", epoch, done, planned, epoch)
            return
        trainer.save_checkpoint(str(self.dirpath / f"epoch{epoch:03d}.ckpt"))


class BestCheckpoint(ModelCheckpoint):
    """The best checkpoint by the monitored metric. A run folder moved or copied and resumed there keeps its
    best: Lightning forgets the best seen so far when the folder's path changed, so a worse later epoch was
    saved as a second best and reported as the run's value; the state is re-rooted here when the files it
    names lie in this folder under their names (another run's checkpoint resumed in a new folder is not).
    Its name's ``{epoch}`` counts the epochs begun (1-based), as the kept ``epochNNN.ckpt`` do, so that
    ``epoch001-mae...ckpt`` and ``epoch001.ckpt`` are the same epoch's weights (Lightning's is 0-based).
    A resume on other data (``start_new_ranking``) restores no best: that segment's validations are ranked
    among themselves, and every checkpoint it saves names the earlier best files (``SUPERSEDED_KEY``)."""

    new_ranking = False
    superseded: tuple[str, ...] = ()

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        if self.superseded:
            checkpoint[SUPERSEDED_KEY] = list(self.superseded)

    def on_load_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        earlier = checkpoint.get(SUPERSEDED_KEY)
        if isinstance(earlier, (list, tuple)):
            self.superseded = tuple(dict.fromkeys([*map(str, earlier), *self.superseded]))

    def format_checkpoint_name(self, metrics: dict[str, Any], filename: str | None = None, ver: int | None = None,
                               prefix: str | None = None) -> str:
        if "epoch" in metrics:
            metrics = {**metrics, "epoch": metrics["epoch"] + 1}
        return super().format_checkpoint_name(metrics, filename=filename, ver=ver, prefix=prefix)

    @property
    def state_key(self) -> str:  # ModelCheckpoint's, under which every run's checkpoints keep this state
        return super().state_key.replace(type(self).__qualname__, ModelCheckpoint.__qualname__, 1)

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if self.new_ranking:  # the earlier segment's best, on other data: kept as a file, ranked no more
            best = [*(state_dict.get("best_k_models") or {}), state_dict.get("best_model_path") or ""]
            names = [os.path.basename(str(p)) for p in best if p]  # those in this folder: a checkpoint resumed
            names = [n for n in names if self.dirpath and os.path.isfile(os.path.join(self.dirpath, n))]  # elsewhere
            self.superseded = tuple(dict.fromkeys([*self.superseded, *names]))
            return
        old = state_dict.get("dirpath")
        if old and self.dirpath and old != self.dirpath:
            here = lambda p: os.path.join(self.dirpath, os.path.basename(p)) if p else p  # noqa: E731
            best = {here(p): v for p, v in (state_dict.get("best_k_models") or {}).items()}
            if best and all(os.path.isfile(p) for p in best):
                state_dict = {**state_dict, "dirpath": self.dirpath, "best_k_models": best,
                              **{k: here(state_dict.get(k)) for k in ("best_model_path", "kth_best_model_path")}}
        super().load_state_dict(state_dict)


def start_new_ranking(trainer: L.Trainer) -> None:
    """A resume on other data: its best checkpoint is the best among its own validations (``BestCheckpoint``),
    as their errors are not comparable with those measured on the earlier data; said in one line."""
    best = trainer.checkpoint_callback
    if isinstance(best, BestCheckpoint):
        best.new_ranking = True
        log.info("resuming on other data: the best checkpoint by %s is chosen among this run's validations "
                 "from now on; the earlier best checkpoints stay in %s but are not the run's best", best.monitor,
                 best.dirpath)


def last_checkpoint(dirpath: Path) -> ModelCheckpoint:
    """``<dirpath>/last.ckpt`` rewritten at the end of every training epoch (after its validation, when one
    runs): always the latest weights and training state, the one to resume from. A callback of its own
    because ``ModelCheckpoint(monitor=..., save_last=True)`` refreshes ``last.ckpt`` only when it saves a
    new best checkpoint, and saving at the epoch's end rather than after validation because validation
    may skip epochs (``trainer.check_val_every_n_epoch=2``), whose weights would be saved nowhere."""
    return ModelCheckpoint(dirpath=dirpath, filename="last", monitor=None, save_top_k=1, enable_version_counter=False,
                           save_on_train_epoch_end=True)


class CheckpointWriteError(CicfwError):
    """A checkpoint could not be written (a full disk ...); the ones written before are intact."""


class AtomicCheckpointIO(TorchCheckpointIO):
    """Checkpoints written to a temporary file beside their final name, then renamed, as the collector
    writes its files: a full disk or a kill never leaves a truncated checkpoint under the final name,
    and the previous ``last.ckpt`` stays whole. (Lightning stages in the system's temporary folder and
    copies the file over when that is another filesystem: a full disk left half a file there.)"""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            return super().save_checkpoint(checkpoint, path, storage_options)  # refuses them, with its message

        buffer = io.BytesIO()
        torch.save(checkpoint, buffer)
        try:
            atomic_write(Path(path), buffer.getbuffer())
        except OSError as err:
            raise checkpoint_write_error(err, Path(path)) from None


def checkpoint_write_error(err: OSError, path: Path) -> CheckpointWriteError:
    """One line for a checkpoint that could not be written: why, and how to go on."""
    last = path.parent / "last.ckpt"
    go_on = f"resume with ckpt_path={last}" if last.is_file() else "run the same command again"
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        free = shutil.disk_usage(path.parent).free / 1e6
        return CheckpointWriteError(f"no space left on the device of {path.parent} while writing the checkpoint "
                                    f"{path.name} ({free:.1f} MB free; the checkpoints written before are intact): "
                                    f"free some space, then {go_on}")
    return CheckpointWriteError(f"could not write the checkpoint {path} ({err.strerror or err}; the checkpoints "
                                f"written before are intact): {go_on}")


def with_checkpoint_io(plugins: Any) -> list[Any]:
    """``trainer.plugins`` plus ``AtomicCheckpointIO``, unless the user gave a CheckpointIO of their own."""
    plugins = list(plugins) if isinstance(plugins, (list, tuple)) else ([] if plugins is None else [plugins])
    return plugins if any(isinstance(p, CheckpointIO) for p in plugins) else [*plugins, AtomicCheckpointIO()]


def build_callbacks(cfg: DictConfig, run_dir: Path) -> list[Callback]:
    """The best checkpoint by ``optimized_metric`` (first: ``trainer.checkpoint_callback``, and it saves
    before ``last.ckpt`` so that file records the updated best), ``last.ckpt``, the mixer's diagnostics,
    the data-wait report, the kept epochs, the weights' moving average and the progress bar."""
    callbacks: list[Callback] = [
        BestCheckpoint(dirpath=run_dir / "checkpoints", monitor=cfg.optimized_metric, mode="min",
                        save_last=False, filename="epoch{epoch:03d}-mae{val/steer_mae:.4f}",
                        auto_insert_metric_name=False),
        last_checkpoint(run_dir / "checkpoints"),
        MixerDiagnostics(),  # heatmaps of what the mixer learned (C, gates, alphas) per validation epoch
        DataWait(),  # the share of step time spent waiting for data, in the log each epoch
    ]
    epochs = cfg.get("keep_epoch_checkpoints") or []
    if epochs:
        callbacks.append(EpochCheckpoints(run_dir / "checkpoints", epochs, cfg.trainer.get("max_epochs")))
    ema_decay = float(cfg.model.get("ema_decay", 0.0))
    if ema_decay > 0:  # validation and every checkpoint's state_dict see the average; training the raw weights
        callbacks.append(EMAWeightAveraging(decay=ema_decay))
    if cfg.get("progress_bar", True):
        callbacks.append(RichProgressBar())
    return callbacks


def trainer_kwargs(cfg: DictConfig) -> dict[str, Any]:
    """``lightning.Trainer``'s arguments: ``cfg.trainer`` checked against its schema (every argument of
    ``Trainer.__init__`` with its type)."""
    return checked_trainer(cfg)


def build_trainer(cfg: DictConfig, run_dir: Path) -> L.Trainer:
    """The Lightning Trainer; an unknown argument or a value Lightning refuses (``max_epochs=-2``,
    ``accelerator=gpu`` without a GPU) is one ``ValueError`` naming it."""
    kwargs = trainer_kwargs(cfg)
    if cfg.logger is None:
        logger: Logger | bool = False
    elif cfg.logger.name not in LOGGERS:
        raise CicfwError(f"unknown logger {cfg.logger.name!r}; known loggers: {', '.join(sorted(LOGGERS))}")
    else:
        logger = LOGGERS[cfg.logger.name](run_dir)
    if kwargs.get("enable_progress_bar") is None:  # Lightning's default: follow progress_bar
        kwargs["enable_progress_bar"] = bool(cfg.get("progress_bar", True))
    kwargs["plugins"] = with_checkpoint_io(kwargs.get("plugins"))
    callbacks = build_callbacks(cfg, run_dir)  # outside the try below: its errors name their own keys

    try:
        trainer = L.Trainer(default_root_dir=str(run_dir), logger=logger, callbacks=callbacks, **kwargs)
    except (MisconfigurationException, ValueError, TypeError, AttributeError) as err:  # max_time=1:00
        raise CicfwError(f"trainer: {' '.join(str(err).split())}", key="trainer") from None
    asked = str(kwargs.get("precision"))
    if asked.startswith("16") and str(trainer.precision).startswith("bf16"):  # Lightning's swap on a CPU
        raise ConfigError("trainer.precision", asked, "bf16-mixed or 32 here: fp16 autocast needs a GPU, and on "
                                                      "this CPU Lightning would train in bf16 under the name you gave")
    return trainer


# ckpt_path values Lightning resolves itself (no file to check before training).
LIGHTNING_CKPT_NAMES = ("last", "best", "hpc", "registry")


def load_checkpoint_safely(path: str | Path, what: str = "ckpt_path") -> dict[str, Any]:
    """``torch.load(path, weights_only=True)``: tensors and plain data only, never pickled code (a
    checkpoint that holds other objects is refused, whatever TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD says).
    A missing, truncated or foreign file is one ``ValueError`` / ``FileNotFoundError`` naming it."""
    p = Path(path).expanduser()
    if p.is_dir():
        raise CicfwError(f"{what}={path} is a folder; give the checkpoint file, e.g. {p}/checkpoints/last.ckpt",
                         key=what, value=path)
    if not p.is_file():
        raise FileNotFoundError(f"{what}={path}: no such file")
    try:
        ckpt = load_weights_only(p)
    except UnloadableCheckpoint as err:
        if err.code:
            raise CicfwError(
                f"{what}={path}: refused: the file holds pickled Python objects besides tensors and plain data "
                f"({err.reason}), which could run code when loaded; cicfw loads checkpoints with "
                f"torch.load(weights_only=True) only", key=what, value=path) from None
        raise CicfwError(f"{what}={path} is not a readable checkpoint (truncated, or not written by "
                         f"torch.save): {err.reason}", key=what, value=path) from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict):
        raise CicfwError(f"{what}={path} is not a Lightning training checkpoint (no 'state_dict'); "
                         f"give a .ckpt written by cicfw train (<run>/checkpoints/last.ckpt)", key=what, value=path)
    return ckpt


def check_resume_checkpoint(path: str | Path | None, model: CICModule,
                            trainer_cfg: Mapping[str, Any] | None = None,
                            split: Mapping[str, Any] | None = None,
                            horizon: Mapping[str, Any] | None = None) -> str | None:
    """Check ``ckpt_path`` before any data is read: a file that loads with ``weights_only=True``,
    holds the training state (not weights only), fits this run's model, was trained with this run's
    optimizer settings and, given ``split`` (``split_settings``), this run's train/validation split and samples,
    given ``horizon`` (``horizon_settings``), the run length its learning-rate schedule is spread over, and,
    given ``trainer_cfg``, leaves something to train. Returns the path for ``Trainer.fit`` (None to start
    afresh)."""
    if path is None or str(path) == "":
        return None
    if str(path) in LIGHTNING_CKPT_NAMES:
        return str(path)
    ckpt = load_checkpoint_safely(path)
    if "optimizer_states" not in ckpt or "loops" not in ckpt:
        raise CicfwError(f"ckpt_path={path} holds the weights only (no optimizer or loop state), so training "
                         f"cannot resume from it; resume from <run>/checkpoints/last.ckpt, or evaluate it "
                         f"with cicfw evaluate checkpoint={path}", key="ckpt_path", value=path)
    misfit = weights_misfit(model.state_dict(), ckpt["state_dict"])
    if misfit:
        check_weights_fit_their_model(path, ckpt, model)
        saved = parts_label(ckpt.get("hyper_parameters") or {})
        raise CicfwError(
            f"ckpt_path={path} was saved by another model (encoder/mixer/head {saved}; this run: "
            f"{parts_label(model.hparams)}): {misfit}; resume with the options the checkpoint was trained with",
            key="ckpt_path", value=path)
    check_resumed_optimizer(path, ckpt, model)
    check_resumed_encoding(path, ckpt.get("hyper_parameters") or {}, model.hparams)  # speed scale, bins
    if split is not None:
        check_resumed_split(path, ckpt, split)
    if horizon is not None:
        check_resumed_horizon(path, ckpt, model.hparams, horizon)
    if trainer_cfg is not None:
        check_epochs_left(path, ckpt, trainer_cfg)
    return str(path)


def check_weights_fit_their_model(path: str | Path, ckpt: Mapping[str, Any], model: CICModule) -> None:
    """A checkpoint whose weights do not fit this run's model: refused as damaged or edited when they do not fit
    the model its own ``hyper_parameters`` record either (no options would resume it). Returns when they fit it
    (another model's checkpoint), or when that model cannot be built here and it names other parts than this run."""
    hp = ckpt.get("hyper_parameters")
    hp = hp if isinstance(hp, Mapping) else {}
    saved, here = parts_label(hp), parts_label(model.hparams)
    theirs = None
    if all(isinstance(hp.get(k), str) for k in PART_KEYS):
        try:
            theirs = model_from_hparams(hp, str(path)).state_dict()
        except (KeyError, TypeError, ValueError):  # a part not installed here, kwargs it does not take
            pass
    if theirs is None and saved != here:
        return
    misfit = weights_misfit(theirs if theirs is not None else model.state_dict(), ckpt["state_dict"])
    if misfit:
        same = ", this run's too" if saved == here else f"; this run: {here}"
        raise CicfwError(
            f"ckpt_path={path}: its weights do not fit the model its own hyper_parameters record (encoder/mixer/head "
            f"{saved}{same}), a damaged or edited file: "
            f"{misfit}; resume from an intact checkpoint", key="ckpt_path", value=path)


def check_resumed_optimizer(path: str | Path, ckpt: Mapping[str, Any], model: CICModule) -> None:
    """Resuming restores the optimizer (its lr, betas, weight decay) and its schedule from the checkpoint, so
    a ``model.*`` value that differs from the checkpoint's would be recorded but not used: refused, naming
    each key and both values."""
    saved = saved_hparams(ckpt.get("hyper_parameters") or {}, str(path))
    differ = []
    for key in TRAINING_DEFAULTS:  # the optimizer's and its schedule's state: what resuming restores
        theirs = saved[key]
        ours = model.hparams.get(key)
        if not same_value(ours, theirs):
            differ.append(f"model.{key}={_plain(ours)} (the checkpoint's: {_plain(theirs)})")
    if differ:
        raise CicfwError(f"ckpt_path={path}: resuming restores the optimizer and its schedule from the checkpoint, so "
                         f"{', '.join(differ)} would not take effect; resume with the checkpoint's values, or start a "
                         f"fresh run (no ckpt_path) with the new ones", key="ckpt_path", value=path)


def _plain(value: Any) -> str:
    """A config value as it is written on the command line (``[0.7, 0.85]``, ``0.0002``)."""
    return str(list(value)) if isinstance(value, tuple) else str(value)


def epochs_finished(ckpt: Mapping[str, Any]) -> int:
    """How many training epochs ``ckpt`` has finished (its fit loop's count; else its epoch index + 1)."""
    try:
        return int(ckpt["loops"]["fit_loop"]["epoch_progress"]["current"]["processed"])
    except (KeyError, TypeError, ValueError):
        return int(ckpt.get("epoch", -1)) + 1


def check_epochs_left(path: str | Path, ckpt: Mapping[str, Any], trainer_cfg: Mapping[str, Any]) -> None:
    """A checkpoint that has reached ``trainer.max_epochs`` (or ``max_steps``) leaves nothing to train:
    refused, rather than a run that trains nothing and reports no metric."""
    done, step = epochs_finished(ckpt), int(ckpt.get("global_step", 0))
    max_epochs, max_steps = trainer_cfg.get("max_epochs"), trainer_cfg.get("max_steps")
    if is_integer(max_epochs) and max_epochs >= 0 and done >= max_epochs:
        raise CicfwError(f"ckpt_path={path} has finished {done} epoch(s) and trainer.max_epochs={max_epochs}: nothing "
                         f"is left to train; give trainer.max_epochs greater than {done} to train on from it",
                         key="trainer.max_epochs", value=max_epochs)
    if is_integer(max_steps) and max_steps >= 0 and step >= max_steps:
        raise CicfwError(f"ckpt_path={path} has trained {step} step(s) and trainer.max_steps={max_steps}: nothing is "
                         f"left to train; give trainer.max_steps greater than {step} to train on from it",
                         key="trainer.max_steps", value=max_steps)


def fit_kwargs() -> dict[str, Any]:
    """``weights_only=True`` for ``Trainer.fit`` where Lightning takes it (2.6+); older Lightning
    loads with torch's default, after ``check_resume_checkpoint`` loaded the same file safely."""
    return {"weights_only": True} if "weights_only" in inspect.signature(L.Trainer.fit).parameters else {}


def check_slurm_tasks() -> None:
    """SLURM's task count as Lightning reads it: ``SLURM_NTASKS`` > 1 without ``SLURM_NTASKS_PER_NODE`` (an
    salloc or sbatch shell, the command not started by srun) fails in the Trainer with a traceback; one line
    naming the variables before any work."""
    ntasks = os.environ.get("SLURM_NTASKS", "1")
    if "SLURM_NTASKS_PER_NODE" in os.environ or not SLURMEnvironment.detect():
        return
    if ntasks.strip().isdigit() and int(ntasks) <= 1:
        return
    named = ", ".join(f"{k}={os.environ[k]}" for k in ("SLURM_JOB_ID", "SLURM_NTASKS", "SLURM_JOB_NAME",
                                                       "SLURM_PROCID") if k in os.environ)
    raise CicfwError(f"SLURM variables set ({named}) but not by srun (no SLURM_NTASKS_PER_NODE): Lightning would "
                     f"take this process for one of {ntasks} SLURM tasks; start the command with srun "
                     f"(srun --ntasks-per-node=N, with trainer.devices=N), or unset the SLURM_* variables to train "
                     f"in this process alone", key="SLURM_NTASKS", value=ntasks)


def checked_setup(cfg: DictConfig, refuse_finished: bool = False) -> tuple[CICModule, str | None, CILDataModule]:
    """The model, the checkpoint to resume from and the datamodule (no file read yet), each checked: the
    config's top-level keys, the encoder/mixer/head/model nodes, ``optimized_metric``, ``ckpt_path`` and the
    ``data`` node. What ``train`` checks before the Trainer; ``check_config`` checks the same."""
    check_top_level(cfg)  # +evaluate_aftr=true would silently skip the evaluation
    model = build_model(cfg)  # names, keys and value types of the encoder/mixer/head/model nodes
    check_optimized_metric(cfg.optimized_metric, model)  # the best checkpoint's monitor, logged by the model
    # a safe, whole, matching checkpoint, with this run's optimizer settings and epochs left to train
    ckpt_path = check_resume_checkpoint(cfg.get("ckpt_path"), model, cfg.trainer if refuse_finished else None,
                                        split_settings(cfg.data),  # the same split and samples
                                        horizon_settings(cfg))  # the same schedule length
    datamodule = make_datamodule(cfg)  # data.* arguments (batch size a multiple of 4 ...)
    return model, ckpt_path, datamodule


def check_evaluation(cfg: DictConfig) -> None:
    """With ``evaluate_after``, the evaluation's overrides: a typo there does not wait for the training.
    Without it, ``return_closed_loop=true`` would return the validation metric to a sweeper told it gets
    the success rate, and ``evaluate_overrides`` given on the command line would go unused: refused (an
    experiment's own ``evaluate_overrides``, for when the evaluation is asked for, are not)."""
    if cfg.get("evaluate_after"):
        check_evaluation_overrides(cfg.get("evaluate_overrides"))
    elif cfg.get("return_closed_loop"):
        raise ConfigError("return_closed_loop", True, "false without evaluate_after=true (the closed-loop success "
                          "rate it returns is measured by the evaluation after training)")
    elif cfg.get("evaluate_overrides") and "evaluate_overrides" in command_line_keys(cfg, "train"):
        raise ConfigError("evaluate_overrides", list(cfg.evaluate_overrides), "given with evaluate_after=true (they "
                          "set the evaluation after training, which runs only then): add evaluate_after=true, or "
                          "leave evaluate_overrides out")


def check_config(cfg: DictConfig, refuse_finished: bool = True) -> None:
    """Every value ``train`` checks before it collects or reads data, without building the Trainer or
    touching a folder: a multirun checks each job's config with it before its first job trains
    (``cicfw.core.override_hints.SweepJobsCheck``, conf/train.yaml), ``cicfw.testing.fast_dev_run`` before it
    writes its tiny dataset. ``refuse_finished``: as ``train``'s."""
    check_slurm_tasks()  # SLURM variables without srun: Lightning's Trainer would fail with a traceback
    checked_seed(cfg.seed)
    checked_setup(cfg, refuse_finished=refuse_finished)
    trainer_kwargs(cfg)
    checked_speed(cfg)
    EpochCheckpoints(Path("checkpoints"), cfg.get("keep_epoch_checkpoints") or [], cfg.trainer.get("max_epochs"))
    check_evaluation(cfg)


def check_data_path(cfg: DictConfig) -> None:
    """A multirun job's data path checked before any job trains (conf/train.yaml's ``SweepJobsCheck``), as
    the run reads it (``find_files``: a folder holding an HDF5 file, or a glob matching one): cheap, where
    it names the user's own data; data the default collects (``data.collect``) is made when its job runs."""
    if cfg.data.get("collect") is not None:
        return
    path = str(cfg.data.path)
    try:
        find_files(path)
    except FileNotFoundError as err:  # a single run's one line, raised as a user error the sweep check names
        raise CicfwError(" ".join(str(err.args[0] if err.args else err).split()), key="data.path",
                         value=path) from None


def train(cfg: DictConfig, run_dir: Path, refuse_finished: bool = False,
          on_start: Callable[[], Any] | None = None, *, claim: bool = True) -> float:
    """Fit and return the best ``cfg.optimized_metric`` (validation steer MAE by default); with
    ``evaluate_after`` run the closed-loop suite afterwards (and return its success rate, in %, when
    ``return_closed_loop``). Ctrl-C raises ``Interrupted`` saying what is kept and how to go on.
    ``refuse_finished``: refuse a ``ckpt_path`` with no epoch left to train (the app does; a caller that
    resumes whatever it finds, as a reproduce cell does, gets a run that trains nothing and says so).
    ``on_start`` is called when everything is checked and training starts.

    ``run_dir`` is made this call's own first, as the app's run folder is: ``claim_folder`` (another app's
    run or a folder inside one, the data folder or files no cicfw app wrote are refused), then held
    (``hold_train_folder``: another run's outputs, unless ``ckpt_path`` resumes from a checkpoint inside it,
    or a folder another run holds are refused) until it returns; refused, it is one ``RunFolderError`` or
    ``FolderBusy`` naming ``run_dir``, the folder left as it was. ``claim=False``: the caller claimed and
    holds it already (the app, a reproduction's cell)."""
    run_dir = Path(run_dir)
    if not claim or is_worker_process():  # a DDP worker rank trains in the folder its rank 0 claimed
        return _train(cfg, run_dir, refuse_finished, on_start)
    claim_folder(run_dir, "train", "run_dir", data=data_folders(cfg))
    return _train_held(cfg, run_dir, "run_dir", refuse_finished, on_start)


def _train(cfg: DictConfig, run_dir: Path, refuse_finished: bool,
           on_start: Callable[[], Any] | None) -> float:
    """``train`` in a folder the caller holds."""
    forget_empty_cache_setting()  # CICFW_CACHE= means the default cache, not the file-system root
    check_slurm_tasks()  # first: Lightning's own lines would already take this process for a SLURM task's
    L.seed_everything(checked_seed(cfg.seed), workers=True)
    cfg = with_checkpoint_file(cfg, run_dir)  # ckpt_path=last: the file, checked as any other
    # Everything a user can get wrong in the config fails first, before any image is collected or read:
    model, ckpt_path, datamodule = checked_setup(cfg, refuse_finished)
    speed = checked_speed(cfg)  # cicfw's speed switches (speed.adam=fusd)
    trainer = build_trainer(cfg, run_dir)  # trainer.* keys and values
    check_evaluation(cfg)
    ensure_data(cfg.data)  # then the data: collected if needed,
    record, other_data = data_record(cfg, datamodule.path, run_dir)  # recorded (other data than a resumed run's:
    if other_data:  # refused unless resume_on_other_data), and then validation errors start a new ranking
        start_new_ranking(trainer)
    trainer.callbacks.append(RecordInCheckpoints({CHECKPOINT_KEY: record,  # into every checkpoint too,
                                                  SPLIT_KEY: split_settings(cfg.data),  # with the split
                                                  SCHEDULE_KEY: horizon_settings(cfg)}))  # and run length
    datamodule.trainer = trainer  # its world size: each rank on a node holding the images in RAM counts
    datamodule.setup("fit")  # read: bad files and empty splits fail here, before training starts
    train_batches = len(datamodule.train_dataloader())
    check_validation_interval(trainer, train_batches)
    with on_interrupt("during the compile warm-up, before the first training step: nothing to keep yet (what "
                      "was compiled is cached), run the same command again"):
        apply_speed_from_config(model, speed, cfg.trainer,  # compile (or its one-line fallback),
                                cfg.data.batch_size, train_batches)  # channels_last, Adam
    before = checkpoint_files(run_dir)
    if not is_worker_process():  # written once everything is checked: a refused run leaves the folder's as it was
        write_record(run_dir, record)
    if on_start is not None:
        on_start()
    fit(trainer, model, datamodule, ckpt_path, run_dir)
    ckpt = trainer.checkpoint_callback
    best = ckpt.best_model_score if ckpt is not None and ckpt.best_model_score is not None else None
    value = best if best is not None else trainer.callback_metrics.get(cfg.optimized_metric)
    metric = float(value) if value is not None else None  # None: no validation ran
    best_file = Path(ckpt.best_model_path).name if best is not None and ckpt.best_model_path else None
    if trainer.is_global_zero:  # the run's last line, once: not again by each DDP rank
        log.info("%s", outcome(cfg.optimized_metric, metric, run_dir, before, trainer, bool(cfg.get("evaluate_after")),
                               best_file))
    # the closed-loop suite on the best checkpoint (docs/evaluation.md), driven once: by rank 0, not by every
    # DDP rank into the same folder (the second refused there, or rank 0 itself)
    if cfg.get("evaluate_after") and not is_worker_process():
        success = evaluate_after_training(cfg, trainer, run_dir)["success"]
        if cfg.get("return_closed_loop"):
            return float(success)
    return metric if metric is not None else float("nan")


class RecordInCheckpoints(Callback):
    """The run's records in every checkpoint it saves, each under its key: the data record
    (``cicfw.data.provenance``), the split settings (``cicfw.train.split_record``), the run length the
    learning-rate schedule is spread over (``cicfw.train.schedule_record``), and the number of processes
    (``WORLD_SIZE_KEY``: each trains on batches of its own, so the samples seen count them all)."""

    def __init__(self, records: Mapping[str, Mapping[str, Any]]) -> None:
        self.records = {key: dict(record) for key, record in records.items()}

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        checkpoint.update(self.records)
        checkpoint[WORLD_SIZE_KEY] = int(trainer.world_size)


def data_record(cfg: DictConfig, data_path: str, run_dir: Path) -> tuple[dict[str, Any], bool]:
    """The record of the data this run trains on (its absolute path, its files' names, sizes and SHA-256:
    ``cicfw.data.provenance``), which ``train`` writes to ``<run_dir>/data.json`` once every check passed.
    Resuming (``ckpt_path``) compares it with the checkpoint's: another file set is refused, naming both,
    unless ``resume_on_other_data=true``; then, or when the same files lie in another folder, the record keeps
    the checkpoint's under ``before``. It holds
    the towns and weathers the data was collected in (``SETS_KEY``; a resume on the same files keeps the
    checkpoint's), so that an evaluation labels its table's columns from them, not from the metadata then.
    Also whether the run resumes on other files than the checkpoint trained on."""
    ckpt = cfg.get("ckpt_path")
    earlier = None
    if ckpt is not None and str(ckpt) != "":
        earlier = (folder_record(run_dir) if str(ckpt) in LIGHTNING_CKPT_NAMES
                   else checkpoint_record(Path(str(ckpt)).expanduser()))
    record = record_data(data_path, known=earlier)
    record[SETS_KEY] = recorded_sets(cfg.data)  # the suite's training columns, as the data says now
    if earlier is not None:
        if not cfg.get("resume_on_other_data"):
            check_same_data(earlier, record, "data.path", f"ckpt_path={ckpt}",
                            f"resume on the data it trained on (data.path={earlier['path']}), or add "
                            f"resume_on_other_data=true to go on training on this data on purpose")
        same = same_files(earlier, record)  # a record made before links counted once: compared as it was made
        if not same or not same_place(earlier["path"], record["path"]):
            log.info("resuming on %s; the checkpoint trained on %s (both are recorded in %s)", summary(record),
                     summary(earlier), run_dir / "data.json")
            record = with_earlier(record, earlier)
        elif earlier.get("before"):
            record["before"] = earlier["before"]
        if same and isinstance(earlier.get(SETS_KEY), dict):
            record[SETS_KEY] = earlier[SETS_KEY]  # the same files: what the data said when training started
    return record, earlier is not None and not same_files(earlier, record)


def checkpoint_files(run_dir: Path) -> dict[str, tuple[int, int]]:
    """The run's checkpoint files now: name -> (modification time in ns, size)."""
    folder = run_dir / "checkpoints"
    if not folder.is_dir():
        return {}
    return {p.name: (p.stat().st_mtime_ns, p.stat().st_size) for p in sorted(folder.glob("*.ckpt"))}


def outcome(metric_name: str, metric: float | None, run_dir: Path, before: Mapping[str, tuple[int, int]],
            trainer: L.Trainer, evaluate_after: bool = False, best_file: str | None = None) -> str:
    """The run's last line, saying what happened: the metric (None: no validation ran; NaN or inf: the
    validation ran and the model's steering is not finite), the best checkpoint it is of (``best_file``: it
    may be one an earlier run of a resumed one wrote) and the checkpoints this run wrote (or that it wrote
    none, and why when Lightning saves none)."""
    said = (f"{metric_name}: no value (no validation ran)" if metric is None else
            f"best {metric_name} = {metric:.4f} ({best_file})" if best_file and math.isfinite(metric) else
            f"{metric_name} = {metric:.4f}" if math.isfinite(metric) else
            f"{metric_name} = {metric} (validated, but the model steers NaN or inf: training diverged; lower "
            f"model.lr, or look for NaN or huge values in the data)")
    written = [name for name, stamp in checkpoint_files(run_dir).items() if before.get(name) != stamp]
    if written:
        return f"{said}; checkpoints written in {run_dir / 'checkpoints'}: {', '.join(written)}"
    why = " (trainer.fast_dev_run saves none)" if trainer.fast_dev_run else ""
    then = ("; evaluate_after saves the final weights as checkpoints/final.ckpt and drives them"
            if evaluate_after and not saved_checkpoint(trainer) else "")  # else an earlier run's, e.g. last.ckpt
    return f"{said}; no checkpoint written{why}{then}"


def check_validation_interval(trainer: L.Trainer, train_batches: int) -> None:
    """An integer ``trainer.val_check_interval`` beyond an epoch's training batches (after
    ``limit_train_batches``), refused as Lightning's fit loop refuses it, but before this run's records are
    written: Lightning checks it only inside ``fit``."""
    interval, limit = trainer.val_check_interval, trainer.limit_train_batches
    if not isinstance(interval, int) or isinstance(interval, bool) or trainer.check_val_every_n_epoch is None:
        return
    batches = min(train_batches, limit) if isinstance(limit, int) else int(train_batches * limit)
    if interval > batches:
        raise CicfwError(f"trainer.val_check_interval={interval} is more than the {batches} training batches of an "
                         f"epoch; give at most {batches}, a fraction of the epoch (e.g. 0.5), or "
                         f"trainer.check_val_every_n_epoch=null to count batches across epochs",
                         key="trainer.val_check_interval", value=interval)


def fit(trainer: L.Trainer, model: CICModule, datamodule: CILDataModule, ckpt_path: str | None, run_dir: Path) -> None:
    """``trainer.fit``; Lightning turns Ctrl-C into ``sys.exit(1)`` after its graceful shutdown, which
    becomes ``Interrupted`` naming the checkpoint to resume from."""
    try:  # trainer.val_check_interval against the epoch's batches: check_validation_interval, before the records
        trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path, **fit_kwargs())
    except SystemExit:
        if not trainer.interrupted:
            raise
        last = run_dir / "checkpoints" / "last.ckpt"
        if last.is_file():
            raise Interrupted(f"during training epoch {trainer.current_epoch + 1}: the finished epochs are kept in "
                              f"{last.parent}; resume with ckpt_path={last}") from None
        raise Interrupted("during the first training epoch: no epoch finished, nothing to keep; run the same "
                          "command again") from None


def _forget(run_dir: Path) -> None:
    """``forget_failed_run``, said in the log: a run stopped before its first checkpoint."""
    removed = forget_failed_run(run_dir)
    if removed:
        log.info("no checkpoint was written: removed this run's %s from %s, so that the same command runs there "
                 "again", ", ".join(removed), run_dir)


def train_in_folder(cfg: DictConfig, run_dir: Path, key: str = "hydra.run.dir") -> float:
    """The app's ``train``: ``run_dir`` held until it ends (``_train_held``), and a checkpoint with nothing
    left to train refused."""
    return _train_held(cfg, run_dir, key, refuse_finished=True)


def _train_held(cfg: DictConfig, run_dir: Path, key: str, refuse_finished: bool,
                on_start: Callable[[], Any] | None = None) -> float:
    """``_train`` with ``run_dir`` held (``hold_train_folder``) until it ends. A run refused before it trains
    leaves the folder as it found it (the app's run folder, ``key`` ``hydra.run.dir``: ``undo_run_folder``,
    no ``.hydra`` or empty log of a run that never was); a multirun job's folder keeps its log, which the
    sweep's failure line names. A run that stops before its first checkpoint (a full disk, Ctrl-C) takes
    back the metrics it logged (``forget_failed_run``), so the same command or call, which its error
    advises, runs there again."""
    hold_train_folder(run_dir, cfg.get("ckpt_path"), key, cfg)  # cfg: a requeued SLURM job's folder is its own
    started = []

    def start() -> None:
        started.append(True)
        if on_start is not None:
            on_start()

    try:
        return _train(cfg, run_dir, refuse_finished, start)
    except USER_ERRORS:
        if not started and key == "hydra.run.dir":
            release_run_folder(run_dir)
            undo_run_folder(run_dir)
        elif started:
            _forget(run_dir)
        raise
    except BaseException:
        if started:  # a Ctrl-C in the first epoch says "run the same command again" too
            _forget(run_dir)
        raise
    finally:
        release_run_folder(run_dir)


@hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="train")
@report_user_errors
def main(cfg: DictConfig) -> float:
    multirun = HydraConfig.get().mode == RunMode.MULTIRUN
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    return train_in_folder(cfg, Path(HydraConfig.get().runtime.output_dir), key)

