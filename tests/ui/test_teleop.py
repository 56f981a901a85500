"""A teleop session moves the arm from targets and records an episode into the store."""

import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

from studio.data.store import EpisodeStore
from studio.ui.teleop import TeleopSession


def test_session_records_and_saves(tmp_path):
    session = TeleopSession("push", "sawyer", "push/red-forward", 3)
    try:
        start = session.env.ee_pos.copy()
        session.start_recording()
        target = start + np.array([0.05, 0.05, -0.05])
        session.set_target(target)
        session.set_gripper(1.0)
        deadline = time.time() + 10
        while time.time() < deadline and np.linalg.norm(session.env.ee_pos - target) > 0.005:
            time.sleep(0.05)
        assert np.linalg.norm(session.env.ee_pos - target) < 0.005
        session.set_target([np.nan, 0, 0])  # ignored, the arm stays put
        time.sleep(1.0)
        assert np.all(np.isfinite(session.env.ee_pos))
        rec = session.stop_recording(n_frames=20)
        assert rec is not None and rec.num_steps > 10 and len(rec.frames) == 20
        assert rec.arrays["gripper_cmd"][-1] == 1.0
        with EpisodeStore(tmp_path) as store:
            meta = store.add_episode(rec, role="expert", source="teleop")
            assert store.get(meta.id).task == "push/red-forward"
            assert store.load_frames(meta.id).shape[0] == 20
        assert session.stop_recording() is None  # nothing left to stop
    finally:
        session.close()
