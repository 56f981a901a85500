"""SimEnv.restore / MetaWorldEnv.restore: an episode continued from a recorded tick is the same episode."""

import mujoco
import numpy as np
import pytest

from studio.sim.experts import expert_waypoints
from studio.sim.physics_state import STATE_SPEC, check_states, state_size
from studio.sim.recorder import Recorder
from studio.sim.waypoints import WaypointController


def _scripted_episode(env, task: str, seed: int):
    """Run the scripted expert; return the recorder and the (target, gripper) command of every tick."""
    env.reset(task, seed)
    rec = Recorder(env)
    rec.tick()
    commands: list[tuple[np.ndarray, float]] = []
    real_step = env.step

    def step(target, gripper):
        commands.append((np.array(target, dtype=np.float64), float(gripper)))
        real_step(target, gripper)

    env.step = step
    try:
        WaypointController(env, on_tick=rec.tick).execute(expert_waypoints(env))
    finally:
        del env.step
    return rec, commands


@pytest.mark.parametrize(
    ("scene", "robot", "task"),
    [
        ("pick_place", "panda", "pick_place/cube->red"),
        ("push", "sawyer", "push/red-forward"),
        ("pick_place", "hand", "pick_place/cube->red"),  # mid-episode the cube is held by the pinch weld
    ],
)
def test_stepping_on_from_a_restored_tick_repeats_the_episode_bit_for_bit(env_factory, scene, robot, task):
    env = env_factory(scene, robot)
    rec, commands = _scripted_episode(env, task, 3)
    assert len(commands) == len(rec) - 1 > 100
    k = len(commands) // 2  # mid-episode: the arm is moving (and holding the cube in pick-and-place)
    states = np.stack(rec.states)
    env.restore(task, 3, states[: k + 1], gripper_cmd=rec.rows[k]["gripper_cmd"])
    assert env.steps == k
    if robot == "hand":
        assert env.held_object() == "cube", "the restored pinch still holds the cube"
    now = np.empty(state_size(env.model))
    mujoco.mj_getState(env.model, env.data, now, STATE_SPEC)
    np.testing.assert_array_equal(now, states[k])
    for t in range(k, len(commands)):
        env.step(*commands[t])
        mujoco.mj_getState(env.model, env.data, now, STATE_SPEC)
        np.testing.assert_array_equal(now, states[t + 1], err_msg=f"tick {t + 1} differs")


def test_restore_counts_the_stages_reached_before_the_restored_tick(env_factory):
    env = env_factory("pick_place", "panda")
    rec, _ = _scripted_episode(env, "pick_place/cube->red", 1)
    assert env.stages()["grasped"]
    states = np.stack(rec.states)
    k = len(rec) - 1  # after the release and the retreat: nothing is held any more, but it was
    env.restore("pick_place/cube->red", 1, states[: k + 1], gripper_cmd=rec.rows[k]["gripper_cmd"])
    assert env.held_object() is None
    assert env.stages() == {"reached": True, "grasped": True, "placed": True}
    env.restore("pick_place/cube->red", 1, states[:1], gripper_cmd=0.0)
    assert not env.stages()["grasped"] and env.steps == 0


def test_states_of_another_model_are_refused_with_the_reason(env_factory):
    panda = env_factory("pick_place", "panda")
    push = env_factory("push", "panda")
    push.reset("push/red-forward", 0)
    s = np.empty(state_size(push.model))
    mujoco.mj_getState(push.model, push.data, s, STATE_SPEC)
    with pytest.raises(ValueError, match="the scene changed since the episode was recorded"):
        panda.restore("pick_place/cube->red", 0, s[None], gripper_cmd=0.0)
    with pytest.raises(ValueError, match="shape"):
        check_states(panda.model, np.zeros((0, state_size(panda.model))))
    bad = np.full((1, state_size(panda.model)), np.nan)
    with pytest.raises(ValueError, match="non-finite"):
        check_states(panda.model, bad)
