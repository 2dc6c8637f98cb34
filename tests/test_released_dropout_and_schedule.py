"""cicfw 0.2's training recipe: dropout where the CIL authors' released network has it, and
the cosine learning-rate schedule. Expected values are written out from their sources, not read back
from the modules."""
from __future__ import annotations

import math

import lightning as L
import pytest
import torch
from torch import nn

import cicfw.train.app as train_mod
from cicfw.core.errors import ConfigError
from cicfw.train.app import build_model, train
from cicfw.model.checkpoint import load_model
from conftest import TINY_TRAIN, compose_train, train_tiny_run, write_tiny_dataset

# carla-simulator/imitation-learning, imitation_learning_network.py: dropout_vec holds KEEP probabilities,
# 1.0 for the 8 convolutions, 0.7 for the two image FCs, 0.5 for the two speed FCs and the join, then
# per branch 0.5 after the first hidden FC and 1.0 after the second. As drop rates, in execution order:
RELEASED_ENCODER = [0.3, 0.3, 0.5, 0.5, 0.5]
RELEASED_BRANCH = [0.5, 0.0]


def _drop_rates_in_execution_order(model: nn.Module) -> list[float]:
    rates: list[float] = []
    hooks = [m.register_forward_hook(lambda mod, i, o: rates.append(mod.p))
             for m in model.modules() if isinstance(m, (nn.Dropout, nn.Dropout2d))]
    image = torch.zeros(4, 3, 88, 200, dtype=torch.uint8)
    with torch.no_grad():
        model(image, torch.zeros(4), torch.arange(4))
    for h in hooks:
        h.remove()
    return rates


def test_the_default_cil_row_drops_where_the_released_network_does():
    model = build_model(compose_train())
    rates = _drop_rates_in_execution_order(model)
    assert rates == RELEASED_ENCODER + RELEASED_BRANCH * 4  # the encoder, then each of the four branches


@pytest.mark.parametrize("mixer", ["independent", "gtu", "moe", "soft_sharing", "sluice", "cross_stitch", "re"])
def test_every_rows_branches_use_the_released_pair(mixer):
    model = build_model(compose_train(f"mixer={mixer}"))
    assert _drop_rates_in_execution_order(model)[:5] == RELEASED_ENCODER
    # sluice and cross-stitch run the branches layer by layer, so look at each branch's own layers
    for branch in model.mixer.branches:
        assert [m.p for m in branch.modules() if isinstance(m, nn.Dropout)] == RELEASED_BRANCH


def test_cicfw_0_1_layout_is_still_reachable():
    """The old layout: Dropout2d 0.2 after each of the 8 convolutions, 0.5 after every FC and both branch layers."""
    model = build_model(compose_train("encoder.dropout_conv=0.2", "encoder.dropout_fc=0.5", "mixer.dropout=0.5"))
    assert _drop_rates_in_execution_order(model) == [0.2] * 8 + [0.5] * 5 + [0.5, 0.5] * 4


def _lrs_seen(tmp_path, monkeypatch, *overrides: str) -> list[float]:
    """The learning rate the optimizer holds at the start of every training batch."""
    seen: list[float] = []

    class Record(L.Callback):
        def on_train_batch_start(self, trainer, *args):
            seen.append(trainer.optimizers[0].param_groups[0]["lr"])

    _train_tiny(tmp_path, monkeypatch, Record(), "trainer.max_epochs=2", "trainer.limit_train_batches=3", *overrides)
    return seen


def _train_tiny(tmp_path, monkeypatch, record: L.Callback, *overrides: str) -> None:
    """Train a tiny dataset in ``tmp_path / "run"`` with ``record`` among the callbacks, in batches of 4 (the
    smallest the data allows): the schedule and the average follow the steps, whatever a step's size."""
    build = train_mod.build_callbacks
    monkeypatch.setattr(train_mod, "build_callbacks", lambda cfg, run_dir: [*build(cfg, run_dir), record])
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=32)
    cfg = compose_train("data=cil_hdf5", f"data.path={data}", "data.batch_size=4", "data.val_batch_size=4",
                        "progress_bar=false", "speed.compile=false", "trainer.limit_val_batches=1",
                        "trainer.num_sanity_val_steps=0", "trainer.enable_model_summary=false", *overrides)
    train(cfg, tmp_path / "run")


@pytest.mark.slow  # trains
@pytest.mark.parametrize("final", [0.0, 0.1])
def test_cosine_schedule_follows_half_a_cosine_over_the_run(tmp_path, monkeypatch, final):
    lr, total = 2e-4, 6  # 2 epochs x 3 batches
    seen = _lrs_seen(tmp_path, monkeypatch, "model.lr_schedule=cosine", f"model.lr_final_factor={final}")
    # step t trains at lr * (final + (1 - final) * (1 + cos(pi t / T)) / 2): lr at t = 0, lr * final at t = T
    expected = [lr * (final + (1 - final) * (1 + math.cos(math.pi * t / total)) / 2) for t in range(total)]
    assert seen == pytest.approx(expected, rel=1e-9, abs=1e-15)
    assert seen[0] == pytest.approx(lr) and seen[3] == pytest.approx(lr * (final + (1 - final) / 2))


@pytest.mark.slow  # trains
def test_constant_schedule_keeps_the_papers_rate(tmp_path, monkeypatch):
    assert _lrs_seen(tmp_path, monkeypatch) == [2e-4] * 6


def test_unknown_schedule_is_one_line():
    with pytest.raises(ValueError, match=r"model.lr_schedule='step' is not known; use one of constant, cosine"):
        build_model(compose_train("model.lr_schedule=step"))


def test_a_final_factor_the_constant_schedule_never_reads_is_one_line():
    build_model(compose_train("model.lr_final_factor=0.0"))  # the default, beside the default constant schedule
    with pytest.raises(ConfigError) as err:
        build_model(compose_train("model.lr_final_factor=0.1"))
    assert (err.value.key, err.value.value) == ("model.lr_final_factor", 0.1) and "model.lr_schedule" in str(err.value)


@pytest.fixture(scope="module")
def tiny_last(tmp_path_factory):
    """The last checkpoint of one tiny training, shared: each test edits a copy of it."""
    return train_tiny_run(tmp_path_factory.mktemp("tiny"), *TINY_TRAIN, "trainer.limit_train_batches=1")["last"]


@pytest.mark.slow  # trains
@pytest.mark.parametrize("saved", [{"lr_final_factor": 0.1}, {"lr_schedule": None, "lr_final_factor": None}])
def test_checkpoints_saved_with_an_unused_factor_or_without_the_keys_load_and_resume(tiny_last, tmp_path, saved):
    last = tmp_path / "last.ckpt"
    ckpt = torch.load(tiny_last, weights_only=True)
    for key, value in saved.items():  # None: a checkpoint from before the key existed
        ckpt["hyper_parameters"].pop(key) if value is None else ckpt["hyper_parameters"].update({key: value})
    torch.save(ckpt, last)
    assert load_model(last).hparams.lr_final_factor == 0.0
    train_mod.check_resumed_optimizer(last, ckpt, build_model(compose_train()))


@pytest.mark.slow  # trains
@pytest.mark.parametrize("schedule, fraction, expected", [
    # 6 steps, round(0.34 * 6) = 2 of warm-up (lr/2, lr), then half a cosine over the other 4 steps
    ("cosine", 0.34, [0.5, 1.0, 1.0, (1 + math.cos(math.pi / 4)) / 2, 0.5, (1 + math.cos(3 * math.pi / 4)) / 2]),
    ("constant", 0.5, [1 / 3, 2 / 3, 1.0, 1.0, 1.0, 1.0]),  # 3 steps of warm-up, then the constant lr
])
def test_warmup_rises_linearly_then_hands_over_to_the_schedule(tmp_path, monkeypatch, schedule, fraction, expected):
    seen = _lrs_seen(tmp_path, monkeypatch, f"model.lr_schedule={schedule}", f"model.lr_warmup_fraction={fraction}")
    assert seen == pytest.approx([2e-4 * f for f in expected], rel=1e-9, abs=1e-15)


@pytest.mark.slow  # trains
def test_ema_checkpoints_hold_the_moving_average_of_the_trained_weights(tmp_path, monkeypatch):
    decay = 0.6
    raw: list[dict[str, torch.Tensor]] = []

    class Record(L.Callback):  # the trained (not averaged) weights after every optimizer step
        def on_train_batch_end(self, trainer, pl_module, *args):
            raw.append({k: v.detach().clone() for k, v in pl_module.named_parameters()})

    _train_tiny(tmp_path, monkeypatch, Record(), "trainer.max_epochs=1", "trainer.limit_train_batches=4",
                f"model.ema_decay={decay}")
    # by hand: the first average is the first step's weights, then a <- decay * a + (1 - decay) * w
    average = dict(raw[0])
    for weights in raw[1:]:
        average = {k: decay * average[k] + (1 - decay) * w for k, w in weights.items()}
    saved = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert len(raw) == 4
    for name, value in average.items():
        torch.testing.assert_close(saved["state_dict"][name], value, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(saved["current_model_state"][name], raw[-1][name])  # resumes from these


@pytest.mark.parametrize("key, value", [("lr_warmup_fraction", 1.0), ("lr_warmup_fraction", -0.1),
                                        ("ema_decay", 1.0), ("ema_decay", -0.5)])
def test_warmup_and_ema_ranges_are_one_line(key, value):
    with pytest.raises(ConfigError) as err:
        build_model(compose_train(f"model.{key}={value}"))
    assert (err.value.key, err.value.value) == (f"model.{key}", value)


@pytest.mark.parametrize("override, key, value", [("model.betas=[1.5,0.85]", "model.betas", [1.5, 0.85]),
                                                 ("model.betas=[0.9]", "model.betas", [0.9]),
                                                 ("model.weight_decay=-1", "model.weight_decay", -1.0)])
def test_adam_settings_out_of_range_are_one_line_before_any_data(override, key, value):
    """Adam refused these only inside fit, with a traceback, after the run folder was made."""
    with pytest.raises(ConfigError) as err:
        build_model(compose_train(override))
    assert (err.value.key, err.value.value) == (key, value)
