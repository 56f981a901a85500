"""Meta-World scenes: seeded resets, our stepping (no time limit, no auto-reset), camera, state, success."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import pytest
from metaworld_cases import TEST_AND_TWINS

from studio.sim.env import SimEnv, make_env
from studio.sim.grasp_correction import segment_largest
from studio.sim.metaworld_env import MetaWorldEnv, metaworld_env_class, quaternion_orders
from studio.sim.metaworld_tasks import ENV_NAMES, MetaWorldTask
from studio.sim.recording import ARRAY_FIELDS
from studio.sim.tasks import get_task, list_tasks
from studio.sim.waypoints import WaypointController


@pytest.fixture(scope="module")
def env():
    e = MetaWorldEnv(image_size=(64, 64))
    yield e
    e.close()


def _snapshot(e: MetaWorldEnv) -> dict[str, np.ndarray]:
    m, d = e.model, e.data
    return {
        "qpos": d.qpos.copy(),
        "qvel": d.qvel.copy(),
        "mocap": d.mocap_pos.copy(),
        "body_pos": m.body_pos.copy(),
        "site_pos": m.site_pos.copy(),
        "goal": e.metaworld_env._get_pos_goal().copy(),
    }


def test_task_names_match_the_installed_package():
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS
    from metaworld.policies import ENV_POLICY_MAP

    assert list(ENV_NAMES) == list(ALL_V3_ENVIRONMENTS) and set(ENV_NAMES) == set(ENV_POLICY_MAP)
    names = list_tasks("metaworld")
    assert len(names) == 50 and names[0] == "metaworld/assembly-v3"
    assert set(names) <= set(list_tasks()) and not set(names) & set(list_tasks("pick_place"))
    assert get_task("metaworld/door-unlock-v3") == MetaWorldTask(
        "metaworld/door-unlock-v3", "metaworld", "door-unlock-v3"
    )
    with pytest.raises(ValueError, match="unknown Meta-World task"):
        get_task("metaworld/door-smash-v3")


def test_factory_and_bad_arguments():
    e = make_env("metaworld", "sawyer")
    assert isinstance(e, MetaWorldEnv) and e.image_size == (224, 224)
    with pytest.raises(ValueError, match="only the Sawyer"):
        make_env("metaworld", "panda")
    with pytest.raises(RuntimeError, match="before reset"):
        e.step(np.zeros(3), 0.0)
    e.close()
    tabletop = make_env("push", "sawyer")
    assert isinstance(tabletop, SimEnv) and tabletop.image_size == (240, 320)
    with pytest.raises(ValueError, match="belongs to scene 'metaworld'"):
        tabletop.reset("metaworld/reach-v3", 0)
    tabletop.close()


@pytest.mark.parametrize("task", TEST_AND_TWINS)
def test_reset_is_deterministic_by_seed(env, task):
    np.random.seed(1)  # noqa: NPY002 — the global state must not matter
    env.reset(task, 7)
    a = _snapshot(env)
    env.reset("metaworld/reach-v3", 7)  # another task (another model) in between
    env.reset(task, 8)
    b = _snapshot(env)
    np.random.seed(2)  # noqa: NPY002
    env.reset(task, 7)
    c = _snapshot(env)
    for k in a:
        assert np.array_equal(a[k], c[k]), k
    assert any(not np.array_equal(a[k], b[k]) for k in ("body_pos", "site_pos", "qpos", "goal"))
    assert env.steps == 0 and env.data.time == 0.0 and not env.success()
    assert np.allclose(env.target, env.ee_pos)


def test_state_camera_and_render(env):
    env.reset("metaworld/hammer-v3", 3)
    s = env.state()
    assert set(s) == set(ARRAY_FIELDS)
    assert (
        s["qpos"].shape == (9,)
        and s["object_poses"].shape == (2, 7)
        and env.object_names == ("object0", "object1")
    )
    assert np.allclose(np.linalg.norm(s["object_poses"][:, 3:], axis=1), 1.0)
    cam = env.camera_model("external")
    assert (cam.width, cam.height) == (64, 64)
    assert np.allclose(cam.cam_to_world(s["ee_pos_cam"]), s["ee_pos_world"])
    u, v = cam.world_to_pixel(env.ee_pos)
    assert 0 < u < 64 and 0 < v < 64  # the hand starts in view
    # Upright: the table (low z) is in the lower half of the image, higher points above it.
    assert cam.world_to_pixel(np.array([0.0, 0.7, 0.0]))[1] > cam.world_to_pixel(np.array([0.0, 0.7, 0.3]))[1]
    assert abs(2 * np.degrees(np.arctan(32 / cam.K[1, 1])) - 30.0) < 1e-6
    img = env.render()
    assert img.shape == (64, 64, 3) and img.dtype == np.uint8 and img.std() > 10
    depth = env.render_depth("external", size=(32, 32))
    assert depth.shape == (32, 32) and 0.5 < float(np.median(depth)) < 3.0
    with pytest.raises(ValueError, match=r"no camera 'nope'.*'wrist'"):
        env.render("nope")


def test_the_wrist_camera_rides_on_the_hand_and_finds_the_puck_between_the_fingers(env):
    env.reset("metaworld/pick-place-wall-v3", 0)
    puck = env.object_poses()["object0"][:3]
    for offset in ([0.0, 0.0, 0.12], [0.03, -0.02, 0.12]):
        for _ in range(150):
            env.step(puck + np.array(offset), 0.0)
        cam = env.camera_model("wrist")  # recomputed at every call: the camera moves with the hand
        assert np.allclose(cam.T_world_cam[:3, 3], env.ee_pos + np.array([0.0, 0.0, 0.04]), atol=3e-3)
        u, v = cam.world_to_pixel(env.ee_pos - np.array([0.0, 0.0, 0.1]))  # straight down the gripper axis
        assert abs(u - 32) < 1.5 and abs(v - 32) < 1.5
        found = segment_largest(env.render_depth("wrist"), cam, near=env.ee_pos, radius=0.06)
        assert found is not None and np.linalg.norm(found.world[:2] - puck[:2]) < 0.004
    with pytest.raises(ValueError, match="re-mounted"):
        env.render("behindGripper")


def test_quaternion_orders_follow_the_source():
    # MuJoCo quaternions, SciPy ones and a mix of both (stick-pull) — one order per reported quaternion.
    assert quaternion_orders(metaworld_env_class("button-press-v3")) == ("wxyz",)
    assert quaternion_orders(metaworld_env_class("pick-place-v3")) == ("xyzw",)
    assert quaternion_orders(metaworld_env_class("stick-pull-v3")) == ("xyzw", "wxyz")
    assert quaternion_orders(metaworld_env_class("window-open-v3")) == ("wxyz",)  # np.zeros(4): identity


def test_object_orientation_is_wxyz(env):
    env.reset("metaworld/pick-place-v3", 0)  # the puck stands upright: identity rotation
    assert np.allclose(env.object_poses()["object0"][3:], [1, 0, 0, 0], atol=1e-3)
    env.reset("metaworld/window-open-v3", 0)  # reports no orientation
    assert np.array_equal(env.object_poses()["object0"][3:], [1.0, 0.0, 0.0, 0.0])


def test_step_moves_mocap_with_bounded_speed_and_clamps(env):
    env.reset("metaworld/reach-v3", 0)
    start = env.data.mocap_pos[0].copy()
    env.step(env.ee_pos + np.array([0.5, 0.0, 0.0]), 1.0)  # far: capped at 1 cm along x
    assert np.allclose(env.data.mocap_pos[0] - start, [0.01, 0.0, 0.0], atol=1e-9)
    env.step(env.ee_pos + np.array([0.0, 0.02, 0.0]), 1.0)  # near: a quarter of the hand's error
    assert np.isclose(env.data.mocap_pos[0][1] - start[1], 0.25 * 0.02, atol=2e-3)
    assert env.gripper_cmd == 1.0 and np.allclose(env.data.ctrl, [1.0, -1.0])
    env.step(np.array([np.nan, 0, 0]), np.nan)  # ignored: keeps the last target and gripper
    assert env.gripper_cmd == 1.0 and np.all(np.isfinite(env.target))
    for _ in range(150):
        env.step(np.array([5.0, 5.0, 5.0]), 0.0)
    assert np.allclose(env.data.mocap_pos[0], env.workspace[1])
    assert env.steps == 153 and np.isclose(env.data.time, 153 * env.control_dt)


def test_evaluation_episode_never_resets(env):
    """> 500 ticks (Meta-World's horizon): time and steps keep increasing, nothing is re-initialised."""
    env.reset("metaworld/button-press-v3", 4)
    body_pos = env.model.body_pos.copy()
    button = env.object_poses()["object0"][:3]
    press = button + np.array([0.0, 0.12, -0.07])
    times, hand = [], []
    for i in range(620):
        env.step(press if i < 300 else press - np.array([0.0, 0.15, 0.0]), 0.0)
        times.append(env.data.time)
        hand.append(env.ee_pos)
    assert env.steps == 620 and np.all(np.diff(times) > 0)
    # A reset would put the hand back at Meta-World's home and re-draw the button's position.
    assert np.max(np.linalg.norm(np.diff(hand, axis=0), axis=1)) < 0.03
    assert np.linalg.norm(hand[-1] - (press - [0.0, 0.15, 0.0])) < 0.01
    assert np.array_equal(env.model.body_pos, body_pos)
    assert env.metaworld_env.curr_path_length == 0  # metaworld's own step() was never called
    assert env.success() and not env.success_now()  # pressed once (latched), released since
    assert env.stages() == {"reached": True, "grasped": True, "placed": True}


def test_mujoco_autoreset_is_off(env):
    env.reset("metaworld/reach-v3", 1)
    assert env.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_AUTORESET


def test_waypoint_controller_presses_the_button(env):
    env.reset("metaworld/button-press-v3", 11)
    b = env.object_poses()["object0"][:3]
    front = [b[0], b[1] - 0.10, b[2] - 0.07, 0.0]
    waypoints = np.array([front, [b[0], b[1] + 0.12, b[2] - 0.07, 0.0], front])
    ticks: list[int] = []
    result = WaypointController(env, on_tick=lambda: ticks.append(env.steps)).execute(waypoints)
    assert result.success and result.reached[0] and result.reached[2]
    assert ticks == list(range(1, result.ticks + 1))
    assert env.stages()["placed"] and not env.success_now()


def test_stages_before_anything_happens(env):
    env.reset("metaworld/pick-place-wall-v3", 2)
    assert env.stages() == {"reached": False, "grasped": False, "placed": False}


def test_restore_continues_an_episode_bit_for_bit(env):
    from studio.sim.physics_state import STATE_SPEC, state_size
    from studio.sim.recorder import Recorder

    task = "metaworld/button-press-v3"
    env.reset(task, 4)
    rng = np.random.default_rng(0)
    goal = env.ee_pos + np.array([0.0, 0.1, -0.1])
    commands = [(goal + 0.02 * rng.standard_normal(3), float(i > 30)) for i in range(60)]
    rec = Recorder(env)
    rec.tick()
    for c in commands:
        env.step(*c)
        rec.tick()
    final_obs, final_stages = env.observation().copy(), env.stages()
    k = 25
    env.restore(task, 4, np.stack(rec.states[: k + 1]), gripper_cmd=rec.rows[k]["gripper_cmd"])
    assert env.steps == k
    now = np.empty(state_size(env.model))
    for t in range(k, len(commands)):
        env.step(*commands[t])
        mujoco.mj_getState(env.model, env.data, now, STATE_SPEC)
        np.testing.assert_array_equal(now, rec.states[t + 1], err_msg=f"tick {t + 1} differs")
    np.testing.assert_array_equal(env.observation(), final_obs)
    assert env.stages() == final_stages
