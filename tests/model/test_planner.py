"""Planner: shapes, frames, resolution handling, expert-context reuse, checkpoint loading, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from synthetic_pairs import SyntheticPairs, tiny_run_config

from studio.model.osvi_wm import OSVIWM
from studio.model.planner import Planner
from studio.model.train import train

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def planner() -> Planner:
    torch.manual_seed(0)
    return Planner(OSVIWM(tiny_run_config().model))


@pytest.fixture(scope="module")
def sample() -> dict:
    return SyntheticPairs()[0]


def _pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T[:3, 3] = [0.5, -0.2, 1.0]
    return T


def test_plan_returns_five_world_waypoints_and_the_latent_trajectory(planner, sample):
    res = planner.plan(sample["expert_frames"], sample["agent_frames"][0], sample["K"], _pose())
    assert res.waypoints_world.shape == res.waypoints_cam.shape == (5, 4)
    assert res.latent_states.shape == (2, 16, 6, 8) and res.pooled_states.shape == (2, 32)
    T = _pose()
    assert np.allclose(
        res.waypoints_world[:, :3], res.waypoints_cam[:, :3] @ T[:3, :3].T + T[:3, 3], atol=1e-6
    )
    assert ((res.waypoints_world[:, 3] >= 0) & (res.waypoints_world[:, 3] <= 1)).all()
    assert res.gripper_closed.dtype == bool and res.timing["total"] > 0


def test_layouts_and_resolutions_give_the_same_plan(planner, sample):
    planner.clear_cache()
    base = planner.plan(sample["expert_frames"], sample["agent_frames"][0], sample["K"], np.eye(4))
    hwc = planner.plan(
        sample["expert_frames"].transpose(0, 2, 3, 1),
        sample["agent_frames"][0].transpose(1, 2, 0),
        sample["K"],
        np.eye(4),
    )
    assert np.allclose(base.waypoints_cam, hwc.waypoints_cam, atol=1e-6)
    # a 2x larger input with its own intrinsics maps to the same model input and the same camera points
    big = SyntheticPairs(image_size=(96, 128))[0]
    res = planner.plan(big["expert_frames"], big["agent_frames"][0], big["K"], np.eye(4))
    assert np.allclose(res.waypoints_cam[:, :3], base.waypoints_cam[:, :3], atol=0.05)


def test_replanning_with_the_same_demonstration_reuses_its_context(planner, sample):
    planner.clear_cache()
    cold = planner.plan(sample["expert_frames"], sample["agent_frames"][1], sample["K"], np.eye(4))
    warm = planner.plan(sample["expert_frames"], sample["agent_frames"][1], sample["K"], np.eye(4))
    assert not cold.reused_expert_context and warm.reused_expert_context
    assert np.allclose(cold.waypoints_world, warm.waypoints_world, atol=1e-6)
    other = SyntheticPairs()[20]["expert_frames"]
    assert not planner.plan(other, sample["agent_frames"][1], sample["K"], np.eye(4)).reused_expert_context


def test_longer_videos_are_resampled_to_n_frames(planner, sample):
    video = np.repeat(sample["expert_frames"], 3, axis=0)
    res = planner.plan(video, sample["agent_frames"][0], sample["K"], np.eye(4))
    assert res.waypoints_world.shape == (5, 4)


def test_bad_input_is_rejected(planner, sample):
    with pytest.raises(ValueError, match="uint8"):
        planner.plan(
            sample["expert_frames"].astype(np.float32), sample["agent_frames"][0], sample["K"], np.eye(4)
        )
    with pytest.raises(ValueError, match="dimensions"):
        planner.plan(sample["expert_frames"][0], sample["agent_frames"][0], sample["K"], np.eye(4))
    with pytest.raises(ValueError, match="K must be"):
        planner.plan(sample["expert_frames"], sample["agent_frames"][0], np.eye(4), np.eye(4))


def test_load_from_a_training_checkpoint(tmp_path, sample):
    run = tiny_run_config(max_steps=1, batch_size=4, val_every=100)
    train(run, SyntheticPairs(), None, tmp_path, show_progress=False)
    planner = Planner.load(tmp_path / "last.pt")
    assert planner.cfg == run.model
    assert planner.plan(
        sample["expert_frames"], sample["agent_frames"][0], sample["K"], np.eye(4)
    ).waypoints_world.shape == (5, 4)
    assert planner.name_demonstration(sample["expert_frames"]) is None  # trained without a task head


def test_the_task_head_names_a_demonstration_by_its_parts(tmp_path, sample):
    source = SyntheticPairs(n_tasks=3)
    source.tasks = ["push/red-forward", "push/red-backward", "push/blue-forward"]
    run = tiny_run_config(
        max_steps=1, batch_size=4, val_every=100, demo_task_weight=1.0, demo_task_labels="parts"
    )
    train(run, source, None, tmp_path, show_progress=False)
    planner = Planner.load(tmp_path / "last.pt")
    box, direction = planner.name_demonstration(sample["expert_frames"])
    assert box in ("red", "blue") and direction in ("forward", "backward")
    longer = np.concatenate([sample["expert_frames"]] * 2)  # resampled to N frames, as for planning
    assert planner.name_demonstration(longer) == (box, direction)


def test_bfloat16_planning_stays_close_to_float32(sample):
    torch.manual_seed(0)
    model = OSVIWM(tiny_run_config().model)
    fp32 = Planner(model).plan(sample["expert_frames"], sample["agent_frames"][0], sample["K"], np.eye(4))
    bf16 = Planner(model, precision="bf16").plan(
        sample["expert_frames"], sample["agent_frames"][0], sample["K"], np.eye(4)
    )
    assert np.abs(bf16.waypoints_cam - fp32.waypoints_cam).max() < 0.05
    with pytest.raises(ValueError, match="precision"):
        Planner(model, precision="fp8")
