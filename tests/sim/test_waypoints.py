"""Waypoint controller: reaching, re-planning inside one episode, grasp correction."""

import numpy as np
import pytest

from studio.sim.experts import expert_waypoints
from studio.sim.waypoints import ControllerConfig, WaypointController, commanded_waypoints


def test_reaches_given_waypoints(env_factory):
    env = env_factory("pick_place", "panda")
    env.reset("pick_place/cube->red", 2)
    wps = np.array([[0.1, 0.45, 0.2, 0], [-0.1, 0.5, 0.15, 0], [0.0, 0.4, 0.25, 0]])
    result = WaypointController(env).execute(wps)
    assert all(result.reached)
    assert np.linalg.norm(env.ee_pos - wps[-1, :3]) < 0.01


def test_replanning_continues_the_same_episode(env_factory):
    env = env_factory("pick_place", "sawyer")
    env.reset("pick_place/cube->red", 4)
    ctl = WaypointController(env, ControllerConfig(grasp_correction=False))
    # A first plan that misses (grasps empty air), then a good plan from where the arm stands.
    miss = np.array([[0.3, 0.8, 0.1, 1], [0.3, 0.8, 0.15, 1], [0.3, 0.8, 0.15, 0]])
    first = ctl.execute(miss)
    assert not first.success
    steps, time_before = env.steps, env.data.time
    moved = {o: p.copy() for o, p in env.object_poses().items()}
    second = ctl.execute(expert_waypoints(env))
    assert second.success
    assert env.steps > steps and env.data.time > time_before  # no reset happened in between
    assert env.steps == first.ticks + second.ticks
    # Objects the second plan did not touch are where the first plan left them.
    assert np.allclose(env.object_poses()["bar"][:3], moved["bar"][:3], atol=2e-3)


def test_invalid_waypoints_are_rejected(env_factory):
    env = env_factory("push", "panda")
    env.reset("push/red-forward", 0)
    with pytest.raises(ValueError, match="waypoints"):
        WaypointController(env).execute(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        WaypointController(env).execute(np.full((2, 4), np.nan))


def test_grasp_correction_centres_on_an_offset_object(env_factory):
    env = env_factory("pick_place", "panda")
    env.reset("pick_place/cylinder->green", 7)
    obj = env.object_poses()["cylinder"][:3]
    events = []
    ctl = WaypointController(env, on_event=lambda k, i: events.append((k, i)))
    above = obj + np.array([0.02, 0.0, 0.12])  # 2 cm off in x
    ctl.move_to(above, 0.0)
    corrected, top = ctl.correct_grasp(above)
    assert np.linalg.norm(corrected[:2] - obj[:2]) < 0.005
    assert abs(top - 2 * obj[2]) < 0.01  # the cylinder's top, seen from above (it stands on the table)
    assert np.linalg.norm(env.ee_pos[:2] - obj[:2]) < 0.006
    assert sum(1 for k, i in events if k == "grasp_correction" and i["found"]) == 3


def test_a_gripper_change_happens_at_the_lower_of_its_two_waypoints():
    from studio.sim.waypoints import gripper_flags

    scripted = np.array(
        [[0, 0, 0.045, 1], [0, 0, 0.15, 1], [0, 1, 0.15, 1], [0, 1, 0.055, 0], [0, 1, 0.15, 0]]
    )
    assert gripper_flags(scripted).tolist() == [True, True, True, False, False]  # already on the lower points
    # The same pick and place summarised the other way round: open at the object, closed above the zone.
    shifted = np.array([[0, 0, 0.25, 0], [0, 0, 0.05, 0], [0, 1, 0.16, 1], [0, 1, 0.04, 1], [0, 1, 0.11, 0]])
    assert gripper_flags(shifted).tolist() == [False, True, True, False, False]


def test_a_plan_that_closes_after_the_object_still_picks_and_places(env_factory):
    env = env_factory("pick_place", "panda")
    env.reset("pick_place/cube->red", 4)
    scripted = expert_waypoints(env)
    grasp, place = scripted[0, :3], scripted[3, :3]
    up = np.array([0.0, 0.0, 1.0])
    shifted = np.array(
        [
            [*(grasp + 0.2 * up), 0],
            [*grasp, 0],  # above the cube and at it, still open
            [*(place + 0.1 * up), 1],
            [*place, 1],  # carried to the zone and lowered, closed
            [*(place + 0.08 * up), 0],  # opened on the way up
        ]
    )
    assert WaypointController(env).execute(shifted).success


@pytest.mark.parametrize("correct_height", [True, False])
def test_a_grasp_planned_too_high_is_lowered_to_the_object_only_with_height_correction(
    env_factory, correct_height
):
    env = env_factory("pick_place", "panda")
    env.reset("pick_place/bar->blue", 4)
    scripted = expert_waypoints(env)
    high = scripted.copy()
    high[0, 2] += 0.03  # the model's typical miss on the flat bar: the grasp 2-3 cm above the scripted one
    cfg = ControllerConfig(correct_grasp_height=correct_height)
    assert WaypointController(env, cfg).execute(high).success == correct_height


def test_a_waypoint_the_hand_cannot_reach_is_left_once_the_hand_stops_when_stall_ticks_is_set(env_factory):
    env = env_factory("pick_place", "panda")
    below = np.array([0.0, 0.5, 0.012])  # the open fingertips meet the table 2 cm above this
    ticks = {}
    for stall in (None, 10):
        env.reset("pick_place/cube->red", 2)
        events: list[str] = []
        config = ControllerConfig(grasp_correction=False, stall_ticks=stall)
        ctl = WaypointController(env, config, on_event=lambda k, i, seen=events: seen.append(k))
        start = env.steps
        assert not ctl.move_to(below, 0.0)
        ticks[stall] = env.steps - start
        assert ("stalled" in events) == (stall is not None)
    assert ticks[None] == ControllerConfig().max_ticks and ticks[10] < 60, ticks


def test_each_waypoint_moves_for_at_most_its_share_of_a_plans_ticks(env_factory):
    env = env_factory("pick_place", "panda")
    far = np.array([[0.25, 0.35, 0.3, 0], [-0.25, 0.65, 0.3, 0], [0.25, 0.35, 0.3, 0]])  # 0.58 m apart
    ctl = WaypointController(env, ControllerConfig(grasp_correction=False, max_ticks=200))
    env.reset("pick_place/cube->red", 2)
    whole = ctl.execute(far)
    assert all(whole.reached) and whole.ticks > 120  # the controller's own limit lets it get there
    env.reset("pick_place/cube->red", 2)
    short = ctl.execute(far, waypoint_ticks=30)
    assert not short.reached[1] and short.ticks <= 90


def test_commanded_waypoints_are_where_the_controller_takes_the_arm(env_factory):
    """A plan outside the workspace (below the table, past its edges) is commanded to the clipped points, a grasp
    no lower than the robot's lowest grasp, with the gripper flags the controller holds; the hand ends at the last
    commanded point, not at the predicted one."""
    env = env_factory("pick_place", "panda")
    env.reset("pick_place/cube->red", 2)
    wps = np.array(
        [
            [0.10, 0.45, 0.20, 0.2],
            [0.70, 0.45, 0.15, 0.9],  # past the workspace's +x edge (0.45), and a grasp
            [0.00, 0.50, -0.20, 0.8],  # below the table
            [0.30, 0.45, 0.90, 0.1],  # above its ceiling (0.55), and a release
        ]
    )
    reach = commanded_waypoints(env, wps)
    assert np.allclose(reach[0], [0.10, 0.45, 0.20, 0.0])
    assert np.allclose(reach[1], [0.45, 0.45, 0.15, 1.0])
    # The workspace's floor; the release planned at the next, higher waypoint happens down here (gripper_flags).
    assert np.allclose(reach[2], [0.00, 0.50, 0.012, 0.0])
    assert np.allclose(reach[3], [0.30, 0.45, 0.55, 0.0])
    low = commanded_waypoints(env, [[0.1, 0.45, 0.0, 0.0], [0.1, 0.45, 0.0, 1.0]])
    assert np.allclose(low[:, 2], [0.012, 0.045])  # a grasp stays above the Panda's lowest grasp
    WaypointController(env, ControllerConfig(grasp_correction=False)).execute(wps)
    assert np.linalg.norm(env.ee_pos - reach[-1, :3]) < 0.02, (env.ee_pos, reach[-1])


def test_commanded_waypoints_keep_to_the_meta_world_mocap_box():
    """Meta-World bounds the hand's target to its task's mocap box, inside the studio's workspace on some sides."""
    from studio.sim.env import WORKSPACE, make_env

    env = make_env("metaworld", "sawyer")
    try:
        env.reset("metaworld/door-unlock-v3", 0)
        low, high = env.workspace
        reach = commanded_waypoints(env, [[2.0, -2.0, 2.0, 0.0], [-2.0, 2.0, -2.0, 0.0]])
        assert np.allclose(reach[0, :3], np.minimum(np.maximum([2.0, -2.0, 2.0], low), high).clip(*WORKSPACE))
        assert np.allclose(
            reach[1, :3], np.minimum(np.maximum([-2.0, 2.0, -2.0], low), high).clip(*WORKSPACE)
        )
        assert (reach[:, :3] >= low - 1e-9).all() and (reach[:, :3] <= high + 1e-9).all()
    finally:
        env.close()
