"""Soft-DTW: against a naive float64 dynamic program (values and gradients, masked lengths) and tslearn."""

from __future__ import annotations

import pytest
import torch

from studio.model.soft_dtw import soft_dtw, soft_dtw_divergence, soft_dtw_from_cost

torch.set_num_threads(1)


def naive_soft_dtw(x: torch.Tensor, y: torch.Tensor, gamma: float) -> torch.Tensor:
    """The textbook O(nm) recursion on one pair, differentiable through autograd."""
    n, m = x.shape[0], y.shape[0]
    inf = torch.tensor(float("inf"), dtype=x.dtype)
    R = [[inf] * (m + 1) for _ in range(n + 1)]
    R[0][0] = torch.tensor(0.0, dtype=x.dtype)
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            cost = ((x[i - 1] - y[j - 1]) ** 2).sum()
            prev = torch.stack([R[i - 1][j - 1], R[i - 1][j], R[i][j - 1]])
            R[i][j] = cost - gamma * torch.logsumexp(-prev / gamma, dim=0)
    return R[n][m]


@pytest.mark.parametrize("gamma", [1.0, 0.1, 1e-3])
def test_values_and_gradients_match_naive_dp(gamma):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 7, 4, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.randn(3, 5, 4, generator=g, dtype=torch.float64, requires_grad=True)
    ours = soft_dtw(x, y, gamma)
    ref = torch.stack([naive_soft_dtw(x[b], y[b], gamma) for b in range(3)])
    assert torch.allclose(ours, ref, rtol=1e-10, atol=1e-10)
    w = torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64)
    gx, gy = torch.autograd.grad((ours * w).sum(), (x, y))
    rx, ry = torch.autograd.grad((ref * w).sum(), (x, y))
    assert torch.allclose(gx, rx, rtol=1e-8, atol=1e-10)
    assert torch.allclose(gy, ry, rtol=1e-8, atol=1e-10)


def test_gradcheck_on_cost():
    g = torch.Generator().manual_seed(1)
    cost = torch.rand(2, 4, 6, generator=g, dtype=torch.float64, requires_grad=True)
    lx = torch.tensor([4, 2])
    ly = torch.tensor([6, 3])
    assert torch.autograd.gradcheck(lambda c: soft_dtw_from_cost(c, 0.5, lx, ly), (cost,))


def test_masked_lengths_equal_unpadded_and_padding_is_inert():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(2, 8, 3, generator=g, dtype=torch.float64)
    y = torch.randn(2, 6, 3, generator=g, dtype=torch.float64)
    x[1, 5:] = float("nan")  # padding values must not matter, even NaN
    y[0, 4:] = 1e30
    x.requires_grad_(True)
    y.requires_grad_(True)
    lx = torch.tensor([8, 5])
    ly = torch.tensor([4, 6])
    ours = soft_dtw(x, y, 0.1, lx, ly)
    gx, gy = torch.autograd.grad(ours.sum(), (x, y))
    assert torch.isfinite(ours).all() and torch.isfinite(gx).all() and torch.isfinite(gy).all()
    for b in range(2):
        xb = x[b, : lx[b]].detach().clone().requires_grad_(True)
        yb = y[b, : ly[b]].detach().clone().requires_grad_(True)
        ref = naive_soft_dtw(xb, yb, 0.1)
        assert torch.allclose(ours[b], ref, rtol=1e-10)
        rx, ry = torch.autograd.grad(ref, (xb, yb))
        assert torch.allclose(gx[b, : lx[b]], rx, rtol=1e-8, atol=1e-12)
        assert torch.allclose(gy[b, : ly[b]], ry, rtol=1e-8, atol=1e-12)
        assert (gx[b, lx[b] :] == 0).all() and (gy[b, ly[b] :] == 0).all()


@pytest.mark.slow
@pytest.mark.parametrize("normalize", [False, True])
def test_matches_tslearn(normalize):
    from tslearn.metrics import SoftDTWLossPyTorch

    g = torch.Generator().manual_seed(3)
    x = torch.randn(4, 12, 4, generator=g, requires_grad=True)
    y = torch.randn(4, 9, 4, generator=g, requires_grad=True)
    ref_fn = SoftDTWLossPyTorch(gamma=0.05, normalize=normalize)
    ref = ref_fn(x, y)
    ours = soft_dtw_divergence(x, y, 0.05) if normalize else soft_dtw(x, y, 0.05)
    assert torch.allclose(ours, ref, rtol=1e-4, atol=1e-4)
    gx, gy = torch.autograd.grad(ours.sum(), (x, y))
    rx, ry = torch.autograd.grad(ref.sum(), (x, y))
    assert torch.allclose(gx, rx, rtol=1e-3, atol=1e-4)
    assert torch.allclose(gy, ry, rtol=1e-3, atol=1e-4)


def test_divergence_is_zero_at_equality_and_positive_elsewhere():
    g = torch.Generator().manual_seed(4)
    x = torch.randn(3, 10, 2, generator=g, dtype=torch.float64)
    assert torch.allclose(soft_dtw_divergence(x, x, 0.5), torch.zeros(3, dtype=torch.float64), atol=1e-12)
    y = x + 0.3 * torch.randn(3, 10, 2, generator=g, dtype=torch.float64)
    assert (soft_dtw_divergence(x, y, 0.5) > 0).all()


def test_small_gamma_approaches_hard_dtw_in_float32():
    x = torch.tensor([[[0.0], [1.0], [2.0]]])
    y = torch.tensor([[[0.0], [0.0], [1.0], [2.0], [2.0]]])
    value = soft_dtw(x, y, 1e-4)
    assert torch.isfinite(value).all()
    assert abs(value.item()) < 1e-3  # a zero-cost alignment exists


def test_bad_lengths_are_rejected():
    x = torch.zeros(2, 3, 1)
    with pytest.raises(ValueError, match="x_lengths"):
        soft_dtw(x, x, 1.0, x_lengths=torch.tensor([0, 3]))
    with pytest.raises(ValueError, match="gamma"):
        soft_dtw(x, x, 0.0)
