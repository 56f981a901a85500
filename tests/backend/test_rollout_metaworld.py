"""Rollouts on Meta-World: run_rollout executes planned waypoints with the waypoint controller, re-plans in-episode.

The oracle planner of the tabletop scenes reads our own experts' waypoints; here a planner made for the
tests derives the waypoints from Meta-World's scripted policy instead: it runs the policy from the same
(task, seed) in a scratch environment until ten ticks after its first success (success thresholds are
tight: a plan ending exactly where the signal first came on stops short by the controller's tolerance)
and keeps five hand positions evenly spaced in time, gripper closed where the policy's effort is positive.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

from studio.backend.rollout import run_rollout
from studio.sim.metaworld_env import MetaWorldEnv
from studio.sim.metaworld_experts import expert_action, scripted_policy

SIZE = (64, 64)


class PolicyTracePlanner:
    """Five waypoints along the scripted policy's hand path of the rollout env's episode."""

    def __init__(self, env: MetaWorldEnv, miss_first: bool = False):
        self.env = env
        self.scratch = MetaWorldEnv(image_size=SIZE)
        self.miss_first = miss_first
        self.seen_steps: list[int] = []

    def plan(self, expert_frames, agent_frame, K, T_world_cam):
        assert agent_frame.shape == (*SIZE, 3) and K.shape == (3, 3) and T_world_cam.shape == (4, 4)
        self.seen_steps.append(self.env.steps)
        if self.miss_first and len(self.seen_steps) == 1:  # a useless first plan: hover where the hand is
            wps = np.tile(np.append(self.env.ee_pos + np.array([0.0, 0.0, 0.05]), 0.0), (5, 1))
            return type("Plan", (), {"waypoints_world": wps})()
        s = self.scratch
        s.reset(self.env.task.name, self.env.seed)
        policy = scripted_policy(self.env.task.name)
        hand, closed, first = [], [], None
        for _ in range(500):
            a = expert_action(policy, s)
            s.step_action(a)
            hand.append(s.ee_pos)
            closed.append(float(a[3] > 0))
            first = first or (s.steps if s.success_now() else None)
            if first and s.steps >= first + 10:
                break
        assert first, "the scripted policy failed on this seed"
        idx = np.round(np.linspace(0, len(hand) - 1, 6)[1:]).astype(int)
        wps = np.column_stack([np.array(hand)[idx], np.array(closed)[idx]])
        return type("Plan", (), {"waypoints_world": wps})()

    def close(self):
        self.scratch.close()


@pytest.fixture(scope="module")
def env():
    e = MetaWorldEnv(image_size=SIZE)
    yield e
    e.close()


def test_rollout_presses_the_button(env):
    planner = PolicyTracePlanner(env)
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
    planner = PolicyTracePlanner(env, miss_first=True)
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
