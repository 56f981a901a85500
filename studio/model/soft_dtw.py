"""Soft dynamic time warping (Cuturi & Blondel, 2017) in plain PyTorch, on any device.

``soft_dtw(x, y, gamma)`` is the soft-min over all monotone alignments of the summed squared Euclidean costs;
``soft_dtw_divergence`` subtracts the two self-similarities so the result is ≥ 0 and exactly 0 for x = y.

The dynamic program R[i, j] = D[i, j] + softmin_γ(R[i−1, j−1], R[i−1, j], R[i, j−1]) is swept one anti-diagonal
at a time (all cells with i + j = k depend only on diagonals k−1 and k−2), vectorised over the batch and the
diagonal, so the Python loop has n + m − 1 iterations. The tables are stored skewed — row k of the table is
anti-diagonal k indexed by i — so a diagonal's predecessors are contiguous slices, not gathers. The backward pass
is written by hand with the standard E-recursion (the expected alignment matrix), swept in reverse diagonals,
instead of letting autograd record the forward loop: memory is two (B, n+m+3, n+2) tables and no graph of n·m
nodes.

Variable lengths: ``x_lengths``/``y_lengths`` give each sequence's true length; the value is read at
R[len_x, len_y] and the E-recursion starts there. Padded cells are computed on zeroed costs and masked out of the
backward sweep with ``torch.where`` (never multiplied), so padding — whatever its values — cannot produce NaN or
leak gradient. The cost tensor's padded entries receive exactly zero gradient.
"""

from __future__ import annotations

import functools

import torch

_INF = float("inf")


@functools.lru_cache(maxsize=32)
def _skew_index(n: int, m: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Gather indices between the padded (n+2, m+2) grid and the skewed (n+m+3 diagonals, n+2 rows) layout.

    Returns ``to_skew`` (n+m+3, n+2): flat grid index of cell (i, k − i), or of the zero corner when the cell
    falls outside the grid; and ``from_skew`` (n, m): flat skewed index of cell (i, j), 1 ≤ i ≤ n, 1 ≤ j ≤ m.
    """
    k = torch.arange(n + m + 3)[:, None]
    i = torch.arange(n + 2)[None, :]
    j = k - i
    inside = (j >= 0) & (j <= m + 1)
    to_skew = torch.where(inside, i * (m + 2) + j, torch.zeros_like(j))
    ii = torch.arange(1, n + 1)[:, None]
    jj = torch.arange(1, m + 1)[None, :]
    from_skew = (ii + jj) * (n + 2) + ii
    return to_skew.to(device), from_skew.to(device)


def _skewed_cells(n: int, m: int, x_lengths: torch.Tensor, y_lengths: torch.Tensor) -> torch.Tensor:
    """(B, n+m+3, n+2) mask of the cells (i, j = k − i) with 1 ≤ i ≤ len_x and 1 ≤ j ≤ len_y."""
    dev = x_lengths.device
    k = torch.arange(n + m + 3, device=dev)[None, :, None]
    i = torch.arange(n + 2, device=dev)[None, None, :]
    j = k - i
    lx = x_lengths[:, None, None]
    ly = y_lengths[:, None, None]
    return (i >= 1) & (i <= lx) & (j >= 1) & (j <= ly)


class _SoftDTW(torch.autograd.Function):
    """R and E live in a skewed layout — row k holds anti-diagonal i + j = k indexed by i — so the three
    predecessors (or successors) of a whole diagonal are plain slices of the neighbouring rows."""

    @staticmethod
    def forward(ctx, cost, gamma, x_lengths, y_lengths):
        B, n, m = cost.shape
        dt, dev = cost.dtype, cost.device
        valid = _valid_mask(x_lengths, y_lengths, n, m)
        D = torch.zeros(B, n + 2, m + 2, dtype=dt, device=dev)
        D[:, 1 : n + 1, 1 : m + 1] = torch.where(valid, cost, torch.zeros((), dtype=dt, device=dev))
        to_skew, _ = _skew_index(n, m, dev)
        Dk = D.flatten(1)[:, to_skew]  # (B, n+m+3, n+2)
        cells = _skewed_cells(n, m, x_lengths, y_lengths)
        grid = _skewed_cells(n, m, torch.full_like(x_lengths, n), torch.full_like(y_lengths, m))[0]
        R = torch.full_like(Dk, _INF)
        R[:, 0, 0] = 0.0
        inf = torch.full((), _INF, dtype=dt, device=dev)
        for k in range(2, n + m + 1):
            prev = torch.stack([R[:, k - 2, 0:n], R[:, k - 1, 0:n], R[:, k - 1, 1 : n + 1]], dim=-1)
            soft = -gamma * torch.logsumexp(-prev / gamma, dim=-1)
            R[:, k, 1 : n + 1] = torch.where(grid[k, 1 : n + 1], Dk[:, k, 1 : n + 1] + soft, inf)
        b = torch.arange(B, device=dev)
        value = R[b, x_lengths + y_lengths, x_lengths]
        ctx.save_for_backward(Dk, R, cells, x_lengths, y_lengths)
        ctx.gamma = gamma
        return value

    @staticmethod
    def backward(ctx, grad_value):
        Dk, R, cells, x_lengths, y_lengths = ctx.saved_tensors
        gamma = ctx.gamma
        _, K, rows = R.shape
        n = rows - 2
        m = K - n - 3
        E = torch.zeros_like(R)
        zero = torch.zeros((), dtype=R.dtype, device=R.device)
        one = torch.ones((), dtype=R.dtype, device=R.device)
        rows_i = torch.arange(1, n + 1, device=R.device)[None, :]
        end_k = (x_lengths + y_lengths)[:, None]
        lx = x_lengths[:, None]
        here = slice(1, n + 1)
        down = slice(2, n + 2)
        for k in range(n + m, 1, -1):
            r = R[:, k, here]
            total = torch.zeros_like(r)
            for kk, rr in ((k + 1, down), (k + 1, here), (k + 2, down)):  # (i+1, j), (i, j+1), (i+1, j+1)
                weight = torch.exp((R[:, kk, rr] - r - Dk[:, kk, rr]) / gamma)
                total = total + torch.where(cells[:, kk, rr], weight * E[:, kk, rr], zero)
            is_end = (k == end_k) & (rows_i == lx)
            E[:, k, here] = torch.where(is_end, one, torch.where(cells[:, k, here], total, zero))
        _, from_skew = _skew_index(n, m, R.device)
        grad_cost = E.flatten(1)[:, from_skew] * grad_value[:, None, None]
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
