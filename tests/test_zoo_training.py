"""Every mixer x head trains: built by CICModule from names, one Lightning fast_dev_run step, a falling
loss on a fixed batch; MixerDiagnostics writes its heatmaps."""
from __future__ import annotations

import itertools

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader

from cicfw.model.diagnostics import MixerDiagnostics
from cicfw.model.module import CICModule

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

MIXERS = ["independent", "gtu", "re", "moe", "soft_sharing", "cross_stitch", "sluice"]
HEADS = ["regression", "softmax", "hybrid", "coexistence", "sine"]
PAIRS = list(itertools.product(MIXERS, HEADS))
NO_DROPOUT = {"dropout_conv": 0.0, "dropout_fc": 0.0}


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Batches of 4 gain nothing from a second thread, and on a busy 2-core machine two threads wait on
    each other: measured under load 7, this file took 205 s with 2 threads and 40 s with 1."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _batch(n: int = 4, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "image": torch.randint(0, 256, (n, 3, 88, 200), dtype=torch.uint8, generator=g),
        "speed": torch.rand(n, generator=g) * 30,  # km/h
        "command": torch.arange(n) % 4,
        "steer": torch.rand(n, generator=g) * 1.6 - 0.8,
    }


def _model(mixer: str, head: str, **kw) -> CICModule:
    torch.manual_seed(0)
    return CICModule(encoder_kwargs=NO_DROPOUT, mixer=mixer, mixer_kwargs={"dropout": 0.0, **kw},
                     head=head, lr=1e-3)


def _loader(n_batches: int, n: int = 4) -> DataLoader:
    return DataLoader([_batch(n, seed=i) for i in range(n_batches)], batch_size=None)


def _trainer(**kw) -> L.Trainer:
    return L.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                     enable_model_summary=False, **kw)


#: every mixer and every head in one Lightning step each: each mixer with the next head in turn (7 pairs,
#: each head at least once). The step's cost is the encoder's, the same in every pair; what differs between
#: pairs, the mixer and head training together, is what every pair's fixed-batch fit below tests.
COVER = [(m, HEADS[i % len(HEADS)]) for i, m in enumerate(MIXERS)]


@pytest.mark.parametrize("mixer, head", COVER)
def test_mixer_and_head_train_one_fast_dev_run_step_through_the_encoder(mixer, head):
    model = _model(mixer, head)
    assert type(model.mixer).__module__.endswith(mixer) and model.hparams.head == head
    enc_before = [p.detach().clone() for p in model.encoder.parameters()]
    _trainer(fast_dev_run=1).fit(model, _loader(1), _loader(1))
    # The step reached the encoder through the mixer and head (nothing detached on the way).
    assert any(not torch.equal(a, b) for a, b in zip(enc_before, model.encoder.parameters()))


@pytest.mark.parametrize("mixer, head", PAIRS)
def test_pair_fits_a_fixed_batch(mixer, head):
    model = _model(mixer, head)
    assert type(model.mixer).__module__.endswith(mixer) and model.hparams.head == head
    # 20 optimizer steps on one fixed batch. The encoder (the same in every pair, tested end to end by
    # the step above, and most of a step's cost on CPU) is a fixed feature extractor here, computed
    # once, so the 35 pairs stay fast; the mixer and head, what differs between pairs, train on it
    # with the module's branch selection and loss.
    batch = _batch()
    model.train()
    model.encoder.requires_grad_(False).eval()
    with torch.no_grad():
        h = model.encoder(batch["image"], batch["speed"] / model.speed_norm_kmh)
    rows = torch.arange(h.shape[0])
    opt = model.configure_optimizers()  # Adam skips the frozen parameters (their grad stays None)

    def loss() -> torch.Tensor:
        out = model.mixer(h)[rows, batch["command"]]  # as CICModule.forward: each sample's own branch
        return model.head.loss(out, batch["steer"]) + model.mixer.regularizer()

    first = loss()
    for _ in range(20):
        opt.zero_grad()
        value = loss()
        value.backward()
        opt.step()
    last = loss().item()
    assert torch.isfinite(first) and last < first.item() - 0.2 * abs(first.item()), (first.item(), last)


def test_mixer_diagnostics_writes_the_colearning_heatmaps(tmp_path):
    model = _model("gtu", "regression")
    diag = MixerDiagnostics()
    trainer = _trainer(default_root_dir=str(tmp_path), max_epochs=2, limit_train_batches=1,
                       num_sanity_val_steps=0, callbacks=[diag])
    trainer.fit(model, _loader(1, n=8), _loader(2, n=8))
    pngs = sorted(p.name for p in (tmp_path / "diagnostics").glob("*.png"))
    assert pngs == ["epoch_000_C.png", "epoch_001_C.png"]
    assert all(p.stat().st_size > 5000 for p in (tmp_path / "diagnostics").glob("*.png"))
    # Mean |off-diagonal C| logged per validation epoch, and within tanh * sigmoid's range.
    value = trainer.callback_metrics["diagnostics/C_offdiag_abs"]
    assert 0 < value < 1
    assert {f"diagnostics/C_offdiag_abs/{c}" for c in ("follow", "left", "right", "straight")} <= set(
        trainer.callback_metrics)
    # The per-command average is the mean of the last epoch's per-sample C over that command's samples.
    sums, counts = diag.sums["C"], diag.counts["C"]
    assert torch.equal(counts, torch.full((4,), 4.0, dtype=torch.float64))
    assert torch.allclose(torch.diagonal(sums / counts[:, None, None], dim1=1, dim2=2), torch.ones(4, 4,
                          dtype=torch.float64))


def test_mixer_diagnostics_sends_images_to_tensorboard(tmp_path):
    from lightning.pytorch.loggers import TensorBoardLogger
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    model = _model("moe", "softmax", experts=3)
    logger = TensorBoardLogger(str(tmp_path), name="tb", version="")
    trainer = L.Trainer(accelerator="cpu", logger=logger, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, max_epochs=1, limit_train_batches=1, num_sanity_val_steps=0,
                        callbacks=[MixerDiagnostics()])
    trainer.fit(model, _loader(1, n=8), _loader(1, n=8))
    assert (tmp_path / "tb" / "diagnostics" / "epoch_000_gates.png").exists()  # under the logger's log_dir
    events = EventAccumulator(str(tmp_path / "tb")).Reload()
    assert "diagnostics/gates" in events.Tags()["images"]


PAPER_GRID = {  # experiment -> (mixer, head, head values the paper fixes)
    "paper_cil": ("independent", "regression", {}),
    "paper_gtu": ("gtu", "regression", {}),
    "paper_re": ("re", "regression", {}),
    "paper_soft_sharing": ("soft_sharing", "regression", {}),
    "paper_moe": ("moe", "regression", {}),
    "paper_sluice": ("sluice", "regression", {}),
    "paper_cross_stitch": ("cross_stitch", "regression", {}),
    "paper_classification": ("independent", "softmax", {}),
    "paper_coexistence": ("independent", "coexistence", {"W": 0.6, "sigma2": 1.0}),
    "paper_hybrid": ("independent", "hybrid", {"W": 10}),
    "paper_sine": ("independent", "sine", {}),
}


def test_the_paper_grid_glob_selects_every_paper_experiment():
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        parser = OverridesParser.create(config_loader=GlobalHydra.instance().config_loader())
        (override,) = parser.parse_overrides(["experiment=glob(paper_*)"])
        assert sorted(override.sweep_string_iterator()) == sorted(PAPER_GRID)


@pytest.mark.parametrize("experiment", sorted(PAPER_GRID))
def test_paper_experiment_composes_to_its_model(experiment):
    from conftest import compose_train
    from cicfw.train.app import build_model

    cfg = compose_train(f"experiment={experiment}")
    mixer, head, values = PAPER_GRID[experiment]
    assert (cfg.mixer.name, cfg.head.name) == (mixer, head)
    for key, value in values.items():
        assert cfg.head[key] == value
    model = build_model(cfg)
    assert model.hparams.mixer == mixer and model.hparams.head == head


@pytest.mark.parametrize("mixer, head", [("re", "coexistence"), ("sluice", "sine"), ("moe", "hybrid")])
def test_zoo_checkpoint_round_trip_gives_identical_outputs(tmp_path, mixer, head):
    kwargs = {"R": [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1], [0, 0, 1, 0]]} if mixer == "re" else {}
    model = _model(mixer, head, **kwargs).eval()
    trainer = _trainer(max_epochs=0)
    trainer.strategy.connect(model)
    trainer.save_checkpoint(tmp_path / "m.ckpt")
    loaded = CICModule.load_from_checkpoint(tmp_path / "m.ckpt", weights_only=True).eval()
    b = _batch()
    args = (b["image"], b["speed"], b["command"])
    assert torch.equal(model(*args), loaded(*args))
    assert torch.equal(model.predict_steer(*args), loaded.predict_steer(*args))
