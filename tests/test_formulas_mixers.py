"""Every mixer's equation, recomputed in plain numpy (float64) from the module's own or hand-set
parameters, never from what the module reports about itself.

The rule these tests keep: replacing any single line of a mixer's formula by another plausible one
(tanh -> sigmoid, alpha -> alpha.T, dropping beta or R, a shared gate, pairs counted twice ...)
makes one of them fail.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from cicfw.model.mixers.cross_stitch import CrossStitchMixer
from cicfw.model.mixers.gtu import GTUMixer
from cicfw.model.mixers.independent import IndependentMixer
from cicfw.model.mixers.moe import MoEMixer
from cicfw.model.mixers.re import REMixer
from cicfw.model.mixers.sluice import SluiceMixer
from cicfw.model.mixers.soft_sharing import SoftSharingMixer

torch.set_num_threads(1)

IN, HID, K, B = 5, 6, 3, 3
N = 4  # branches: follow, left, right, straight


# ---------------------------------------------------------------- plain-numpy building blocks
def np_h(seed: int = 0, scale: float = 1.0) -> np.ndarray:
    return scale * np.random.default_rng(seed).standard_normal((B, IN))


def run(mixer: nn.Module, h: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return mixer(torch.from_numpy(h)).numpy()


def build(cls, **kw) -> nn.Module:
    torch.manual_seed(0)
    return cls(IN, K, hidden=HID, dropout=0.0, **kw).double().eval()


def wb(layer: nn.Linear) -> tuple[np.ndarray, np.ndarray]:
    return layer.weight.detach().numpy().copy(), layer.bias.detach().numpy().copy()


def lin(layer: nn.Linear, x: np.ndarray) -> np.ndarray:
    w, b = wb(layer)
    return x @ w.T + b


def relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0)


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def linears(seq: nn.Module) -> list[nn.Linear]:
    return [m for m in seq.modules() if isinstance(m, nn.Linear)]


def cil_branch(seq: nn.Module, x: np.ndarray) -> np.ndarray:
    """CIL's branch: Linear, ReLU, Linear, ReLU, Linear (dropout off)."""
    l1, l2, l3 = linears(seq)
    return lin(l3, relu(lin(l2, relu(lin(l1, x)))))


def offdiag_to_matrix(coefs: np.ndarray) -> np.ndarray:
    """(B, 12) -> C (B, 4, 4) = I + the coefficients written row by row off the diagonal."""
    c = np.tile(np.eye(N), (coefs.shape[0], 1, 1))
    for b in range(coefs.shape[0]):
        k = 0
        for i in range(N):
            for j in range(N):
                if i != j:
                    c[b, i, j] = coefs[b, k]
                    k += 1
    return c


def apply_c(c: np.ndarray, a_hat: np.ndarray) -> np.ndarray:
    """A_i = Σ_j C_ij Â_j per sample, written as loops (the paper's expanded A_t)."""
    out = np.zeros_like(a_hat)
    for b in range(a_hat.shape[0]):
        for i in range(N):
            for j in range(N):
                out[b, i] += c[b, i, j] * a_hat[b, j]
    return out


def close(actual, expected) -> None:
    np.testing.assert_allclose(actual, expected, rtol=1e-10, atol=1e-12)


# ---------------------------------------------------------------- independent (CIL)
def test_independent_is_four_separate_cil_mlps():
    mixer = build(IndependentMixer)
    h = np_h()
    expected = np.stack([cil_branch(mixer.branches[k], h) for k in range(N)], axis=1)
    close(run(mixer, h), expected)


# ---------------------------------------------------------------- gtu (CIC)
@pytest.mark.parametrize("scale", [1.0, 4.0])
def test_gtu_is_C_times_A_hat_with_gated_tanh_coefficients(scale):
    """C = I + offdiag(tanh(W_a h) * sigmoid(W_g h)), A = C Â (paper Eq. 1 with GTUs)."""
    mixer = build(GTUMixer)
    h = np_h(seed=1, scale=scale)
    a_hat = np.stack([cil_branch(mixer.branches[k], h) for k in range(N)], axis=1)
    coefs = np.tanh(lin(mixer.coef, h)) * sigmoid(lin(mixer.gate, h))
    c = offdiag_to_matrix(coefs)
    assert not np.allclose(c, np.transpose(c, (0, 2, 1)))  # asymmetric, so C and Cᵀ differ
    close(run(mixer, h), apply_c(c, a_hat))
    close(mixer.inspect()["C"].numpy(), c)


def test_gtu_coefficient_and_gate_are_not_interchangeable():
    """W_a feeds tanh and W_g feeds sigmoid: with W_a's output negative, the coefficients are
    negative (tanh < 0, sigmoid > 0); swapped, they would all be positive."""
    mixer = build(GTUMixer)
    with torch.no_grad():
        mixer.coef.weight.zero_()
        mixer.coef.bias.fill_(-2.0)
        mixer.gate.weight.zero_()
        mixer.gate.bias.fill_(0.5)
    h = np_h()
    mixer(torch.from_numpy(h))
    c = mixer.inspect()["C"].numpy()
    off = c[:, ~np.eye(N, dtype=bool)]
    close(off, np.full_like(off, np.tanh(-2.0) * sigmoid(0.5)))


# ---------------------------------------------------------------- re (CIC fine tuning, C = R ∘ E)
R_ASYM = [[1, 1, 0, 1],
          [0, 0, 1, 0],
          [1, 0, 1, 1],
          [0, 1, 0, 0]]


@pytest.mark.parametrize("scale", [1.0, 4.0])
def test_re_is_identity_plus_R_times_tanh_of_the_coefficient_mlp(scale):
    """C = I + R ∘ offdiag(tanh(E(h))), E a Linear-ReLU-Linear; R asymmetric, its diagonal ignored."""
    mixer = build(REMixer, R=R_ASYM, coef_hidden=7)
    h = np_h(seed=2, scale=scale)
    a_hat = np.stack([cil_branch(mixer.branches[k], h) for k in range(N)], axis=1)
    e1, e2 = linears(mixer.coef)
    e = np.tanh(lin(e2, relu(lin(e1, h))))
    r = np.array(R_ASYM, dtype=float)
    c = offdiag_to_matrix(e)
    off = ~np.eye(N, dtype=bool)
    c[:, off] *= r[off]  # R ∘ E off the diagonal; the diagonal stays 1
    close(run(mixer, h), apply_c(c, a_hat))
    close(mixer.inspect()["C"].numpy(), c)


# ---------------------------------------------------------------- moe (MMoE)
def test_moe_each_branch_reads_the_experts_through_its_own_softmax_gate():
    mixer = build(MoEMixer, experts=3, expert_dim=4)
    with torch.no_grad():
        mixer.gates.weight.mul_(5.0)  # gates far from uniform, and different per branch
    h = np_h(seed=3)
    E, D = 3, 4
    wide = relu(lin(linears(mixer.experts)[0], h))  # (B, E*D)
    experts = [wide[:, e * D:(e + 1) * D] for e in range(E)]  # expert e: columns e*D .. (e+1)*D
    logits = lin(mixer.gates, h)  # (B, 4*E): branch k's gate logits are columns k*E .. (k+1)*E
    outs, gates = [], []
    for k in range(N):
        z = logits[:, k * E:(k + 1) * E]
        g = np.exp(z - z.max(1, keepdims=True))
        g /= g.sum(1, keepdims=True)
        gates.append(g)
        x_k = sum(g[:, e:e + 1] * experts[e] for e in range(E))
        outs.append(cil_branch(mixer.branches[k], x_k))
    gates = np.stack(gates, axis=1)
    assert np.abs(gates - gates[:, :1]).max() > 0.05  # the branches' gates really differ
    close(run(mixer, h), np.stack(outs, axis=1))
    close(mixer.inspect()["gates"].numpy(), gates)


# ---------------------------------------------------------------- cross-stitch
def asymmetric(n: int, seed: int) -> np.ndarray:
    a = np.random.default_rng(seed).uniform(-0.5, 1.0, (n, n))
    assert np.abs(a - a.T).max() > 0.3
    return a


def test_cross_stitch_mixes_rows_into_rows_with_an_asymmetric_alpha():
    """x'_i = Σ_j α_ij x_j after each hidden layer (rows of α mix into rows), then the output layer."""
    mixer = build(CrossStitchMixer)
    alphas = [asymmetric(N, 10), asymmetric(N, 11)]
    with torch.no_grad():
        for p, a in zip(mixer.alphas, alphas):
            p.copy_(torch.from_numpy(a))
    h = np_h(seed=4)
    x = [h] * N
    for layer, a in enumerate(alphas):
        y = [relu(lin(linears(mixer.branches[k])[layer], x[k])) for k in range(N)]
        x = [sum(a[i, j] * y[j] for j in range(N)) for i in range(N)]
    expected = np.stack([lin(linears(mixer.branches[k])[2], x[k]) for k in range(N)], axis=1)
    close(run(mixer, h), expected)


# ---------------------------------------------------------------- sluice
BETA = [[0.3, 0.7], [1.2, -0.4], [-0.5, 0.25], [0.6, 0.9]]  # neither (0, 1) nor the same per branch


def test_sluice_uses_alpha_over_branch_subspaces_and_beta_over_layers():
    """u_{k,s} = subspace s (a contiguous slice) of branch k's hidden layer; x'_{k,s} = Σ_{j,t}
    α_{(k,s),(j,t)} u_{j,t}; z_k = Σ_l β_{k,l} x'^l_k; output layer of branch k on z_k."""
    S = 2
    mixer = build(SluiceMixer, subspaces=S)
    alphas = [asymmetric(N * S, 20), asymmetric(N * S, 21)]
    with torch.no_grad():
        for p, a in zip(mixer.alphas, alphas):
            p.copy_(torch.from_numpy(a))
        mixer.beta.copy_(torch.tensor(BETA, dtype=torch.float64))
    h = np_h(seed=5)
    w = HID // S
    x, per_layer = [h] * N, []
    for layer, a in enumerate(alphas):
        y = [relu(lin(linears(mixer.branches[k])[layer], x[k])) for k in range(N)]
        units = {(k, s): y[k][:, s * w:(s + 1) * w] for k in range(N) for s in range(S)}
        mixed = {}
        for k in range(N):
            for s in range(S):
                mixed[k, s] = sum(a[k * S + s, j * S + t] * units[j, t] for j in range(N) for t in range(S))
        x = [np.concatenate([mixed[k, s] for s in range(S)], axis=1) for k in range(N)]
        per_layer.append(x)
    z = [sum(BETA[k][l] * per_layer[l][k] for l in range(len(alphas))) for k in range(N)]
    expected = np.stack([lin(linears(mixer.branches[k])[2], z[k]) for k in range(N)], axis=1)
    close(run(mixer, h), expected)


@pytest.mark.parametrize("S", [2, 3])
def test_sluice_orthogonality_is_a_hand_sum_over_subspace_pairs(S):
    """ortho · Σ_k Σ_l Σ_{s<t} ||W^l_{k,s} W^l_{k,t}ᵀ||_F², W^l_{k,s} the rows of subspace s."""
    mixer = build(SluiceMixer, subspaces=S, ortho=0.25)
    w = HID // S
    total = 0.0
    for k in range(N):
        for layer in linears(mixer.branches[k])[:2]:
            weight, _ = wb(layer)
            rows = [weight[s * w:(s + 1) * w] for s in range(S)]
            for s in range(S):
                for t in range(s + 1, S):
                    total += float(((rows[s] @ rows[t].T) ** 2).sum())
    close(mixer.regularizer().item(), 0.25 * total)


# ---------------------------------------------------------------- soft sharing
def test_soft_sharing_penalty_with_hand_set_constant_branches():
    """Branch k's parameters all equal v_k: λ Σ_{i<j} ||θ_i − θ_j||² = λ P Σ_{i<j} (v_i − v_j)²."""
    lam = 0.3
    mixer = build(SoftSharingMixer, lam=lam)
    values = [0.0, 0.5, -1.0, 2.0]
    with torch.no_grad():
        for k, branch in enumerate(mixer.branches):
            for p in branch.parameters():
                p.fill_(values[k])
    n_params = IN * HID + HID + HID * HID + HID + HID * K + K
    pairs = sum((values[i] - values[j]) ** 2 for i in range(N) for j in range(i + 1, N))
    close(mixer.regularizer().item(), lam * n_params * pairs)


def test_soft_sharing_penalty_against_a_hand_sum_over_named_parameters():
    lam = 0.07
    mixer = build(SoftSharingMixer, lam=lam)
    states = [{k: v.numpy() for k, v in b.state_dict().items()} for b in mixer.branches]
    total = 0.0
    for i in range(N):
        for j in range(i + 1, N):
            total += sum(float(((states[i][name] - states[j][name]) ** 2).sum()) for name in states[i])
    close(mixer.regularizer().item(), lam * total)
