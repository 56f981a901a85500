"""Training objective 𝓛 = 𝓛_sdtw + α(τ)·𝓛_wm and the validation errors reported alongside it.

* ``densify_waypoints``: a predicted set of n waypoints becomes a polyline that starts at the ground-truth start
  pose (position + gripper) and visits the n waypoints; it is sampled at ``dense_points`` instants evenly spaced
  in "segment time" (each segment takes equal time, the reference code's 60 // n points per segment), and every
  sample carries the gripper value of its segment's destination waypoint.
* ``endpoint_loss``: squared distance from each set's last waypoint to the path's end (opt-in, not in the paper).
* ``waypoint_loss``: soft-DTW (γ = 1e-3 as in the reference; raw value by default as in the paper, the
  divergence with ``normalize=True``) between each densified set and the dense ground-truth path (P = 50 points,
  camera-frame metres + gripper), under the squared Euclidean cost of (x, y, z, w·g) with w = ``gripper_weight``;
  averaged over the sets 1..5 and the batch. Predicted gripper values are probabilities (sigmoid of the logit),
  the labels 0 (open) … 1 (closed).
* ``world_model_loss``: mean absolute error between the pooled predicted states and the pooled encodings of the
  real future agent frames (targets computed without gradient by the model when the stop-gradient is on). The
  mean runs over steps and keypoint coordinates (the reference's ``L1Loss``; the paper's formula sums the
  coordinates — a constant factor absorbed in α).
* ``alpha``: constant, or exponential α_end + (α − α_end)·exp(−k·τ/T) (1 → 0.05 with k = 10 ≈ one e-fold per
  epoch of a 10-epoch run, the reference's Meta-World schedule).
"""

from __future__ import annotations

import math

import torch

from studio.model.config import TrainConfig
from studio.model.soft_dtw import soft_dtw, soft_dtw_divergence


def densify_waypoints(start: torch.Tensor, waypoints: torch.Tensor, points: int) -> torch.Tensor:
    """Polyline from ``start`` (B, D) through ``waypoints`` (B, n, D) sampled at ``points`` instants (B, points, D).

    The last feature is treated as the gripper: constant over a segment, equal to its destination's value.
    """
    n = waypoints.shape[1]
    nodes = torch.cat([start[:, None, :], waypoints], dim=1)
    s = torch.linspace(0.0, float(n), points, device=waypoints.device, dtype=waypoints.dtype)
    seg = s.floor().clamp(max=n - 1).long()
    frac = (s - seg.to(s.dtype))[None, :, None]
    a = nodes[:, seg, :]
    z = nodes[:, seg + 1, :]
    pos = a[..., :-1] + frac * (z[..., :-1] - a[..., :-1])
    return torch.cat([pos, z[..., -1:]], dim=-1)


def waypoint_loss(
    position: torch.Tensor,
    gripper: torch.Tensor,
    path: torch.Tensor,
    cfg: TrainConfig,
    max_waypoints: int,
    path_lengths: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Soft-DTW loss of the stacked waypoint sets against the ground-truth path.

    Args:
        position: (B, R, 3) predicted camera-frame positions of all R = 1 + … + max_waypoints rows.
        gripper: (B, R) predicted gripper probabilities.
        path: (B, P, 4) ground-truth path (camera-frame xyz, gripper 0..1).
        path_lengths: optional (B,) true path lengths when paths are padded.
    Returns:
        (the mean loss, the (max_waypoints,) per-set means).
    """
    b = position.shape[0]
    w = cfg.gripper_weight
    rows = torch.cat([position, w * gripper[..., None]], dim=-1).float()
    target = torch.cat([path[..., :3], w * path[..., 3:4]], dim=-1).float()
    start = target[:, 0]
    dense = []
    for n in range(1, max_waypoints + 1):
        first = n * (n - 1) // 2
        dense.append(densify_waypoints(start, rows[:, first : first + n], cfg.dense_points))
    pred = torch.cat(dense, dim=0)
    gt = target.repeat(max_waypoints, 1, 1)
    lengths = None if path_lengths is None else path_lengths.repeat(max_waypoints)
    fn = soft_dtw_divergence if cfg.sdtw_normalize else soft_dtw
    values = fn(pred, gt, cfg.sdtw_gamma, None, lengths).reshape(max_waypoints, b)
    per_set = values.mean(dim=1)
    return per_set.mean(), per_set.detach()


def endpoint_loss(
    position: torch.Tensor, path: torch.Tensor, max_waypoints: int, path_lengths: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean squared distance (m²) from the last waypoint of every set to the path's end.

    ``position`` (B, R, 3) holds the stacked sets' rows (set n ends at row n(n+1)/2 − 1); ``path`` (B, P, ≥3) the
    ground truth, whose end is its last row or, with ``path_lengths``, row ``length − 1``. Not in the paper
    (``TrainConfig.endpoint_weight``): soft-DTW aligns the last dense point with the path's end, but as one cell of
    a sum over the whole alignment, so an end a few centimetres off costs it little.
    """
    b = position.shape[0]
    lasts = torch.tensor([n * (n + 1) // 2 - 1 for n in range(1, max_waypoints + 1)], device=position.device)
    ends = path[:, -1, :3] if path_lengths is None else path[torch.arange(b), path_lengths.long() - 1, :3]
    return (position[:, lasts].float() - ends[:, None].float()).square().sum(-1).mean()


def world_model_loss(pooled: torch.Tensor, target_pooled: torch.Tensor) -> torch.Tensor:
    """Mean absolute error between pooled predicted states and pooled target encodings (B, S, 2C)."""
    if pooled.shape != target_pooled.shape:
        raise ValueError(
            f"predicted {tuple(pooled.shape)} and target {tuple(target_pooled.shape)} states differ"
        )
    return (pooled.float() - target_pooled.float()).abs().mean()


def alpha(step: int, total_steps: int, cfg: TrainConfig) -> float:
    """α(τ) weighting the world-model loss at optimiser step ``step`` of ``total_steps``."""
    if not cfg.wm_loss or step < cfg.alpha_warmup * total_steps:
        return 0.0
    if cfg.alpha_schedule == "constant":
        return cfg.alpha
    progress = min(max(step / max(total_steps, 1), 0.0), 1.0)
    return cfg.alpha_end + (cfg.alpha - cfg.alpha_end) * math.exp(-cfg.alpha_decay * progress)


@torch.no_grad()
def waypoint_errors(position: torch.Tensor, path: torch.Tensor, n: int) -> dict[str, torch.Tensor]:
    """Per-sample errors (metres) of the n-waypoint set (the last n rows) against the ground-truth path.

    ``final``: distance from the last waypoint to the path's end; ``path``: mean distance from each ground-truth
    path point to the nearest point of the densified predicted polyline.
    """
    wps = position[:, -n:, :].float()
    gt = path[..., :3].float()
    final = (wps[:, -1] - gt[:, -1]).norm(dim=-1)
    ones = torch.zeros_like(gt[:, 0, :1])
    start = torch.cat([gt[:, 0], ones], dim=-1)
    wps4 = torch.cat([wps, torch.zeros_like(wps[..., :1])], dim=-1)
    dense = densify_waypoints(start, wps4, 20 * n)[..., :3]
    nearest = torch.cdist(gt, dense).min(dim=-1).values
    return {"final": final, "path": nearest.mean(dim=-1)}
