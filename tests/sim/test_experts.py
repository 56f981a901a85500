"""Scripted experts succeed on every task with every robot (one seed each here; the benchmark does 50)."""

import pytest

from studio.sim.experts import expert_waypoints, record_expert, run_expert
from studio.sim.tasks import list_tasks


@pytest.mark.parametrize("robot", ["panda", "sawyer", "hand"])
def test_expert_succeeds_on_every_task(env_factory, robot):
    failures = []
    for scene in ("pick_place", "push"):
        env = env_factory(scene, robot)
        for i, task in enumerate(list_tasks(scene)):
            env.reset(task, 100 + i)
            if not run_expert(env):
                failures.append((task, env.stages()))
    assert not failures


def test_expert_plans_five_attributed_waypoints(env_factory):
    env = env_factory("pick_place", "panda")
    env.reset("pick_place/bar->blue", 0)
    w = expert_waypoints(env)
    assert w.shape == (5, 4)
    assert list(w[:, 3]) == [1, 1, 1, 0, 0]


def test_record_expert_returns_a_full_recording():
    rec = record_expert("push", "sawyer", "push/blue-backward", 3, image_size=(48, 64), min_frames=20)
    assert rec.success
    assert rec.frames.shape[1:] == (48, 64, 3) and len(rec.frames) == 20
    assert rec.frame_steps[0] == 0 and rec.frame_steps[-1] == rec.num_steps - 1
    assert rec.arrays["object_poses"].shape == (rec.num_steps, 2, 7)
    assert rec.camera.width == 64
