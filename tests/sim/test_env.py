"""SimEnv: target tracking, clamping, rendering, state."""

import numpy as np
import pytest

from studio.sim.env import WORKSPACE
from studio.sim.recording import ARRAY_FIELDS


@pytest.mark.parametrize("robot", ["panda", "sawyer", "hand"])
def test_settles_on_static_target(env_factory, robot):
    env = env_factory("pick_place", robot)
    env.reset("pick_place/cube->red", 0)
    target = np.array([0.12, 0.5, 0.18])
    for _ in range(100):
        env.step(target, 0.0)
    assert np.linalg.norm(env.ee_pos - target) < 0.005


@pytest.mark.parametrize("robot", ["panda", "sawyer", "hand"])
def test_follows_moving_target(env_factory, robot):
    env = env_factory("push", robot)
    env.reset("push/red-forward", 0)
    centre = np.array([0.0, 0.45, 0.2])
    errors = []
    for i in range(200):
        t = i * env.control_dt
        target = centre + 0.08 * np.array([np.cos(t * 1.5), np.sin(t * 1.5), 0.0])
        env.step(target, 0.0)
        if i > 50:
            errors.append(np.linalg.norm(env.ee_pos - target))
    assert np.mean(errors) < 0.02 and np.max(errors) < 0.04


@pytest.mark.parametrize("robot", ["panda", "sawyer", "hand"])
def test_unreachable_and_invalid_targets_stay_finite(env_factory, robot):
    env = env_factory("pick_place", robot)
    env.reset("pick_place/cube->red", 0)
    for target in ([3.0, 3.0, 3.0], [0.0, 0.4, -1.0], [np.nan, 0.0, 0.0]):
        for _ in range(60):
            env.step(np.array(target), 1.0)
        assert np.all(np.isfinite(env.data.qpos)) and np.all(np.isfinite(env.ee_pos))
        assert np.all(env.target >= WORKSPACE[0]) and np.all(env.target <= WORKSPACE[1])
    # In the table: the grasp site stays above it.
    assert env.ee_pos[2] > 0.0


def test_step_before_reset_is_an_error():
    from studio.sim.env import SimEnv

    env = SimEnv("push", "sawyer")
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(np.zeros(3), 0.0)
    env.close()


def test_render_shapes_and_content(env_factory):
    env = env_factory("pick_place", "panda")
    env.reset("pick_place/cube->red", 1)
    rgb = env.render()
    assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
    assert rgb.std() > 20, "image looks blank"
    small = env.render(size=(96, 128))
    assert small.shape == (96, 128, 3)
    depth = env.render_depth("wrist")
    assert depth.shape == (64, 64) and 0.0 < depth.min() < depth.max() < 2.0


def test_state_has_every_recorded_field(env_factory):
    env = env_factory("pick_place", "sawyer")
    env.reset("pick_place/cube->red", 1)
    s = env.state()
    assert set(s) == set(ARRAY_FIELDS)
    assert s["object_poses"].shape == (4, 7)
    cam = env.camera_model()
    assert np.allclose(cam.cam_to_world(s["ee_pos_cam"]), s["ee_pos_world"])
