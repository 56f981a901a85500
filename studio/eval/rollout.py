"""One imitation rollout: plan from the expert video and the agent's first frame, execute, re-plan on failure.

This is where the model and the simulator meet (they never import each other). A rollout:

1. resets the scene (task, seed) — once; re-planning never resets it;
2. renders the agent's current frame and asks the planner for 5 attributed waypoints;
3. executes them with the waypoint controller (grasp correction from the wrist depth camera in the
   pick-and-place and Meta-World scenes, :data:`GRASP_CORRECTION_SCENES`);
4. if the task has not succeeded and re-plans remain, takes a fresh observation of the *same* episode and
   plans again with the same demonstration.

``plan_ticks`` bounds each plan's execution in control ticks (the paper's Meta-World protocol: 500 steps per
plan, so 2,000 in all with 3 re-plans); an execution cut there counts as a failed attempt and the next plan, if
any, starts from where the arm is. Within a bound the controller spends the time as the paper's code does: each of
the K waypoints may take ``plan_ticks // K`` ticks (the reference's ``try_limit``, 100 for 500 ticks and 5
waypoints), and a waypoint where the hand has stopped short (:data:`STALL_TICKS`) is left at once. None: no bound
but the controller's own per-waypoint limits.

Everything needed to inspect it afterwards is returned: the recording (frames + full-rate arrays), every
plan (waypoints in world and camera frames, the predicted latent trajectory, planning time, the tick it
started at), the outcome with the stage at which it failed, and the physics state of every tick, from which
the rollout can be continued exactly (forked) at any moment.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np

from studio.data.forks import write_states
from studio.sim.env import SimEnv
from studio.sim.recorder import Recorder
from studio.sim.recording import Recording
from studio.sim.waypoints import ControllerConfig, WaypointController, commanded_waypoints

#: Failure stages, in the order a rollout passes them (the paper's breakdown).
STAGES = ("reached", "grasped", "placed")
FAILURE_NAMES = {"reached": "reach", "grasped": "grasp", "placed": "place"}
#: Scenes whose rollouts correct grasps from the wrist depth camera by default (the paper's execution).
GRASP_CORRECTION_SCENES = ("pick_place", "metaworld")
#: How a rollout corrects grasps (``studio eval --grasp-correction``): ``auto`` = the scene's default (below),
#: ``height`` = centre over the object and grasp no higher than its middle, ``centre`` = centre only (the paper's
#: correction), ``off`` = execute the grasp as planned.
GRASP_MODES = ("auto", "height", "centre", "off")
#: Within a plan's tick budget, a waypoint is left when the hand has moved less than 2 mm in this many ticks.
STALL_TICKS = 10


def protocol_plan_ticks(scene: str) -> int | None:
    """The bound on one plan's execution under ``scene``'s protocol (its split's ``plan_ticks``; Meta-World: the
    paper's 500 steps), None for a scene without one: what the studio's rollouts default to."""
    from studio.data.splits import available_splits, load_split

    return load_split(scene).plan_ticks if scene in available_splits() else None


def grasp_controller(scene: str, mode: str = "auto") -> ControllerConfig:
    """The waypoint controller's settings for grasp correction ``mode`` (:data:`GRASP_MODES`) in ``scene``: ``auto``
    corrects with the grasp height in :data:`GRASP_CORRECTION_SCENES` and not at all elsewhere."""
    if mode not in GRASP_MODES:
        raise ValueError(f"unknown grasp correction {mode!r}; choose from {', '.join(GRASP_MODES)}")
    if mode == "auto":
        mode = "height" if scene in GRASP_CORRECTION_SCENES else "off"
    return ControllerConfig(grasp_correction=mode != "off", correct_grasp_height=mode == "height")


class PlannerLike(Protocol):
    def plan(
        self, expert_frames: np.ndarray, agent_frame: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray
    ): ...


@dataclass
class PlanRecord:
    """One planning call inside a rollout."""

    waypoints_world: np.ndarray
    waypoints_cam: np.ndarray | None
    planning_time_s: float
    start_tick: int
    latent_states: np.ndarray | None = None
    pooled_states: np.ndarray | None = None
    #: (S, h, w, 3) uint8: the predicted latent states decoded to images (when the model has a decoder).
    latent_images: np.ndarray | None = None
    #: (5, 4) with demonstration guidance: the plan from the null demonstration (``PlanResult``).
    null_waypoints_world: np.ndarray | None = None
    #: with guidance and a world model: the demonstration's gain, and whether this plan was guided (``PlanResult``).
    guidance_gain: float | None = None
    #: with a surprise gate: the demonstration's surprise (``PlanResult``).
    guidance_surprise: float | None = None
    guided: bool = False
    #: the guidance that made a guided plan (``PlanResult.guidance_scale``); None when not guided.
    guidance_scale: float | None = None
    #: (K, 4) the targets the controller commanded for the waypoints from where the arm stood (workspace-clipped,
    #: gripper flags as held: :func:`studio.sim.waypoints.commanded_waypoints`).
    waypoints_commanded: np.ndarray | None = None


@dataclass
class RolloutOutcome:
    """Everything one rollout produced."""

    task: str
    seed: int
    robot: str
    success: bool
    stages: dict[str, bool]
    failure_stage: str | None
    plans: list[PlanRecord]
    recording: Recording
    duration_s: float
    events: list[tuple[str, dict]] = field(default_factory=list)
    # The breakdown after each attempt (plan + execution): the outcome a smaller re-plan budget would have had.
    attempt_stages: list[dict[str, bool]] = field(default_factory=list)
    #: (T, S) MuJoCo integration state of every tick (what forking the rollout at a tick restores).
    states: np.ndarray | None = None

    @property
    def replans(self) -> int:
        return max(0, len(self.plans) - 1)

    @property
    def planning_time_s(self) -> float:
        return float(np.mean([p.planning_time_s for p in self.plans])) if self.plans else 0.0


def failure_stage(stages: dict[str, bool]) -> str | None:
    """The first stage not reached, or None on success."""
    if stages.get("placed"):
        return None
    for s in STAGES:
        if not stages.get(s):
            return FAILURE_NAMES[s]
    return "place"


def run_rollout(
    env: SimEnv,
    planner: PlannerLike,
    expert_frames: np.ndarray,
    task: str,
    seed: int,
    *,
    replans: int = 0,
    grasp_correction: bool | None = None,
    n_frames: int = 30,
    on_event: Callable[[str, dict], None] | None = None,
    on_tick: Callable[[], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    controller_config: ControllerConfig | None = None,
    plan_ticks: int | None = None,
) -> RolloutOutcome:
    """Run one rollout of ``task`` from ``seed`` on ``env`` imitating ``expert_frames`` (N, H, W, 3) uint8.

    ``on_tick`` is called after every control tick (live display); ``should_stop`` is polled every tick
    and ends the rollout early (cancellation) — the outcome then says ``failure_stage="cancelled"``.
    """
    if plan_ticks is not None and plan_ticks < 1:
        raise ValueError(f"plan_ticks must be >= 1, got {plan_ticks}")
    started = time.perf_counter()
    env.reset(task, seed)
    events: list[tuple[str, dict]] = []

    def event(kind: str, info: dict) -> None:
        events.append((kind, info))
        if on_event is not None:
            on_event(kind, info)

    recorder = Recorder(env)
    recorder.tick()

    attempt_state = {"ticks": 0, "cut": False, "stopped": False}

    def tick() -> None:
        recorder.tick()
        attempt_state["ticks"] += 1
        if on_tick is not None:
            on_tick()
        if should_stop is not None and should_stop():
            attempt_state["stopped"] = True
            controller.cancelled = True
        elif plan_ticks is not None and attempt_state["ticks"] >= plan_ticks:
            attempt_state["cut"] = True  # this plan's time is up: end its execution, not the rollout
            controller.cancelled = True

    cfg = controller_config or grasp_controller(env.scene)
    if grasp_correction is not None:
        cfg.grasp_correction = grasp_correction
    if plan_ticks is not None and cfg.stall_ticks is None:
        cfg = replace(cfg, stall_ticks=STALL_TICKS)
    controller = WaypointController(env, cfg, on_tick=tick, on_event=event)
    plans: list[PlanRecord] = []
    attempt_stages: list[dict[str, bool]] = []
    for attempt in range(replans + 1):
        if attempt:
            event("replanning", {"attempt": attempt, "of": replans})
        frame = env.render("external")
        cam = env.camera_model("external")
        event("planning", {"attempt": attempt})
        t0 = time.perf_counter()
        result = planner.plan(expert_frames, frame, cam.K, cam.T_world_cam)
        dt = time.perf_counter() - t0
        wps = np.asarray(result.waypoints_world, dtype=np.float64)
        commanded = commanded_waypoints(env, wps, cfg)
        plans.append(
            PlanRecord(
                waypoints_world=wps,
                waypoints_cam=getattr(result, "waypoints_cam", None),
                planning_time_s=dt,
                start_tick=env.steps,
                latent_states=getattr(result, "latent_states", None),
                pooled_states=getattr(result, "pooled_states", None),
                null_waypoints_world=getattr(result, "null_waypoints_world", None),
                guidance_gain=getattr(result, "guidance_gain", None),
                guidance_surprise=getattr(result, "guidance_surprise", None),
                guided=bool(getattr(result, "guided", False)),
                guidance_scale=getattr(result, "guidance_scale", None),
                waypoints_commanded=commanded,
            )
        )
        event(
            "planned",
            {"attempt": attempt, "waypoints": wps.tolist(), "commanded": commanded.tolist(), "seconds": dt},
        )
        controller.execute(wps, None if plan_ticks is None else plan_ticks // max(1, len(wps)))
        if attempt_state["cut"] and not attempt_state["stopped"]:
            event("plan time up", {"attempt": attempt, "ticks": attempt_state["ticks"]})
            controller.cancelled = False
        attempt_state.update(ticks=0, cut=False)
        attempt_stages.append({k: bool(v) for k, v in env.stages().items()})
        if attempt_stages[-1]["placed"] or controller.cancelled:
            break
    stages = attempt_stages[-1]  # the breakdown after the last attempt is the outcome
    outcome_stage = "cancelled" if controller.cancelled and not stages["placed"] else failure_stage(stages)
    event("outcome", {"success": stages["placed"], "failure_stage": outcome_stage})
    recording = recorder.finish(n_frames=n_frames, success=stages["placed"])
    return RolloutOutcome(
        task=task,
        seed=int(seed),
        robot=env.robot,
        success=stages["placed"],
        stages=stages,
        failure_stage=outcome_stage,
        plans=plans,
        recording=recording,
        duration_s=time.perf_counter() - started,
        events=events,
        attempt_stages=attempt_stages,
        states=np.stack(recorder.states),
    )


def store_rollout(
    store,
    out: RolloutOutcome,
    *,
    expert_episode_id: str | None,
    checkpoint_id: str | None,
    eval_id: str | None = None,
    keep: bool = True,
    extra: dict | None = None,
):
    """Write a rollout's plans and events into ``<root>/rollouts/<id>/`` (atomically) and index it.

    The recording becomes an agent episode (source ``rollout``) in the same catalog transaction as the
    rollout row. Returns the stored :class:`studio.data.catalog.RolloutRecord`.
    """
    import json
    import os
    import uuid

    from studio.data.catalog import RolloutRecord

    rollout_id = f"r-{uuid.uuid4().hex[:12]}"
    path = None
    if keep:
        folder = store.root / "rollouts" / rollout_id
        tmp = store.root / "rollouts" / f".{rollout_id}.tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        arrays = {}
        for i, p in enumerate(out.plans):
            arrays[f"plan{i}_waypoints_world"] = p.waypoints_world
            if p.waypoints_cam is not None:
                arrays[f"plan{i}_waypoints_cam"] = np.asarray(p.waypoints_cam)
            if p.latent_states is not None:
                arrays[f"plan{i}_latent_states"] = np.asarray(p.latent_states, dtype=np.float16)
            if p.pooled_states is not None:
                arrays[f"plan{i}_pooled_states"] = np.asarray(p.pooled_states, dtype=np.float32)
            if p.latent_images is not None:
                arrays[f"plan{i}_latent_images"] = np.asarray(p.latent_images, dtype=np.uint8)
            if p.null_waypoints_world is not None:
                arrays[f"plan{i}_null_waypoints_world"] = np.asarray(p.null_waypoints_world)
                arrays[f"plan{i}_guided"] = np.array(p.guided)
            if p.guidance_gain is not None:
                arrays[f"plan{i}_guidance_gain"] = np.array(p.guidance_gain)
            if p.guidance_surprise is not None:
                arrays[f"plan{i}_guidance_surprise"] = np.array(p.guidance_surprise)
            if p.guidance_scale is not None:
                arrays[f"plan{i}_guidance_scale"] = np.array(p.guidance_scale)
            if p.waypoints_commanded is not None:
                arrays[f"plan{i}_waypoints_commanded"] = np.asarray(p.waypoints_commanded)
        arrays["plan_start_ticks"] = np.array([p.start_tick for p in out.plans])
        arrays["plan_seconds"] = np.array([p.planning_time_s for p in out.plans])
        np.savez_compressed(tmp / "plans.npz", allow_pickle=False, **arrays)
        (tmp / "events.json").write_text(json.dumps(out.events, default=float))
        if out.states is not None:
            write_states(tmp, out.states)
        os.replace(tmp, folder)
        path = str(folder)
    record = RolloutRecord(
        id=rollout_id,
        task=out.task,
        success=out.success,
        checkpoint_id=checkpoint_id,
        expert_episode_id=expert_episode_id,
        robot=out.robot,
        seed=out.seed,
        failure_stage=out.failure_stage,
        replans=out.replans,
        planning_time_s=out.planning_time_s,
        duration_s=out.duration_s,
        num_steps=out.recording.num_steps,
        path=path,
        eval_id=eval_id,
        extra={"stages": out.stages, **(extra or {})},
    )
    return store.add_rollout(record, out.recording if keep else None)
