"""Scripted experts for every tabletop task on every robot (the arms and the hand), as attributed-waypoint plans.

An expert reads the true object and target poses after reset and writes the five waypoints a perfect
planner would: for pick-and-place grasp → lift → carry above the target → place (release) → retreat;
for pushing, go down behind the box with the gripper closed (the waypoint controller approaches from
above), push through, lift away. The :class:`~studio.sim.waypoints.WaypointController` executes them
— the same controller that executes the model's waypoints — without grasp correction (the expert
knows where the object is).
"""

from __future__ import annotations

import numpy as np

from studio.sim.env import SimEnv
from studio.sim.recorder import Recorder
from studio.sim.recording import Recording
from studio.sim.waypoints import ControllerConfig, WaypointController

LIFT_Z = 0.15
PUSH_Z = 0.03
PUSH_BEHIND = 0.09  # grasp site distance from the box centre when starting a push (open fingers clear it)
# The hand's open fingers and thumb reach 6 cm from its grasp site (the grippers' 4 cm), so it starts further off.
PUSH_BEHIND_OF_ROBOT = {"hand": 0.115}
PUSH_THROUGH = 0.18  # where the grasp site ends, beyond the box centre


def expert_waypoints(env: SimEnv) -> np.ndarray:
    """The expert's (5, 4) waypoints [x, y, z, gripper] for the env's current task and state."""
    task, layout = env.task, env.layout
    if task is None or layout is None:
        raise RuntimeError("expert_waypoints needs a reset env")
    obj = env.object_poses()[task.obj][:3]
    min_z = ControllerConfig().min_grasp_z[env.robot]
    if task.scene == "pick_place":
        grasp_z = max(obj[2], min_z)
        tgt = layout.target_pos[task.target]
        place_z = grasp_z + 0.01
        return np.array(
            [
                [obj[0], obj[1], grasp_z, 1.0],
                [obj[0], obj[1], LIFT_Z, 1.0],
                [tgt[0], tgt[1], LIFT_Z, 1.0],
                [tgt[0], tgt[1], place_z, 0.0],
                [tgt[0], tgt[1], LIFT_Z, 0.0],
            ]
        )
    sign = 1.0 if task.target == "forward" else -1.0
    z = max(PUSH_Z, min_z)
    start = obj[1] - sign * PUSH_BEHIND_OF_ROBOT.get(env.robot, PUSH_BEHIND)
    end = obj[1] + sign * PUSH_THROUGH
    return np.array(
        [
            [obj[0], start, z, 1.0],
            [obj[0], (start + end) / 2, z, 1.0],
            [obj[0], end, z, 1.0],
            [obj[0], end - sign * 0.03, z + 0.02, 1.0],
            [obj[0], end - sign * 0.03, LIFT_Z, 1.0],
        ]
    )


def run_expert(env: SimEnv, recorder: Recorder | None = None) -> bool:
    """Run the scripted expert on the env's current episode; True if the task succeeded."""
    controller = WaypointController(
        env, ControllerConfig(grasp_correction=False), on_tick=recorder.tick if recorder else None
    )
    return controller.execute(expert_waypoints(env)).success


def record_expert(
    scene: str,
    robot: str,
    task: str,
    seed: int,
    image_size: tuple[int, int] = (240, 320),
    min_frames: int = 30,
    env: SimEnv | None = None,
) -> Recording:
    """One scripted episode, recorded: full-rate arrays and ``min_frames`` evenly spaced frames.

    Pass ``env`` to reuse an environment across episodes (it must match scene, robot and image size).
    """
    own = env is None
    env = env or SimEnv(scene, robot, image_size=image_size)
    try:
        env.reset(task, seed)
        rec = Recorder(env)
        rec.tick()
        run_expert(env, rec)
        return rec.finish(n_frames=min_frames)
    finally:
        if own:
            env.close()
