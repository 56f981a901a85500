"""Scenes for viewers without a live simulation: a stored episode replayed, or the start of (task, seed).

Episodes store the robot's joint positions and the free objects' poses at every control tick, not the
whole physics state; forward kinematics of the scene model on those gives every body's pose, in the
same row order as the live :class:`~studio.backend.messages.PoseFrame` stream. The scene model is built
and reset to the episode's (task, seed) first, so target zones sit where they were.

Meta-World objects are not restored (their poses are not free joints of our making); the robot is.
"""

from __future__ import annotations

import mujoco
import numpy as np

from studio.backend import messages as msg
from studio.backend.scene_state import body_poses, scene_geometry


class EpisodeReplay:
    """Body poses of a stored episode. ``poses_at(step)`` is (nbody, 7) float32 (xyz + quaternion wxyz)."""

    def __init__(self, store, episode_id: str):
        from studio.sim.env import make_env
        from studio.sim.recording import robot_of

        meta = store.get(episode_id)
        if not meta.has_arrays or meta.seed is None:
            raise ValueError(f"episode {episode_id} has no robot state to replay (a human video?)")
        _, frame_steps, arrays = store.load_arrays(episode_id)
        self.meta = meta
        self.arrays = arrays
        self.num_steps = len(arrays["qpos"])
        self.frame_steps = (
            np.asarray(frame_steps, dtype=np.int64)
            if frame_steps is not None
            else np.round(np.linspace(0, self.num_steps - 1, meta.num_frames)).astype(np.int64)
        )
        env = make_env(meta.scene, robot_of(meta.embodiment))  # the simulated hand for "human"
        try:
            env.reset(meta.task, meta.seed)
            self.geometry: msg.SceneGeometry = scene_geometry(env.model)
            model = env.model
            data = mujoco.MjData(model)
            data.qpos[:] = env.data.qpos
            data.mocap_pos[:] = env.data.mocap_pos
            data.mocap_quat[:] = env.data.mocap_quat
            robot_qadr = np.asarray(env._robot_qadr)
            obj_qadr = getattr(env, "_obj_qadr", {})
            names = list(meta.object_names)
            qpos, objects = arrays["qpos"], arrays["object_poses"]
            poses = np.empty((self.num_steps, model.nbody, 7), np.float32)
            for t in range(self.num_steps):
                data.qpos[robot_qadr] = qpos[t][: len(robot_qadr)]
                for k, name in enumerate(names):
                    if name in obj_qadr:
                        a = obj_qadr[name]
                        data.qpos[a : a + 7] = objects[t, k]
                mujoco.mj_kinematics(model, data)
                poses[t] = body_poses(data)
            self._poses = poses
        finally:
            env.close()

    def poses_at(self, step: int) -> np.ndarray:
        return self._poses[int(np.clip(step, 0, self.num_steps - 1))]

    def ee_path(self) -> np.ndarray:
        """(T, 3) end-effector positions in the world."""
        return np.asarray(self.arrays["ee_pos_world"], dtype=np.float64)


def scene_snapshot(scene: str, robot: str, task: str, seed: int) -> tuple[msg.SceneGeometry, np.ndarray]:
    """The geometry of (scene, robot) and every body's pose right after ``reset(task, seed)``.

    This is the state a rollout of (task, seed) starts from, so viewers can show it before it runs.
    """
    from studio.sim.env import make_env

    env = make_env(scene, robot)
    try:
        env.reset(task, seed)
        return scene_geometry(env.model), body_poses(env.data)
    finally:
        env.close()
