"""Soft dynamic time warping (Cuturi & Blondel, 2017) in plain PyTorch, on any device.

``soft_dtw(x, y, gamma)`` is the soft-min over all monotone alignments of the summed squared Euclidean costs;
``soft_dtw_divergence`` subtracts the two self-similarities so the result is ≥ 0 and exactly 0 for x = y.

The dynamic program R[i, j] = D[i, j] + softmin_γ(R[i−1, j−1], R[i−1, j], R[i, j−1]) is swept one anti-diagonal
at a time (all cells with i + j = k depend only on diagonals k−1 and k−2), vectorised over the batch and the
diagonal, so the Python loop has n + m − 1 iterations. The backward pass is written by hand with the standard
E-recursion (the expected alignment matrix), swept in reverse diagonals, instead of letting autograd record the
forward loop: memory is two (B, n+2, m+2) tables and there is no graph of n·m nodes.

Variable lengths: ``x_lengths``/``y_lengths`` give each sequence's true length; the value is read at
R[len_x, len_y] and the E-recursion starts there. Padded cells are computed on zeroed costs and masked out of the
backward sweep with ``torch.where`` (never multiplied), so padding — whatever its values — cannot produce NaN or
leak gradient. The cost tensor's padded entries receive exactly zero gradient.
"""

from __future__ import annotations

import torch

_INF = float("inf")


def _diagonals(n: int, m: int, device: torch.device) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """1-based (i, j) indices of every anti-diagonal i + j = k, k = 2 … n + m."""
    out = []
    for k in range(2, n + m + 1):
        i = torch.arange(max(1, k - m), min(n, k - 1) + 1, device=device)
        out.append((i, k - i))
    return out


class _SoftDTW(torch.autograd.Function):
    @staticmethod
    def forward(ctx, cost, gamma, x_lengths, y_lengths):
        B, n, m = cost.shape
        valid = _valid_mask(x_lengths, y_lengths, n, m)
        D = torch.zeros(B, n + 2, m + 2, dtype=cost.dtype, device=cost.device)
        D[:, 1 : n + 1, 1 : m + 1] = torch.where(
            valid, cost, torch.zeros((), dtype=cost.dtype, device=cost.device)
        )
        R = torch.full((B, n + 2, m + 2), _INF, dtype=cost.dtype, device=cost.device)
        R[:, 0, 0] = 0.0
        diagonals = _diagonals(n, m, cost.device)
        for i, j in diagonals:
            prev = torch.stack([R[:, i - 1, j - 1], R[:, i - 1, j], R[:, i, j - 1]], dim=-1)
            soft = -gamma * torch.logsumexp(-prev / gamma, dim=-1)
            R[:, i, j] = D[:, i, j] + soft
        b = torch.arange(B, device=cost.device)
        value = R[b, x_lengths, y_lengths]
        ctx.save_for_backward(D, R, x_lengths, y_lengths)
        ctx.gamma = gamma
        ctx.diagonals = diagonals
        return value

    @staticmethod
    def backward(ctx, grad_value):
        D, R, x_lengths, y_lengths = ctx.saved_tensors
        gamma = ctx.gamma
        n, m = R.shape[1] - 2, R.shape[2] - 2
        E = torch.zeros_like(R)
        lx = x_lengths[:, None]
        ly = y_lengths[:, None]
        zero = torch.zeros((), dtype=R.dtype, device=R.device)
        one = torch.ones((), dtype=R.dtype, device=R.device)
        for i, j in reversed(ctx.diagonals):
            r = R[:, i, j]
            total = torch.zeros_like(r)
            for di, dj in ((1, 0), (0, 1), (1, 1)):
                ni, nj = i + di, j + dj
                inside = (ni <= lx) & (nj <= ly)
                weight = torch.exp((R[:, ni, nj] - r - D[:, ni, nj]) / gamma)
                total = total + torch.where(inside, weight * E[:, ni, nj], zero)
            is_end = (i == lx) & (j == ly)
            in_range = (i <= lx) & (j <= ly)
            E[:, i, j] = torch.where(is_end, one, torch.where(in_range, total, zero))
        grad_cost = E[:, 1 : n + 1, 1 : m + 1] * grad_value[:, None, None]
        return grad_cost, None, None, None


def _valid_mask(x_lengths: torch.Tensor, y_lengths: torch.Tensor, n: int, m: int) -> torch.Tensor:
    rows = torch.arange(n, device=x_lengths.device)[None, :, None] < x_lengths[:, None, None]
    cols = torch.arange(m, device=y_lengths.device)[None, None, :] < y_lengths[:, None, None]
    return rows & cols


def _lengths(
    lengths: torch.Tensor | None, batch: int, full: int, device: torch.device, name: str
) -> torch.Tensor:
    if lengths is None:
        return torch.full((batch,), full, dtype=torch.long, device=device)
    lengths = torch.as_tensor(lengths, device=device).long()
    if lengths.shape != (batch,):
        raise ValueError(f"{name} must have shape ({batch},), got {tuple(lengths.shape)}")
    if bool((lengths < 1).any()) or bool((lengths > full).any()):
        raise ValueError(f"{name} must lie in 1..{full}, got {lengths.tolist()}")
    return lengths


def soft_dtw_from_cost(
    cost: torch.Tensor,
    gamma: float,
    x_lengths: torch.Tensor | None = None,
    y_lengths: torch.Tensor | None = None,
) -> torch.Tensor:
    """Soft-DTW values (B,) of a pairwise cost tensor (B, n, m), optionally with per-sample lengths."""
    if cost.ndim != 3:
        raise ValueError(f"cost must be (B, n, m), got shape {tuple(cost.shape)}")
    if gamma <= 0:
        raise ValueError(f"gamma must be positive, got {gamma}")
    B, n, m = cost.shape
    lx = _lengths(x_lengths, B, n, cost.device, "x_lengths")
    ly = _lengths(y_lengths, B, m, cost.device, "y_lengths")
    return _SoftDTW.apply(cost, float(gamma), lx, ly)


def squared_euclidean_cost(
    x: torch.Tensor,
    y: torch.Tensor,
    x_lengths: torch.Tensor | None = None,
    y_lengths: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, n, d), (B, m, d) → (B, n, m) squared distances; padded steps are zeroed first (no NaN from padding)."""
    if x.ndim != 3 or y.ndim != 3 or x.shape[0] != y.shape[0] or x.shape[2] != y.shape[2]:
        raise ValueError(
            f"x and y must be (B, n, d) and (B, m, d), got {tuple(x.shape)} and {tuple(y.shape)}"
        )
    if x_lengths is not None:
        keep = (
            torch.arange(x.shape[1], device=x.device)[None, :]
            < torch.as_tensor(x_lengths, device=x.device)[:, None]
        )
        x = torch.where(keep[..., None], x, torch.zeros((), dtype=x.dtype, device=x.device))
    if y_lengths is not None:
        keep = (
            torch.arange(y.shape[1], device=y.device)[None, :]
            < torch.as_tensor(y_lengths, device=y.device)[:, None]
        )
        y = torch.where(keep[..., None], y, torch.zeros((), dtype=y.dtype, device=y.device))
    diff = x[:, :, None, :] - y[:, None, :, :]
    return (diff * diff).sum(-1)


def soft_dtw(
    x: torch.Tensor,
    y: torch.Tensor,
    gamma: float = 1.0,
    x_lengths: torch.Tensor | None = None,
    y_lengths: torch.Tensor | None = None,
) -> torch.Tensor:
    """Soft-DTW (B,) between sequences x (B, n, d) and y (B, m, d) under the squared Euclidean cost."""
    return soft_dtw_from_cost(squared_euclidean_cost(x, y, x_lengths, y_lengths), gamma, x_lengths, y_lengths)


def soft_dtw_divergence(
    x: torch.Tensor,
    y: torch.Tensor,
    gamma: float = 1.0,
    x_lengths: torch.Tensor | None = None,
    y_lengths: torch.Tensor | None = None,
) -> torch.Tensor:
    """Soft-DTW divergence sdtw(x, y) − ½(sdtw(x, x) + sdtw(y, y)) (B,), non-negative and 0 at x = y."""
    xy = soft_dtw(x, y, gamma, x_lengths, y_lengths)
    xx = soft_dtw(x, x, gamma, x_lengths, x_lengths)
    yy = soft_dtw(y, y, gamma, y_lengths, y_lengths)
    return xy - 0.5 * (xx + yy)
