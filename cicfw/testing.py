"""The checks a plugin author runs: the Mixer and Head contracts, and one tiny end-to-end training.

    from cicfw.testing import check_head, check_mixer, fast_dev_run

    def test_contract():
        check_mixer("attention")          # by registered name: also proves the entry point works

    def test_trains(tmp_path):
        assert fast_dev_run(tmp_path, "mixer=attention") >= 0  # also proves the config is found

Each check raises ``AssertionError`` with a message that says which rule was broken.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_module
from hydra.errors import HydraException

from cicfw import N_COMMANDS
from cicfw.core.errors import CicfwError, ConfigError
from cicfw.core.override_hints import composition_error
from cicfw.core.files import atomic_write
from cicfw.data.cil_hdf5 import N_TARGETS, T, file_bytes
from cicfw.model.heads import Head
from cicfw.model.mixers import Mixer
from cicfw.registry import HEADS, MIXERS
from cicfw.train.app import check_config, train
from cicfw.train.schema import without_plus_on_trainer


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise AssertionError(message)


def _at_least(key: str, value: object, least: int, why: str) -> None:
    """A size the contract checks are run at: an empty batch would pass every check while checking nothing."""
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ConfigError(key, value, f"an integer >= {least} ({why})")


def check_mixer(name: str, in_dim: int = 64, batch: int = 5, **kwargs) -> Mixer:
    """Build the registered mixer ``name`` with ``kwargs`` and check the Mixer contract:
    (B, in_dim) -> (B, 4, K) for K = 1 and 9, finite, no mixing across samples, a scalar
    regularizer, a gradient for every parameter (DDP needs that), well-shaped ``inspect()``,
    and a state_dict that rebuilds the same mixer. Returns the last mixer built."""
    _at_least("batch", batch, 2, "samples; that none mixes with another needs two")
    _at_least("in_dim", in_dim, 1, "features per sample")
    cls = MIXERS.get(name)
    torch.manual_seed(0)
    h = torch.randn(batch, in_dim)
    for out_dim in (1, 9):
        mixer = cls(in_dim=in_dim, out_dim=out_dim, **kwargs)
        _require(isinstance(mixer, Mixer), f"mixer {name!r}: {cls.__name__} must subclass cicfw.model.mixers.Mixer")
        mixer.train()
        out = mixer(h)
        shape = (batch, N_COMMANDS, out_dim)
        _require(tuple(out.shape) == shape, f"mixer {name!r}: forward gave {tuple(out.shape)}, expected {shape}")
        _require(bool(torch.isfinite(out).all()), f"mixer {name!r}: forward gave non-finite values")
        reg = mixer.regularizer()
        _require(isinstance(reg, torch.Tensor) and reg.dim() == 0 and bool(torch.isfinite(reg)),
                 f"mixer {name!r}: regularizer() must return a finite scalar tensor, got {reg!r}")
        (out.square().mean() + reg).backward()
        unused = [n for n, p in mixer.named_parameters() if p.requires_grad and p.grad is None]
        _require(not unused, f"mixer {name!r}: parameters without a gradient (DDP would fail): {unused}")
        for key, m in mixer.inspect().items():
            _require(isinstance(m, torch.Tensor) and (m.dim() == 2 or (m.dim() == 3 and m.shape[0] == batch)),
                     f"mixer {name!r}: inspect()[{key!r}] must be (r, c) or (B={batch}, r, c), got "
                     f"{getattr(m, 'shape', m)!r}")
        mixer.eval()
        with torch.no_grad():
            full = mixer(h)
            _require(torch.allclose(full[:2], mixer(h[:2]), atol=1e-5),
                     f"mixer {name!r}: in eval mode a sample's output depends on the rest of the batch")
            twin = cls(in_dim=in_dim, out_dim=out_dim, **kwargs)
            twin.load_state_dict(mixer.state_dict())
            twin.eval()
            _require(torch.allclose(full, twin(h), atol=1e-6),
                     f"mixer {name!r}: a copy built from its state_dict gives other outputs")
    return mixer


def check_head(name: str, batch: int = 6, **kwargs) -> Head:
    """Build the registered head ``name`` with ``kwargs`` and check the Head contract: a positive
    ``out_dim``, a finite differentiable scalar loss, decoded steering (B,) in [-1, 1], and for
    classification heads ``predict_class`` within the bins. Returns the head."""
    _at_least("batch", batch, 1, "samples the loss and decoding are checked on")
    cls = HEADS.get(name)
    head = cls(**kwargs)
    _require(isinstance(head, Head), f"head {name!r}: {cls.__name__} must subclass cicfw.model.heads.Head")
    k = getattr(head, "out_dim", None)
    _require(isinstance(k, int) and k >= 1, f"head {name!r}: out_dim must be a positive int set in __init__, got {k!r}")
    torch.manual_seed(0)
    out = torch.randn(batch, k, requires_grad=True)
    steer = torch.linspace(-0.8, 0.8, batch)
    loss = head.loss(out, steer)
    _require(isinstance(loss, torch.Tensor) and loss.dim() == 0 and bool(torch.isfinite(loss)),
             f"head {name!r}: loss() must return a finite scalar tensor, got {loss!r}")
    loss.backward()
    _require(out.grad is not None and bool(out.grad.abs().sum() > 0), f"head {name!r}: the loss has no gradient")
    with torch.no_grad():
        steer_hat = head.decode(out)
    _require(tuple(steer_hat.shape) == (batch,), f"head {name!r}: decode() gave {tuple(steer_hat.shape)}, expected ({batch},)")
    _require(bool(((steer_hat >= -1) & (steer_hat <= 1)).all()), f"head {name!r}: decode() left [-1, 1]")
    if head.bins is not None:
        cls_hat = head.predict_class(out.detach())
        _require(tuple(cls_hat.shape) == (batch,) and not cls_hat.is_floating_point(),
                 f"head {name!r}: predict_class() must give integer classes (B,), got {cls_hat!r}")
        _require(bool(((cls_hat >= 0) & (cls_hat < head.bins.n)).all()), f"head {name!r}: predict_class() left the bins")
    return head


def make_targets(n: int, rng: np.random.Generator, commands=(2, 3, 4, 5)) -> np.ndarray:
    """CIL ``targets`` (n, 28): random steer and speed, the commands and the three cameras cycled."""
    t = np.zeros((n, N_TARGETS), np.float32)
    t[:, T.STEER] = rng.uniform(-0.6, 0.6, n)
    t[:, T.SPEED] = rng.uniform(0, 30, n)
    t[:, T.COMMAND] = np.resize(np.asarray(commands, np.float32), n)
    t[:, T.CAMERA_ID] = np.resize(np.array([0, 1, 2], np.float32), n)
    t[:, T.CAMERA_YAW] = np.resize(np.array([0, -30, 30], np.float32), n)
    return t


def write_tiny_dataset(folder: Path, n_files: int = 6, n: int = 24, seed: int = 0, commands=(2, 3, 4, 5),
                       overwrite: bool = False) -> Path:
    """``n_files`` CIL HDF5 files of ``n`` random samples, every given command and camera present. A file of
    that name already there with other contents is refused unless ``overwrite`` (the same files written again
    are not: a helper may call this twice): ``data_00000.h5`` ... is how CoRL-2017's own files are named, so a
    folder of real data given by mistake would get random pixels in place of its images."""
    folder = Path(folder)
    rng = np.random.default_rng(seed)
    files = {}
    for i in range(n_files):
        t = make_targets(n, rng, commands)
        files[folder / f"data_{i:05d}.h5"] = file_bytes(rng.integers(0, 255, (n, 88, 200, 3), dtype=np.uint8), t)
    other = [p for p, data in files.items() if p.exists() and not _holds(p, data)]
    if other and not overwrite:
        raise CicfwError(f"write_tiny_dataset: {str(other[0])!r} already exists with other contents ({len(other)} of "
                         f"the {n_files} files it would write); give a fresh folder (pytest's tmp_path), or "
                         f"overwrite=True to replace them", key="folder", value=str(folder))
    for path, data in files.items():
        atomic_write(path, data)
    return folder


def _holds(path: Path, data: bytes) -> bool:
    """Whether the file at ``path`` is exactly ``data`` (its size first: a large file is not read)."""
    try:
        return path.stat().st_size == len(data) and path.read_bytes() == data
    except OSError:
        return False


def fast_dev_run(tmp_path: Path, *overrides: str) -> float:
    """Compose the train config with ``overrides`` on a tiny dataset written under ``tmp_path`` and
    run one training and one validation batch; returns the validation metric (finite)."""
    tmp_path = Path(tmp_path)
    for sub in ("data", "run"):  # meant for a fresh folder (pytest's tmp_path): never write over a user's files
        folder = tmp_path / sub
        if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
            raise CicfwError(f"fast_dev_run: {str(folder)!r} already exists and is not empty; give a fresh folder "
                             f"(pytest's tmp_path), whose data/ and run/ it writes", key="tmp_path", value=str(tmp_path))
    base = ["data=cil_hdf5", f"data.path={tmp_path / 'data'}", "data.batch_size=8", "data.val_batch_size=8",
            "debug=fast", "progress_bar=false"]
    args = without_plus_on_trainer([*base, *overrides])
    try:  # composed first: a bad override is refused as the CLI refuses it, before anything is written
        with initialize_config_module("cicfw.conf", version_base="1.3"):
            cfg = compose("train", overrides=args)
    except HydraException as err:
        refused = composition_error(err, list(overrides))
        if refused is None:
            raise
        raise refused from None
    check_config(cfg, refuse_finished=False)  # what train refuses (+evaluate_aftr=true ...), before the data is written
    write_tiny_dataset(tmp_path / "data")
    value = train(cfg, tmp_path / "run")
    _require(bool(np.isfinite(value)), f"fast_dev_run with {list(overrides)} gave {cfg.optimized_metric} = {value}")
    return value
