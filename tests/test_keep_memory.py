"""``speed.keep_memory`` (cicfw/model/memory.py): the training step stops page-faulting its activations
in again, and computes exactly what it computed without the switch. Both variants run in one fresh process,
through ``apply_speed_from_config`` as cicfw.train applies it: first without the switch, then with it (the
switch is process-wide and not undone, so the plain steps must come first)."""
from __future__ import annotations

import json
import platform
import statistics
import subprocess
import sys

import pytest

from cicfw.core.config_checks import SchemaError
from cicfw.model.speed import SpeedConfig

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

STEPS = """
import json, resource, sys
import torch
from hydra import compose, initialize_config_module
from cicfw.model.speed import apply_speed_from_config, dummy_batch
from cicfw.train.app import build_model
from cicfw.train.schema import checked_speed

torch.set_num_threads(1)


def steps(keep):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("train", overrides=["experiment=paper_cil", "speed.compile=false", "speed.channels_last=true",
                                          "speed.adam=for-loop", f"speed.keep_memory={keep}"])
    torch.manual_seed(0)
    model = build_model(cfg).train()
    variant = apply_speed_from_config(model, checked_speed(cfg), cfg.trainer, 16, 6)
    opt = model.configure_optimizers()
    opt = opt["optimizer"] if isinstance(opt, dict) else opt
    batch = dummy_batch(None, 16)
    faults, losses = [], []
    for i in range(6):
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        opt.zero_grad()
        loss = model.training_step(batch, i)
        loss.backward()
        opt.step()
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
        losses.append(float(loss))
    return {"variant": variant, "faults": faults, "losses": losses,
            "weights": [float(p.double().sum()) for p in model.parameters()]}


print(json.dumps([steps(False), steps(True)]))
"""


def run() -> tuple[dict, dict]:
    """The plain steps, then the same steps with the switch on, in one fresh process."""
    out = subprocess.run([sys.executable, "-c", STEPS], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    plain, kept = json.loads(out.stdout.strip().splitlines()[-1])
    return plain, kept


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                    reason="the switch sets glibc's malloc thresholds")
def test_kept_memory_stops_the_page_faults_and_computes_the_same():
    plain, kept = run()
    assert "freed memory kept" in kept["variant"] and "freed memory kept" not in plain["variant"]
    assert kept["losses"] == plain["losses"] and kept["weights"] == plain["weights"]  # bit for bit
    # after two steps of warm-up the heap holds what a step needs. Measured at batch 16: 8-32 k faults a
    # step without the switch, 0 in most steps with it (now and then a few thousand as the heap grows)
    assert statistics.median(kept["faults"][2:]) * 10 < statistics.median(plain["faults"][2:]), (
        kept["faults"], plain["faults"])


def test_keep_memory_takes_true_or_false_only():
    from cicfw.core.config_checks import checked
    from cicfw.train.schema import SPEED

    with pytest.raises(SchemaError) as err:  # the speed node's schema, as composing applies it
        checked(SPEED, {"keep_memory": "maybe"}, "speed")
    assert (err.value.kind, err.value.key) == ("wrong type", "speed.keep_memory"), err.value
    assert SpeedConfig().keep_memory is True  # the default (conf/speed/default.yaml)


def test_train_takes_the_switch_as_its_own_not_as_a_trainer_argument():
    from hydra import compose, initialize_config_module

    from cicfw.train.app import trainer_kwargs

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("train", overrides=["speed.keep_memory=false"])
    assert cfg.speed.keep_memory is False and "keep_memory" not in trainer_kwargs(cfg)


def test_a_bad_value_is_refused_before_any_data_is_collected(tmp_path, monkeypatch):
    from hydra import compose, initialize_config_module

    import cicfw.train.app as train_app

    def no_data(*args, **kwargs):
        raise AssertionError("the data was reached before the bad switch was refused")

    monkeypatch.setattr(train_app, "ensure_data", no_data)
    from hydra.errors import HydraException

    from cicfw.core.config_checks import config_error

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        with pytest.raises(HydraException) as err:  # the schema: SpeedConfig's keep_memory is a bool
            compose("train", overrides=["speed.keep_memory=maybe"])
    refused = config_error(err.value)
    assert (refused.kind, refused.key) == ("wrong type", "speed.keep_memory"), refused
