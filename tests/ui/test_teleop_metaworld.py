"""Teleop on a Meta-World scene: drag the Sawyer onto the button, record, store as a demonstration."""

import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

from studio.data.store import EpisodeStore
from studio.sim.metaworld_env import MetaWorldEnv
from studio.ui.teleop import TeleopSession

TASK = "metaworld/button-press-v3"


def _wait(session: TeleopSession, target: np.ndarray, tol: float, seconds: float = 10.0) -> None:
    deadline = time.time() + seconds
    while time.time() < deadline and np.linalg.norm(session.env.ee_pos - target) > tol:
        time.sleep(0.05)


def test_drag_the_sawyer_press_and_save(tmp_path):
    session = TeleopSession("metaworld", "sawyer", TASK, 2)
    try:
        assert isinstance(session.env, MetaWorldEnv) and session.env.task.name == TASK
        button = session.env.object_poses()["object0"][:3]
        front = button + np.array([0.0, -0.10, -0.07])
        session.start_recording()
        session.set_target(front)
        _wait(session, front, 0.01)
        assert np.linalg.norm(session.env.ee_pos - front) < 0.01
        session.set_target(front + np.array([0.0, 0.22, 0.0]))  # push through the button
        deadline = time.time() + 10
        while time.time() < deadline and not session.call(session.env.success):
            time.sleep(0.05)
        session.set_target(front)
        _wait(session, front, 0.02)
        rec = session.stop_recording(n_frames=20)
        assert rec is not None and rec.success and rec.scene == "metaworld" and rec.task == TASK
        assert rec.frames.shape == (20, 224, 224, 3) and rec.num_steps > 40
        preview = session.render()
        assert preview.shape == (120, 160, 3)
        with EpisodeStore(tmp_path) as store:
            meta = store.add_episode(rec, role="expert", source="teleop")
            assert store.get(meta.id).scene == "metaworld" and store.get(meta.id).embodiment == "sawyer"
    finally:
        session.close()
