"""Records an episode while it runs and renders its frames afterwards.

Every control tick the recorder keeps the dataset arrays (:meth:`studio.sim.env.SimEnv.state`) and
MuJoCo's compact physics state. Frames are rendered only at the end, at evenly spaced ticks, by
restoring those states — so an episode costs the renders it stores and no more, whatever its length.
"""

from __future__ import annotations

import mujoco
import numpy as np

from studio.sim.env import Simulator
from studio.sim.physics_state import STATE_SPEC
from studio.sim.recording import Recording

#: A person's recording is kept from this long before its first motion (seconds) ...
LEAD_IN_S = 0.2
#: ... to this long after its last (fingers still opening or closing, objects settling).
LEAD_OUT_S = 0.5
#: The grasp point has moved once it is this far (metres) from where the recording started (or ended).
MOVED_M = 0.01


def active_span(rows: list[dict], control_dt: float) -> tuple[int, int]:
    """The ticks ``[start, end)`` of a recording in which something happened: from LEAD_IN_S before the grasp
    point first moved (or the gripper command first changed) to LEAD_OUT_S after it last did.

    A person opening the page, reading the panel or reaching for the mouse before the first click is not part
    of the demonstration; scripted demonstrations start moving at their first tick, and the planner samples its
    frames evenly over the video, so idle time at either end takes frames from the task itself."""
    n = len(rows)
    if n == 0:
        return 0, 0
    ee = np.asarray([r["ee_pos_world"] for r in rows], dtype=np.float64)
    grip = np.asarray([r["gripper_cmd"] for r in rows], dtype=np.float64)
    from_start = (np.linalg.norm(ee - ee[0], axis=1) > MOVED_M) | (np.abs(grip - grip[0]) > 1e-6)
    from_end = (np.linalg.norm(ee - ee[-1], axis=1) > MOVED_M) | (np.abs(grip - grip[-1]) > 1e-6)
    if not from_start.any():
        return 0, n
    first = int(np.argmax(from_start))
    last = n - 1 - int(np.argmax(from_end[::-1]))
    lead_in, lead_out = round(LEAD_IN_S / control_dt), round(LEAD_OUT_S / control_dt)
    return max(0, first - lead_in), min(n, last + 1 + lead_out)


class Recorder:
    """Collects one episode of ``env``; call :meth:`tick` after reset and after every step."""

    def __init__(self, env: Simulator):
        self.env = env
        self.rows: list[dict] = []
        self.states: list[np.ndarray] = []
        self._size = mujoco.mj_stateSize(env.model, STATE_SPEC)

    def tick(self) -> None:
        self.rows.append(self.env.state())
        s = np.empty(self._size)
        mujoco.mj_getState(self.env.model, self.env.data, s, STATE_SPEC)
        self.states.append(s)

    def __len__(self) -> int:
        return len(self.rows)

    def frame_steps(self, n_frames: int) -> np.ndarray:
        """Evenly spaced tick indices, first and last included (all ticks if there are fewer)."""
        n = len(self.rows)
        if n == 0:
            raise ValueError("nothing recorded: call Recorder.tick() after reset and each step")
        return np.unique(np.round(np.linspace(0, n - 1, min(n_frames, n))).astype(np.int64))

    def finish(self, n_frames: int = 30, success: bool | None = None) -> Recording:
        """Render the frames and return the :class:`Recording`. The env's current state is kept."""
        env = self.env
        if env.task is None or env.seed is None:
            raise RuntimeError("Recorder.finish: the env has no episode (reset it before recording)")
        keep = np.empty(self._size)
        mujoco.mj_getState(env.model, env.data, keep, STATE_SPEC)
        steps = self.frame_steps(n_frames)
        frames = []
        for i in steps:
            mujoco.mj_setState(env.model, env.data, self.states[i], STATE_SPEC)
            mujoco.mj_forward(env.model, env.data)
            frames.append(env.render("external"))
        mujoco.mj_setState(env.model, env.data, keep, STATE_SPEC)
        mujoco.mj_forward(env.model, env.data)
        arrays = {k: np.stack([np.asarray(r[k], dtype=np.float64) for r in self.rows]) for k in self.rows[0]}
        return Recording(
            scene=env.scene,
            robot=env.robot,
            task=env.task.name,
            seed=int(env.seed),
            success=bool(env.success() if success is None else success),
            camera=env.camera_model("external"),
            frames=np.stack(frames),
            frame_steps=steps,
            arrays=arrays,
            object_names=list(env.scene_info.objects),
            control_dt=env.control_dt,
        )
