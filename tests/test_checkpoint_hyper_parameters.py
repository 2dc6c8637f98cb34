"""A hand-edited checkpoint that evaluation, export, diagnose and the Agent rebuild: a part kwarg its constructor
refuses, a bad speed scale or a weight saved twice is one ``CheckpointError`` naming the file and the key."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cicfw.model.checkpoint import CheckpointError, load_model
from cicfw.model.net import SteeringNet

PARTS = {"encoder": "cil", "mixer": "independent", "head": "regression"}


@pytest.fixture(scope="module")
def weights() -> dict[str, torch.Tensor]:
    """The default SteeringNet's state_dict, built once."""
    torch.manual_seed(0)
    return SteeringNet().state_dict()


def save(path: Path, state: dict, **hp) -> Path:
    torch.save({"state_dict": state, "hyper_parameters": {**PARTS, **hp}}, path)
    return path


@pytest.mark.parametrize("edit, key, value", [
    ({"head_kwargs": {"loss": "mse", "decode": "argmax"}}, "head_kwargs.decode", "argmax"),  # TypeError
    ({"mixer_kwargs": {"gates": 3}}, "mixer_kwargs.gates", 3),  # TypeError
    ({"encoder_kwargs": {"out_dim": -5}}, "encoder_kwargs.out_dim", -5),  # torch's RuntimeError
    ({"encoder_kwargs": {"dropout_conv": 0.1, "out_dim": -5}}, "encoder_kwargs.out_dim", -5),  # one of two
    ({"head_kwargs": {"loss": "huber"}}, "head_kwargs.loss", "huber"),  # the head's ConfigError
    ({"mixer_kwargs": {"in_dim": 7}}, "mixer_kwargs.in_dim", 7),  # SteeringNet gives it
    ({"speed_norm_kmh": -40.0}, "hyper_parameters.speed_norm_kmh", -40.0),  # SteeringNet's own ConfigError
    ({"encoder_kwargs": [512]}, "encoder_kwargs", [512]),  # not a mapping
])
def test_hyper_parameters_the_parts_refuse_are_one_error_naming_the_file_and_key(
        tmp_path: Path, weights: dict, edit: dict, key: str, value):
    path = save(tmp_path / "edited.ckpt", weights, **edit)
    with pytest.raises(CheckpointError) as err:
        load_model(path)
    assert (err.value.key, err.value.value) == (key, value)
    assert str(path) in str(err.value) and key in str(err.value) and "\n" not in str(err.value)


def test_an_unexpected_keyword_lists_those_the_part_takes(tmp_path: Path, weights: dict):
    with pytest.raises(CheckpointError) as err:
        load_model(save(tmp_path / "m.ckpt", weights, head="hybrid", head_kwargs={"decoder": "argmax"}))
    assert err.value.key == "head_kwargs.decoder"
    assert all(name in str(err.value) for name in ("W", "n_classes", "bin_width", "decode"))  # the bins' too


def test_a_weight_saved_with_and_without_the_compile_prefix_is_refused(tmp_path: Path, weights: dict):
    """Both would load into one parameter, the later silently winning (here: zeros)."""
    name = "mixer.branches.0.0.weight"
    state = {**weights, f"_orig_mod.{name}": torch.zeros_like(weights[name])}
    path = save(tmp_path / "twice.ckpt", state)
    with pytest.raises(CheckpointError) as err:
        load_model(path)
    assert (err.value.key, err.value.value) == ("checkpoint", str(path))
    assert repr(name) in str(err.value) and "damaged or edited" in str(err.value)


def test_prefixed_weights_alone_still_load(tmp_path: Path, weights: dict):
    state = {f"_orig_mod.{k}": v for k, v in weights.items()}
    net = load_model(save(tmp_path / "compiled.ckpt", state))
    assert torch.equal(net.state_dict()["mixer.branches.0.0.weight"], weights["mixer.branches.0.0.weight"])
