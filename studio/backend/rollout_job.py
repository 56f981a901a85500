"""The ``rollout`` job of a sim worker: one imitation rollout, streamed live to the bus and stored.

A thin handler: the rollout itself is :func:`studio.eval.rollout.run_rollout`; this module turns the job's spec into
its arguments, its events into job progress and body poses, paces it for watching, and stores the outcome with
the demonstration's score (:mod:`studio.eval.demo_score`), which the *Inspect* tab shows beside the plan.
"""

from __future__ import annotations

import time
from typing import Annotated, Any, Literal

import msgspec
import numpy as np

from studio.backend.messages import ContentId
from studio.backend.plan_job import Name, PathText, SceneSeed, checked_checkpoint


class RolloutJobSpec(msgspec.Struct, forbid_unknown_fields=True):
    """What a ``rollout`` job runs.

    Attributes:
        checkpoint: checkpoint path or ``"oracle"``.
        expert_episode_id: the stored demonstration imitated.
        task: the task's name; seed: the scene's seed.
        replans: re-plans allowed within the episode after a failed attempt.
        robot: the agent (default: the Panda; the Sawyer in Meta-World).
        checkpoint_id: the catalog id stored with the rollout (default: the file registered as
            ``<run-dir>/<name>``, see :func:`studio.eval.evaluation.register_checkpoint`).
        speed: simulated seconds per wall-clock second (1 = real time, so viewers see it live; 0 = as fast as
            possible).
        plan_ticks: control ticks each plan may execute; None: the scene's protocol (Meta-World: the paper's 500,
            as ``studio eval`` and ``studio results`` run it; no bound elsewhere), 0: no bound.
        inputs: content id of the job's inputs (:class:`~studio.backend.artifact_transfer.InputManifest`), which
            a worker with its own data dir fetches before the job runs (set by the hub's job client).
    """

    checkpoint: PathText
    expert_episode_id: Name
    task: Name
    seed: SceneSeed
    replans: Annotated[int, msgspec.Meta(ge=0, le=20)] = 0
    robot: Literal["panda", "sawyer"] | None = None
    checkpoint_id: Name | None = None
    speed: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] = 1.0
    plan_ticks: Annotated[int, msgspec.Meta(ge=0, le=100_000)] | None = None
    inputs: ContentId | None = None


def parse_spec(spec: dict[str, Any]) -> RolloutJobSpec:
    """The spec as a :class:`RolloutJobSpec`; ``ValueError`` naming what is missing or wrong."""
    missing = [k for k in ("checkpoint", "expert_episode_id", "task", "seed") if k not in spec]
    if missing:
        raise ValueError(f"rollout job spec lacks {missing}")
    try:
        return msgspec.convert(spec, RolloutJobSpec)
    except msgspec.ValidationError as e:
        raise ValueError(f"invalid rollout job spec: {e}") from None


def run_rollout_job(ctx) -> dict:
    """The ``rollout`` job of a sim worker (spec: :class:`RolloutJobSpec`).

    Streams progress (planning, waypoint i of 5, grasp correction, re-planning, outcome) and body poses at ≤ 30 Hz,
    stores the rollout with the demonstration's score (``extra["demo_score"]``) and returns its summary.
    """
    from studio.backend.scene_state import pose_frame
    from studio.data.store import EpisodeStore
    from studio.eval.demo_score import worker_score
    from studio.eval.evaluation import plan_ticks_of, register_checkpoint
    from studio.eval.latents import attach_latent_images
    from studio.eval.planners import load_planner, process_cached
    from studio.eval.rollout import run_rollout, store_rollout
    from studio.sim.env import make_env
    from studio.sim.tasks import get_task

    spec = parse_spec(dict(ctx.spec))
    if ctx.data_dir is None:
        raise ValueError(
            "rollout jobs need a worker started with --data-dir (the store with the demonstration)"
        )
    spec = msgspec.structs.replace(
        spec, checkpoint=checked_checkpoint(ctx.data_dir, spec.checkpoint, "rollout")
    )
    task = get_task(spec.task)
    robot = spec.robot or ("sawyer" if task.scene == "metaworld" else "panda")
    replans = spec.replans
    plan_ticks = plan_ticks_of(spec.plan_ticks, task.scene)  # absent: the scene's protocol; 0: no bound
    store = process_cached(("store", str(ctx.data_dir)), lambda: EpisodeStore(ctx.data_dir))
    # One simulator per job, closed by the job's own thread: an EGL context current in one (still living)
    # thread cannot be made current in another, so a simulator shared across job threads fails to render.
    env = make_env(task.scene, robot)
    try:
        planner = load_planner(spec.checkpoint, env)
        if hasattr(planner, "clear_cache"):
            planner.clear_cache()
        expert_frames = store.load_frames(spec.expert_episode_id)
        speed = spec.speed
        total_ticks = [0]
        last_pose = [-1.0]
        seq = [0]

        def on_event(kind: str, info: dict) -> None:
            if kind == "waypoint":
                msg = f"waypoint {info['index'] + 1} of {info['total']}"
            elif kind == "grasp_correction":
                msg = f"grasp correction {info['iteration']}/3" + (
                    "" if info.get("found") else " (nothing seen)"
                )
            elif kind == "replanning":
                msg = f"re-planning ({info['attempt']} of {info['of']})"
            elif kind == "planning":
                msg = "planning"
            elif kind == "planned":
                # The plan's waypoints ride along as metrics (wp<i>_x/y/z/g) so viewers can draw every re-plan live,
                # at the targets the controller commands (the stored plan keeps what the model predicted).
                wps = np.asarray(info["commanded"], dtype=float).reshape(-1, 4)
                metrics = {f"wp{i}_{c}": float(v) for i, row in enumerate(wps) for c, v in zip("xyzg", row)}
                ctx.progress(total_ticks[0], message=f"planned ({info['attempt'] + 1})", **metrics)
                return
            elif kind == "plan time up":
                msg = f"plan {info['attempt'] + 1} used its {plan_ticks} control ticks"
            elif kind == "outcome":
                msg = "success" if info["success"] else f"failed at {info['failure_stage']}"
            else:
                return
            ctx.progress(total_ticks[0], message=msg)

        wall_start: list[float] = []

        def on_tick() -> None:
            total_ticks[0] += 1
            now = time.monotonic()
            if speed > 0:  # paced for watching: simulated time runs at `speed` x wall time
                if not wall_start:
                    wall_start.append(now - env.data.time / speed)
                ahead = wall_start[0] + env.data.time / speed - now
                if ahead > 0:
                    ctx.wait_cancelled(ahead)
                    now = time.monotonic()
            # Poses go out at ≤ 30 Hz of the viewer's clock. Paced, that clock is simulated time over `speed`,
            # so every stretch of the rollout is shown alike even when a busy machine makes the loop catch up
            # in bursts; unpaced, it is the wall clock.
            clock = env.data.time / speed if speed > 0 else now
            if clock - last_pose[0] >= 1 / 30:
                last_pose[0] = clock
                seq[0] += 1
                ctx.poses(
                    pose_frame(
                        env.data,
                        seq=seq[0],
                        step=env.steps,
                        ack_seq=0,
                        ee_pos=env.ee_pos,
                        gripper=env.gripper_cmd,
                    )
                )

        out = run_rollout(
            env,
            planner,
            expert_frames,
            task.name,
            spec.seed,
            replans=replans,
            on_event=on_event,
            on_tick=on_tick,
            should_stop=lambda: ctx.cancelled,
            plan_ticks=plan_ticks,
        )
        ctx.raise_if_cancelled()
        checkpoint = spec.checkpoint
        demo_score: dict[str, Any] | None = None
        if checkpoint != "oracle":
            # Decoded here, where the model lives, so that viewers (the UI) never need torch.
            attach_latent_images(checkpoint, out.plans)
            demo_score = worker_score(planner.model, checkpoint, spec.expert_episode_id, expert_frames, store)
        checkpoint_id = spec.checkpoint_id
        if checkpoint != "oracle" and not checkpoint_id:
            checkpoint_id = register_checkpoint(store.root, checkpoint)
        extra: dict[str, Any] = {"job": ctx.job, "checkpoint": ctx.hub_path(checkpoint)}
        if demo_score is not None:
            extra["demo_score"] = demo_score
        if plan_ticks is not None:
            extra["plan_ticks"] = plan_ticks
        record = store_rollout(
            store,
            out,
            expert_episode_id=spec.expert_episode_id,
            checkpoint_id=None if checkpoint == "oracle" else str(checkpoint_id),
            extra=extra,
        )
        if record.episode_id is not None:  # to the hub's store, when it is not this worker's
            ctx.output_episode(record.episode_id, record)
        return {
            "rollout_id": record.id,
            "success": out.success,
            "failure_stage": out.failure_stage,
            "replans": out.replans,
            "planning_time_s": out.planning_time_s,
            "episode_id": record.episode_id,
            "stages": out.stages,
            "demo_score": demo_score,
            "plan_ticks": plan_ticks,
        }
    finally:
        env.close()
