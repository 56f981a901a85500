"""An episode of a dataset written by LeRobot, imported as a demonstration, is imitated by a shipped policy.

The fixture ``hand-push`` (fixtures/lerobot/make_fixtures.py) is the simulated hand's scripted push of the
held-out ``push/blue-backward``, filmed at another size and frame rate (180×240 at 15 fps; the simulator
renders 240×320 at about 8 fps) and written by ``LeRobotDataset.create/add_frame/save_episode/finalize``
(AV1). Imported as a demonstration video of that task, it is planned and executed by the shipped policy that
learnt from human demonstrations — the same planner and rollout the *Imitate* tab's jobs run.
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

from studio.data.lerobot import import_lerobot
from studio.data.paths import SHIPPED_POLICY_DIR
from studio.data.store import EpisodeStore
from studio.eval.planners import load_planner
from studio.eval.rollout import run_rollout
from studio.sim.env import make_env

FIXTURE = Path(__file__).parent / "fixtures" / "lerobot" / "hand-push"
PUSH_HELD_OUT = "push/blue-backward"


def test_the_hands_push_from_a_lerobot_dataset_is_imitated_by_the_shipped_push_policy(tmp_path):
    store = EpisodeStore(tmp_path / "store")
    (meta,) = import_lerobot(store, FIXTURE, task=PUSH_HELD_OUT)
    assert (meta.task, meta.role, meta.embodiment, meta.source) == (
        PUSH_HELD_OUT,
        "expert",
        "human",
        "import",
    )
    assert meta.extra["source_size"] == [180, 240] and meta.extra["source_fps"] == 15.0
    assert meta.extra["lerobot_task"] == "push the blue box backward, towards the robot"
    frames = store.load_frames(meta.id)
    assert frames.shape[1:] == (240, 320, 3)

    env = make_env("push", "panda")
    try:
        planner = load_planner(str(SHIPPED_POLICY_DIR / "push-human-demos.pt"), env)
        out = run_rollout(env, planner, frames, PUSH_HELD_OUT, 3, replans=0)
    finally:
        env.close()
    assert out.plans and np.isfinite(out.plans[0].waypoints_world).all()
    assert out.success, out.failure_stage
