"""Waypoint densification, the soft-DTW waypoint loss, the world-model loss, α schedules and errors."""

from __future__ import annotations

import math

import pytest
import torch

from studio.model.config import TrainConfig
from studio.model.losses import (
    alpha,
    densify_waypoints,
    endpoint_loss,
    waypoint_errors,
    waypoint_loss,
    world_model_loss,
)

torch.set_num_threads(1)


def test_densified_polyline_starts_at_the_start_pose_and_ends_at_the_last_waypoint():
    start = torch.tensor([[0.0, 0.0, 1.0, 0.0]])
    wps = torch.tensor([[[1.0, 0.0, 1.0, 1.0], [1.0, 2.0, 1.0, 0.0]]])
    dense = densify_waypoints(start, wps, 61)
    assert dense.shape == (1, 61, 4)
    assert torch.allclose(dense[0, 0], torch.tensor([0.0, 0.0, 1.0, 1.0]))  # gripper of the segment's target
    assert torch.allclose(dense[0, -1], wps[0, -1])
    assert torch.allclose(dense[0, 15, :3], torch.tensor([0.5, 0.0, 1.0]))  # equal time per segment
    assert (dense[0, :30, 3] == 1).all() and (dense[0, 31:, 3] == 0).all()


def _rows_on_path(path: torch.Tensor) -> torch.Tensor:
    """Waypoint sets of 1..5 that lie on a straight path, spaced like the densification."""
    rows = []
    for n in range(1, 6):
        for k in range(1, n + 1):
            idx = round(k / n * (path.shape[1] - 1))
            rows.append(path[:, idx])
    return torch.stack(rows, 1)


def test_divergence_loss_vanishes_for_waypoints_on_a_straight_path_and_grows_off_it():
    s = torch.linspace(0, 1, 61)[:, None]
    path = torch.cat(
        [s * torch.tensor([0.3, -0.1, 0.2]) + torch.tensor([0.0, 0.0, 1.0]), torch.zeros(61, 1)], 1
    )[None]
    rows = _rows_on_path(path)
    cfg = TrainConfig(sdtw_normalize=True, sdtw_gamma=1e-4)
    on, per_set = waypoint_loss(rows[..., :3], rows[..., 3], path, cfg, 5)
    assert on.abs() < 1e-4 and per_set.shape == (5,)
    off, _ = waypoint_loss(rows[..., :3] + 0.05, rows[..., 3], path, cfg, 5)
    assert off > 100 * on.abs()


def test_waypoint_loss_gradients_reach_every_row():
    path = torch.rand(2, 50, 4)
    pos = torch.rand(2, 15, 3, requires_grad=True)
    grip = torch.rand(2, 15, requires_grad=True)
    loss, _ = waypoint_loss(pos, grip, path, TrainConfig(), 5)
    loss.backward()
    assert torch.isfinite(loss) and (pos.grad.abs().sum(-1) > 0).all() and (grip.grad != 0).all()


def test_world_model_loss_is_mean_absolute_error():
    a, b = torch.zeros(2, 3, 4), torch.full((2, 3, 4), 0.5)
    assert world_model_loss(a, b) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="differ"):
        world_model_loss(a, b[:, :2])


def test_alpha_schedules():
    const = TrainConfig(alpha=10.0)
    assert alpha(0, 100, const) == alpha(99, 100, const) == 10.0
    exp = TrainConfig(alpha_schedule="exponential", alpha=1.0, alpha_end=0.05, alpha_decay=10.0)
    assert alpha(0, 100, exp) == pytest.approx(1.0)
    assert alpha(100, 100, exp) == pytest.approx(0.05 + 0.95 * math.exp(-10))
    assert alpha(10, 100, exp) == pytest.approx(0.05 + 0.95 * math.exp(-1))
    assert alpha(5, 100, TrainConfig(wm_loss=False)) == 0.0
    late = TrainConfig(alpha_warmup=0.2, alpha_schedule="exponential")
    assert alpha(0, 100, late) == alpha(19, 100, late) == 0.0  # no world-model loss during the warm-up
    assert alpha(20, 100, late) == alpha(20, 100, exp)  # then the schedule, timed from the start of training


def test_waypoint_errors():
    path = torch.zeros(1, 10, 4)
    path[0, :, 0] = torch.linspace(0, 1, 10)
    pos = torch.zeros(1, 15, 3)
    pos[0, -5:, 0] = torch.tensor([0.2, 0.4, 0.6, 0.8, 0.9])
    err = waypoint_errors(pos, path, 5)
    assert err["final"].item() == pytest.approx(0.1)
    assert err["path"].item() < 0.02


def test_the_endpoint_loss_is_the_mean_squared_distance_of_each_sets_last_waypoint_to_the_path_end():
    path = torch.zeros(2, 7, 4)
    path[:, :, 0] = torch.linspace(0.0, 0.6, 7)  # ends at x = 0.6
    rows = torch.zeros(2, 15, 3)
    lasts = [0, 2, 5, 9, 14]
    rows[:, lasts, 0] = 0.6
    assert float(endpoint_loss(rows, path, 5)) == 0.0
    rows[:, 3, 1] = 5.0  # a row that ends no set: not counted
    assert float(endpoint_loss(rows, path, 5)) == 0.0
    rows[0, 14, 2] = 0.1  # set 5 of sample 0 ends 10 cm off: 0.01 m² over 2 samples x 5 sets
    assert math.isclose(float(endpoint_loss(rows, path, 5)), 0.01 / 10, rel_tol=1e-6)


def test_the_endpoint_loss_reads_a_padded_paths_end_at_its_length_and_moves_only_the_last_rows():
    path = torch.zeros(1, 6, 4)
    path[0, :4, 1] = torch.tensor([0.0, 0.1, 0.2, 0.3])  # true length 4; the padding (zeros) is not the end
    rows = torch.zeros(1, 3, 3, requires_grad=True)  # sets 1 and 2: rows 0 and 2 end them
    loss = endpoint_loss(rows, path, 2, path_lengths=torch.tensor([4]))
    assert math.isclose(float(loss.detach()), 0.09, rel_tol=1e-6)
    loss.backward()
    assert rows.grad is not None
    assert float(rows.grad[0, 1].abs().sum()) == 0.0 and float(rows.grad[0, 0].abs().sum()) > 0
