"""MixerDiagnostics: shows what a mixer learned, as heatmaps, each validation epoch.

During validation it collects ``pl_module.mixer.inspect()`` after every batch: per-sample matrices
(B, r, c) -- the co-learning matrix C of ``gtu``/``re``, the gate usage of ``moe`` -- are averaged over
the samples of each command; global ones (r, c) -- cross-stitch / sluice α, sluice β -- are taken as
they are. At the end of the epoch each matrix becomes one figure: a PNG under
``<log dir>/diagnostics/epoch_XXX_<name>.png`` always, and an image in TensorBoard when a
TensorBoard logger is attached. Square matrices also log the mean off-diagonal |value| (how much the
branches mix) as ``diagnostics/<name>_offdiag_abs``.
"""
from __future__ import annotations

import io
import os
import warnings
from typing import Any, Mapping

import lightning as L
import numpy as np
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from cicfw import COMMANDS, N_COMMANDS
from cicfw.core.files import atomic_write

# Axis titles by matrix name (prefix match); rows first.
AXES = {
    "C": ("branch i (receives)", r"branch j (gives): $A_i = \sum_j C_{ij} \hat{A}_j$"),
    "gates": ("branch", "expert"),
    "alpha": ("to unit", "from unit"),
    "beta": ("branch", "hidden layer"),
}


def tick_labels(size: int, axis_title: str) -> list[str]:
    """Command names for 4 branches, ``command/subspace`` for 4*S units, indices otherwise."""
    if "expert" in axis_title or "layer" in axis_title:
        return [str(i + 1) for i in range(size)]
    if size == N_COMMANDS:
        return list(COMMANDS)
    if size % N_COMMANDS == 0:
        s = size // N_COMMANDS
        return [f"{COMMANDS[i // s]}/{i % s + 1}" for i in range(size)]
    return [str(i) for i in range(size)]


def offdiag_abs(m: torch.Tensor) -> float:
    """Mean |m_ij| over i != j of a square matrix; for C (diagonal 1) this is how much branches mix."""
    n = m.shape[-1]
    return float(m[~torch.eye(n, dtype=torch.bool)].abs().mean())


def heatmap_figure(name: str, panels: Mapping[str, np.ndarray], epoch: int) -> Figure:
    """One heatmap per panel, side by side, values written in the cells, a shared colour scale."""
    rows_t, cols_t = next((v for k, v in AXES.items() if name.startswith(k)), ("row", "column"))
    values = np.stack(list(panels.values()))
    nonneg = bool((values >= 0).all())
    vmax = float(np.abs(values).max()) or 1.0
    vmin, cmap = (0.0, "viridis") if nonneg else (-vmax, "RdBu_r")
    r, c = values.shape[1:]
    cell = 0.55 if max(r, c) <= 8 else 0.3
    fig = Figure(figsize=(len(panels) * (c * cell + 1.6) + 0.8, r * cell + 2.3), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (title, m) in zip(axes, panels.items()):
        im = ax.imshow(m, cmap=cmap, vmin=vmin, vmax=vmax)
        ax.set_title(title, fontsize=9)
        ax.set_xticks(range(c), tick_labels(c, cols_t), rotation=60, fontsize=7)
        ax.set_yticks(range(r), tick_labels(r, rows_t), fontsize=7)
        if max(r, c) <= 12:
            for i in range(r):
                for j in range(c):
                    bright = (m[i, j] - vmin) / (vmax - vmin + 1e-12)
                    dark_cell = bright < 0.5 if nonneg else abs(m[i, j]) > 0.6 * vmax
                    ax.text(j, i, f"{m[i, j]:.2f}", ha="center", va="center", fontsize=6,
                            color="white" if dark_cell else "black")
        ax.set_xlabel(cols_t, fontsize=7)
    axes[0].set_ylabel(rows_t, fontsize=7)
    fig.colorbar(im, ax=list(axes), shrink=0.8)
    fig.suptitle(f"{name}, validation epoch {epoch}", fontsize=10)
    return fig


def figure_rgb(fig: Figure) -> np.ndarray:
    """The figure rendered as an (H, W, 3) uint8 array."""
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def save_png(fig: Figure, path: str) -> None:
    """Write atomically, with the umask's mode (the shared writer, ``cicfw.core.files``)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write(path, buf.getbuffer())


class MixerDiagnostics(L.Callback):
    """Per-command averages of the mixer's ``inspect()`` matrices over each validation epoch, as heatmaps."""

    def __init__(self, subdir: str = "diagnostics") -> None:
        self.subdir = subdir
        self._reset()

    def _reset(self) -> None:
        self.sums: dict[str, torch.Tensor] = {}  # name -> (4, r, c) float64 sums per command
        self.counts: dict[str, torch.Tensor] = {}  # name -> (4,) samples per command
        self.globals: dict[str, torch.Tensor] = {}  # name -> (r, c)
        self.written: list[str] = []  # PNG paths of the last epoch (for users and tests)

    def on_validation_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._reset()

    def on_validation_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        mixer = getattr(pl_module, "mixer", None)
        if trainer.sanity_checking or mixer is None or not hasattr(mixer, "inspect"):
            return
        command = batch["command"].long().cpu()
        for name, m in mixer.inspect().items():
            m = m.detach().double().cpu()
            if m.dim() == 2:
                self.globals[name] = m
            elif m.dim() == 3 and m.shape[0] == command.shape[0]:
                if name not in self.sums:
                    self.sums[name] = torch.zeros((N_COMMANDS, *m.shape[1:]), dtype=torch.float64)
                    self.counts[name] = torch.zeros(N_COMMANDS, dtype=torch.float64)
                self.sums[name].index_add_(0, command, m)
                self.counts[name] += torch.bincount(command, minlength=N_COMMANDS).double()
            else:
                warnings.warn(f"MixerDiagnostics: skipped {name!r} of shape {tuple(m.shape)}: expected (r, c) "
                              f"or (B={command.shape[0]}, r, c)", stacklevel=2)

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or not (self.sums or self.globals):
            return
        log_dir = trainer.log_dir or trainer.default_root_dir  # every rank must call log_dir
        figures: dict[str, dict[str, np.ndarray]] = {}
        for name, sums in self.sums.items():
            counts = self.counts[name]
            seen = [k for k in range(N_COMMANDS) if counts[k] > 0]
            means = {k: sums[k] / counts[k] for k in seen}
            figures[name] = {f"command {COMMANDS[k]} (n={int(counts[k])})": means[k].numpy() for k in seen}
            if sums.shape[1] == sums.shape[2]:
                total = sums.sum(0) / counts.sum()
                pl_module.log(f"diagnostics/{name}_offdiag_abs", offdiag_abs(total))
                for k in seen:
                    pl_module.log(f"diagnostics/{name}_offdiag_abs/{COMMANDS[k]}", offdiag_abs(means[k]))
        for name, m in self.globals.items():
            figures[name] = {"learned (global)": m.numpy()}
            if m.shape[0] == m.shape[1]:
                pl_module.log(f"diagnostics/{name}_offdiag_abs", offdiag_abs(m))
        if not trainer.is_global_zero:
            return
        tensorboards = [lg for lg in trainer.loggers if isinstance(lg, TensorBoardLogger)]
        epoch = trainer.current_epoch
        for name, panels in figures.items():
            fig = heatmap_figure(name, panels, epoch)
            path = os.path.join(log_dir, self.subdir, f"epoch_{epoch:03d}_{name}.png")
            save_png(fig, path)
            self.written.append(path)
            for tb in tensorboards:
                tb.experiment.add_image(f"diagnostics/{name}", figure_rgb(fig), trainer.global_step,
                                        dataformats="HWC")
