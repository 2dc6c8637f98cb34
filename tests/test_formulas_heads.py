"""Every head's equation against a hand computation (python ``math`` on a 2-sample batch), the bin
edges, and cross-entropy on saturated logits.

The rule these tests keep: replacing any single line of a head's formula by another plausible one
(log(softmax) for log_softmax, W on the wrong term, σ for σ², bin edges shifted, sin(x − φ) ...)
makes one of them fail. Targets' classes and midpoints are written out by hand here, not read from
the implementation.
"""
from __future__ import annotations

import math

import pytest
import torch

from cicfw.model.heads.bins import SteeringBins
from cicfw.model.heads.coexistence import CoexistenceHead
from cicfw.model.heads.hybrid import HybridHead
from cicfw.model.heads.regression import RegressionHead
from cicfw.model.heads.sine import SineHead
from cicfw.model.heads.softmax import SoftmaxHead

torch.set_num_threads(1)

# The paper's 9 bins of 0.2 on [-0.9, 0.9]: bin i = (-0.9 + 0.2 i, -0.7 + 0.2 i], midpoint -0.8 + 0.2 i.
MID = [-0.8, -0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6, 0.8]

# A 2-sample batch: logits, targets, and the targets' bins worked out by hand.
LOGITS = [[0.3, -1.2, 2.0, 0.0, 0.7, -0.4, 1.1, -2.5, 0.2],
          [-0.6, 1.5, 0.1, -0.3, 2.2, 0.9, -1.0, 0.4, 1.3]]
Y = [0.33, -0.62]
Y_CLASS = [6, 1]  # 0.33 in (0.3, 0.5]; -0.62 in (-0.7, -0.5]


def softmax(z: list[float]) -> list[float]:
    m = max(z)
    e = [math.exp(v - m) for v in z]
    return [v / sum(e) for v in e]


def log_softmax(z: list[float], i: int) -> float:
    m = max(z)
    return z[i] - m - math.log(sum(math.exp(v - m) for v in z))


def out64(rows) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


def y64(values) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


def close(actual: torch.Tensor, expected: float, rel: float = 1e-7) -> None:
    assert actual.shape == ()
    assert math.isclose(actual.item(), expected, rel_tol=rel, abs_tol=1e-14), (actual.item(), expected)


# ---------------------------------------------------------------- bins
EDGE_CASES = [  # (steer, class): on an inner edge -> the bin on its left; the ends open outwards
    (-1.0, 0), (-0.9, 0), (-0.7, 0), (-0.5, 1), (-0.3, 2), (-0.1, 3),
    (0.1, 4), (0.3, 5), (0.5, 6), (0.7, 7), (0.9, 8), (1.0, 8),
    (-0.8, 0), (0.0, 4), (0.8, 8), (-0.69, 1), (0.71, 8), (0.095, 4), (0.105, 5),
]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bins_on_every_edge_at_the_ends_and_beyond(dtype):
    bins = SteeringBins(9, -0.9, 0.9)
    steer = torch.tensor([s for s, _ in EDGE_CASES], dtype=dtype)
    assert bins.to_class(steer).tolist() == [c for _, c in EDGE_CASES]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_just_either_side_of_each_edge(dtype):
    bins = SteeringBins(9, -0.9, 0.9)
    eps = 1e-5
    for k in range(1, 9):  # inner edge k separates bins k-1 and k
        edge = round(-0.9 + 0.2 * k, 10)
        got = bins.to_class(torch.tensor([edge - eps, edge, edge + eps], dtype=dtype)).tolist()
        assert got == [k - 1, k - 1, k], (edge, got)


def test_head_midpoints_and_decode_by_argmax():
    head = SoftmaxHead()
    torch.testing.assert_close(head.midpoints, torch.tensor(MID))
    out = torch.full((9, 9), -1.0)
    out[range(9), range(9)] = 1.0
    torch.testing.assert_close(head.decode(out), torch.tensor(MID))


# ---------------------------------------------------------------- cross-entropy, saturated logits
SATURATED = [[1000.0, -1000.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
             [-1000.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1000.0]]
SAT_Y = [-0.6, 0.8]  # classes 1 and 8: the first sample's target scores e^-2000 (0 in any float)
SAT_CLASS = [1, 8]


def stable_cce(rows, classes) -> float:
    return sum(-log_softmax(z, c) for z, c in zip(rows, classes)) / len(rows)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_softmax_cross_entropy_on_saturated_logits_is_finite_and_stable(dtype):
    out = torch.tensor(SATURATED, dtype=dtype, requires_grad=True)
    loss = SoftmaxHead().loss(out, torch.tensor(SAT_Y, dtype=dtype))
    assert torch.isfinite(loss)
    assert math.isclose(loss.item(), stable_cce(SATURATED, SAT_CLASS), rel_tol=1e-6)  # = 1000.0
    loss.backward()
    assert torch.isfinite(out.grad).all()


@pytest.mark.parametrize("head", [HybridHead(W=10.0), CoexistenceHead(W=0.6)], ids=["hybrid", "coexistence"])
def test_other_classification_losses_on_saturated_logits_are_finite(head):
    out = torch.tensor(SATURATED, requires_grad=True)
    loss = head.loss(out, torch.tensor(SAT_Y))
    assert torch.isfinite(loss)
    loss.backward()
    assert torch.isfinite(out.grad).all()


def test_softmax_loss_by_hand():
    close(SoftmaxHead().loss(out64(LOGITS), y64(Y)), stable_cce(LOGITS, Y_CLASS))


def test_softmax_expectation_decode_by_hand():
    got = SoftmaxHead(decode="expectation").decode(out64(LOGITS))
    for b in range(2):
        assert math.isclose(got[b].item(), sum(o * m for o, m in zip(softmax(LOGITS[b]), MID)), rel_tol=1e-6)


# ---------------------------------------------------------------- hybrid (paper Eq. 3)
@pytest.mark.parametrize("W", [10.0, 3.5])
def test_hybrid_loss_by_hand(W):
    """l = −Σ ȳ_i log O_i + W (y − Σ O_i m_i)², averaged over the 2 samples."""
    total = 0.0
    for z, y, c in zip(LOGITS, Y, Y_CLASS):
        o = softmax(z)
        y_hat = sum(oi * mi for oi, mi in zip(o, MID))
        total += -math.log(o[c]) + W * (y - y_hat) ** 2
    close(HybridHead(W=W).loss(out64(LOGITS), y64(Y)), total / 2)


def test_hybrid_decodes_the_expectation_by_hand():
    got = HybridHead().decode(out64(LOGITS))
    for b in range(2):
        assert math.isclose(got[b].item(), sum(o * m for o, m in zip(softmax(LOGITS[b]), MID)), rel_tol=1e-6)


# ---------------------------------------------------------------- co-existence (paper Eq. 4)
@pytest.mark.parametrize("W, sigma2", [(0.6, 1.0), (0.3, 2.5)])
def test_coexistence_loss_by_hand(W, sigma2):
    """l = −(1−W) Σ ȳ_i log O_i − W Oᵀ μ O, μ_ij = exp(−(i−j)² / 2σ²), averaged over 2 samples."""
    mu = [[math.exp(-((i - j) ** 2) / (2 * sigma2)) for j in range(9)] for i in range(9)]
    total = 0.0
    for z, c in zip(LOGITS, Y_CLASS):
        o = softmax(z)
        quad = sum(o[i] * mu[i][j] * o[j] for i in range(9) for j in range(9))
        total += -(1 - W) * math.log(o[c]) - W * quad
    close(CoexistenceHead(W=W, sigma2=sigma2).loss(out64(LOGITS), y64(Y)), total / 2, rel=1e-6)


# ---------------------------------------------------------------- regression (CIL)
def test_regression_losses_and_decode_by_hand():
    out, y = [[0.25], [-1.4]], [0.5, -0.62]
    mse = ((0.25 - 0.5) ** 2 + (-1.4 + 0.62) ** 2) / 2
    l1 = (abs(0.25 - 0.5) + abs(-1.4 + 0.62)) / 2
    close(RegressionHead("mse").loss(out64(out), y64(y)), mse)
    close(RegressionHead("l1").loss(out64(out), y64(y)), l1)
    assert RegressionHead().decode(out64([[0.3], [-1.7], [2.0]])).tolist() == [0.3, -1.0, 1.0]


# ---------------------------------------------------------------- sine encoding
@pytest.mark.parametrize("n_units, phase_range", [(7, 0.8), (21, 0.9)])
def test_sine_encoding_loss_and_decode_by_hand(n_units, phase_range):
    """t_n = sin(x_n + φ), x_n = 2πn/N, φ = steer·phase_range·π; loss = mean over batch and units."""
    head = SineHead(n_units=n_units, phase_range=phase_range)
    y = [0.37, -0.9]
    x = [2 * math.pi * n / n_units for n in range(n_units)]
    target = [[math.sin(xn + s * phase_range * math.pi) for xn in x] for s in y]
    got = head.encode(torch.tensor(y))
    for b in range(2):
        for n in range(n_units):
            assert math.isclose(got[b, n].item(), target[b][n], abs_tol=1e-6)
    out = [[0.1 * ((n * 7 + b * 3) % 5) - 0.2 for n in range(n_units)] for b in range(2)]
    mse = sum((out[b][n] - target[b][n]) ** 2 for b in range(2) for n in range(n_units)) / (2 * n_units)
    assert math.isclose(head.loss(torch.tensor(out), torch.tensor(y)).item(), mse, rel_tol=1e-5)
    # decode reads the phase back: 0.5 · sin(x + φ) decodes to the steer
    wave = [[0.5 * math.sin(xn + s * phase_range * math.pi) for xn in x] for s in y]
    dec = head.decode(torch.tensor(wave))
    for b in range(2):
        assert math.isclose(dec[b].item(), y[b], abs_tol=1e-5)
