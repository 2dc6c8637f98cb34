"""Loading a cicfw checkpoint safely: the model it describes, rebuilt and checked.

Checkpoints are read with ``torch.load(weights_only=True)``: only tensors and plain containers are
ever unpickled, never an arbitrary class. The hyper-parameters saved by ``CICModule`` (registry names
and plain kwargs) rebuild its network, a ``SteeringNet``, as ``CICModule.load_from_checkpoint`` would,
after checking that every part it names is installed. Each way a checkpoint can be wrong is one clear
error.
"""
from __future__ import annotations

import hashlib
import inspect
import io
import json
import math
import os
import pickle
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Mapping

import torch
from omegaconf import OmegaConf
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from cicfw.core.errors import CicfwError, ConfigError
from cicfw.data.provenance import CHECKPOINT_KEY, folder_record, is_record
from cicfw.model.net import NET_DEFAULTS, NET_KEYS, PART_REGISTRIES, SteeringNet, build_part
from cicfw.model.speed import keep_fp32

#: the CICModule arguments that name registered parts, with the registry that must know each
PART_KEYS = ("encoder", "mixer", "head")
#: how many folders above a checkpoint's to look for its training run's ``.hydra/config.yaml``
RUN_CONFIG_LEVELS = 3


class CheckpointError(CicfwError):
    """A checkpoint that cannot be used; the message says why and what is accepted."""


@dataclass(frozen=True, eq=False)
class CheckpointBytes:
    """A checkpoint file's bytes, read once, with their SHA-256: what is hashed is what is loaded, whatever
    replaces the file meanwhile (a training run rewrites its ``last.ckpt`` each epoch). It pickles with its
    bytes, so a worker process given it builds the very weights that were hashed. ``str()`` is the path."""

    path: Path
    data: bytes = field(repr=False)
    sha256: str

    @classmethod
    def read(cls, path: str | Path, accepted: str = "a .ckpt file written by cicfw train, or its run folder"
             ) -> "CheckpointBytes":
        """The bytes of the file ``resolve_checkpoint(path, accepted)`` names, read in one pass."""
        p = resolve_checkpoint(path, accepted)
        data = p.read_bytes()
        return cls(p, data, hashlib.sha256(data).hexdigest())

    def open(self) -> IO[bytes]:
        """The bytes as a file object (for ``torch.load``, ``torch.jit.load``, ``zipfile``)."""
        return io.BytesIO(self.data)

    def __str__(self) -> str:
        return str(self.path)


#: the checkpoint key naming the best checkpoints of a run's earlier segments, on other data than it trains on
#: since (``resume_on_other_data``): their validation errors are not comparable with this data's, so no
#: picker of the run's best takes them (``BestCheckpoint`` in cicfw/train/app.py writes it)
SUPERSEDED_KEY = "cicfw_superseded_best"


def superseded_best(folder: Path) -> set[str]:
    """The names of the best checkpoints ``<folder>/last.ckpt`` says belong to a ranking a resume on other data
    ended (``SUPERSEDED_KEY``); none when it says none or cannot be read."""
    last = folder / "last.ckpt"
    names = _mapped(last).get(SUPERSEDED_KEY) if last.is_file() else None
    return {str(n) for n in names} if isinstance(names, (list, tuple)) else set()


#: the file that makes a folder a reproduction cell's (its ``epochs``: the final checkpoint's epoch)
CELL_FILE = "cell.json"
#: the name of a checkpoint ``keep_epoch_checkpoints`` kept (``epoch001.ckpt``), never a run's best
KEPT_EPOCH = re.compile(r"epoch\d{3,}\.ckpt")


def resolve_checkpoint(path: str | Path, accepted: str = "a .ckpt file written by cicfw train, or its run folder") -> Path:
    """The checkpoint file for ``path``: the file itself, or a training run folder holding exactly one
    best checkpoint (``last.ckpt``, kept ``epochNNN.ckpt`` and the best ones of segments before a resume on
    other data, which its ``last.ckpt`` names under ``SUPERSEDED_KEY``, aside) in its ``checkpoints/``, else its
    ``last.ckpt``; a folder without ``checkpoints/`` is searched below, and must hold one run's only. A
    reproduction cell's folder means the final weights its table drove (``train/checkpoints/epochNNN.ckpt`` of
    its last epoch, as its ``cell.json`` records it, else a ``last.ckpt`` of that epoch: ``cell_final``), never
    its best validation checkpoint.
    ``accepted``: what the caller takes, for the line refusing a missing path or a folder that holds no
    checkpoint."""
    p = Path(str(path)).expanduser()
    if (p / CELL_FILE).is_file():
        return cell_final(p, path).resolve()
    if p.is_dir():
        own = p / "checkpoints"
        # a run folder: its own checkpoints only, not those of a run trained in a folder inside it
        every = sorted(own.glob("*.ckpt")) if own.is_dir() else sorted(p.rglob("*.ckpt"))
        runs = sorted({f.parent for f in every})
        if len(runs) > 1:  # a folder above several runs: which one is meant is not ours to guess
            raise CheckpointError(
                f"checkpoint={str(path)!r} holds the checkpoints of {len(runs)} runs "
                f"({', '.join(str(r) for r in runs[:4])}{' ...' if len(runs) > 4 else ''}); give one run's "
                f"folder or one .ckpt file", key="checkpoint", value=path)
        # keep_epoch_checkpoints' epochNNN.ckpt are points on a learning curve, never chosen by validation: a
        # run without a best checkpoint means its last.ckpt, not the weights after some earlier epoch
        found = [f for f in every if f.name != "last.ckpt" and not KEPT_EPOCH.fullmatch(f.name)]
        if len(found) > 1 and len(runs) == 1:  # the best of segments before a resume on other data: not ranked
            old = superseded_best(runs[0])
            found = [f for f in found if f.name not in old] if old else found
        if len(found) == 1:
            return found[0].resolve()
        if not found and runs and (runs[0] / "last.ckpt").is_file():
            return (runs[0] / "last.ckpt").resolve()
        if not every:  # say what the folder holds instead (a folder of exported models, of data ...)
            held = sorted(f.name for f in p.iterdir())
            raise CheckpointError(f"checkpoint={str(path)!r} is a folder holding no .ckpt file ("
                                  f"{', '.join(held[:6]) + (' ...' if len(held) > 6 else '') or 'nothing'}); "
                                  f"give {accepted}", key="checkpoint", value=path)
        listing = ", ".join(str(f) for f in found[:8]) or "none"
        raise CheckpointError(
            f"checkpoint={str(path)!r} is a folder with {len(found)} .ckpt files besides last.ckpt and kept "
            f"epochNNN.ckpt ({listing}); "
            f"give one .ckpt file", key="checkpoint", value=path)
    if not p.is_file():  # named as given (a .pt, an .onnx ...), with what the caller accepts
        raise FileNotFoundError(f"checkpoint {str(path)!r} does not exist; give {accepted} "
                                f"(cicfw train writes outputs/<run>/checkpoints/*.ckpt)")
    return p.resolve()


def cell_final(folder: Path, given: str | Path | None = None) -> Path:
    """The final weights of a reproduction cell (``folder`` holding ``cell.json``): its
    ``train/checkpoints/epochNNN.ckpt`` of the epochs ``cell.json`` records, else its ``last.ckpt`` when that is the
    same epoch's (Lightning's ``epoch``, and ``global_step`` where the cell recorded its samples seen and batch size);
    else one ``CheckpointError`` naming the missing file: the best validation checkpoint is not what the table drove."""
    given = folder if given is None else given
    accepted = ("give the cell's folder with its final checkpoint, or a .ckpt file explicitly "
                "(e.g. one of its train/checkpoints/)")
    try:
        cell = json.loads((folder / CELL_FILE).read_text())
    except (OSError, ValueError) as err:
        raise CheckpointError(f"checkpoint={str(given)!r} is a reproduction cell whose {CELL_FILE} cannot be read "
                              f"({err}); {accepted}", key="checkpoint", value=str(given)) from None
    cell = cell if isinstance(cell, Mapping) else {}
    epochs = cell.get("epochs")
    if not isinstance(epochs, int) or isinstance(epochs, bool) or epochs < 1:
        raise CheckpointError(f"checkpoint={str(given)!r} is a reproduction cell whose {CELL_FILE} records no final "
                              f"epoch (epochs={epochs!r}, status={cell.get('status')!r}: a cell that did not finish); "
                              f"{accepted}", key="checkpoint", value=str(given))
    ckpts = folder / "train" / "checkpoints"
    final = ckpts / f"epoch{epochs:03d}.ckpt"
    if final.is_file():
        return final
    last = ckpts / "last.ckpt"
    why = "there is no last.ckpt either"
    if last.is_file():
        ck = _mapped(last)
        epoch, step = ck.get("epoch"), ck.get("global_step")
        recipe = cell.get("recipe") if isinstance(cell.get("recipe"), Mapping) else {}
        batch = recipe.get("data").get("batch_size") if isinstance(recipe.get("data"), Mapping) else None
        seen = cell.get("samples_seen")
        steps_known = all(isinstance(v, int) and not isinstance(v, bool) for v in (step, batch, seen))
        if isinstance(epoch, int) and epoch + 1 == epochs and (not steps_known or samples_seen(ck, batch) == seen):
            return last
        why = (f"its last.ckpt is not that epoch's (epoch {epoch + 1 if isinstance(epoch, int) else None}, "
               f"global step {step}"
               f"{f', {samples_seen(ck, batch)} samples seen, the cell saw {seen}' if steps_known else ''})")
    raise CheckpointError(f"checkpoint={str(given)!r} is a reproduction cell whose final checkpoint {final} (epoch "
                          f"{epochs}, as its {CELL_FILE} records) is missing and {why}; {accepted}",
                          key="checkpoint", value=str(given))


#: the checkpoint key of the number of processes (DDP ranks) that trained it, each on batches of its own
WORLD_SIZE_KEY = "cicfw_world_size"


def batches_trained(ck: Mapping[str, Any], accumulate: int = 1) -> int:
    """Training batches one process went through until ``ck`` was saved: Lightning's fit-loop progress (every
    batch counts, whether its step came then or after accumulating); for a checkpoint without it, ``global_step``
    x ``accumulate`` (the run's ``accumulate_grad_batches``)."""
    try:
        n = ck["loops"]["fit_loop"]["epoch_loop.batch_progress"]["total"]["processed"]
    except (KeyError, TypeError):
        n = None
    if isinstance(n, int) and not isinstance(n, bool):
        return n
    return int(ck.get("global_step", 0) or 0) * int(accumulate)


def samples_seen(ck: Mapping[str, Any], batch_size: int, accumulate: int = 1) -> int:
    """Training samples a run saw until checkpoint ``ck``: the batches each process went through
    (``batches_trained``) x ``batch_size`` x the processes (``WORLD_SIZE_KEY``, 1 when not recorded)."""
    world = ck.get(WORLD_SIZE_KEY)
    world = world if isinstance(world, int) and not isinstance(world, bool) and world > 0 else 1
    return batches_trained(ck, accumulate) * int(batch_size) * world


def is_torchscript(path: Path | CheckpointBytes) -> bool:
    """A TorchScript archive (``torch.jit.save``) rather than a checkpoint (``torch.save``): it holds code."""
    source = path.open() if isinstance(path, CheckpointBytes) else path
    if not zipfile.is_zipfile(source):
        return False
    with zipfile.ZipFile(source) as z:
        return any(n.split("/", 1)[-1].startswith("code/") for n in z.namelist())


def refuse_exported_model(path: Path | CheckpointBytes) -> None:
    """One line for a model ``cicfw export`` wrote (TorchScript, ONNX) given where a training checkpoint is
    needed (exporting, diagnosing: they rebuild the CICModule), naming the checkpoint its sidecar records;
    ``CheckpointBytes`` are judged by those bytes, not by what the file holds now."""
    read = path if isinstance(path, CheckpointBytes) else None
    p = Path(read.path if read else path)
    if (read is not None or p.is_file()) and is_torchscript(read or p):
        what = "an exported TorchScript model (cicfw export format=torchscript)"
    elif (read is not None or p.is_file()) and ".onnx" in (p.suffix.lower(), p.resolve().suffix.lower()):
        what = "an exported ONNX model (cicfw export format=onnx)"
    else:
        return
    try:  # the sidecar export writes beside the model names the checkpoint it came from
        source = json.loads(p.with_name(p.name + ".json").read_text())["checkpoint"]["path"]
        origin = f" (its sidecar names {str(source)!r})"
    except (OSError, ValueError, KeyError, TypeError):
        origin = ""
    raise CheckpointError(f"checkpoint={str(path)!r} is {what}, not a training checkpoint; give the .ckpt it was "
                          f"exported from{origin}, or any .ckpt written by cicfw train "
                          f"(outputs/<run>/checkpoints/*.ckpt) or its run folder", key="checkpoint", value=str(path))


class UnloadableCheckpoint(Exception):
    """``torch.load(weights_only=True)`` failed. ``code`` names the class or function the file would
    have had built (``exec``): it holds pickled code; None when the file is no torch checkpoint or is
    damaged. ``reason`` is torch's error in a few words."""

    def __init__(self, reason: str, code: str | None = None) -> None:
        super().__init__(reason)
        self.reason, self.code = reason, code


def load_weights_only(path: Path | CheckpointBytes) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU (of the bytes already read, for ``CheckpointBytes``):
    tensors and plain containers only, never an arbitrary class. Every failure (torch raises many types) is one
    ``UnloadableCheckpoint``; the callers word it for their own argument."""
    try:
        return torch.load(path.open() if isinstance(path, CheckpointBytes) else path, map_location="cpu",
                          weights_only=True)
    except Exception as err:
        code = re.search(r"GLOBAL ([\w.]+)", str(err)) if isinstance(err, pickle.UnpicklingError) else None
        if code:  # a class or function the safe unpickler will not build
            raise UnloadableCheckpoint(f"Unsupported global: GLOBAL {code.group(1)}", code.group(1)) from None
        raise UnloadableCheckpoint(_short_reason(err)) from None


def _short_reason(err: BaseException) -> str:
    """``Type: first sentence`` of torch's error (``Unsupported operand 110`` for a file that is no
    pickle: the rest of that message is advice about ``weights_only``)."""
    text = str(err).strip()
    if not text:
        return type(err).__name__
    found = re.search(r"Unsupported operand \d+", text)
    return f"{type(err).__name__}: {found.group(0) if found else text.splitlines()[0].split('. ')[0].rstrip('.')}"


def read_checkpoint(path: str | Path | CheckpointBytes) -> dict[str, Any]:
    """The checkpoint's dict, unpickled with ``weights_only=True``; errors for files that are not one.
    ``CheckpointBytes``: from those bytes, the file not read again."""
    read = path if isinstance(path, CheckpointBytes) else None
    p = read.path if read else resolve_checkpoint(path)
    refuse_exported_model(read or p)
    try:
        ckpt = load_weights_only(read or p)
    except UnloadableCheckpoint as err:
        if err.code:
            raise CheckpointError(
                f"checkpoint {str(p)!r} holds Python objects other than tensors and plain containers "
                f"({err.code}), so cicfw refuses to unpickle it (weights_only=True); cicfw checkpoints hold "
                f"only those", key="checkpoint", value=p) from None
        raise CheckpointError(f"{str(p)!r} is not a PyTorch checkpoint, or it is truncated ({err.reason})",
                              key="checkpoint", value=p) from None
    return check_cicfw_checkpoint(ckpt, str(p))


def checkpoint_record(path: str | os.PathLike | CheckpointBytes) -> dict[str, Any] | None:
    """The data record of a checkpoint (None when it has none: written before runs recorded their data, or
    not a cicfw checkpoint). The checkpoint is memory-mapped, so its weights are not read (``CheckpointBytes``:
    those bytes are unpickled)."""
    record = _mapped(path).get(CHECKPOINT_KEY)
    return dict(record) if is_record(record) else None


def recorded_data_paths(checkpoint: str | Path, run: str | Path | None = None) -> tuple[str | None, str | None]:
    """The data path ``checkpoint`` recorded and the one its run folder's ``data.json`` recorded (``run``, by
    default ``<run>/checkpoints/x.ckpt``'s), None for no record: a checkpoint copied into another run's
    folder names other data than the folder does."""
    theirs = folder_record(Path(checkpoint).parent.parent if run is None else run)
    return (checkpoint_record(checkpoint) or {}).get("path"), (theirs or {}).get("path")


#: the checkpoint key holding the data settings of its run's split and samples (``data.seed``, ``val_fraction``,
#: ``cameras`` ...: cicfw/train/split_record.py writes it)
SPLIT_KEY = "cicfw_split"


def checkpoint_split(path: str | os.PathLike) -> dict[str, Any]:
    """The data settings a checkpoint recorded for its split and samples ({} when it recorded none: written
    before checkpoints recorded them, or not a cicfw checkpoint), its weights not read."""
    split = _mapped(path).get(SPLIT_KEY)
    return dict(split) if isinstance(split, Mapping) else {}


def check_cicfw_checkpoint(ckpt: Any, where: str) -> dict[str, Any]:
    """Check ``ckpt`` is a cicfw CICModule checkpoint whose encoder, mixer and head are installed."""
    hp = ckpt.get("hyper_parameters") if isinstance(ckpt, Mapping) else None
    if not isinstance(hp, Mapping) or not isinstance(ckpt.get("state_dict"), Mapping) \
            or not all(isinstance(hp.get(k), str) for k in PART_KEYS):
        what = f"keys {sorted(map(str, ckpt))[:8]}" if isinstance(ckpt, Mapping) else type(ckpt).__name__
        raise CheckpointError(
            f"{where!r} is not a cicfw checkpoint: it needs Lightning's 'state_dict' and the CICModule "
            f"'hyper_parameters' naming an encoder, mixer and head (found {what}); checkpoints come from "
            f"cicfw train (outputs/<run>/checkpoints/*.ckpt)", key="checkpoint", value=where)
    for key in PART_KEYS:
        reg = PART_REGISTRIES[key]
        if hp[key] not in reg:
            raise CheckpointError(
                f"checkpoint {where!r} was trained with {key} {hp[key]!r}, which is not installed here; "
                f"installed {key}s: {', '.join(reg.names())} (install the plugin that provides {hp[key]!r})",
                key=key, value=hp[key])
    return dict(ckpt)


#: the hyper-parameters ``CICModule`` saves for training alone, with their defaults: driving reads none of them
#: (a test holds these and ``NET_KEYS`` to CICModule's signature)
TRAINING_DEFAULTS: dict[str, Any] = {"lr": 2e-4, "betas": (0.7, 0.85), "weight_decay": 0.0, "lr_schedule": "constant",
                                     "lr_final_factor": 0.0, "lr_warmup_fraction": 0.0, "ema_decay": 0.0}


class SavedHparams(dict):
    """A checkpoint's hyper-parameters, read as keys or as attributes (``hp.mixer``), as Lightning's ``hparams``."""

    def __getattr__(self, key: str) -> Any:
        try:
            return self[key]
        except KeyError:
            raise AttributeError(key) from None


def saved_hparams(hp: Mapping[str, Any], where: str) -> SavedHparams:
    """Every ``CICModule`` argument as the checkpoint's ``hyper_parameters`` give it, in the constructor's order:
    an argument saved before it existed takes its default, as does an ``lr_final_factor`` saved beside the
    constant schedule, which never read it (and once accepted any). A key ``CICModule`` does not take is one
    ``CheckpointError``."""
    unknown = sorted(str(k) for k in hp if k not in NET_KEYS and k not in TRAINING_DEFAULTS)
    if unknown:
        raise CheckpointError(f"checkpoint {where!r}: its hyper_parameters do not fit this cicfw's CICModule "
                              f"(unknown {', '.join(map(repr, unknown))}; it takes "
                              f"{', '.join([*NET_KEYS, *TRAINING_DEFAULTS])})", key="checkpoint", value=where)
    hp = dict(hp)
    if hp.get("lr_schedule", "constant") == "constant":
        hp.pop("lr_final_factor", None)
    return SavedHparams({**NET_DEFAULTS, **TRAINING_DEFAULTS, **hp})


#: what a part's constructor raises for a value it refuses (cicfw's ConfigError is a ValueError)
BUILD_ERRORS = (TypeError, ValueError, RuntimeError)


def model_from_hparams(hp: Mapping[str, Any], where: str) -> SteeringNet:
    """The ``SteeringNet`` a checkpoint's ``hyper_parameters`` describe (its weights not loaded), holding them all
    as ``hparams``. A value a part refuses is one ``CheckpointError`` naming its key (``head_kwargs.decode``)."""
    every = saved_hparams(hp, where)
    for part in PART_KEYS:
        kwargs = every[f"{part}_kwargs"]
        if kwargs is not None and not (isinstance(kwargs, Mapping) and all(isinstance(k, str) for k in kwargs)):
            raise CheckpointError(f"checkpoint {where!r}: its hyper_parameters.{part}_kwargs={kwargs!r} is not a "
                                  f"mapping of keyword names to values, as cicfw train saves it; a damaged or edited "
                                  f"file", key=f"{part}_kwargs", value=kwargs)
    try:
        model = SteeringNet(**{k: every[k] for k in NET_KEYS})
    except BUILD_ERRORS as err:
        raise unbuildable(every, where, err) from err
    model.hparams = every
    return model


def _keywords(cls: type) -> dict[str, Any]:
    """The keyword arguments ``cls`` takes, with their defaults (``inspect.Parameter.empty`` for none), following
    ``**kwargs`` passed on to a base class's ``__init__`` (a hybrid head's bins)."""
    found: dict[str, Any] = {}
    for c in cls.__mro__:
        init = c.__dict__.get("__init__")
        if init is None or c is object:
            continue
        try:
            params = list(inspect.signature(init).parameters.values())[1:]
        except (TypeError, ValueError):
            break
        for p in params:
            if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
                found.setdefault(p.name, p.default)
        if not any(p.kind is p.VAR_KEYWORD for p in params):
            break
    return found


def unbuildable(every: Mapping[str, Any], where: str, err: BaseException) -> CheckpointError:
    """The ``CheckpointError`` for hyper-parameters ``SteeringNet`` refused with ``err``: the part that refused is
    rebuilt alone, and the key of its kwargs that it refused found (by the error's own key or keyword, or as the
    one whose default lets the part build), so the line names the checkpoint, that key and what it accepts."""
    cause, culprit = err, None
    key = getattr(err, "key", None) or ""
    if isinstance(err, ConfigError) and key.startswith("model."):  # SteeringNet's own argument (speed_norm_kmh)
        name = key.split(".", 1)[1]
        return CheckpointError(f"checkpoint {where!r}: its hyper_parameters.{name}={err.value!r} is refused: it "
                               f"must be {err.accepted}; a damaged or edited file",
                               key=f"hyper_parameters.{name}", value=err.value)
    built: dict[str, Any] = {}

    def build(part: str, kwargs: Mapping[str, Any] | None) -> Any:  # as SteeringNet builds it
        widths = (built["encoder"].out_dim, built["head"].out_dim) if part == "mixer" else None
        return build_part(part, every[part], kwargs, widths)

    for part in ("encoder", "head", "mixer"):  # SteeringNet's order: the mixer needs both widths
        try:
            built[part] = build(part, every[f"{part}_kwargs"])
        except BUILD_ERRORS as e:
            culprit, cause = part, e
            break
    if culprit is None:  # the parts build alone: SteeringNet's joining of them refused
        return CheckpointError(f"checkpoint {where!r}: its hyper_parameters do not build a SteeringNet "
                               f"({type(err).__name__}: {' '.join(str(err).split())}); a damaged or edited file",
                               key="checkpoint", value=where)
    kwargs = dict(every[f"{culprit}_kwargs"] or {})
    label = f"{culprit} {every[culprit]!r}"
    takes = _keywords(PART_REGISTRIES[culprit].get(every[culprit]))
    if culprit == "mixer":  # SteeringNet gives these itself
        takes.pop("in_dim", None), takes.pop("out_dim", None)
    ckey = getattr(cause, "key", None) or ""
    name = None
    if isinstance(cause, ConfigError) and "." in ckey:
        name = ckey.split(".", 1)[1]
    elif isinstance(cause, TypeError):
        found = re.search(r"argument:? '(\w+)'", str(cause))
        name = found.group(1) if found else None
    if name is None:  # the one key whose default lets the part build
        for k in kwargs:
            try:
                build(culprit, {n: v for n, v in kwargs.items() if n != k})
            except BUILD_ERRORS:
                continue
            name = k
            break
    what = f"{culprit}_kwargs" + (f".{name}" if name else "")
    value = kwargs.get(name) if name else kwargs
    given = f"{what}={value!r}" if name is None or name in kwargs else f"{what} (not given)"
    if isinstance(cause, ConfigError):
        accepted = f"it must be {cause.accepted}"
    elif name is not None and name not in takes:
        accepted = f"a checkpoint gives {label} only {', '.join(takes) or 'no keyword arguments'}"
    else:
        default = takes.get(name, inspect.Parameter.empty) if name else inspect.Parameter.empty
        accepted = (f"{label} refuses it ({type(cause).__name__}: {' '.join(str(cause).split())})"
                    + (f"; its default is {default!r}" if default is not inspect.Parameter.empty else ""))
    return CheckpointError(f"checkpoint {where!r}: its hyper_parameters.{given} does not build {label}: {accepted}; "
                           f"a damaged or edited file", key=f"{what}", value=value)


def parts_label(hp: Mapping[str, Any]) -> str:
    """``encoder/mixer/head`` as hyper-parameters name them (``cil/independent/regression``; ``?`` for none)."""
    return "/".join(str(hp.get(k, "?")) for k in PART_KEYS)


def weights_misfit(want: Mapping[str, Any], got: Mapping[str, Any]) -> str | None:
    """How state_dict ``got`` fails a strict load into a model whose state_dict is ``want``: the counts of
    missing, unexpected and reshaped weights and the first of them (``1 missing, 0 unexpected, 0 reshaped
    weights, e.g. missing 'mixer.branches.3.6.bias'``); None when every key and shape fits. Resuming and
    loading a checkpoint both say it so, rather than torch's multi-line error."""
    missing = [k for k in want if k not in got]
    unexpected = [k for k in got if k not in want]
    reshaped = [k for k in want if k in got and hasattr(got[k], "shape") and hasattr(want[k], "shape")
                and tuple(got[k].shape) != tuple(want[k].shape)]
    if not (missing or unexpected or reshaped):
        return None
    if missing:
        example = f"missing {missing[0]!r}"
    elif unexpected:
        example = f"unexpected {unexpected[0]!r}"
    else:
        k = reshaped[0]
        example = f"{k!r} of shape {list(got[k].shape)}, the model's {list(want[k].shape)}"
    return (f"{len(missing)} missing, {len(unexpected)} unexpected, {len(reshaped)} reshaped weights, "
            f"e.g. {example}")


def load_model(path: str | Path | CheckpointBytes) -> SteeringNet:
    """The ``SteeringNet`` in eval mode rebuilt from a checkpoint (or the ``CheckpointBytes`` read from one), on
    the CPU: the network ``CICModule.load_from_checkpoint(path, weights_only=True)`` holds, after the checks above,
    without importing Lightning."""
    keep_fp32()  # it drives in the precision it was licensed in: no TF32 on a GPU
    ckpt = read_checkpoint(path)
    model = model_from_hparams(ckpt["hyper_parameters"], str(path))
    # cicfw saves plain keys even from a torch.compile'd run; a module compiled with the
    # torch.compile(model) wrapper elsewhere prefixes them with "_orig_mod.": the same weights, so a weight saved
    # both with and without it is two copies of one, one of which would silently replace the other
    state: dict[str, Any] = {}
    saved_as: dict[str, str] = {}
    twice = None
    for k, v in ckpt["state_dict"].items():
        plain = k.replace("_orig_mod.", "")
        if plain in saved_as and twice is None:
            twice = f"{plain!r} saved twice, as {saved_as[plain]!r} and {k!r} (with and without '_orig_mod.')"
        state[plain] = v
        saved_as.setdefault(plain, k)
    misfit = twice or weights_misfit(model.state_dict(), state)
    if misfit is None:
        try:
            model.load_state_dict(state, strict=True)
        except RuntimeError as err:  # keys and shapes fit, a value does not (no tensor): torch's words, one line
            misfit = " ".join(str(err).split())
    if misfit:
        raise CheckpointError(f"checkpoint {str(path)!r}: its weights do not fit the model its hyper_parameters "
                              f"describe (encoder/mixer/head {parts_label(ckpt['hyper_parameters'])}), a damaged "
                              f"or edited file: {misfit}", key="checkpoint", value=str(path))
    # a diverged run saves NaN weights: refused here, not as a NaN steer in the middle of a suite or export
    bad = next((k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()), None)
    if bad is not None:
        raise CheckpointError(f"checkpoint {str(path)!r}: its weights hold NaN or inf (first in {bad!r}): the run "
                              f"that wrote it diverged; retrain it (a lower model.lr)", key="checkpoint", value=str(path))
    return model.eval()


def prepare_for_inference(model, fuse: bool = True):
    """Make an eval-mode model cheaper to run, computing the same function (up to float rounding):
    each BatchNorm2d is folded into the Conv2d before it, and it and each Dropout (the identity in eval)
    become ``nn.Identity`` in place, so a Sequential keeps its indices (cross_stitch and sluice slice
    their branches by index); the weights go to the NHWC layout (``use_channels_last``). Done in place;
    returns the model."""
    if not fuse:
        return model

    assert not model.training, "prepare_for_inference needs an eval-mode model"
    dropouts = (nn.Dropout, nn.Dropout1d, nn.Dropout2d, nn.Dropout3d)
    for seq in [m for m in model.modules() if isinstance(m, nn.Sequential)]:
        names, kids = list(seq._modules), list(seq.children())
        for i, mod in enumerate(kids):
            if isinstance(mod, nn.Conv2d) and i + 1 < len(kids) and isinstance(kids[i + 1], nn.BatchNorm2d):
                seq._modules[names[i]] = fuse_conv_bn_eval(mod, kids[i + 1])
                seq._modules[names[i + 1]] = nn.Identity()
            elif isinstance(mod, dropouts):
                seq._modules[names[i]] = nn.Identity()
    if hasattr(model, "use_channels_last"):
        model.use_channels_last()
    return model


def decoder_info(head: nn.Module, name: str) -> dict[str, Any]:
    """How the head's output becomes steering, in words and numbers (the sidecar's ``decoder``)."""
    mode = getattr(head, "decode_mode", None)
    if mode is not None and getattr(head, "bins", None) is not None:
        mids = [round(float(m), 6) for m in head.bins.midpoints]
        what = ("the expectation: softmax scores times the bin midpoints" if mode == "expectation"
                else "the midpoint of the argmax bin")
        return {"head": name, "decode": mode, "bin_midpoints": mids, "description": what}
    if hasattr(head, "max_phase"):
        return {"head": name, "decode": "phase", "n_units": int(head.out_dim),
                "phase_range": round(float(head.max_phase) / math.pi, 12),
                "description": "the phase of the output wave (atan2 of its projections on cos and sin) / "
                               "(phase_range * pi), clamped to [-1, 1]"}
    if name == "regression":
        return {"head": name, "decode": "identity", "description": "the single output, clamped to [-1, 1]"}
    return {"head": name, "decode": type(head).__name__ + ".decode", "description": "the head's own decode()"}


def describe(hp: Mapping[str, Any]) -> str:
    """A short model label from hyper-parameters, e.g. ``gtu+regression``, ``independent+hybrid/expectation``
    (a classification head's decoder is part of the label: it changes how the model steers)."""
    decode = (hp.get("head_kwargs") or {}).get("decode")
    return f"{hp.get('mixer')}+{hp.get('head')}" + (f"/{decode}" if decode else "")


def config_parts_differ(cfg: Mapping[str, Any], hp: Mapping[str, Any]) -> str | None:
    """How a training run's saved config names other parts than a checkpoint's hyper-parameters (e.g.
    ``mixer independent, checkpoint gtu``), or None when they agree or the config names no parts (a
    reproduce cell's). A checkpoint copied into another run's folder would otherwise borrow that run's
    config: its row, its data split."""
    differ = []
    for part in ("encoder", "mixer", "head"):
        node = cfg.get(part)
        name = node.get("name") if isinstance(node, Mapping) else None
        if name is not None and hp.get(part) is not None and str(name) != str(hp[part]):
            differ.append(f"{part} {name}, checkpoint {hp[part]}")
    return "; ".join(differ) or None


def run_config_files(checkpoint: Path) -> list[Path]:
    """Every ``.hydra/config.yaml`` at most ``RUN_CONFIG_LEVELS`` folders above ``checkpoint``, nearest first:
    the saved config of the ``cicfw train`` run or ``cicfw reproduce`` cell that wrote it, and those around it."""
    folders = [checkpoint.parent, *checkpoint.parent.parents][:RUN_CONFIG_LEVELS + 1]
    return [f / ".hydra" / "config.yaml" for f in folders if (f / ".hydra" / "config.yaml").is_file()]


def where_it_ran(path: Any, config_file: Path) -> Any:
    """A relative ``data.path`` of a run's saved config (``config_file``), made absolute against the directory
    the run was started from (``hydra.runtime.cwd`` in the ``hydra.yaml`` beside it), not the one reading it;
    as it is where that is not recorded. (A run that recorded its data, ``cicfw.data.provenance``, gives the
    absolute path itself.)"""
    if not isinstance(path, str) or os.path.isabs(os.path.expanduser(path)):
        return path
    try:
        cwd = OmegaConf.select(OmegaConf.load(config_file.parent / "hydra.yaml"), "hydra.runtime.cwd")
    except Exception:
        return path
    return os.path.join(str(cwd), path) if cwd else path


def checkpoint_hyper_parameters(path: str | Path) -> dict[str, Any]:
    """A checkpoint's hyper-parameters ({} when it has none or is unreadable), memory-mapped: the weights are
    not read."""
    hp = _mapped(path).get("hyper_parameters")
    return dict(hp) if isinstance(hp, Mapping) else {}


def _mapped(path: str | os.PathLike | CheckpointBytes) -> dict[str, Any]:
    """The checkpoint at ``path`` memory-mapped where it can be (its weights not read), loaded otherwise
    (``CheckpointBytes``: from those bytes); {} when it is unreadable or not a dict."""
    if isinstance(path, CheckpointBytes):
        try:
            ckpt = load_weights_only(path)
        except UnloadableCheckpoint:
            return {}
        return ckpt if isinstance(ckpt, dict) else {}
    for mmap in (True, False):
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
            return ckpt if isinstance(ckpt, dict) else {}
        except Exception:
            continue
    return {}
