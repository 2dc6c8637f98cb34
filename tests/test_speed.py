"""The training speed switches (cicfw/model/speed.py, conf/speed/default.yaml): the default variant
computes what eager computes, falls back to eager with one warning where compile cannot work, and
writes checkpoints that load in an eager process and in the closed-loop policy."""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from cicfw.benchmark.checkpoint_policy import CheckpointPolicy
from cicfw.benchmark.policy import Observations
from cicfw.model.checkpoint import load_model
from cicfw.model.module import CICModule
from cicfw.model.speed import AUTO_COMPILE_MIN_STEPS, SpeedConfig, apply_speed, dummy_batch, planned_steps, time_steps
from cicfw.train.app import train
from cicfw.train.schema import checked_speed

from conftest import compose_train

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

# The default variant against eager, same weights, same fixed batch, train mode without dropout (so
# the step is deterministic). Measured differences: outputs and loss ~4e-8, gradients ~5e-6 of each
# tensor's largest entry (fp32 summation order in the compiled and NHWC kernels). Stated tolerances:
OUT_ATOL = 1e-6           # outputs are ~0.05 in size: 1e-6 is ~2e-5 relative
GRAD_RTOL_OF_MAX = 1e-4   # per parameter tensor: max |g_fast - g_eager| <= 1e-4 * max |g_eager|
NO_DROPOUT = {"encoder_kwargs": {"dropout_conv": 0.0, "dropout_fc": 0.0}, "mixer_kwargs": {"dropout": 0.0}}


def default_speed() -> SpeedConfig:
    speed = checked_speed(compose_train())
    speed.compile = speed.compile in (True, "auto")  # the main job's runs are long enough for auto
    return speed


def _step(model: CICModule, batch):
    model.train()
    model.zero_grad(set_to_none=True)
    _, loss, out = model._losses(batch)
    loss.backward()
    return loss.detach(), out.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}


def test_default_variant_equals_eager_on_a_fixed_batch():
    speed = default_speed()
    assert speed.compile and speed.channels_last and speed.adam == "for-loop"  # what this test vouches for
    torch.manual_seed(0)
    eager, fast = CICModule(**NO_DROPOUT), CICModule(**NO_DROPOUT)
    fast.load_state_dict(eager.state_dict())
    variant = apply_speed(fast, speed, batch_size=8)
    assert variant.startswith("compile+channels_last") and fast._compiled_step is not None, variant
    batch = dummy_batch(fast, 8)
    loss_e, out_e, grad_e = _step(eager, batch)
    loss_f, out_f, grad_f = _step(fast, batch)
    torch.testing.assert_close(out_f, out_e, rtol=0, atol=OUT_ATOL)
    torch.testing.assert_close(loss_f, loss_e, rtol=0, atol=OUT_ATOL)
    for name, g in grad_e.items():
        err = (grad_f[name] - g).abs().max().item()
        assert err <= GRAD_RTOL_OF_MAX * g.abs().max().item() + 1e-12, f"{name}: |dgrad| {err:.3g}"
    # BatchNorm's running statistics move the same way
    for (name, a), b in zip(eager.named_buffers(), fast.buffers()):
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6, msg=name)


def test_fused_adam_step_equals_the_for_loop_step():
    torch.manual_seed(0)
    ref, fused = CICModule(), CICModule()
    fused.load_state_dict(ref.state_dict())
    fused.adam_impl = "fused"
    opts = [m.configure_optimizers() for m in (ref, fused)]
    assert opts[1].defaults["fused"] and not opts[0].defaults.get("fused")
    for _ in range(3):
        for p, q in zip(ref.parameters(), fused.parameters()):
            p.grad = torch.randn_like(p)
            q.grad = p.grad.clone()
        for o in opts:
            o.step()
    for p, q in zip(ref.parameters(), fused.parameters()):
        torch.testing.assert_close(q, p, rtol=1e-6, atol=1e-7)


def test_time_steps_takes_the_training_steps_a_hand_loop_takes():
    """bench/'s timing loop: one optimizer step per batch, the same losses and weights as a hand-written
    training loop from the same start, and a rate over the steps after the warm-up."""
    torch.manual_seed(0)
    timed, hand = CICModule(), CICModule()
    hand.load_state_dict(timed.state_dict())
    opts = [m.configure_optimizers() for m in (timed, hand)]
    batches = [dummy_batch(None, 6), {**dummy_batch(None, 6), "steer": torch.zeros(6)}] * 2
    torch.manual_seed(1)
    losses: list[float] = []
    rate, cores = time_steps(timed, opts[0], batches, warmup=1, losses=losses)
    torch.manual_seed(1)
    hand.train()
    expected = []
    for b in batches:
        _, loss, _ = hand._losses(hand.on_after_batch_transfer(b, 0))
        opts[1].zero_grad()
        loss.backward()
        opts[1].step()
        expected.append(loss.item())
    assert losses == pytest.approx(expected, rel=1e-6)
    for p, q in zip(timed.parameters(), hand.parameters()):
        torch.testing.assert_close(p, q)
    assert rate > 0 and cores > 0


def _failing_compile(when: str):
    def compile_(fn, *args, **kwargs):
        if when == "call":
            raise RuntimeError("torch.compile is not supported on this platform")

        def compiled(*a, **k):  # inductor fails at the first call, e.g. without a C compiler
            raise RuntimeError("InvalidCxxCompiler: No working C++ compiler found in torch._inductor.config.cpp.cxx\n"
                               "second line of the message")
        return compiled
    return compile_


@pytest.mark.parametrize("when", ["call", "first step"])
def test_compile_failure_falls_back_with_one_warning(monkeypatch, caplog, when):
    monkeypatch.setattr(torch, "compile", _failing_compile(when))
    torch.manual_seed(0)
    model = CICModule()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with caplog.at_level(logging.WARNING):
        variant = apply_speed(model, SpeedConfig(channels_last=True, compile=True, adam="fused", keep_memory=False),
                              batch_size=8)
    assert variant == "channels_last, Adam fused" and model._compiled_step is None
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "\n" not in warnings[0].getMessage() and not warnings[0].exc_info, \
        [r.getMessage() for r in warnings]
    assert "without compile" in warnings[0].getMessage()
    for k, v in model.state_dict().items():  # the failed warm-up left the model as it was
        assert torch.equal(v, before[k]), k
    _step(model, dummy_batch(model, 8))  # and it trains


def test_train_with_compile_forced_and_no_compiler_still_trains(monkeypatch, caplog, fast_cfg, tmp_path):
    monkeypatch.setattr(torch, "compile", _failing_compile("first step"))
    fast_cfg.speed.compile = True
    with caplog.at_level(logging.WARNING):
        train(fast_cfg, tmp_path / "run")
    assert sum("torch.compile is not usable" in r.getMessage() for r in caplog.records) == 1


def test_auto_compiles_only_runs_long_enough_to_pay():
    from omegaconf import open_dict

    full = compose_train()
    cfg = full.trainer
    assert full.speed.compile == "auto"

    def trainer(**values):
        """The default trainer node with ``values`` set, as the overrides ``trainer.<key>=<value>`` give it."""
        node = cfg.copy()
        with open_dict(node):
            node.update(values)
        return node

    assert planned_steps(cfg, 250) == 250 * cfg.max_epochs >= AUTO_COMPILE_MIN_STEPS
    assert planned_steps(trainer(max_epochs=1), 3) == 3 < AUTO_COMPILE_MIN_STEPS
    assert planned_steps(trainer(fast_dev_run=True), 250) == 1
    assert planned_steps(trainer(max_steps=50), 250) == 50
    assert planned_steps(trainer(max_epochs=-1), 3) == float("inf")
    assert planned_steps(trainer(limit_train_batches=0.5), 250) == 125 * cfg.max_epochs


def test_every_trainer_config_and_experiment_gets_the_default_speed():
    from cicfw.conf import __file__ as conf_init
    from pathlib import Path

    experiments = sorted(p.stem for p in (Path(conf_init).parent / "experiment").glob("*.yaml"))
    default = default_speed()
    for over in [[], ["trainer=ddp"], *[[f"experiment={e}"] for e in experiments]]:
        speed = checked_speed(compose_train(*over))
        speed.compile = speed.compile in (True, "auto")
        assert speed == default, over


def test_checkpoint_of_a_compiled_run_loads_eager_and_in_the_policy(tiny_data, tmp_path, caplog):
    cfg = compose_train("data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "data.val_batch_size=16",
                        "data.batches_per_epoch=2", "trainer.max_epochs=1", "speed.compile=true",
                        "encoder.dropout_conv=0", "encoder.dropout_fc=0", "mixer.dropout=0",  # test 1's graph: cached
                        "progress_bar=false")
    with caplog.at_level(logging.INFO, logger="cicfw.speed"):
        train(cfg, tmp_path / "run")
    assert any("training step compiled" in r.getMessage() for r in caplog.records)  # compile did run
    path = tmp_path / "run" / "checkpoints" / "last.ckpt"
    state = torch.load(path, weights_only=True)["state_dict"]
    assert not [k for k in state if "_orig_mod" in k or "_compiled" in k]
    model = load_model(path)  # strict load into a plain, eager CICModule
    policy = CheckpointPolicy(checkpoint=str(path))  # BN folded, NHWC
    rng = np.random.default_rng(0)
    obs = Observations(images={"centre": rng.integers(0, 256, (4, 88, 200, 3), dtype=np.uint8)},
                       speed_kmh=np.array([0.0, 10.0, 20.0, 30.0]), command=np.array([2, 3, 4, 5]),
                       pose=np.zeros((4, 3)), routes=[None] * 4, episode=np.arange(4))
    steer = policy.act(obs)
    img = torch.from_numpy(obs.images["centre"]).permute(0, 3, 1, 2)
    with torch.no_grad():
        ref = model.predict_steer(img, torch.tensor(obs.speed_kmh, dtype=torch.float32), torch.arange(4))
    np.testing.assert_allclose(steer, ref.clamp(-1, 1).numpy(), atol=1e-5)


def test_a_checkpoint_with_compile_wrapper_prefixes_loads_in_the_policy(tmp_path):
    import lightning as L

    torch.manual_seed(0)
    model = CICModule()
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, max_epochs=0)
    trainer.strategy.connect(model)
    trainer.save_checkpoint(tmp_path / "plain.ckpt")
    ckpt = torch.load(tmp_path / "plain.ckpt", weights_only=True)
    # what torch.compile(model) / torch.compile(model.encoder) would have saved
    ckpt["state_dict"] = {k.replace("encoder.", "encoder._orig_mod.", 1): v for k, v in ckpt["state_dict"].items()}
    torch.save(ckpt, tmp_path / "prefixed.ckpt")
    loaded = load_model(tmp_path / "prefixed.ckpt")
    for k, v in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
