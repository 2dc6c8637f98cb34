"""``python -m cicfw.export``: a checkpoint's whole driving function as one ONNX or TorchScript graph.

    python -m cicfw.export checkpoint=outputs/<run>/checkpoints/<best>.ckpt format=onnx out=cil.onnx
    cicfw export checkpoint=<run folder> format=torchscript out=cil.pt

The graph is ``cicfw.export.agent.DrivingFunction``: uint8 RGB frames (B, 88, 200, 3), speed km/h (B,), CIL
command code (B,) 2-5 -> steering (B,) in [-1, 1], with the normalisation, the command's branch and the
head's decoder inside, and a dynamic batch. Before anything is written the exported graph is run by
its own runtime (onnxruntime, torch.jit) on real frames and random inputs, at batch 1 and batch 2n,
and compared with the checkpoint's ``CICModule.predict_steer``; a model off by more than ``tolerance``
is refused with one line naming the input. The model (its description inside: ONNX metadata, a
TorchScript extra file) and a sidecar ``<out>.json`` are written under temporary names, then renamed.
``cicfw.export.agent.Agent.load(out)`` drives it; docs/deploy.md shows how to drive it without cicfw.
"""
from __future__ import annotations

import copy
import glob
import hashlib
import io
import json
import logging
import os
import re
import sys
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

import cicfw
from cicfw.export.agent import (COMMAND_CODES, IMAGE_SHAPE, INPUT_NAMES, METADATA_KEY, OUTPUT_NAME, DrivingFunction,
                                onnx_runner, onnx_session, torch_runner)
from cicfw.core.config_checks import is_integer, is_number
from cicfw.core.errors import CicfwError, report_user_errors
from cicfw.core.files import write_together
from cicfw.core.json_files import read_json
from cicfw.core.run_folder import enclosing_run
from cicfw.data.cil_hdf5 import CILFormatError, T, check_file, find_files, read_rgb, read_targets
from cicfw.data.frames import META_NAME
from cicfw.data.provenance import SETS_KEY
from cicfw.model.checkpoint import (CheckpointBytes, checkpoint_record, config_parts_differ, decoder_info, describe,
                                    load_model, prepare_for_inference, recorded_data_paths, refuse_exported_model,
                                    resolve_checkpoint, run_config_files, where_it_ran)
from cicfw.registry import ENCODERS, HEADS, MIXERS
from cicfw.sim.backends import EmbeddedBackend
from cicfw.sim.env import get_renderer

log = logging.getLogger("cicfw.export")

#: format -> the file suffix it writes (``out`` must end in it; the default ``out`` gets it)
FORMATS = {"onnx": ".onnx", "torchscript": ".pt"}
#: steering difference the parity check accepts (steering lives in [-1, 1]; float32 rounding is ~1e-6)
TOLERANCE = 1e-4
#: an argmax decoder may pick either bin when the checkpoint's two best logits are this close (a tie in
#: float rounding, not an export error)
TIE_MARGIN = 1e-4
#: the ONNX opset used when none is given
DEFAULT_OPSET = 17


class ExportError(CicfwError):
    """An export that cannot be done or failed its parity check; the message says why, in one line."""


# ---- inputs for the parity check ----------------------------------------------------------------
@dataclass
class CheckInputs:
    """A batch for the parity check: frames, speeds, command codes, and a name for each row."""

    images: np.ndarray  # (N, 88, 200, 3) uint8 RGB
    speed_kmh: np.ndarray  # (N,) float32
    command: np.ndarray  # (N,) int64, CIL codes 2-5
    names: list[str]

    def __len__(self) -> int:
        return len(self.command)

    def __add__(self, other: "CheckInputs") -> "CheckInputs":
        return CheckInputs(np.concatenate([self.images, other.images]), np.concatenate([self.speed_kmh, other.speed_kmh]),
                           np.concatenate([self.command, other.command]), self.names + other.names)


def enough_frames(n: int, held: int, where: str, instead: str) -> None:
    """``n_frames`` real frames or none: more than ``where`` holds (``held``) is refused in one line, where the
    check would otherwise run on fewer (or repeated) real frames than docs/deploy.md promises."""
    if n > held:
        raise ExportError(f"n_frames={n} asks for more real frames than {where} holds ({held}); give "
                          f"n_frames={held} or fewer{instead}", key="n_frames", value=n)


def rendered_frames(n: int, town: str = "town_a", weather: str = "ClearNoon") -> CheckInputs:
    """``n`` centre-camera frames of the embedded simulator's expert driving the training town's first
    left-turn and first right-turn single-turn routes (follow lane, then the turn), evenly spaced over
    both episodes, with their speeds and commands: real frames under every turn command, without a
    dataset on disk. Deterministic."""
    backend = EmbeddedBackend()
    routes = backend.single_turn_routes(town)
    frames, names = [], []
    for code in (3, 4):  # left, right: driven without pictures, so n_frames is checked before any is drawn
        route = next(r for r in routes if code in np.asarray(r.commands))
        env = backend.make_env(town, route, weather, cameras=("centre",), renderer=False)
        obs, step = env.reset(), 0
        while True:
            frames.append(obs)
            names.append(f"real frame {step} of the embedded simulator ({town}, {weather}, route {route.name!r})")
            if env.done:
                break
            steer, v = env.expert_action()
            obs, _, _ = env.step(steer, target_speed_kmh=v)
            step += 1
    enough_frames(n, len(frames), f"the embedded simulator's two rendered episodes ({town})",
                  ", or frames=<a CIL HDF5 file or folder>")
    pick = np.linspace(0, len(frames) - 1, n).round().astype(int)
    renderer = get_renderer(env.town, env.weather, env.seed, env.cameras)  # the one make_env would have drawn with
    return CheckInputs(np.stack([renderer.render(*frames[i]["pose"], frames[i]["t"])["centre"] for i in pick]),
                       np.array([frames[i]["speed_kmh"] for i in pick], np.float32),
                       np.array([frames[i]["command"] for i in pick], np.int64), [names[i] for i in pick])


def frame_files(path: str | Path) -> list[Path]:
    """The CIL HDF5 files ``frames=`` names (a file, a folder or a glob), each checked as training checks
    its data (``check_file``), with no sample among them: else one ``ExportError`` naming ``frames=``."""
    try:
        files = find_files(path)
    except FileNotFoundError:
        raise ExportError(f"frames={str(path)!r} matches no HDF5 file; give a CIL HDF5 file, a folder that holds "
                          f"*.h5 / *.hdf5 files (searched recursively) or a glob, or leave frames out (frames "
                          f"rendered by the embedded simulator)", key="frames", value=path) from None
    try:
        n = sum(check_file(f).n for f in files)
    except CILFormatError as err:
        raise ExportError(f"frames={str(path)!r} is not CIL data: {err}", key="frames", value=path) from None
    if n == 0:
        raise ExportError(f"frames={str(path)!r} holds no frame (its {len(files)} HDF5 file(s) are empty); "
                          f"give CIL data with frames, or leave frames out", key="frames", value=path)
    return files


def dataset_frames(path: str | Path, n: int) -> CheckInputs:
    """``n`` frames of a CIL HDF5 file or folder (centre camera where the files say which), evenly spaced
    over its first file(s), with their speeds and commands."""
    files = frame_files(path)  # a folder, a file or a glob; an error naming frames= when it holds no data
    images, targets, names = [], [], []
    for f in files:
        t = read_targets(f)
        rows = np.flatnonzero(t[:, T.CAMERA_ID] == 0) if np.any(t[:, T.CAMERA_ID] == 0) else np.arange(len(t))
        rgb = read_rgb(f)
        images.append(rgb[rows])
        targets.append(t[rows])
        names += [f"real frame {r} of {f}" for r in rows]
        if sum(len(t) for t in targets) >= 4 * n:
            break
    rgb, t = np.concatenate(images), np.concatenate(targets)
    enough_frames(n, len(t), f"frames={str(path)!r}", ", or frames with more of them")
    pick = np.linspace(0, len(t) - 1, n).round().astype(int)
    bad = [i for i in pick if t[i, T.COMMAND] not in COMMAND_CODES]  # the model has no branch for it
    if bad:
        codes = ", ".join(f"{k} {v}" for k, v in COMMAND_CODES.items())
        raise ExportError(f"frames={str(path)!r}: {names[bad[0]]} has command code {t[bad[0], T.COMMAND]:g}, which is "
                          f"not a CIL command ({codes}); give CIL data, or leave frames out (frames rendered by the "
                          f"embedded simulator)", key="frames", value=path)
    return CheckInputs(rgb[pick], t[pick, T.SPEED].astype(np.float32), t[pick, T.COMMAND].astype(np.int64),
                       [names[i] for i in pick])


def random_inputs(n: int, seed: int = 0) -> CheckInputs:
    """``n`` random frames (uniform pixels), speeds in [0, 60) km/h and command codes, every command present."""
    rng = np.random.default_rng(seed)
    codes = np.array(list(COMMAND_CODES), np.int64)
    return CheckInputs(rng.integers(0, 256, (n, *IMAGE_SHAPE), dtype=np.uint8),
                       rng.uniform(0, 60, n).astype(np.float32), np.resize(codes, n),
                       [f"random input {i} (seed {seed})" for i in range(n)])


# ---- the graph ---------------------------------------------------------------------------------
def graph_module(model: torch.nn.Module) -> torch.nn.Module:
    """The module that is exported: the driving function of an inference-prepared copy of ``model``."""
    return DrivingFunction(prepare_for_inference(copy.deepcopy(model))).eval()


@contextmanager
def _tracing(module: torch.nn.Module, onnx: bool) -> Iterator[None]:
    """Tracing switches: Lightning's own (``to_torchscript``'s) so tracing may read a LightningModule
    without a Trainer, and for ONNX the MultiheadAttention fast path off (its fused kernel has no ONNX
    form; the decomposed attention computes the same), tracer warnings muted."""
    lightning = [m for m in module.modules() if hasattr(type(m), "_jit_is_scripting")]
    fast = torch.backends.mha.get_fastpath_enabled()
    for m in lightning:
        m._jit_is_scripting = True
    if onnx:
        torch.backends.mha.set_fastpath_enabled(False)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        torch.backends.mha.set_fastpath_enabled(fast)
        for m in lightning:
            m._jit_is_scripting = False


@contextmanager
def _stdout_muted() -> Iterator[None]:
    """File descriptor 1 to /dev/null: the legacy ONNX exporter prints its whole graph from C++ on a failure,
    and a failure here is one line."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _example(inputs: CheckInputs, n: int = 2) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return (torch.from_numpy(inputs.images[:n]), torch.from_numpy(inputs.speed_kmh[:n]),
            torch.from_numpy(inputs.command[:n]))


def to_onnx(module: torch.nn.Module, example: tuple, metadata: str, opset: int = DEFAULT_OPSET) -> bytes:
    """The ONNX bytes of ``module`` (legacy TorchScript-based exporter: no extra packages), dynamic batch,
    ``metadata`` under the key ``cicfw.json``."""
    import onnx

    buf = io.BytesIO()
    batch = {0: "batch"}
    with _tracing(module, onnx=True), torch.no_grad(), _stdout_muted():
        torch.onnx.export(module, example, buf, dynamo=False, opset_version=opset, input_names=list(INPUT_NAMES),
                          output_names=[OUTPUT_NAME], dynamic_axes={k: batch for k in (*INPUT_NAMES, OUTPUT_NAME)},
                          do_constant_folding=True)
    proto = onnx.load_from_string(buf.getvalue())
    proto.metadata_props.add(key=METADATA_KEY, value=metadata)
    proto.producer_name = "cicfw export"
    return proto.SerializeToString()


def to_torchscript(module: torch.nn.Module, example: tuple, metadata: str) -> bytes:
    """The TorchScript bytes of ``module`` (traced; the batch size stays dynamic), ``metadata`` as the
    extra file ``cicfw.json``."""
    with _tracing(module, onnx=False), torch.no_grad():
        traced = torch.jit.trace(module, example, check_trace=False)
    buf = io.BytesIO()
    torch.jit.save(traced, buf, _extra_files={METADATA_KEY: metadata})
    return buf.getvalue()


def runner(fmt: str, data: bytes) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """A function running exported ``data`` in its own runtime: onnxruntime, or torch.jit.load."""
    if fmt == "onnx":
        return onnx_runner(onnx_session(data))
    return torch_runner(torch.jit.load(io.BytesIO(data), map_location="cpu").eval(), torch.device("cpu"))


# ---- parity ------------------------------------------------------------------------------------
def reference_steer(model: torch.nn.Module, inputs: CheckInputs) -> tuple[np.ndarray, np.ndarray]:
    """The checkpoint's own steering, ``CICModule.predict_steer`` in eval mode, clamped to [-1, 1] as the
    suite steers; and per row whether its decoder sits on a tie (an argmax head whose two best logits
    are within ``TIE_MARGIN``: float rounding may pick either bin there)."""
    image = torch.from_numpy(inputs.images).permute(0, 3, 1, 2)
    speed, branch = torch.from_numpy(inputs.speed_kmh), torch.from_numpy(inputs.command - 2)
    with torch.inference_mode():
        steer = model.predict_steer(image, speed, branch).float().clamp(-1.0, 1.0).numpy()
        tie = np.zeros(len(inputs), bool)
        if getattr(model.head, "decode_mode", None) == "argmax":
            top2 = model(image, speed, branch).topk(2, dim=-1).values
            tie = (top2[:, 0] - top2[:, 1]).numpy() < TIE_MARGIN
    return steer, tie


def parity(run: Callable, model: torch.nn.Module, inputs: CheckInputs, tolerance: float = TOLERANCE,
           batches: tuple[int, ...] | None = None) -> float:
    """Run the exported model on ``inputs`` in chunks of each size in ``batches`` (default: 1 and all)
    and compare with the checkpoint; the largest difference, or an ``ExportError`` naming the worst input."""
    want, tie = reference_steer(model, inputs)
    worst = 0.0
    for b in batches or (1, len(inputs)):
        got = np.concatenate([np.asarray(run(inputs.images[i:i + b], inputs.speed_kmh[i:i + b],
                                             inputs.command[i:i + b])).reshape(-1)
                              for i in range(0, len(inputs), b)])
        diff = np.where(tie, 0.0, np.abs(got.astype(np.float64) - want))
        diff[~np.isfinite(got)] = np.inf
        k = int(np.argmax(diff))
        if diff[k] > tolerance:
            code = int(inputs.command[k])
            raise ExportError(
                f"the exported model fails the parity check, so nothing was written: on {inputs.names[k]} "
                f"(command {code} {COMMAND_CODES.get(code, '?')}, {inputs.speed_kmh[k]:.1f} km/h, batch {b}) it "
                f"steers {got[k]:+.4f} where the checkpoint steers {want[k]:+.4f} (off by {diff[k]:.2g}; "
                f"tolerance {tolerance:g})")
        worst = max(worst, float(diff.max()))
    return worst


# ---- what is written ---------------------------------------------------------------------------
def _jsonable(obj: Any) -> Any:
    return json.loads(json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def run_config(checkpoint: Path) -> tuple[dict[str, Any] | None, Path | None]:
    """The training run's saved config (the nearest of ``run_config_files``), unresolved interpolations left as
    written; (None, None) when there is none."""
    path = next(iter(run_config_files(checkpoint)), None)
    try:
        return (None, None) if path is None else (OmegaConf.to_container(OmegaConf.load(path), resolve=False), path)
    except Exception:
        return None, path


def other_run(cfg: dict[str, Any], cfg_path: Path, hp: dict[str, Any], checkpoint: Path) -> str | None:
    """How the run config found beside ``checkpoint`` is another run's (a checkpoint copied into its folder):
    other parts, or other data than the checkpoint recorded (its run's ``data.json``); None when it is its own."""
    differ = config_parts_differ(cfg, hp)
    own, theirs = recorded_data_paths(checkpoint, cfg_path.parent.parent)
    return differ or (f"data {theirs}, checkpoint {own}" if own and theirs and own != theirs else None)


def training_dataset(checkpoint: CheckpointBytes, cfg_path: Path | None) -> dict[str, Any]:
    """The data the model trained on, as its checkpoint recorded it (``cicfw.data.provenance``: the
    absolute path, the number of files and the hash of their names, sizes and SHA-256, whatever the folder
    holds now, and the towns and weathers it was collected in when training started: an evaluation's training
    columns); for a checkpoint written before runs recorded their data, ``dataset_hash`` of its run config."""
    record = checkpoint_record(checkpoint)
    if record is None:
        return dataset_hash(cfg_path)
    out = {"path": record["path"], "hash": record.get("hash"), "hash_of": record.get("hash_of"),
           "files": record.get("n_files", len(record["files"])), "bytes": record.get("bytes"),
           "collect_config_hash": record.get("collect_config_hash"), SETS_KEY: record.get(SETS_KEY),
           "from": "the checkpoint's record of its data"}
    if record.get("before"):  # resumed on other data on purpose: what it trained on before
        out["before"] = [{"path": b.get("path"), "hash": b.get("hash"), "files": b.get("n_files"),
                          SETS_KEY: b.get(SETS_KEY)} for b in record["before"]]
    return out


def dataset_hash(cfg_path: Path | None) -> dict[str, Any]:
    """The training dataset of the run config at ``cfg_path``: its path (a relative one read against the
    directory the run started in, ``hydra.runtime.cwd``) and a hash of its files' names and sizes
    (``cicfw reproduce``'s ``config_hash``), with the collector's own config hash when it wrote one."""
    if cfg_path is None:
        return {"path": None, "hash": None, "why": "no training run config (.hydra/config.yaml) beside the checkpoint"}
    try:
        raw = OmegaConf.select(OmegaConf.load(cfg_path), "data.path", throw_on_resolution_failure=True)
    except Exception as err:
        return {"path": None, "hash": None, "why": f"data.path in {cfg_path} does not resolve here ({err})"}
    if not raw:
        return {"path": None, "hash": None, "why": f"{cfg_path} names no data.path"}
    p = Path(where_it_ran(str(raw), cfg_path)).expanduser()
    if not p.is_absolute():
        return {"path": str(p), "hash": None, "why": f"data.path in {cfg_path} is relative to a directory the run "
                                                     f"did not record"}
    files = (sorted(p.rglob("*.h5")) + sorted(p.rglob("*.hdf5")) if p.is_dir()
             else sorted(Path(q) for q in glob.glob(str(p), recursive=True)))
    if not files:
        return {"path": str(p), "hash": None, "why": "the dataset is not on this machine"}
    chash = hashlib.sha256("".join(f"{f.name}:{f.stat().st_size}" for f in files).encode()).hexdigest()[:16]
    meta_file = (p if p.is_dir() else p.parent) / META_NAME
    meta = read_json(meta_file, default={})  # a record that is no object (null) carries no collector hash
    return {"path": str(p), "hash": chash, "hash_of": "file names and sizes", "files": len(files),
            "collect_config_hash": meta.get("config_hash") if isinstance(meta, dict) else None}


def describe_model(model: torch.nn.Module, read: CheckpointBytes, fmt: str, opset: int | None) -> dict[str, Any]:
    """The exported model's description: what it is, its inputs and output, its decoder, its provenance
    (``read``: the bytes ``model`` was built from, hashed and read for its data record)."""
    checkpoint = read.path
    hp = _jsonable(dict(model.hparams))
    cfg, cfg_path = run_config(checkpoint)
    if cfg is not None and (differ := other_run(cfg, cfg_path, hp, checkpoint)):  # not this model's folder
        log.warning("%s is not the config of %s (%s); the sidecar's row_config is left null", cfg_path,
                    checkpoint, differ)
        cfg, cfg_path = None, None
    row = None
    if cfg is not None:
        row = {k: cfg.get(k) for k in ("experiment", "encoder", "mixer", "head", "model", "seed") if k in cfg}
        if "cell" in cfg:  # a cicfw reproduce cell: its row and seed
            row["cell"] = cfg["cell"]
    h, w, c = IMAGE_SHAPE
    return {
        "format": fmt, "opset": opset, "cicfw_version": cicfw.__version__, "torch_version": torch.__version__,
        "label": describe(hp), "encoder": hp["encoder"], "mixer": hp["mixer"], "head": hp["head"],
        "hyper_parameters": hp, "row_config": row, "run_config_file": str(cfg_path) if cfg_path else None,
        "inputs": [
            {"name": "images", "dtype": "uint8", "shape": ["batch", h, w, c], "layout": "NHWC, RGB, 0-255",
             "camera": "centre (CIL's crop of the camera image resized to 200x88, as cicfw's cameras deliver it)"},
            {"name": "speed_kmh", "dtype": "float32", "shape": ["batch"], "unit": "km/h"},
            {"name": "command", "dtype": "int64", "shape": ["batch"], "codes": {str(k): v for k, v in COMMAND_CODES.items()},
             "note": "CIL command code; the branch is code - 2"},
        ],
        "output": {"name": OUTPUT_NAME, "dtype": "float32", "shape": ["batch"], "range": [-1.0, 1.0],
                   "convention": "steering, positive = right (CARLA's)"},
        "normalisation": {"pixels": "/ 255", "speed": f"speed_kmh / {float(model.speed_norm_kmh):g}"},
        "command_codes": {str(k): v for k, v in COMMAND_CODES.items()},
        "decoder": decoder_info(model.head, hp["head"]),
        "checkpoint": {"path": str(checkpoint), "sha256": read.sha256},
        "training_dataset": training_dataset(read, cfg_path),
    }


def write_files(files: Mapping[Path, bytes], new: Iterable[Path] = ()) -> None:
    """Write each file under a temporary name (fsynced), then rename them all, in order
    (``cicfw.core.files.write_together``): a failure while writing (a full disk, a folder that turns out
    read-only) leaves nothing behind. ``new``: names that were free when the export checked ``out``, only
    created, never replaced: one another process wrote meanwhile (a second export to the same ``out``) is
    one line, and this export's files are gone again."""
    try:
        write_together(files, fsync=True, new=new)
    except FileExistsError as err:
        raise ExportError(f"out: {err.filename!r} was written by another process while this export ran (another "
                          f"export to the same out?), and is left as it is; nothing of this export was written: "
                          f"give out=<another file>", key="out", value=err.filename) from None
    except OSError as err:
        raise ExportError(f"cannot write {err.filename!r}: {err.strerror or err}; "
                          f"nothing was written; give out=<a file in a writable folder with room>", key="out",
                          value=err.filename) from None


def output_path(out: str | None, checkpoint: Path, fmt: str) -> Path:
    """Where the model goes (default: beside the checkpoint, its name with the format's suffix), after
    checking its folder can be written."""
    p = Path(str(out)).expanduser() if out else checkpoint.with_suffix(FORMATS[fmt])
    if p.is_dir():
        raise ExportError(f"out={str(p)!r} is a folder; give out=<a file name>, e.g. out={str(p / ('model' + FORMATS[fmt]))}",
                          key="out", value=p)
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise ExportError(f"out={str(p)!r} cannot be written: the folder {str(folder)!r} does not exist; create it "
                          f"or give out=<a file in a writable folder>", key="out", value=p)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ExportError(f"out={str(p)!r} cannot be written: the folder {str(folder)!r} is not writable; give "
                          f"out=<a file in a writable folder>", key="out", value=p)
    return p


def check_out_suffix(out: str | None, fmt: str) -> None:
    """``out`` must end in the suffix of ``fmt`` (an ONNX graph named ``x.pt`` would be loaded as TorchScript
    by ``Agent.load``, and the other way round): one line naming both formats' suffixes."""
    if not out:
        return
    suffix = Path(str(out)).suffix
    if suffix != FORMATS[fmt]:
        each = ", ".join(f"format={f} writes {s}" for f, s in FORMATS.items())
        raise ExportError(f"out={str(out)!r} ends in {suffix or 'no suffix'!r}, but format={fmt} writes a "
                          f"{FORMATS[fmt]} file ({each}); give out=<name>{FORMATS[fmt]} or the format that fits",
                          key="out", value=out)


def check_not_the_checkpoint(path: Path, checkpoint: Path) -> None:
    """Neither the model nor its sidecar may be the checkpoint being exported (``out=`` the checkpoint's
    own path would replace it with the exported bytes)."""
    for what in (path, path.with_name(path.name + ".json")):
        same = what.resolve() == checkpoint.resolve()
        if not same and what.exists():
            same = os.path.samefile(what, checkpoint)
        if same:
            raise ExportError(f"out={str(path)!r} would write over the checkpoint being exported "
                              f"({str(checkpoint)!r}); give out=<another file>", key="out", value=path)


def check_outside_other_runs(path: Path, checkpoint: Path) -> None:
    """``out``'s folder is no other cicfw app's run nor inside one (``enclosing_run``), as every app's output
    folder: a model there would read as part of that run. The checkpoint's own run (where the default
    ``out``, beside the checkpoint, goes) takes one."""
    found = enclosing_run(path.parent if str(path.parent) else Path("."), include_self=True)
    if found is None or found == enclosing_run(checkpoint.parent, include_self=True):
        return
    run, owner = found
    what = "results folder" if owner == "reproduce" else "run"
    raise ExportError(f"out={str(path)!r} lies inside the cicfw {owner} {what} {str(run)!r}, not the checkpoint's own "
                      f"run, among whose files cicfw export would write; give out=<a file outside it>, or leave out "
                      f"unset to write beside the checkpoint", key="out", value=str(path))


def check_own_output(path: Path, checkpoint: CheckpointBytes, fmt: str, overwrite: bool = False) -> None:
    """``out`` and its sidecar are written only where nothing is, over this checkpoint's own earlier export
    (its sidecar names the SHA-256 of the checkpoint's bytes as read, and the format, and
    the model has the size the sidecar records), or with ``overwrite=true``: anything else (another run's file,
    another checkpoint's export, a file edited since) is refused in one line before the model is loaded."""
    sidecar = path.with_name(path.name + ".json")
    if overwrite or not (path.exists() or sidecar.exists()):
        return
    why = None
    try:
        side = json.loads(sidecar.read_text()) if sidecar.is_file() else None
    except (OSError, ValueError):
        side = {}
    if side is None:
        why = f"it exists and has no sidecar {sidecar.name!r} saying cicfw export wrote it"
    elif not (isinstance(side, dict) and isinstance(side.get("checkpoint"), dict) and "size_bytes" in side):
        why = f"{sidecar.name!r} exists and is not the sidecar of a cicfw export"
    elif side["checkpoint"].get("sha256") != checkpoint.sha256 or side.get("format") != fmt:
        why = (f"it is the {side.get('format')} export of another checkpoint "
               f"({side['checkpoint'].get('path')!r}, or another state of it)")
    elif path.exists() and path.stat().st_size != side["size_bytes"]:
        why = f"it has changed since cicfw export wrote it ({path.stat().st_size} bytes, {side['size_bytes']} then)"
    if why:
        raise ExportError(f"out={str(path)!r}: {why}; export writes only where nothing is or over its own export "
                          f"of this checkpoint: give out=<another file>, or overwrite=true to replace it",
                          key="out", value=str(path))


def _check_format(fmt: str) -> None:
    if fmt not in FORMATS:
        raise ExportError(f"format={fmt!r} is not known; use one of {', '.join(FORMATS)}", key="format", value=fmt)
    if fmt == "onnx":
        try:
            import onnx  # noqa: F401
            import onnxruntime  # noqa: F401
        except ImportError as err:
            raise ExportError(f'format=onnx needs the onnx and onnxruntime packages ({err.name} is missing): '
                              f'pip install "cicfw[export]"') from None


def opset_range() -> tuple[int, int]:
    """The ONNX opsets the exporter ``to_onnx`` uses (torch's TorchScript-based one) can write, as torch states them."""
    try:
        from torch.onnx import _constants as c

        return int(c.ONNX_MIN_OPSET), int(c.ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET)
    except (ImportError, AttributeError):  # a torch that moved them: the range of torch 2.x
        return 7, 20


def _check_opset(opset: Any) -> None:
    """One line for an opset torch cannot write (``opset=abc``, ``opset=99``), before anything is loaded."""
    low, high = opset_range()
    if not (is_integer(opset) and low <= opset <= high):
        raise ExportError(f"opset={opset!r} is not valid; use an integer ONNX opset from {low} to {high} "
                          f"(torch {torch.__version__}'s exporter), e.g. {DEFAULT_OPSET} (the default)", key="opset",
                          value=opset)


def _plugin_parts(hp: Mapping[str, Any]) -> list[str]:
    out = []
    for key, reg in (("encoder", ENCODERS), ("mixer", MIXERS), ("head", HEADS)):
        origin = reg.origin(hp[key])
        if origin != "cicfw":
            out.append(f"its {key} {hp[key]!r} comes from the plugin {origin!r}")
    return out


def _export_failure(err: Exception, fmt: str, hp: Mapping[str, Any], opset: int) -> ExportError:
    """One line for a model the exporter cannot express: which operator, which part, what to do."""
    text = str(err)
    op = re.search(r"operator '([^']+)'", text) or re.search(r"(aten::\w+|\w+::\w+)", text)
    what = f"the operator {op.group(1)!r}" if op else f"an operator ({type(err).__name__}: {text.splitlines()[0] if text else ''})"
    where = f"ONNX opset {opset}" if fmt == "onnx" else "TorchScript tracing"
    parts = _plugin_parts(hp)
    blame = (("; " + ", ".join(parts) + " (cicfw's own parts export)") if parts
             else "; all its parts are cicfw's own: please report this")
    other = "format=torchscript" if fmt == "onnx" else "format=onnx"
    todo = f"try {other}, or ask the part's authors for an exportable operator"
    if fmt == "onnx" and opset < DEFAULT_OPSET:  # an older opset lacks operators: not the parts' fault
        blame, todo = "", f"give opset={DEFAULT_OPSET} (the default) or newer, or {other}"
    return ExportError(f"cannot export {hp['mixer']}+{hp['head']} to {fmt}: {what} has no form in {where}{blame}; "
                       f"{todo}")


def _sources(names: list[str]) -> list[str]:
    """Where the named frames come from, each once, in order (``real frame 3 of X`` -> ``X``)."""
    return list(dict.fromkeys(n.split(" of ", 1)[-1] for n in names))


# ---- the export --------------------------------------------------------------------------------
def export_model(checkpoint: str | Path, fmt: str = "onnx", out: str | Path | None = None,
                 frames: str | Path | None = None, n_frames: int = 8, tolerance: float = TOLERANCE,
                 opset: int | None = None, overwrite: bool = False) -> dict[str, Any]:
    """Export ``checkpoint`` to ``fmt`` at ``out`` (and ``<out>.json``) after the parity check on
    ``n_frames`` real frames (``frames``: a CIL HDF5 file or folder; None: rendered by the embedded
    simulator) plus as many random inputs. ``opset``: the ONNX opset (None: ``DEFAULT_OPSET``); TorchScript
    has none, so one given with ``fmt="torchscript"`` is refused rather than ignored. An existing ``out`` or
    sidecar is replaced only when it is this checkpoint's earlier export, or with ``overwrite``
    (``check_own_output``). Returns the sidecar's content."""
    _check_format(fmt)
    if not (isinstance(n_frames, int) and n_frames >= 1):
        raise ExportError(f"n_frames={n_frames!r} is not valid; use a positive integer (real frames in the parity check)",
                          key="n_frames", value=n_frames)
    if not (is_number(tolerance) and tolerance > 0):  # inf would pass a model that steers NaN
        raise ExportError(f"tolerance={tolerance!r} is not valid; use a finite number > 0 (largest steering difference)",
                          key="tolerance", value=tolerance)
    if fmt == "onnx":
        opset = DEFAULT_OPSET if opset is None else opset
        _check_opset(opset)
    elif opset is not None:
        raise ExportError(f"opset={opset!r} applies to format=onnx only (a TorchScript model has no opset), so "
                          f"format={fmt} would ignore it; leave opset out, or give format=onnx", key="opset",
                          value=opset)
    ckpt = resolve_checkpoint(checkpoint)
    refuse_exported_model(ckpt)
    path = output_path(str(out) if out else None, ckpt, fmt)
    check_not_the_checkpoint(path, ckpt)
    check_outside_other_runs(path, ckpt)
    check_out_suffix(str(out) if out else None, fmt)
    sidecar = path.with_name(path.name + ".json")
    free = [p for p in (path, sidecar) if not os.path.lexists(p)]  # before the check: only created at the end
    # its bytes read once: the sidecar's sha256 is of the very bytes the model is built from (a training run
    # replaces its last.ckpt each epoch), and so is the check of an earlier export at out
    read = CheckpointBytes.read(ckpt)
    check_own_output(path, read, fmt, bool(overwrite))
    # bad frames= or too many n_frames: refused before the model loads
    real = dataset_frames(frames, n_frames) if frames else rendered_frames(n_frames)
    model = load_model(read)  # the checkpoint as CICModule.predict_steer runs it: the parity reference
    inputs = real + random_inputs(n_frames)
    info = describe_model(model, read, fmt, opset if fmt == "onnx" else None)
    module = graph_module(model)
    example = _example(inputs)
    meta = json.dumps(info)
    try:
        data = (to_onnx(module, example, meta, opset) if fmt == "onnx" else to_torchscript(module, example, meta))
    except Exception as err:
        raise _export_failure(err, fmt, info["hyper_parameters"], opset) from None
    worst = parity(runner(fmt, data), model, inputs, tolerance)
    info["parity"] = {"max_abs_diff": worst, "tolerance": tolerance, "inputs": len(inputs),
                      "real_frames": len(inputs) - n_frames, "random_inputs": n_frames,
                      "what": f"{len(inputs) - n_frames} real frames ({'; '.join(_sources(inputs.names[:-n_frames]))}) and "
                              f"{n_frames} random inputs, batch 1 and batch {len(inputs)}, vs the checkpoint's "
                              f"CICModule.predict_steer",
                      "runtime": "onnxruntime" if fmt == "onnx" else "torch.jit"}
    info["size_bytes"] = len(data)
    # the model renamed last: once it is there it is whole, its sidecar beside it
    write_files({sidecar: (json.dumps(info, indent=2) + "\n").encode(), path: data}, new=free)
    log.debug("wrote %s (%.1f MB, %s) and %s; parity %.2g (tolerance %g)", path, len(data) / 1e6, info["label"],
             sidecar.name, worst, tolerance)
    return {**info, "out": str(path), "sidecar": str(sidecar)}


@hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="export")
@report_user_errors
def main(cfg: DictConfig) -> None:
    if not cfg.get("checkpoint"):
        raise ExportError("no checkpoint to export: give checkpoint=path/to.ckpt (written by cicfw train) "
                          "and format=onnx|torchscript out=<file>")
    res = export_model(cfg.checkpoint, str(cfg.format), cfg.get("out"), cfg.get("frames"), cfg.n_frames,
                       cfg.tolerance, cfg.opset, overwrite=bool(cfg.get("overwrite", False)))
    print(f"cicfw export: {res['out']} ({res['size_bytes'] / 1e6:.1f} MB, {res['label']}, {res['format']}); "
          f"sidecar {res['sidecar']}; parity max |diff| {res['parity']['max_abs_diff']:.2g} on "
          f"{res['parity']['inputs']} inputs (tolerance {res['parity']['tolerance']:g})")

