"""Why a model misses turns: how its steering follows the expert's around junctions, and how much
the command moves it (``python -m cicfw.diagnose`` is the app around this module).

On a set of recorded frames (the training run's validation episodes) it measures how the predicted
steering follows the expert's (per command and per phase of a junction) and the command-swap effect (each
frame under all four commands); docs/evaluation.md says how to read both.

**Phases** (``assign_phases``) come from each episode's frame sequence alone (commands, speed, game
time), so they work on CARLA/CoRL-2017 files as well as on the embedded simulator's, with no town model.
The embedded planner turns the command on ``command_distance`` (12 m) before the junction's entry and off
at its exit, so with ``approach_m`` = that distance the phases are the junction's geometry.

The model is any ``steer_all_fn(images, speed_kmh) -> steer under each command``; ``model_steer_all``
is a ``CICModule``'s: one encoder pass, all four branches decoded by the model's head, so classification
heads (softmax, hybrid, coexistence, sine) are measured on the steering they drive with.
"""
from __future__ import annotations

import io
import json
import logging
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from scipy.stats import linregress

from cicfw import COMMANDS, N_COMMANDS
from cicfw.core.errors import CicfwError
from cicfw.core.files import write_together
from cicfw.data.cil_hdf5 import T, read_targets
from cicfw.data.frames import META_NAME, Frames, episode_groups, load_frames
from cicfw.data.images import ImageStore
from cicfw.data.split import check_split_settings, split_frames

log = logging.getLogger(__name__)

FOLLOW, TURN_CODES = 2, (3, 4, 5)  # CIL codes: follow lane; left, right, straight
PHASES = ("lane", "approach", "inside", "exit")  # "unknown" besides: a turn whose onset is not observed
JUNCTION_PHASES = ("approach", "inside", "exit")
SPLITS = ("val", "train", "all")
EPS = 1e-6  # metres / seconds: a boundary reached up to float rounding counts as reached

#: steer_all_fn(images uint8 (B,3,88,200), speed km/h (B,)) -> steer under each command (B, 4), columns in
#: cicfw.COMMANDS order
SteerAllFn = Callable[[Any, Any], Any]


class DiagnosticError(CicfwError):
    """Input the diagnostic cannot measure (no junction frames, a head without a decoder ...): one line."""


# ------------------------------------------------------------------------------------------------
# phases of a junction, from an episode's frame sequence


def assign_phases(codes: Sequence[float], speed_kmh: Sequence[float], time_s: Sequence[float] | None = None, *,
                  approach_m: float = 12.0, exit_s: float = 2.0, dt_s: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """The junction phase of each frame of one time-ordered sequence (one episode, one camera).

    ``codes`` are CIL commands (2 follow, 3 left, 4 right, 5 straight), ``speed_kmh`` the car's speed,
    ``time_s`` the game time; when it is missing or not strictly increasing, frames are ``dt_s`` apart.
    Returns ``phase`` (str: lane / approach / inside / exit / unknown) and ``turn`` (the CIL code of
    the junction a frame belongs to: its own turn command for approach / inside / unknown, the command
    that just ended for exit, 2 for lane).

    A maximal run of one turn code is one junction (a change from one turn code to another starts a
    new one). Its frame k is ``approach`` while the distance driven from the run's first frame to k
    (sum of speed x time step) is below ``approach_m``, else ``inside``; a run that starts at the
    sequence's first frame has no observed onset: ``unknown``. Follow frames less than ``exit_s``
    seconds after a run's end (measured from the first follow frame) are ``exit``.
    """
    codes = np.rint(np.asarray(codes, np.float64)).astype(np.int64)
    n = len(codes)
    speed = np.nan_to_num(np.asarray(speed_kmh, np.float64))
    t = None if time_s is None else np.asarray(time_s, np.float64)
    if t is None or len(t) != n or not np.all(np.isfinite(t)) or (n > 1 and not np.all(np.diff(t) > 0)):
        t = np.arange(n, dtype=np.float64) * dt_s
    step_m = speed[:-1] / 3.6 * np.diff(t)  # metres driven from frame k to k + 1
    phase = np.full(n, "lane", dtype=object)
    turn = np.where(np.isin(codes, TURN_CODES), codes, FOLLOW)
    starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]]) if n else np.zeros(0, np.int64)
    ends = np.r_[starts[1:], n]
    for a, b in zip(starts, ends):
        c = codes[a]
        if c in TURN_CODES:
            if a == 0:
                phase[a:b] = "unknown"
            else:
                driven = np.r_[0.0, np.cumsum(step_m[a:b - 1])]  # from the onset to each frame of the run
                phase[a:b] = np.where(driven < approach_m - EPS, "approach", "inside")
        elif a > 0 and codes[a - 1] in TURN_CODES:
            after = np.flatnonzero(t[a:b] - t[a] < exit_s - EPS) + a
            phase[after] = "exit"
            turn[after] = codes[a - 1]
    return phase.astype(str), turn


def frame_phases(frames: Frames, approach_m: float = 12.0, exit_s: float = 2.0,
                 dt_s: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """``assign_phases`` for every frame of ``frames``, computed on the whole episodes they come from.

    The sequences are read from the files' targets, not from ``frames`` (which the loader filtered:
    |steer| > 0.8 dropped, some cameras dropped): an episode is the files ``episode_groups`` puts
    together, in file order (a collected episode's parts ``<episode>_000.h5``, ``_001`` ...), one
    sequence per camera id, frames in row order, time from targets[20] (ms)."""
    groups_of_file = episode_groups(frames.files)
    phase_of: dict[int, np.ndarray] = {}
    turn_of: dict[int, np.ndarray] = {}
    for g in np.unique(frames.group):
        file_ids = np.flatnonzero(groups_of_file == g)
        parts = [read_targets(frames.files[i]) for i in file_ids]
        t = np.concatenate(parts)
        where = np.concatenate([np.stack([np.full(len(p), i), np.arange(len(p))], 1) for i, p in zip(file_ids, parts)])
        phase, turn = np.empty(len(t), dtype=object), np.empty(len(t), np.int64)
        camera = np.nan_to_num(t[:, T.CAMERA_ID])
        for cam in np.unique(camera):
            sel = np.flatnonzero(camera == cam)
            phase[sel], turn[sel] = assign_phases(
                t[sel, T.COMMAND], t[sel, T.SPEED], t[sel, T.GAME_TIME] / 1000.0,
                approach_m=approach_m, exit_s=exit_s, dt_s=dt_s)
        for i, p in zip(file_ids, parts):
            mine = where[:, 0] == i
            phase_of[int(i)], turn_of[int(i)] = phase[mine], turn[mine]
    phase = np.array([phase_of[int(f)][r] for f, r in zip(frames.file_idx, frames.row)], dtype=str)
    turn = np.array([turn_of[int(f)][r] for f, r in zip(frames.file_idx, frames.row)], dtype=np.int64)
    return phase, turn


# ------------------------------------------------------------------------------------------------
# the model under every command


def _to_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().double().numpy()
    return np.asarray(x, np.float64)


def model_steer_all(model: Any, device: Any = None) -> SteerAllFn:
    """The fast ``steer_all_fn`` of a ``CICModule`` (eval mode): ``branch_outputs`` once (B, 4, K), each
    branch decoded by the model's own head, so every head is measured on the steering it drives with
    (a classification head through its decoder: argmax midpoint or expectation). The same values as
    ``predict_steer`` under each command (a mixer's branches are computed together in both)."""
    head = model.head
    name = type(head).__name__
    device = device or next(model.parameters()).device

    def steer_all(images: Any, speed: Any) -> np.ndarray:
        with torch.inference_mode():
            out = model.branch_outputs(torch.as_tensor(images).to(device), torch.as_tensor(speed).to(device))
            b, c, k = out.shape
            try:
                steer = head.decode(out.reshape(b * c, k))
            except NotImplementedError:
                raise DiagnosticError(f"head {name} has no decode(): the diagnostic compares decoded steering "
                                      f"with the expert's, so it cannot measure this head") from None
        steer = _to_numpy(steer)
        if steer.shape != (b * c,):
            raise DiagnosticError(f"head {name}'s decode() gave shape {steer.shape} for {b * c} outputs; the Head "
                                  f"contract is one steering value per output, so it cannot be diagnosed")
        return steer.reshape(b, c)

    return steer_all


def predict(steer_all: SteerAllFn, images: Callable[[np.ndarray], np.ndarray], speed_kmh: np.ndarray,
            batch_size: int = 128) -> np.ndarray:
    """Steering under each command (n, 4) for every frame; ``images(idx)`` gives frames idx as
    uint8 (len(idx), 88, 200, 3) (HWC, as files store them); batches of ``batch_size``."""
    n = len(speed_kmh)
    out = np.empty((n, N_COMMANDS), np.float64)
    for a in range(0, n, batch_size):
        idx = np.arange(a, min(a + batch_size, n))
        img = torch.from_numpy(np.ascontiguousarray(images(idx))).permute(0, 3, 1, 2)
        out[idx] = _to_numpy(steer_all(img, torch.from_numpy(np.asarray(speed_kmh[idx], np.float32))))
    return out


# ------------------------------------------------------------------------------------------------
# the measures


def fit_line(expert: np.ndarray, pred: np.ndarray) -> dict[str, Any]:
    """Least squares ``pred = slope * expert + offset`` (scipy.stats.linregress), MAE, r and n.
    slope, offset and r are None when the expert's steering does not vary (or n < 3)."""
    expert, pred = np.asarray(expert, np.float64), np.asarray(pred, np.float64)
    n = len(expert)
    res: dict[str, Any] = {"n": n, "slope": None, "offset": None, "r": None,
                           "mae": float(np.mean(np.abs(pred - expert))) if n else None,
                           "expert_mean": float(expert.mean()) if n else None,
                           "pred_mean": float(pred.mean()) if n else None}
    if n >= 3 and np.ptp(expert) > 0:
        fit = linregress(expert, pred)
        res.update(slope=float(fit.slope), offset=float(fit.intercept),
                   r=float(fit.rvalue) if np.ptp(pred) > 0 else None)
    return res


def swap_shifts(steer: np.ndarray, expert: np.ndarray) -> dict[str, float]:
    """On frames ``steer`` (n, 4): the mean of each turn branch's output minus the follow branch's
    (``shift_left`` ...) and what the expert's steering is away from the follow branch's (``needed``)."""
    follow = steer[:, 0]
    out = {f"shift_{name}": float(np.mean(steer[:, i] - follow)) for i, name in enumerate(COMMANDS) if i}
    out["needed"] = float(np.mean(expert - follow))
    return out


def pair_effects(steer: np.ndarray) -> dict[str, float]:
    """Mean ``|steer(a) - steer(b)|`` over the frames, for each pair of commands (``follow-left`` ...)."""
    return {f"{COMMANDS[a]}-{COMMANDS[b]}": float(np.mean(np.abs(steer[:, a] - steer[:, b])))
            for a, b in combinations(range(N_COMMANDS), 2)}


@dataclass
class Diagnosis:
    """The measured frames and what was measured on them (``rows``: one per frame group)."""

    expert: np.ndarray  # (n,) the label
    steer: np.ndarray  # (n, 4) the model's steering under each command
    command: np.ndarray  # (n,) branch index of the recorded command
    phase: np.ndarray  # (n,) str
    turn: np.ndarray  # (n,) CIL code of the frame's junction (2: lane)
    rows: list[dict[str, Any]] = field(default_factory=list)
    pairs: list[dict[str, Any]] = field(default_factory=list)

    @property
    def pred(self) -> np.ndarray:
        """The steering under the recorded command (what the car would have done)."""
        return self.steer[np.arange(len(self.command)), self.command]


def groups(command: np.ndarray, phase: np.ndarray, turn: np.ndarray) -> list[tuple[str, str, str, np.ndarray]]:
    """The frame groups reported: (by, command, phase, mask) per command, per phase, and per junction
    (the junction's command x approach / inside / exit, and follow x lane)."""
    out = [("command", name, "all", command == i) for i, name in enumerate(COMMANDS)]
    out += [("phase", "all", p, phase == p) for p in PHASES]
    out.append(("junction", "follow", "lane", phase == "lane"))
    for code in TURN_CODES:
        out += [("junction", COMMANDS[code - 2], p, (turn == code) & (phase == p)) for p in JUNCTION_PHASES]
    return [g for g in out if g[3].any()]


def diagnose(expert: np.ndarray, steer: np.ndarray, command: np.ndarray, phase: np.ndarray,
             turn: np.ndarray) -> Diagnosis:
    """Every measure on already predicted frames (``measure``'s, which holds a junction frame): ``steer``
    (n, 4) under each command, ``command`` the recorded branch index (0-3), ``phase``/``turn`` from
    ``assign_phases``."""
    expert = np.asarray(expert, np.float64)
    steer, command = np.asarray(steer, np.float64), np.asarray(command, np.int64)
    phase, turn = np.asarray(phase).astype(str), np.asarray(turn, np.int64)
    n = len(expert)
    d = Diagnosis(expert, steer, command, phase, turn)
    pred = d.pred
    for by, cmd, ph, mask in groups(command, phase, turn):
        d.rows.append({"by": by, "command": cmd, "phase": ph, **fit_line(expert[mask], pred[mask]),
                       **swap_shifts(steer[mask], expert[mask])})
    junction = np.isin(phase, ("approach", "inside"))
    for name, mask in (("all", np.ones(n, bool)), ("junction", junction), ("lane", phase == "lane")):
        if mask.any():
            d.pairs.append({"frames": name, "n": int(mask.sum()), **pair_effects(steer[mask])})
    return d


@dataclass
class DataSettings:
    """Which frames to measure: the datamodule's arguments that decide the split and the filters, with its
    defaults (a test holds them to ``CILDataModule``'s), but the seed: None is the training run's."""

    path: str
    seed: int | None = None
    val_fraction: float = 0.3
    max_abs_steer: float = 0.8
    side_camera_correction: float = 0.15
    cameras: Sequence[int] | None = (0, 1, 2)
    val_cameras: Sequence[int] | None = (0,)


def load_split(data: DataSettings, split: str = "val", files: Sequence[str | Path] | None = None):
    """The frames of ``split`` and an image store for them. ``val``/``train``: the training run's split,
    drawn as ``CILDataModule`` draws it (same seed, fraction and filters: the same episodes); ``all``: every
    file. Every split keeps only ``val_cameras`` (the centre camera: what the car drives with). ``files``:
    the files to read instead of every file under ``data.path`` (the files the run recorded: a file added
    to its folder since would move episodes between the splits)."""
    cams = tuple(data.val_cameras) if data.val_cameras is not None else None
    source = [str(f) for f in files] if files is not None else data.path
    if split == "all":
        frames = load_frames(source, data.max_abs_steer, data.side_camera_correction,
                             tuple(data.cameras) if data.cameras is not None else None)
    else:
        if data.seed is None:
            raise CicfwError("data.seed is needed for the training run's split; give data.seed=<its seed>, or split=all")
        cameras, val_cameras = check_split_settings(data.val_fraction, data.max_abs_steer, data.side_camera_correction,
                                                    data.cameras, data.val_cameras)
        _, train, val = split_frames(source, data.val_fraction, int(data.seed), data.max_abs_steer,
                                     data.side_camera_correction, cameras, val_cameras)
        frames = val if split == "val" else train
    if cams is not None:
        frames = frames.subset(np.isin(frames.camera, cams))
    return frames, ImageStore(frames, in_memory=False)


def measure(frames: Frames, images: Callable[[np.ndarray], np.ndarray], steer_all: SteerAllFn, *,
            approach_m: float = 12.0, exit_s: float = 2.0, dt_s: float = 0.1, batch_size: int = 128,
            max_frames: int | None = None) -> tuple[Diagnosis, dict[str, np.ndarray]]:
    """Phases for ``frames`` (from their whole episodes), the model under every command on them
    (``images(idx)`` gives frames idx of ``frames``), and the diagnosis. ``max_frames``: an evenly
    spaced subset (phases are still computed on whole episodes). Returns the diagnosis and per-frame
    arrays (file index, row, episode, speed) for ``write_report``."""
    phase, turn = frame_phases(frames, approach_m, exit_s, dt_s)
    keep = np.arange(len(frames))
    if max_frames is not None and len(keep) > max_frames:
        keep = np.unique(np.linspace(0, len(frames) - 1, int(max_frames)).round().astype(np.int64))
    if not np.isin(phase[keep], ("approach", "inside", "unknown")).any():
        raise DiagnosticError(
            f"no junction frame among the {len(keep)} frames of {len(np.unique(frames.group))} episode(s): no "
            f"left / right / straight command (CIL codes 3-5 in targets[24]); the diagnostic measures how a "
            f"model takes junctions, so give data with turns")
    steer = predict(steer_all, lambda idx: images(keep[idx]), frames.speed[keep], batch_size)
    d = diagnose(frames.steer[keep], steer, frames.command[keep], phase[keep], turn[keep])
    arrays = {"file_idx": frames.file_idx[keep], "row": frames.row[keep], "episode": frames.group[keep],
              "camera": frames.camera[keep], "speed_kmh": frames.speed[keep],
              "files": np.array([str(f) for f in frames.files])}
    return d, arrays


def dataset_command_distance(path: str | Path) -> float | None:
    """The collector's ``command_distance`` (m) from ``dataset_metadata.json`` in a dataset folder,
    None when the folder has none (CARLA / CoRL-2017 data)."""
    meta = Path(str(path)).expanduser() / META_NAME
    if not meta.is_file():
        return None
    try:
        value = json.loads(meta.read_text()).get("config", {}).get("command_distance")
    except (OSError, ValueError, AttributeError):
        return None
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


# ------------------------------------------------------------------------------------------------
# the report


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:+.{digits}f}" if digits else f"{v:.0f}"
    return str(v)


def measured_line(meta: dict[str, Any]) -> str | None:
    """What the numbers were measured on, from a report's ``meta``: the checkpoint, the split and its
    frames (a train-split and a validation-split report read alike otherwise); None when ``meta`` does not say."""
    data = meta.get("data") or {}
    if not data.get("split"):
        return None
    where = "every frame" if data["split"] == "all" else f"the {data['split']} split"
    return (f"Measured on {where} of {data.get('path')} ({data.get('frames')} frames of {data.get('episodes')} "
            f"episodes), checkpoint {meta.get('checkpoint')} (epoch {meta.get('epoch')}, step "
            f"{meta.get('global_step')}).")


def markdown(d: Diagnosis, title: str = "Steering diagnostic", measured: str | None = None) -> str:
    """The two tables (following, and the command-swap shifts per group) and the pair table, under
    ``measured`` (``measured_line``) when given."""
    lines = [f"# {title}", "", *([measured, ""] if measured else []),
             "Predicted vs expert steering, least squares `pred = slope * expert + offset` (slope 1, offset 0: "
             "follows the expert). Shifts: mean steering of each command's branch minus the follow branch's, "
             "on the same frames; `needed`: the expert's steering minus the follow branch's.", "",
             "| by | command | phase | n | slope | offset | r | MAE | expert mean | pred mean | "
             "left - follow | right - follow | straight - follow | needed |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in d.rows:
        lines.append(f"| {r['by']} | {r['command']} | {r['phase']} | {r['n']} | {_fmt(r['slope'])} | "
                     f"{_fmt(r['offset'])} | {_fmt(r['r'])} | {r['mae']:.3f} | {_fmt(r['expert_mean'])} | "
                     f"{_fmt(r['pred_mean'])} | {_fmt(r['shift_left'])} | {_fmt(r['shift_right'])} | "
                     f"{_fmt(r['shift_straight'])} | {_fmt(r['needed'])} |")
    names = [k for k in d.pairs[0] if k not in ("frames", "n")] if d.pairs else []
    lines += ["", "Command-swap effect: mean |steer(a) - steer(b)| on the same frames (0: the command is ignored).",
              "", "| frames | n | " + " | ".join(names) + " |", "|---|---:|" + "---:|" * len(names)]
    for p in d.pairs:
        lines.append(f"| {p['frames']} | {p['n']} | " + " | ".join(f"{p[k]:.3f}" for k in names) + " |")
    return "\n".join(lines) + "\n"


def csv_text(d: Diagnosis) -> str:
    """The group rows as CSV (one header line, None as empty)."""
    keys = list(d.rows[0]) if d.rows else []
    out = io.StringIO()
    out.write(",".join(keys) + "\n")
    for r in d.rows:
        out.write(",".join("" if r[k] is None else (f"{r[k]:.6g}" if isinstance(r[k], float) else str(r[k]))
                           for k in keys) + "\n")
    return out.getvalue()


def scatter_figure(d: Diagnosis, title: str = "Steering diagnostic", max_points: int = 1500, seed: int = 0):
    """Predicted vs expert steering per junction command (rows) and phase (columns), each with its
    fitted line and the identity; the last row: lane following, and the swap shifts per junction."""
    from matplotlib.figure import Figure

    rng = np.random.default_rng(seed)
    pred = d.pred
    fig = Figure(figsize=(10.5, 13), layout="constrained")
    axes = fig.subplots(4, 3, squeeze=False)
    fits = {(r["command"], r["phase"]): r for r in d.rows if r["by"] == "junction"}
    cells = [(COMMANDS[c - 2], c, p) for c in TURN_CODES for p in JUNCTION_PHASES] + [("follow", FOLLOW, "lane")]
    colours = {"follow": "#777777", "left": "#2166ac", "right": "#b2182b", "straight": "#1a9850"}
    for k, (name, code, ph) in enumerate(cells):
        ax = axes[k // 3, k % 3]
        mask = (d.phase == ph) & ((d.turn == code) if ph != "lane" else True)
        idx = np.flatnonzero(mask)
        if len(idx) > max_points:
            idx = np.sort(rng.choice(idx, max_points, replace=False))
        ax.plot([-1, 1], [-1, 1], ls="--", lw=0.8, color="#999999")
        ax.scatter(d.expert[idx], pred[idx], s=4, alpha=0.35, color=colours[name], linewidths=0)
        r = fits.get((name, ph))
        text = f"{name} / {ph}: no frames"
        if r is not None:
            text = f"{name} / {ph}  n={r['n']}"
            if r["slope"] is not None:
                lo, hi = float(d.expert[mask].min()), float(d.expert[mask].max())
                ax.plot([lo, hi], [r["slope"] * lo + r["offset"], r["slope"] * hi + r["offset"]], color="black", lw=1.4)
                text += f"\nslope {r['slope']:.2f}  offset {r['offset']:+.3f}  MAE {r['mae']:.3f}"
        ax.set_title(text, fontsize=8)
        ax.set_xlim(-0.85, 0.85)
        ax.set_ylim(-0.85, 0.85)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        if k % 3 == 0:
            ax.set_ylabel("predicted steer", fontsize=8)
        if k >= 9 or k // 3 == 2:
            ax.set_xlabel("expert steer", fontsize=8)
    ax = axes[3, 1]
    inside = [r for r in d.rows if r["by"] == "junction" and r["phase"] == "inside"]
    x = np.arange(len(inside))
    for j, (key, colour) in enumerate((("shift_left", colours["left"]), ("shift_right", colours["right"]),
                                       ("shift_straight", colours["straight"]), ("needed", "black"))):
        ax.bar(x + (j - 1.5) * 0.2, [r[key] for r in inside], 0.2, color=colour, label=key.replace("shift_", "") +
               (" - follow" if key != "needed" else ": expert - follow"))
    ax.axhline(0, color="#999999", lw=0.8)
    ax.set_xticks(x, [f"{r['command']} command" for r in inside], fontsize=7)
    ax.set_title("inside the junction: branch minus follow branch", fontsize=8)
    ax.legend(fontsize=6)
    ax.tick_params(labelsize=7)
    axes[3, 2].axis("off")
    fig.suptitle(title, fontsize=10)
    return fig


def write_report(out_dir: str | Path, d: Diagnosis, meta: dict[str, Any], arrays: dict[str, np.ndarray] | None = None,
                 plot: bool = True) -> dict[str, Path]:
    """``steer_diagnostic.json`` (meta + rows + pairs), ``.md``, ``.csv``, ``steer_frames.npz`` (every frame's
    expert steering, steering under each command, command, phase, turn, plus ``arrays``) and, with ``plot``,
    ``steer_scatter.png`` (without it, an earlier one is removed); all written or none (a full disk). Returns
    the paths by kind."""
    out = Path(out_dir)
    title = f"Steering diagnostic: {meta.get('model', '')}".rstrip(": ")
    doc = {**meta, "rows": d.rows, "pairs": d.pairs}
    paths = {"json": out / "steer_diagnostic.json", "md": out / "steer_diagnostic.md",
             "csv": out / "steer_diagnostic.csv", "npz": out / "steer_frames.npz"}
    buf = io.BytesIO()
    np.savez_compressed(buf, expert=d.expert, steer=d.steer, command=d.command, phase=d.phase, turn=d.turn,
                        **(arrays or {}))
    data = {"json": (json.dumps(doc, indent=1, default=str) + "\n").encode(),
            "md": markdown(d, title, measured_line(meta)).encode(), "csv": csv_text(d).encode(), "npz": buf.getvalue()}
    if plot:
        fig = scatter_figure(d, title)
        png = io.BytesIO()
        fig.savefig(png, format="png", dpi=90)
        paths["png"], data["png"] = out / "steer_scatter.png", png.getvalue()
    out.mkdir(parents=True, exist_ok=True)
    write_together({paths[k]: v for k, v in data.items()})  # all or none: never one run's table beside another's
    if not plot:  # an earlier diagnosis's plot (other phases) must not pass for this one's
        (out / "steer_scatter.png").unlink(missing_ok=True)
    return paths
