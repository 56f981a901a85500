"""Executes attributed waypoints — the model's output, and our scripted experts' plans — on a SimEnv.

A waypoint is a world position of the grasp site plus a gripper flag (closed or open once the
waypoint is reached). The controller:

* moves to each waypoint in turn, advancing when within ``tolerance`` or after ``max_ticks`` (a smaller per-waypoint
  budget may be given to :meth:`WaypointController.execute`), or — with ``stall_ticks`` set — as soon as the hand has
  stopped moving short of it (blocked by the object it pushes, or out of reach);
* before a *grasp* (open → closed) waypoint, first goes to a point ``approach_height`` above it, runs
  grasp correction from the wrist depth camera if enabled (:mod:`studio.sim.grasp_correction`, three
  iterations), descends, closes the gripper and waits for the fingers to settle. Where the wrist camera found
  the object, the descent goes no higher than the object's middle (half its top height, read from the depth
  image), as the scripted experts grasp: the paper's correction centres the gripper (x, y) only, and a plan
  fitted by five waypoints tends to put the grasp a few centimetres high (``correct_grasp_height``);
* at a *release* (closed → open) waypoint, arrives closed, then opens and waits;
* reads a change of the gripper flag between two waypoints as happening at the *lower* of the two: the
  gripper closes and opens where the hand is down at the object or the zone. A waypoint set fitted to a dense
  demonstrated path (the model's, by Soft-DTW) may put the point at the object on either side of the change —
  open at the object and closed at the carry point above, or closed at the object — and both mean "grasp at
  the object"; our scripted plans put the flag on the lower point already and run unchanged;
* never resets the scene. After the last waypoint the caller may check success, take a fresh
  observation and call :meth:`WaypointController.execute` again with new waypoints — re-planning
  inside the same episode.

Progress is reported through an optional callback (``on_event(kind, info)``) and every tick through
``on_tick()``, so that recorders, rollout jobs and the UI can follow along.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from studio.sim.env import WORKSPACE, SimEnv
from studio.sim.grasp_correction import segment_largest

GRIPPER_THRESHOLD = 0.5


def gripper_flags(waypoints: np.ndarray) -> np.ndarray:
    """The gripper state (closed = True) to hold on arrival at each of the (K, 4) waypoints: the flags as given,
    except that a change between two consecutive waypoints is moved onto the lower of them (module docstring)."""
    wps = np.asarray(waypoints, dtype=np.float64)
    given = wps[:, 3] >= GRIPPER_THRESHOLD
    flags = given.copy()
    for i in range(len(wps) - 1):
        if given[i] != given[i + 1] and wps[i, 2] < wps[i + 1, 2]:
            flags[i] = given[i + 1]  # the change happens down here, not at the higher point that follows
    return flags


def commanded_waypoints(
    env: SimEnv, waypoints: np.ndarray, config: ControllerConfig | None = None
) -> np.ndarray:
    """The (K, 4) targets :meth:`WaypointController.execute` will command for the waypoints from ``env``'s state
    now: each position clipped to the studio's workspace and to the scene's own bounds (Meta-World's mocap box), a
    grasp no lower than the robot's lowest grasp, and the gripper state held on arrival (1 closed, 0 open;
    :func:`gripper_flags`). A plan may put points outside the workspace (a guided plan extrapolates): these are
    where the arm is sent instead. Grasp correction may still move a grasp, by what the wrist camera then sees, and
    a target inside the workspace may still lie beyond what the arm's joints reach."""
    cfg = config or ControllerConfig()
    wps = np.asarray(waypoints, dtype=np.float64).reshape(-1, 4)
    flags = gripper_flags(wps)
    scene_box = getattr(env, "workspace", None)
    closed = env.gripper_cmd >= GRIPPER_THRESHOLD
    out = np.empty_like(wps)
    for i, w in enumerate(wps):
        pos = w[:3].copy()
        if flags[i] and not closed:  # a grasp
            pos[2] = max(pos[2], cfg.min_grasp_z.get(env.robot, 0.03))
        closed = bool(flags[i])
        pos = np.clip(pos, WORKSPACE[0], WORKSPACE[1])
        if scene_box is not None:
            pos = np.clip(pos, scene_box[0], scene_box[1])
        out[i, :3], out[i, 3] = pos, float(closed)
    return out


@dataclass
class ControllerConfig:
    """Tuning of the waypoint controller.

    Attributes:
        tolerance: distance at which a waypoint counts as reached, metres.
        max_ticks: control ticks allowed per waypoint before moving on.
        speed: travel speed of the commanded point, m/s; ``grasp_speed`` for the final descent of a grasp,
            which must also come within ``grasp_tolerance``.
        approach_height: how far above a grasp waypoint the arm first goes.
        grasp_correction: use the wrist depth camera before grasping.
        correction_iterations: how many times grasp correction looks and re-centres.
        correction_radius: only objects within this distance of the planned grasp are candidates.
        correct_grasp_height: when grasp correction found the object, grasp no higher than its middle (half the
            blob's top height above the table), never below ``min_grasp_z``. Not in the paper (its correction
            is horizontal); off gives the paper's behaviour. Measured in docs/experiments.md.
        close_ticks: ticks to wait after closing the gripper; ``open_ticks`` likewise after opening.
        min_grasp_z: lowest grasp-site height for a grasp (keeps fingertips off the table), per robot.
        stall_ticks: once the commanded point has arrived at a waypoint, move on (not reached) when the hand has
            moved less than ``stall_distance`` over this many ticks; None waits for ``max_ticks``. Rollouts whose
            plans have a tick budget set it (:func:`studio.eval.rollout.run_rollout`), as a blocked waypoint
            would otherwise spend ``max_ticks`` of that budget standing still.
    """

    tolerance: float = 0.01
    max_ticks: int = 120
    speed: float = 0.5
    grasp_speed: float = 0.25
    grasp_tolerance: float = 0.005
    approach_height: float = 0.12
    grasp_correction: bool = True
    correction_iterations: int = 3
    correction_radius: float = 0.06
    correct_grasp_height: bool = True
    close_ticks: int = 18
    open_ticks: int = 12
    min_grasp_z: dict[str, float] = field(
        default_factory=lambda: {"panda": 0.045, "sawyer": 0.045, "hand": 0.02}
    )
    stall_ticks: int | None = None
    stall_distance: float = 0.002


@dataclass
class ExecutionResult:
    """What happened while executing one waypoint set."""

    ticks: int
    reached: list[bool]
    corrections: list[np.ndarray]
    success: bool


class WaypointController:
    """Drives ``env`` through attributed waypoints."""

    def __init__(
        self,
        env: SimEnv,
        config: ControllerConfig | None = None,
        on_tick: Callable[[], None] | None = None,
        on_event: Callable[[str, dict], None] | None = None,
    ):
        self.env = env
        self.config = config or ControllerConfig()
        self.on_tick = on_tick
        self.on_event = on_event
        self.cancelled = False

    def _event(self, kind: str, **info) -> None:
        if self.on_event is not None:
            self.on_event(kind, info)

    def _tick(self, target: np.ndarray, gripper: float) -> None:
        self.env.step(target, gripper)
        if self.on_tick is not None:
            self.on_tick()

    def move_to(
        self,
        target: np.ndarray,
        gripper: float,
        max_ticks: int | None = None,
        tolerance: float | None = None,
        speed: float | None = None,
    ) -> bool:
        """Move until the grasp site is within tolerance of ``target``; True if reached.

        The commanded point travels along the straight line from the current pose at ``speed`` (m/s),
        so the arm follows the line instead of cutting corners through objects.
        """
        tol = self.config.tolerance if tolerance is None else tolerance
        limit = self.config.max_ticks if max_ticks is None else max_ticks
        speed = self.config.speed if speed is None else speed
        goal = np.clip(np.asarray(target, dtype=np.float64), WORKSPACE[0], WORKSPACE[1])
        carrot = self.env.ee_pos.copy()
        step = speed * self.env.control_dt
        stall = self.config.stall_ticks
        # The hand's last ``stall + 1`` positions since the commanded point reached the goal.
        arrived: deque[np.ndarray] = deque(maxlen=None if stall is None else stall + 1)
        for _ in range(limit):
            if self.cancelled:
                return False
            delta = goal - carrot
            dist = float(np.linalg.norm(delta))
            carrot = goal.copy() if dist <= step else carrot + delta * (step / dist)
            self._tick(carrot, gripper)
            hand = self.env.ee_pos
            if np.linalg.norm(hand - goal) < tol:
                return True
            if stall is not None and dist <= step:
                arrived.append(hand.copy())
                if len(arrived) > stall and np.linalg.norm(hand - arrived[0]) < self.config.stall_distance:
                    self._event("stalled", distance=float(np.linalg.norm(hand - goal)))
                    return False
        return False

    def hold(self, gripper: float, ticks: int) -> None:
        target = self.env.target.copy()
        for _ in range(ticks):
            if self.cancelled:
                return
            self._tick(target, gripper)

    def correct_grasp(self, above: np.ndarray) -> tuple[np.ndarray, float | None]:
        """Centre the gripper over the largest object blob seen by the wrist camera: the new hover point, and the
        height of the blob's top (None if nothing was found)."""
        point, top = above.copy(), None
        for i in range(self.config.correction_iterations):
            depth = self.env.render_depth("wrist")
            det = segment_largest(
                depth, self.env.camera_model("wrist"), near=above, radius=self.config.correction_radius
            )
            if det is None:
                self._event("grasp_correction", iteration=i + 1, found=False)
                break
            shift = det.world[:2] - self.env.ee_pos[:2]
            point, top = np.array([det.world[0], det.world[1], above[2]]), float(det.world[2])
            self._event("grasp_correction", iteration=i + 1, found=True, shift=shift.tolist())
            self.move_to(point, 0.0, max_ticks=60, tolerance=0.004)
        return point, top

    def execute(self, waypoints: np.ndarray, waypoint_ticks: int | None = None) -> ExecutionResult:
        """Execute (K, 4) waypoints [x, y, z, gripper] in the world frame; ``waypoint_ticks`` lowers the ticks each
        waypoint's move may take below ``max_ticks`` (a plan with a tick budget gives each waypoint its share)."""
        wps = np.asarray(waypoints, dtype=np.float64)
        if wps.ndim != 2 or wps.shape[1] != 4:
            raise ValueError(f"waypoints must be (K, 4) [x, y, z, gripper], got {wps.shape}")
        if not np.all(np.isfinite(wps)):
            raise ValueError("waypoints contain NaN or inf")
        cfg = self.config
        limit = cfg.max_ticks if waypoint_ticks is None else max(1, min(cfg.max_ticks, waypoint_ticks))
        start = self.env.steps
        reached, corrections = [], []
        closed = self.env.gripper_cmd >= GRIPPER_THRESHOLD
        flags = gripper_flags(wps)
        for i, w in enumerate(wps):
            pos, want_closed = w[:3].copy(), bool(flags[i])
            self._event("waypoint", index=i, total=len(wps), position=pos.tolist(), closed=want_closed)
            if want_closed and not closed:  # grasp
                lowest = cfg.min_grasp_z.get(self.env.robot, 0.03)
                pos[2] = max(pos[2], lowest)
                above = pos + np.array([0.0, 0.0, cfg.approach_height])
                self.move_to(above, 0.0, max_ticks=limit)
                if cfg.grasp_correction:
                    above, top = self.correct_grasp(above)
                    corrections.append(above[:2] - pos[:2])
                    pos[:2] = above[:2]
                    if cfg.correct_grasp_height and top is not None:  # the table is at z = 0
                        pos[2] = max(min(pos[2], top / 2.0), lowest)
                ok = self.move_to(pos, 0.0, limit, cfg.grasp_tolerance, cfg.grasp_speed)
                self.hold(1.0, cfg.close_ticks)
                closed = True
            elif closed and not want_closed:  # release
                ok = self.move_to(pos, 1.0, max_ticks=limit)
                self.hold(0.0, cfg.open_ticks)
                closed = False
            else:
                ok = self.move_to(pos, 1.0 if closed else 0.0, max_ticks=limit)
            reached.append(bool(ok))
            if self.cancelled:
                break
        return ExecutionResult(
            ticks=self.env.steps - start, reached=reached, corrections=corrections, success=self.env.success()
        )
