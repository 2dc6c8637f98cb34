"""The mixers' mathematics: each reduces to CIL where it should, C's diagonal, regularizers, bad kwargs."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from cicfw.core.errors import ConfigError
from cicfw.model.mixers.cross_stitch import CrossStitchMixer
from cicfw.model.mixers.gtu import GTUMixer
from cicfw.model.mixers.independent import IndependentMixer
from cicfw.model.mixers.moe import MoEMixer
from cicfw.model.mixers.re import REMixer
from cicfw.model.mixers.sluice import SluiceMixer
from cicfw.model.mixers.soft_sharing import SoftSharingMixer
from cicfw.registry import MIXERS

CONF = Path(__file__).resolve().parents[1] / "conf"
IN, K = 32, 3


def _h(b: int = 6, seed: int = 0) -> torch.Tensor:
    return torch.randn(b, IN, generator=torch.Generator().manual_seed(seed))


def _pair(cls, **kw):
    """A mixer and an ``independent`` mixer with the same branch weights, both in eval mode."""
    torch.manual_seed(0)
    ref = IndependentMixer(IN, K, hidden=16, dropout=0.0).eval()
    mixer = cls(IN, K, hidden=16, dropout=0.0, **kw).eval()
    mixer.branches.load_state_dict(ref.branches.state_dict())
    return mixer, ref


def test_gtu_with_gates_shut_is_independent_exactly():
    mixer, ref = _pair(GTUMixer)
    with torch.no_grad():
        mixer.gate.bias.fill_(-float("inf"))  # sigmoid(-inf) = 0: every gate shut, C = I
    assert torch.equal(mixer(_h()), ref(_h()))
    assert torch.equal(mixer.inspect()["C"], torch.eye(4).expand(6, 4, 4))


def test_gtu_with_gates_open_mixes_branches_as_C_says():
    mixer, ref = _pair(GTUMixer)
    out, branches = mixer(_h()), ref(_h())
    c = mixer.inspect()["C"]
    assert not torch.allclose(out, branches)
    torch.testing.assert_close(out, torch.einsum("bij,bjk->bik", c, branches))


@pytest.mark.parametrize("cls", [GTUMixer, REMixer])
def test_colearning_matrix_has_unit_diagonal_and_bounded_coefficients(cls):
    mixer = cls(IN, K, hidden=16)
    mixer(_h(20) * 10)  # large inputs saturate tanh: coefficients still within [-1, 1]
    c = mixer.inspect()["C"]
    assert c.shape == (20, 4, 4)
    assert torch.equal(torch.diagonal(c, dim1=1, dim2=2), torch.ones(20, 4))
    off = c[:, ~torch.eye(4, dtype=torch.bool)]
    assert off.abs().max() <= 1.0 and off.abs().max() > 0


def test_re_with_zero_R_is_independent_exactly():
    mixer, ref = _pair(REMixer, R=[[0] * 4 for _ in range(4)])
    assert torch.equal(mixer(_h()), ref(_h()))


def test_re_only_links_the_branches_R_allows():
    R = [[1, 1, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1], [0, 0, 0, 0]]
    mixer = REMixer(IN, K, R=R, hidden=16)
    mixer(_h())
    c = mixer.inspect()["C"]
    allowed = torch.tensor(R, dtype=torch.bool) & ~torch.eye(4, dtype=torch.bool)
    assert torch.all(c[:, ~allowed & ~torch.eye(4, dtype=torch.bool)] == 0)
    assert torch.all(c[:, allowed] != 0)


def test_cross_stitch_with_identity_alpha_is_independent_exactly():
    mixer, ref = _pair(CrossStitchMixer)
    with torch.no_grad():
        for a in mixer.alphas:
            a.copy_(torch.eye(4))
    assert torch.equal(mixer(_h()), ref(_h()))


def test_cross_stitch_alpha_starts_at_the_paper_init():
    alpha = CrossStitchMixer(IN, K).inspect()["alpha1"]
    torch.testing.assert_close(torch.diagonal(alpha), torch.full((4,), 0.9))
    torch.testing.assert_close(alpha[0, 1:], torch.full((3,), 0.1 / 3))
    torch.testing.assert_close(alpha.sum(1), torch.ones(4))


def test_sluice_with_identity_alpha_and_last_layer_beta_is_independent():
    mixer, ref = _pair(SluiceMixer)
    with torch.no_grad():
        for a in mixer.alphas:
            a.copy_(torch.eye(8))
        mixer.beta.copy_(torch.tensor([[0.0, 1.0]] * 4))
    torch.testing.assert_close(mixer(_h()), ref(_h()), rtol=0, atol=1e-6)


def test_sluice_orthogonality_is_zero_for_orthogonal_subspaces_and_positive_otherwise():
    mixer = SluiceMixer(IN, K, hidden=16, ortho=0.5)
    assert mixer.regularizer() > 0
    torch.testing.assert_close(mixer.regularizer(), 0.5 * mixer.orthogonality())
    with torch.no_grad():  # rows of subspace 1 on inputs [0, n/2), of subspace 2 on [n/2, n): orthogonal
        for branch in mixer.branches:
            for layer in (branch[0], branch[3]):
                w = layer.weight
                w[: w.shape[0] // 2, w.shape[1] // 2:] = 0
                w[w.shape[0] // 2:, : w.shape[1] // 2] = 0
    assert mixer.orthogonality() == 0


def test_moe_gates_are_a_distribution_per_branch_and_one_expert_is_a_plain_layer():
    mixer = MoEMixer(IN, K, experts=3, expert_dim=8, hidden=16)
    mixer(_h())
    g = mixer.inspect()["gates"]
    assert g.shape == (6, 4, 3) and torch.all(g >= 0)
    torch.testing.assert_close(g.sum(-1), torch.ones(6, 4))
    single = MoEMixer(IN, K, experts=1, expert_dim=8, hidden=16, dropout=0.0).eval()
    x = single.experts(_h())  # with E = 1 every branch reads the one expert
    expected = torch.stack([b(x) for b in single.branches], dim=1)
    torch.testing.assert_close(single(_h()), expected)


def test_soft_sharing_regularizer_is_zero_for_identical_branches_and_positive_otherwise():
    mixer = SoftSharingMixer(IN, K, lam=0.1, hidden=16)
    assert mixer.regularizer() > 0
    expected = sum(((p - q) ** 2).sum() for i in range(4) for j in range(i + 1, 4)
                   for p, q in zip(mixer.branches[i].parameters(), mixer.branches[j].parameters()))
    torch.testing.assert_close(mixer.regularizer(), 0.1 * expected)
    for branch in mixer.branches[1:]:
        branch.load_state_dict(mixer.branches[0].state_dict())
    assert mixer.regularizer() == 0


def test_soft_sharing_branches_are_cil_branches_of_its_width_and_dropout():
    torch.manual_seed(0)
    ref = IndependentMixer(IN, K, hidden=16, dropout=(0.3, 0.1))
    torch.manual_seed(0)
    mixer = SoftSharingMixer(IN, K, lam=0.1, hidden=16, dropout=(0.3, 0.1))
    assert str(mixer.branches) == str(ref.branches)  # the widths and the dropout rates
    assert all(torch.equal(a, b) for a, b in zip(mixer.branches.parameters(), ref.branches.parameters()))


def test_soft_sharing_regularizer_gradient_pulls_branches_together():
    mixer = SoftSharingMixer(IN, K, lam=1.0, hidden=16)
    before = mixer.distance().item()
    opt = torch.optim.SGD(mixer.parameters(), lr=0.01)
    for _ in range(5):
        opt.zero_grad()
        mixer.regularizer().backward()
        opt.step()
    assert mixer.distance().item() < before


@pytest.mark.parametrize(
    "cls, kwargs, words",
    [
        (REMixer, {"R": [[0, 1], [1, 0]]}, ["mixer.R", "4x4"]),
        (REMixer, {"R": [[0, 2, 0, 0]] * 4}, ["mixer.R", "binary", "0/1"]),
        (REMixer, {"R": [[0, 0.5, 0, 0]] * 4}, ["mixer.R", "binary"]),
        (REMixer, {"R": 1}, ["mixer.R", "4x4"]),
        (REMixer, {"coef_hidden": 0}, ["mixer.coef_hidden=0", "positive integer"]),
        (MoEMixer, {"experts": 0}, ["mixer.experts=0", "E >= 1"]),
        (MoEMixer, {"experts": 2.5}, ["mixer.experts=2.5", "E >= 1"]),
        (SoftSharingMixer, {"lam": -0.1}, ["mixer.lam=-0.1", ">= 0"]),
        (CrossStitchMixer, {"alpha_diag": 1.5}, ["mixer.alpha_diag=1.5", "[0, 1]"]),
        (SluiceMixer, {"subspaces": 3}, ["mixer.subspaces=3", "divides"]),
        (SluiceMixer, {"subspaces": 1}, ["mixer.subspaces=1", ">= 2"]),
        (SluiceMixer, {"ortho": -1}, ["mixer.ortho=-1", ">= 0"]),
        (SluiceMixer, {"beta_last": 2}, ["mixer.beta_last=2", "[0, 1]"]),
        (GTUMixer, {"hidden": 0}, ["mixer.hidden=0", "positive integer"]),
        (GTUMixer, {"dropout": 1.0}, ["mixer.dropout=1.0", "[0, 1)"]),
    ],
)
def test_bad_hyperparameters_raise_one_clear_error(cls, kwargs, words):
    with pytest.raises(ValueError) as err:
        cls(IN, K, **kwargs)
    for word in words:
        assert word in str(err.value)


@pytest.mark.parametrize("cls, key, value", [(SluiceMixer, "ortho", math.nan), (SluiceMixer, "ortho", math.inf),
                                             (SoftSharingMixer, "lam", math.inf)])
def test_a_regularizer_weight_that_is_not_finite_is_refused(cls, key, value):
    """``mixer.ortho=nan`` trained two steps and saved a checkpoint whose weights were NaN, exit status 0."""
    with pytest.raises(ConfigError) as err:
        cls(IN, K, **{key: value})
    assert err.value.key == f"mixer.{key}"
    assert err.value.value is value


@pytest.mark.parametrize("path", sorted((CONF / "mixer").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_mixer_config_builds_its_class_through_the_registry(path):
    node = OmegaConf.to_container(OmegaConf.load(path))
    name = node.pop("name")
    assert name == path.stem
    mixer = MIXERS.get(name)(in_dim=IN, out_dim=K, **node)
    assert mixer(_h()).shape == (6, 4, K)
    assert mixer.regularizer().shape == ()
    for key, m in mixer.inspect().items():
        assert m.dim() in (2, 3), key


@pytest.mark.parametrize("n", [2, 3, 4, 5])
def test_offdiag_places_values_row_major_off_the_diagonal(n):
    """``offdiag`` (padding, compile-friendly) puts value k at the k-th off-diagonal cell in row-major order."""
    from cicfw.model.mixers.gtu import offdiag

    v = torch.arange(1.0, 1 + 2 * n * (n - 1)).reshape(2, n * (n - 1))
    expected = torch.zeros(2, n, n)
    cells = [(i, j) for i in range(n) for j in range(n) if i != j]
    for k, (i, j) in enumerate(cells):
        expected[:, i, j] = v[:, k]
    assert torch.equal(offdiag(v, n), expected)
