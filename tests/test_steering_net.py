"""The driving network apart from its training: what a checkpoint rebuilds, and diagnose's split, without
Lightning."""
from __future__ import annotations

import dataclasses
import inspect
import subprocess
import sys

import torch

from cicfw.data.datamodule import CILDataModule
from cicfw.diagnose.steer_diagnostic import DataSettings
from cicfw.model.checkpoint import TRAINING_DEFAULTS, load_model
from cicfw.model.module import CICModule
from cicfw.model.net import NET_DEFAULTS, SteeringNet


def test_the_net_and_training_defaults_are_cicmodule_s_arguments_in_order():
    params = inspect.signature(CICModule.__init__).parameters
    want = {name: p.default for name, p in params.items() if name != "self"}
    assert list(want) == [*NET_DEFAULTS, *TRAINING_DEFAULTS]
    assert want == {**NET_DEFAULTS, **TRAINING_DEFAULTS}


def test_a_training_checkpoint_drives_as_the_module_that_trained(tmp_path):
    torch.manual_seed(0)
    module = CICModule(mixer="gtu", head="hybrid", head_kwargs={"W": 5}, lr=1e-3).eval()
    path = tmp_path / "m.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, path)
    net = load_model(path)
    assert type(net) is SteeringNet and not net.training
    assert dict(net.hparams) == dict(module.hparams) and net.hparams.lr == 1e-3
    image = torch.randint(0, 255, (3, 3, 88, 200), dtype=torch.uint8)
    speed, command = torch.tensor([0.0, 12.0, 30.0]), torch.tensor([0, 2, 3])
    assert torch.equal(net.predict_steer(image, speed, command), module.predict_steer(image, speed, command))


def test_diagnose_s_data_defaults_are_the_datamodule_s():
    params = inspect.signature(CILDataModule.__init__).parameters
    for field in dataclasses.fields(DataSettings):
        if field.name not in ("path", "seed"):  # diagnose's seed: None is the training run's
            assert field.default == params[field.name].default, field.name


#: a fresh process that saves a checkpoint by hand, loads it and drives it through the evaluation, export and
#: diagnose apps' code, then prints what it imported
_DRIVE = r"""
import sys, tempfile, torch
import cicfw.benchmark.app, cicfw.export.app, cicfw.diagnose.app
from cicfw.model.checkpoint import load_model
from cicfw.model.net import SteeringNet
path = tempfile.mkdtemp() + "/m.ckpt"
torch.save({"state_dict": SteeringNet().state_dict(), "hyper_parameters": {"mixer": "independent",
            "head": "regression", "encoder": "cil"}}, path)
load_model(path).predict_steer(torch.zeros(1, 3, 88, 200, dtype=torch.uint8), torch.zeros(1), torch.zeros(1))
print(sorted({m.split(".")[0] for m in sys.modules} & {"lightning", "pytorch_lightning", "torchmetrics"}))
"""


def test_evaluating_exporting_and_diagnosing_import_no_lightning():
    """Lightning and torchmetrics take seconds to import: every evaluation, export, diagnosis and worker process
    starts without them."""
    run = subprocess.run([sys.executable, "-c", _DRIVE], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.split() == ["[]"]
