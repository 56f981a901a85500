"""Rollouts on Meta-World: run_rollout executes planned waypoints with the waypoint controller, re-plans in-episode.

The planner is the package's Meta-World oracle (``OraclePlanner`` → ``metaworld_experts.expert_waypoints``):
five hand positions along Meta-World's scripted policy's own episode from the same (task, seed), evenly spaced
in time up to ten ticks after its first success, gripper closed where the policy's effort is positive.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

from studio.eval.oracle import OraclePlanner
from studio.eval.rollout import run_rollout
from studio.sim.metaworld_env import MetaWorldEnv
from studio.sim.metaworld_experts import expert_waypoints

SIZE = (64, 64)


class RecordingOracle(OraclePlanner):
    """The oracle, noting the tick of every plan; with ``miss_first`` its first plan only hovers."""

    def __init__(self, env: MetaWorldEnv, miss_first: bool = False):
        super().__init__(env)
        self.miss_first = miss_first
        self.seen_steps: list[int] = []

    def plan(self, expert_frames, agent_frame, K, T_world_cam):
        assert agent_frame.shape == (*SIZE, 3) and K.shape == (3, 3) and T_world_cam.shape == (4, 4)
        self.seen_steps.append(self.env.steps)
        if self.miss_first and len(self.seen_steps) == 1:  # a useless first plan: hover where the hand is
            wps = np.tile(np.append(self.env.ee_pos + np.array([0.0, 0.0, 0.05]), 0.0), (5, 1))
            return type("Plan", (), {"waypoints_world": wps})()
        return super().plan(expert_frames, agent_frame, K, T_world_cam)


@pytest.fixture(scope="module")
def env():
    e = MetaWorldEnv(image_size=SIZE)
    yield e
    e.close()


def test_rollout_presses_the_button(env):
    planner = RecordingOracle(env)
    frames = np.zeros((10, *SIZE, 3), np.uint8)
    try:
        out = run_rollout(env, planner, frames, "metaworld/button-press-v3", 21, replans=0, n_frames=20)
    finally:
        planner.close()
    assert out.success and out.failure_stage is None and out.robot == "sawyer"
    assert len(out.plans) == 1 and out.plans[0].waypoints_world.shape == (5, 4)
    rec = out.recording
    assert rec.scene == "metaworld" and rec.success and rec.frames.shape == (20, *SIZE, 3)
    assert rec.num_steps == env.steps + 1 and np.all(np.diff(rec.arrays["time"]) > 0)


def test_replanning_continues_the_same_episode(env):
    planner = RecordingOracle(env, miss_first=True)
    frames = np.zeros((10, *SIZE, 3), np.uint8)
    try:
        out = run_rollout(env, planner, frames, "metaworld/door-unlock-v3", 4, replans=1, n_frames=20)
    finally:
        planner.close()
    assert out.success and out.replans == 1
    first, second = planner.seen_steps
    assert first == 0 and second > 0 and out.plans[1].start_tick == second
    # One episode: time never jumps back, and the episode is as long as both plans' execution.
    t = out.recording.arrays["time"]
    assert np.all(np.diff(t) > 0) and np.isclose(t[-1], env.steps * env.control_dt)


class FixedPlan:
    """A planner that always returns the same waypoints."""

    def __init__(self, waypoints: np.ndarray):
        self.waypoints = waypoints

    def plan(self, expert_frames, agent_frame, K, T_world_cam):
        return type("Plan", (), {"waypoints_world": self.waypoints})()


@pytest.mark.parametrize("seed", [0, 4])
def test_the_wrist_camera_saves_a_grasp_planned_beside_and_above_the_puck(env, seed):
    """The shipped policy's pick-place-wall grasps land about 2 cm beside and 3 cm above the puck; grasp
    correction, on by default on Meta-World as in the paper, centres them, and the plan succeeds."""
    task = "metaworld/pick-place-wall-v3"
    wps = expert_waypoints(task, seed, scratch=env)
    grasp = int(np.argmax(wps[:, 3] > 0.5))
    off = wps.copy()
    off[grasp, :3] += [0.02, -0.015, 0.025]
    frames = np.zeros((10, *SIZE, 3), np.uint8)
    uncorrected = run_rollout(env, FixedPlan(off), frames, task, seed, n_frames=5, grasp_correction=False)
    assert not uncorrected.success and uncorrected.failure_stage == "grasp"
    events: list[tuple[str, dict]] = []
    corrected = run_rollout(
        env, FixedPlan(off), frames, task, seed, n_frames=5, on_event=lambda k, i: events.append((k, i))
    )
    assert corrected.success
    assert [i["found"] for k, i in events if k == "grasp_correction"] == [True, True, True]
    # The exact plan still succeeds with the correction on.
    assert run_rollout(env, FixedPlan(wps), frames, task, seed, n_frames=5).success


def test_oracle_waypoints_follow_the_scripted_episode_and_a_failed_one_still_plans():
    wps = expert_waypoints("metaworld/pick-place-wall-v3", 3)
    assert wps.shape == (5, 4) and set(np.unique(wps[:, 3])) <= {0.0, 1.0}
    assert wps[:, 3].any(), "pick-place-wall closes the gripper on the way"
    assert np.allclose(wps, expert_waypoints("metaworld/pick-place-wall-v3", 3))  # deterministic by seed
    with MetaWorldEnv(image_size=(32, 32)) as scratch:
        with pytest.raises(RuntimeError, match="failed on seed"):
            # one tick is never enough to succeed: the policy "fails"
            import studio.sim.metaworld_experts as experts

            old, experts.MAX_TICKS = experts.MAX_TICKS, 1
            try:
                expert_waypoints("metaworld/door-unlock-v3", 0, scratch=scratch, strict=True)
            finally:
                experts.MAX_TICKS = old
        old, experts.MAX_TICKS = experts.MAX_TICKS, 3
        try:  # evaluation's oracle: the failed attempt is the plan, not an error that stops the evaluation
            failed = expert_waypoints("metaworld/door-unlock-v3", 0, scratch=scratch)
        finally:
            experts.MAX_TICKS = old
        assert failed.shape == (5, 4) and np.isfinite(failed).all()
