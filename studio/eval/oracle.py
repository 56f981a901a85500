"""The oracle planner: waypoints from the simulator's true state instead of from images — the execution ceiling.

``studio eval --checkpoint oracle`` (and the ``"oracle"`` checkpoint of the rollout and plan jobs) plans with it;
evaluation reports it as an upper bound for what the controller can do with perfect waypoints, never as a result
of the model.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np

from studio.sim.env import SimEnv
from studio.sim.experts import expert_waypoints

if TYPE_CHECKING:
    from studio.sim.metaworld_env import MetaWorldEnv


class OraclePlanner:
    """Plans from the simulator's true state (the scripted expert's waypoints): the execution ceiling.

    It ignores the images; evaluation reports it as an upper bound for what the controller can do
    with perfect waypoints, never as a result of the model. On the tabletop the waypoints are our experts'
    for the current state; on Meta-World they are five points along the scripted policy's own episode from the
    same reset (``studio.sim.metaworld_experts.expert_waypoints``), so a re-plan repeats the first plan. Where
    Meta-World's scripted policy fails, its plan follows the failed attempt, or with ``strict`` raises RuntimeError.
    """

    def __init__(self, env: SimEnv, strict: bool = False):
        if env.scene not in ("pick_place", "push", "metaworld"):
            raise ValueError(
                f"the oracle planner knows the tabletop and Meta-World scenes, not {env.scene!r}"
            )
        self.env = env
        self.strict = strict
        self._scratch: MetaWorldEnv | None = None

    def _waypoints(self) -> np.ndarray:
        if self.env.scene != "metaworld":
            return expert_waypoints(self.env)
        from studio.sim.metaworld_env import MetaWorldEnv
        from studio.sim.metaworld_experts import expert_waypoints as metaworld_waypoints

        task, seed = self.env.task, self.env.seed
        if task is None or seed is None:
            raise RuntimeError("the oracle plans for a scene that has been reset (SimEnv.reset)")
        if self._scratch is None:
            self._scratch = MetaWorldEnv(image_size=(32, 32))
        return metaworld_waypoints(task.name, seed, scratch=self._scratch, strict=self.strict)

    def plan(self, expert_frames, agent_frame, K, T_world_cam):
        wps = self._waypoints()
        cam = self.env.camera_model()
        waypoints_cam = np.column_stack([cam.world_to_cam(wps[:, :3]), wps[:, 3]])
        return SimpleNamespace(
            waypoints_world=wps, waypoints_cam=waypoints_cam, latent_states=None, pooled_states=None
        )

    def close(self) -> None:
        if self._scratch is not None:
            self._scratch.close()
            self._scratch = None
