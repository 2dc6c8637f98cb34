"""The heads' mathematics: losses against their formulas, decoding in [-1, 1], bins, bad kwargs."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from cicfw.core.errors import ConfigError
from cicfw.model.heads.coexistence import CoexistenceHead, gaussian_coexistence
from cicfw.model.heads.hybrid import HybridHead
from cicfw.model.heads.sine import SineHead
from cicfw.model.heads.softmax import SoftmaxHead
from cicfw.registry import HEADS

CONF = Path(__file__).resolve().parents[1] / "conf"
PAPER_MIDPOINTS = torch.tensor([-0.8, -0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6, 0.8])


def _out(n: int, k: int, seed: int = 0, scale: float = 3.0) -> torch.Tensor:
    return scale * torch.randn(n, k, generator=torch.Generator().manual_seed(seed))


def _steer(n: int, seed: int = 1) -> torch.Tensor:
    return torch.rand(n, generator=torch.Generator().manual_seed(seed)) * 1.6 - 0.8


@pytest.mark.parametrize("cls", [SoftmaxHead, HybridHead, CoexistenceHead])
def test_classification_heads_use_the_paper_bins(cls):
    head = cls()
    assert head.out_dim == 9 and head.bins.n == 9
    torch.testing.assert_close(head.midpoints, PAPER_MIDPOINTS)
    # Each midpoint falls in its own bin; class 0 is hard left.
    assert torch.equal(head.bins.to_class(PAPER_MIDPOINTS), torch.arange(9))


def test_softmax_loss_is_cross_entropy_and_decodes_argmax_or_expectation():
    out, y = _out(16, 9), _steer(16)
    head = SoftmaxHead()
    torch.testing.assert_close(head.loss(out, y), F.cross_entropy(out, head.bins.to_class(y)))
    torch.testing.assert_close(head.decode(out), PAPER_MIDPOINTS[out.argmax(1)])
    expect = SoftmaxHead(decode="expectation")
    torch.testing.assert_close(expect.decode(out), (out.softmax(1) * PAPER_MIDPOINTS).sum(1))


def test_hybrid_with_W_zero_is_cross_entropy():
    out, y = _out(16, 9), _steer(16)
    torch.testing.assert_close(HybridHead(W=0).loss(out, y), SoftmaxHead().loss(out, y))


def test_hybrid_adds_W_times_the_squared_error_of_the_expectation():
    out, y = _out(16, 9), _steer(16)
    head = HybridHead(W=10)
    y_hat = (out.softmax(1) * PAPER_MIDPOINTS).sum(1)
    expected = F.cross_entropy(out, head.bins.to_class(y)) + 10 * ((y - y_hat) ** 2).mean()
    torch.testing.assert_close(head.loss(out, y), expected)
    torch.testing.assert_close(head.decode(out), y_hat)  # the hybrid decodes its expectation


def test_hybrid_squared_term_is_zero_when_y_is_the_expectation():
    out = _out(16, 9)
    head = HybridHead(W=10)
    y = head.expectation(out)
    assert head.squared_error(out, y) == 0
    torch.testing.assert_close(head.loss(out, y), SoftmaxHead().loss(out, y))


def test_coexistence_mu_is_a_symmetric_gaussian_with_unit_diagonal():
    mu = CoexistenceHead().mu
    assert mu.shape == (9, 9)
    assert torch.equal(mu, mu.T)
    assert torch.equal(torch.diagonal(mu), torch.ones(9))
    torch.testing.assert_close(mu[0, 1], torch.tensor(math.exp(-0.5)))  # σ² = 1
    torch.testing.assert_close(mu[2, 5], torch.tensor(math.exp(-4.5)))
    assert torch.all(mu[0, :-1] > mu[0, 1:])  # falls off with the class distance
    torch.testing.assert_close(gaussian_coexistence(3, 2.0)[0, 2], torch.tensor(math.exp(-1.0)))


def test_coexistence_loss_follows_the_formula_and_prefers_near_misses():
    out, y = _out(16, 9), _steer(16)
    head = CoexistenceHead(W=0.6)
    o = out.softmax(1)
    quad = torch.einsum("bi,ij,bj->b", o, head.mu, o)
    expected = 0.4 * F.cross_entropy(out, head.bins.to_class(y)) - 0.6 * quad.mean()
    torch.testing.assert_close(head.loss(out, y), expected)
    # Scores split between two neighbouring classes cost less than split between two far ones.
    near, far = torch.full((1, 9), -20.0), torch.full((1, 9), -20.0)
    near[0, [4, 5]] = 0.0
    far[0, [4, 8]] = 0.0
    target = torch.tensor([0.0])  # class 4
    assert head.loss(near, target) < head.loss(far, target)


def test_sine_encodes_the_steering_as_the_phase_of_one_period():
    head = SineHead(n_units=21, phase_range=0.9)
    y = torch.tensor([0.0, 0.5, -1.0])
    x = 2 * math.pi * torch.arange(21) / 21
    expected = torch.sin(x[None] + y[:, None] * 0.9 * math.pi)
    torch.testing.assert_close(head.encode(y), expected)
    torch.testing.assert_close(head.loss(expected, y), torch.tensor(0.0))


@pytest.mark.parametrize("n_units", [3, 4, 21, 61, 141])
def test_sine_decode_inverts_encode_over_the_whole_range(n_units):
    head = SineHead(n_units=n_units)
    y = torch.linspace(-1, 1, 4001)
    assert (head.decode(head.encode(y)) - y).abs().max() < 1e-4
    # Decoding reads the phase only: a wave of half the amplitude decodes the same.
    assert (head.decode(0.5 * head.encode(y)) - y).abs().max() < 1e-4


@pytest.mark.parametrize("name", ["regression", "softmax", "hybrid", "coexistence", "sine"])
def test_every_head_decodes_into_the_steering_range(name):
    head = HEADS.get(name)()
    for seed in range(3):
        steer = head.decode(_out(256, head.out_dim, seed=seed, scale=50.0))
        assert steer.shape == (256,)
        assert torch.all(steer >= -1) and torch.all(steer <= 1)


@pytest.mark.parametrize("cls", [SoftmaxHead, HybridHead, CoexistenceHead])
def test_other_bin_layouts_work_when_consistent(cls):
    head = cls(n_classes=5, low=-1.0, high=1.0, bin_width=0.4)
    torch.testing.assert_close(head.midpoints, torch.tensor([-0.8, -0.4, 0.0, 0.4, 0.8]))
    assert head.out_dim == 5 and head.loss(_out(4, 5), _steer(4)).isfinite()
    assert cls(n_classes=11, bin_width=None).bins.n == 11  # width derived from the range


@pytest.mark.parametrize(
    "cls, kwargs, words",
    [
        (SoftmaxHead, {"n_classes": 11}, ["head.n_classes=11", "does not match the bin edges", "= 9"]),
        (HybridHead, {"n_classes": 8}, ["head.n_classes=8", "does not match the bin edges"]),
        (CoexistenceHead, {"bin_width": 0.25}, ["head.n_classes=9", "does not match the bin edges"]),
        (SoftmaxHead, {"n_classes": 1}, ["head.n_classes=1", ">= 2"]),
        (SoftmaxHead, {"low": -1.5, "bin_width": None}, ["head.low=-1.5", "-1 <= low < high <= 1"]),
        (SoftmaxHead, {"decode": "median"}, ["head.decode='median'", "argmax", "expectation"]),
        (HybridHead, {"W": -1}, ["head.W=-1", ">= 0"]),
        (CoexistenceHead, {"W": 0}, ["head.W=0", "(0, 1)"]),
        (CoexistenceHead, {"W": 1.0}, ["head.W=1.0", "(0, 1)"]),
        (CoexistenceHead, {"W": 1.5}, ["head.W=1.5", "(0, 1)"]),
        (CoexistenceHead, {"sigma2": 0}, ["head.sigma2=0", "> 0"]),
        (SineHead, {"n_units": 2}, ["head.n_units=2", "N >= 3"]),
        (SineHead, {"phase_range": 1.0}, ["head.phase_range=1.0", "(0, 1)"]),
    ],
)
def test_bad_hyperparameters_raise_one_clear_error(cls, kwargs, words):
    with pytest.raises(ValueError) as err:
        cls(**kwargs)
    for word in words:
        assert word in str(err.value), str(err.value)


@pytest.mark.parametrize("cls, key, value", [(HybridHead, "W", math.inf), (CoexistenceHead, "sigma2", math.inf),
                                             (HybridHead, "W", math.nan), (CoexistenceHead, "sigma2", math.nan)])
def test_a_loss_weight_that_is_not_finite_is_refused(cls, key, value):
    """An infinite weight trained on an infinite loss: every weight of the saved checkpoint NaN, exit status 0."""
    with pytest.raises(ConfigError) as err:
        cls(**{key: value})
    assert err.value.key == f"head.{key}"
    assert err.value.value is value


@pytest.mark.parametrize("path", sorted((CONF / "head").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_head_config_builds_its_class_through_the_registry(path):
    node = OmegaConf.to_container(OmegaConf.load(path))
    name = node.pop("name")
    assert name == path.stem
    head = HEADS.get(name)(**node)
    out = _out(8, head.out_dim)
    assert head.loss(out, _steer(8)).shape == () and head.decode(out).shape == (8,)
