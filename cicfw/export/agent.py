"""One driving agent for every runtime: ``Agent.load(path)`` and ``act(images, speed_kmh, command) -> steer``.

``path`` is a cicfw checkpoint (run by torch, as the suite always has) or a model written by
``cicfw export`` (``.onnx`` run by onnxruntime, TorchScript ``.pt`` run by torch.jit). Whatever the
runtime, the function is the same one, ``DrivingFunction``: uint8 RGB frames (B, 88, 200, 3) as the
cameras deliver them, the speed in km/h and the CIL command code (2 follow, 3 left, 4 right,
5 straight) in, steering in [-1, 1] out (positive = right), with the pixel and speed normalisation,
the command's branch and the head's decoder inside. The suite's checkpoint policy drives through it,
so the suite, a CARLA client and a user's own stack share one inference path (docs/deploy.md).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch
from torch import nn

from cicfw.core.errors import CicfwError
from cicfw import COMMANDS, MAX_ABS_SPEED_KMH
from cicfw.model.checkpoint import (CheckpointBytes, decoder_info, describe, is_torchscript, load_model,
                                    prepare_for_inference, resolve_checkpoint)

#: what ``Agent.load`` takes, for the line refusing a folder that holds no checkpoint
LOADABLE = "a .ckpt, a TorchScript .pt or an .onnx file, or a training run folder"
#: the CIL command codes the agent accepts, in branch order (branch = code - 2)
COMMAND_CODES = {code: name for code, name in zip(range(2, 2 + len(COMMANDS)), COMMANDS)}
#: one frame as the cameras deliver it: height, width, RGB
IMAGE_SHAPE = (88, 200, 3)
#: the graph's inputs and output, in order (ONNX names, TorchScript argument order)
INPUT_NAMES = ("images", "speed_kmh", "command")
OUTPUT_NAME = "steer"
#: where an exported model carries its description (ONNX metadata key, TorchScript extra file)
METADATA_KEY = "cicfw.json"


class AgentInputError(CicfwError):
    """Inputs the agent cannot take; the message says what it expects."""


class DrivingFunction(nn.Module):
    """The whole driving function of a ``CICModule`` as one module, the graph ``cicfw export`` writes.

    ``images`` uint8 (B, H, W, 3) RGB, ``speed_kmh`` float (B,), ``command`` CIL codes (B,) 2-5 ->
    steering float32 (B,) in [-1, 1]: the model's own ``predict_steer`` (pixels /255, speed /
    ``speed_norm_kmh``, the command's branch, the head's decoder), clamped as the suite always did.
    """

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor, speed_kmh: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        steer = self.model.predict_steer(images.permute(0, 3, 1, 2), speed_kmh, command.long() - 2)
        return steer.float().clamp(-1.0, 1.0)


def _shape(a: np.ndarray) -> str:
    return "(" + ", ".join(str(d) for d in a.shape) + ")"


def _one_per_image(name: str, values: np.ndarray, batch: int, single: bool, what: str) -> np.ndarray:
    """``values`` as one per image (B,): a number or a list of ``batch``; any array of more dimensions is
    refused (a (2, 2) speed for 4 images, flattened, would give each image some other image's value)."""
    if values.ndim > 1:
        want = "a number or shape (1,)" if single else f"shape ({batch},)"
        raise AgentInputError(f"{name} of shape {_shape(values)} for {'one image' if single else f'{batch} images'}: "
                              f"the agent expects one {what} per image, {want}", key=name, value=_shape(values))
    return values.reshape(-1)


def check_inputs(images: Any, speed_kmh: Any, command: Any,
                 image_shape: tuple[int, int, int] = IMAGE_SHAPE) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """The inputs as a batch (uint8 (B, H, W, 3), float32 (B,), int64 (B,)) and whether they were one
    frame; an ``AgentInputError`` that says what is expected for anything else."""
    h, w, c = image_shape
    want = f"uint8 RGB frames ({h}, {w}, {c}) or a batch (B, {h}, {w}, {c}), as the cameras deliver them"
    img = np.asarray(images)
    single = img.ndim == 3
    if img.ndim not in (3, 4):
        raise AgentInputError(f"images of shape {_shape(img)}: the agent expects {want}")
    frame = img.shape[-3:]
    if frame == (c, h, w):
        fix = "image.transpose(1, 2, 0)" if single else "images.transpose(0, 2, 3, 1)"
        raise AgentInputError(f"images of shape {_shape(img)} are channels-first (C, H, W): the agent expects "
                              f"channels last, {want}; use {fix}")
    if frame[:2] == (h, w) and frame[2] == 4:
        raise AgentInputError(f"images of shape {_shape(img)} have 4 channels (BGRA, as a CARLA camera sends "
                              f"them?): the agent expects {want}; use image[..., 2::-1] for BGRA -> RGB")
    if frame != (h, w, c):
        raise AgentInputError(f"images of shape {_shape(img)}: the agent expects {want} (CIL's crop of the "
                              f"camera image, resized to {w}x{h}; docs/deploy.md)")
    if img.dtype != np.uint8:
        raise AgentInputError(f"images of dtype {img.dtype}: the agent expects uint8 pixels 0-255 ({want}); "
                              f"do not normalise them, the model divides by 255 itself")
    batch = 1 if single else img.shape[0]
    if single:
        img = img[None]
    speed_in = np.asarray(speed_kmh)
    if speed_in.dtype.kind not in "iuf":  # True would drive at 1 km/h, "10" at 10: neither is a speed
        shown = speed_in.tolist() if speed_in.dtype.kind != "O" else speed_kmh
        raise AgentInputError(f"speed_kmh {shown!r}: the agent expects real numbers (km/h), one per image",
                              key="speed_kmh", value=shown)
    speed = _one_per_image("speed_kmh", speed_in, batch, single, "speed (km/h)").astype(np.float32)
    cmd_in = np.asarray(command)
    if cmd_in.dtype.kind == "f" and np.all(np.isfinite(cmd_in)) and np.all(cmd_in == np.round(cmd_in)):
        cmd_in = cmd_in.astype(np.int64)  # CIL's targets store the code as a float (24: 2.0 ...)
    codes = ", ".join(f"{k} {v}" for k, v in COMMAND_CODES.items())
    if cmd_in.dtype.kind not in "iu":
        raise AgentInputError(f"command {cmd_in.tolist()!r}: the agent expects CIL command codes ({codes})")
    cmd = _one_per_image("command", cmd_in, batch, single, "command code").astype(np.int64)
    if len(speed) != batch or len(cmd) != batch:
        raise AgentInputError(f"{batch} image(s) but {len(speed)} speed(s) and {len(cmd)} command(s): the agent "
                              f"expects one speed (km/h) and one command code per image")
    bad = cmd[~np.isin(cmd, list(COMMAND_CODES))]
    if len(bad):
        raise AgentInputError(f"command code {int(bad[0])} is not a CIL command: the agent expects {codes} "
                              f"(the branch is code - 2)")
    beyond = np.flatnonzero(~(np.abs(speed) <= MAX_ABS_SPEED_KMH))  # NaN and inf too
    if len(beyond):
        value = float(speed[beyond[0]])
        raise AgentInputError(f"speed_kmh {value:g}: the agent expects finite speeds in km/h within "
                              f"±{MAX_ABS_SPEED_KMH:g}, as the data reader does (negative: rolling backwards)",
                              key="speed_kmh", value=value)
    return np.ascontiguousarray(img), speed, cmd, single


def torch_device(device: str) -> torch.device:
    """The torch device ``device`` names (``auto``: a CUDA GPU when there is one); one ``ValueError`` line
    for a name torch does not know or a CUDA GPU this machine lacks (torch would fail later, deep inside)."""
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise CicfwError(f"device={device!r} is not a torch device; use auto, cpu, cuda or cuda:N", key="device",
                         value=device) from None
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            why = "this torch is built without CUDA" if torch.version.cuda is None else "it sees no CUDA GPU"
            raise CicfwError(f"device={device!r} needs a CUDA GPU, but {why}; use device=cpu (or auto)",
                             key="device", value=device)
        if dev.index is not None and dev.index >= count:
            raise CicfwError(f"device={device!r} is not on this machine: it has {count} CUDA GPU(s), "
                             f"cuda:0 to cuda:{count - 1}; use one of them, or device=auto", key="device", value=device)
    return dev


class Agent:
    """Steering from camera frames, speed and command, whatever runs the model (``runtime``:
    ``torch`` for a checkpoint, ``torchscript`` or ``onnxruntime`` for an exported model).

    ``info`` describes the model (its label, parts, inputs, decoder); ``model`` is the ``CICModule``
    when the agent was loaded from a checkpoint (None for an exported model).
    """

    def __init__(self, run: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray], info: Mapping[str, Any],
                 runtime: str, model: nn.Module | None = None, device: torch.device | None = None) -> None:
        self._run = run
        self.info = dict(info)
        self.runtime = runtime
        self.model = model
        self.device = device or torch.device("cpu")
        layout = {i["name"]: i for i in self.info.get("inputs", [])}
        shape = layout.get("images", {}).get("shape")
        self.image_shape = tuple(shape[1:]) if shape else IMAGE_SHAPE
        self.label = str(self.info.get("label") or "cicfw model")

    @classmethod
    def load(cls, path: str | Path | CheckpointBytes, *, threads: int | None = None, device: str = "cpu",
             fuse: bool = True) -> "Agent":
        """An agent for a checkpoint (``.ckpt`` or a run folder), an ``.onnx`` model or a TorchScript file, or
        for the ``CheckpointBytes`` read from one (built from those bytes: the file is not read again).

        ``threads``: CPU threads (torch's, or the onnxruntime session's); ``device``: where torch runs
        (``auto``, ``cpu``, ``cuda``; onnxruntime runs on the CPU, and refuses ``cuda``); ``fuse``: for a checkpoint, fold
        BatchNorm into the convolutions and use the NHWC layout (the same function, computed faster).
        """
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, (int, np.integer))
                                    or threads < 1):
            raise CicfwError(f"threads={threads!r}: give a whole number of CPU threads >= 1, or None for the "
                             f"runtime's default", key="threads", value=threads)
        read = path if isinstance(path, CheckpointBytes) else None
        p = read.path if read else Path(str(path)).expanduser()
        there = read is not None or p.is_file()
        # by the file's name in any case, or the name a link points at (a link named 'model' to 'm.onnx')
        if there and ".onnx" in (p.suffix.lower(), p.resolve().suffix.lower()):
            if device not in ("cpu", "auto"):  # it would run on the CPU while the caller asked for a GPU
                raise CicfwError(f"device={device!r}: an ONNX model runs on onnxruntime's CPU provider here; use "
                                 f"device=cpu, or load the checkpoint or its TorchScript export to run on a GPU",
                                 key="device", value=device)
            return cls._load_onnx(read or p, threads)
        if there and is_torchscript(read or p):
            return cls._load_torchscript(read or p, threads, device)
        return cls._load_checkpoint(read or p, threads, device, fuse)

    @classmethod
    def _load_checkpoint(cls, path: Path | CheckpointBytes, threads: int | None, device: str, fuse: bool) -> "Agent":
        if threads:
            torch.set_num_threads(int(threads))
        dev = torch_device(device)
        if not isinstance(path, CheckpointBytes):  # a run folder's one best checkpoint: the file named in info
            path = resolve_checkpoint(path, LOADABLE)
        model = prepare_for_inference(load_model(path), fuse).to(dev)
        hp = dict(model.hparams)  # the decoder too, as an exported model's sidecar gives it (docs/deploy.md)
        info = {"label": describe(hp), "encoder": hp["encoder"], "mixer": hp["mixer"], "head": hp["head"],
                "decoder": decoder_info(model.head, hp["head"]), "source": str(path)}
        return cls(torch_runner(DrivingFunction(model).eval(), dev), info, "torch", model=model, device=dev)

    @classmethod
    def _load_torchscript(cls, path: Path | CheckpointBytes, threads: int | None, device: str) -> "Agent":
        if threads:
            torch.set_num_threads(int(threads))
        dev = torch_device(device)
        extra = {METADATA_KEY: ""}
        try:
            source = path.open() if isinstance(path, CheckpointBytes) else str(path)
            module = torch.jit.load(source, map_location=dev, _extra_files=extra)
        except Exception as err:
            raise CicfwError(f"{str(path)!r} is not a TorchScript model cicfw can run, or it is truncated "
                             f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None
        info = _metadata(extra[METADATA_KEY], Path(str(path)))
        return cls(torch_runner(module.eval(), dev), info, "torchscript", device=dev)

    @classmethod
    def _load_onnx(cls, path: Path | CheckpointBytes, threads: int | None) -> "Agent":
        read = path if isinstance(path, CheckpointBytes) else None
        session = onnx_session(read.data if read else path, threads, where=str(path))
        path = Path(str(path))
        names = tuple(i.name for i in session.get_inputs())
        if names != INPUT_NAMES:
            raise CicfwError(f"{str(path)!r} is an ONNX model with inputs {list(names)}, not one written by cicfw "
                             f"export (inputs {list(INPUT_NAMES)})")
        meta = session.get_modelmeta().custom_metadata_map.get(METADATA_KEY, "")
        return cls(onnx_runner(session), _metadata(meta, path), "onnxruntime")

    def act(self, images: Any, speed_kmh: Any, command: Any) -> float | np.ndarray:
        """Steering in [-1, 1] (positive = right): a float for one frame (H, W, 3), float32 (B,) for a
        batch (B, H, W, 3); ``speed_kmh`` and ``command`` (CIL codes 2-5) a number or one per frame."""
        img, speed, cmd, single = check_inputs(images, speed_kmh, command, self.image_shape)
        steer = np.asarray(self._run(img, speed, cmd), dtype=np.float32).reshape(-1)
        return float(steer[0]) if single else steer

    def __repr__(self) -> str:
        return f"Agent({self.label!r}, runtime={self.runtime!r})"


def torch_runner(module: nn.Module, device: torch.device) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """The graph's function on numpy batches, run by torch (``module``: a ``DrivingFunction`` or its TorchScript)."""
    def run(images: np.ndarray, speed: np.ndarray, command: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            steer = module(torch.from_numpy(images).to(device), torch.from_numpy(speed).to(device),
                           torch.from_numpy(command).to(device))
        return steer.cpu().numpy()

    return run


def onnx_runner(session: Any) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """The graph's function on numpy batches, run by an onnxruntime ``session``."""
    return lambda images, speed, command: session.run([OUTPUT_NAME], {"images": images, "speed_kmh": speed,
                                                                      "command": command})[0]


def onnx_session(model: str | Path | bytes, threads: int | None = None, where: str | None = None):
    """An onnxruntime CPU session (``threads`` intra-op threads; onnxruntime's default: all cores); ``where``
    names bytes' file in the error."""
    try:
        import onnxruntime as ort
    except ImportError:
        raise CicfwError('running an .onnx model needs onnxruntime: pip install "cicfw[export]" '
                         '(or pip install onnxruntime)') from None
    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
    opts.log_severity_level = 3  # errors only: no warnings about unused initialisers on stderr
    source = model if isinstance(model, bytes) else str(model)
    try:
        return ort.InferenceSession(source, opts, providers=["CPUExecutionProvider"])
    except Exception as err:
        where = repr(where) if where else "the exported bytes" if isinstance(model, bytes) else repr(str(model))
        raise CicfwError(f"{where} is not an ONNX model onnxruntime can run, or it is truncated "
                         f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None


def _metadata(text: str, path: Path) -> dict[str, Any]:
    """The description an exported model carries (or its sidecar ``<file>.json``); {} for a foreign file."""
    if not text:
        side = path.with_name(path.name + ".json")
        text = side.read_text() if side.is_file() else ""
    try:
        info = json.loads(text) if text else {}
    except json.JSONDecodeError:
        info = {}
    return info if isinstance(info, dict) else {}
