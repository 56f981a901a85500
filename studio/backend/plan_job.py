"""The ``plan`` job of a sim worker: one plan for (task, seed) from an expert demonstration, without executing it.

The UI's *Plan* button runs it: the worker resets the scene exactly as a rollout of the same (task, seed)
would, renders the agent's first frame, asks the planner (a checkpoint, or ``"oracle"``) for the 5
attributed waypoints and, when the checkpoint has a latent decoder, decodes the predicted latent
trajectory into images. Because planning is deterministic, the first plan of a ``rollout`` job with the
same spec is this plan.

The result is written to ``<data-dir>/plans/<job>.npz`` (arrays do not belong in the job journal):

* ``waypoints_world``, ``waypoints_cam``: (5, 4) xyz + gripper probability;
* ``waypoints_commanded``: (5, 4) the targets the controller will command for them and the gripper state it
  holds there (:func:`studio.sim.waypoints.commanded_waypoints`): what the UI draws;
* ``agent_frame``: (H, W, 3) uint8, the observation planned from;
* ``expert_indices``: indices of the expert frames the model saw (evenly spaced, first and last kept);
* ``latent_images``: (S, h, w, 3) uint8 decoded latent states (only with a decoder);
* ``K``, ``T_world_cam``: the external camera.

The result also carries the demonstration's score (:mod:`studio.eval.demo_score`: how far it is from the
demonstrations the policy learnt from, against the policy's calibrated threshold), so that the UI can warn before
a meaningless demonstration's plan is executed.

Planning and decoding are :mod:`studio.eval` (:func:`~studio.eval.planners.load_planner`,
:func:`~studio.eval.latents.decode_latents`, which finds a checkpoint's decoder by convention); this module is the
job's handler and the file it writes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
import numpy as np

from studio.backend.messages import ContentId
from studio.backend.spec_paths import checkpoint_path
from studio.data.atomic_files import atomic_write
from studio.eval.latents import decode_latents, find_decoder

PLANS_DIR = "plans"

#: A checkpoint path or "oracle"; an episode id; a task name.
PathText = Annotated[str, msgspec.Meta(min_length=1, max_length=4096)]
Name = Annotated[str, msgspec.Meta(min_length=1, max_length=200)]
SceneSeed = Annotated[int, msgspec.Meta(ge=0, le=2**63 - 1)]


class PlanJobSpec(msgspec.Struct, forbid_unknown_fields=True):
    """What a ``plan`` job plans: ``checkpoint`` (path or ``"oracle"``) imitating the stored demonstration
    ``expert_episode_id`` on ``task`` with scene ``seed``, for ``robot`` (the Panda; the Sawyer in Meta-World);
    ``inputs``: the content id of the files it reads, for a worker with its own data dir
    (:mod:`studio.backend.artifact_transfer`)."""

    checkpoint: PathText
    expert_episode_id: Name
    task: Name
    seed: SceneSeed
    robot: Literal["panda", "sawyer"] = "panda"
    inputs: ContentId | None = None


def parse_spec(spec: dict[str, Any]) -> PlanJobSpec:
    """The spec as a :class:`PlanJobSpec`; ``ValueError`` naming what is missing or wrong."""
    missing = [k for k in ("checkpoint", "expert_episode_id", "task", "seed") if k not in spec]
    if missing:
        raise ValueError(f"plan job spec lacks {missing}")
    try:
        return msgspec.convert(spec, PlanJobSpec)
    except msgspec.ValidationError as e:
        raise ValueError(f"invalid plan job spec: {e}") from None


def checked_checkpoint(data_dir: Path | None, checkpoint: str, kind: str) -> str:
    """The spec's checkpoint as the worker loads it: ``"oracle"``, or a file in its data dir (a relative path is
    taken from there) or a shipped policy; ``SpecPathError`` (a ValueError) for anything else."""
    resolved = checkpoint_path(data_dir, checkpoint, "checkpoint", kind)
    return checkpoint if checkpoint == "oracle" or Path(checkpoint).is_absolute() else resolved


def expert_indices(n_frames: int, n: int = 10) -> np.ndarray:
    """The frames of an ``n_frames`` video the planner looks at: ``n`` evenly spaced, first and last kept."""
    if n_frames < 1:
        raise ValueError("the expert video has no frames")
    return np.round(np.linspace(0, n_frames - 1, n)).astype(np.int64)


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda f: np.savez_compressed(f, allow_pickle=False, **arrays))


def run_plan_job(ctx) -> dict[str, Any]:
    """Spec: :class:`PlanJobSpec`. Returns the plan file (relative to the data dir) and a summary, with the
    demonstration's score (``demo_score``: :func:`studio.eval.demo_score.worker_score`) and the time it took."""
    import time

    from studio.data.store import EpisodeStore
    from studio.eval.demo_score import worker_score
    from studio.eval.planners import load_planner, process_cached
    from studio.sim.env import make_env
    from studio.sim.tasks import get_task
    from studio.sim.waypoints import commanded_waypoints

    parsed = parse_spec(dict(ctx.spec))
    if ctx.data_dir is None:
        raise ValueError("plan jobs need a worker started with --data-dir (the store with the demonstration)")
    checkpoint = checked_checkpoint(ctx.data_dir, parsed.checkpoint, "plan")
    task = get_task(parsed.task)
    robot = parsed.robot
    if checkpoint != "oracle" and not Path(checkpoint).is_file():
        raise ValueError(f"checkpoint {checkpoint} does not exist on worker {ctx.worker}")
    store = process_cached(("store", str(ctx.data_dir)), lambda: EpisodeStore(ctx.data_dir))
    ctx.progress(0, 3, message="resetting the scene")
    env = make_env(task.scene, robot)  # this job's own: its EGL context belongs to this thread
    try:
        env.reset(task.name, parsed.seed)
        frame = env.render("external")
        cam = env.camera_model("external")
        expert = store.load_frames(parsed.expert_episode_id)
        ctx.progress(1, 3, message="planning")
        planner = load_planner(checkpoint, env)
        if hasattr(planner, "clear_cache"):
            planner.clear_cache()
        t0 = time.perf_counter()
        plan = planner.plan(expert, frame, cam.K, cam.T_world_cam)
        seconds = time.perf_counter() - t0
        commanded = commanded_waypoints(env, plan.waypoints_world)
    finally:
        env.close()
    n_seen = int(getattr(getattr(planner, "cfg", None), "n_expert_frames", 10))
    arrays = {
        "waypoints_world": np.asarray(plan.waypoints_world, dtype=np.float64),
        "waypoints_cam": np.asarray(plan.waypoints_cam, dtype=np.float64),
        "waypoints_commanded": commanded,
        "agent_frame": frame,
        "expert_indices": expert_indices(len(expert), n_seen),
        "K": np.asarray(cam.K, dtype=np.float64),
        "T_world_cam": np.asarray(cam.T_world_cam, dtype=np.float64),
    }
    null = getattr(plan, "null_waypoints_world", None)
    guidance = None
    if null is not None:  # a guided policy: its plan from the scene alone, and whether it guided this one
        arrays["null_waypoints_world"] = np.asarray(null, dtype=np.float64)
        cfg = planner.cfg
        gain = getattr(plan, "guidance_gain", None)
        surprise = getattr(plan, "guidance_surprise", None)
        guidance = {
            "scale": float(getattr(plan, "guidance_scale", None) or cfg.guidance),
            "gate": float(cfg.guidance_gate),
            "gain": None if gain is None else float(gain),
            "guided": bool(getattr(plan, "guided", True)),
        }
        if surprise is not None:  # a policy with a surprise gate
            guidance["surprise"] = float(surprise)
            guidance["surprise_gate"] = float(getattr(cfg, "surprise_gate", 0.0))
    decoded = 0
    pooled = getattr(plan, "pooled_states", None)
    if checkpoint != "oracle" and pooled is not None:
        ctx.progress(2, 3, message="decoding the latent trajectory")
        images = decode_latents(checkpoint, pooled)
        if images is not None:
            arrays["latent_images"] = images
            decoded = len(images)
    t0 = time.perf_counter()
    if checkpoint == "oracle":
        demo_score: dict[str, Any] = {
            "unavailable": "the oracle plans from the simulator, not the demonstration"
        }
    else:
        demo_score = worker_score(planner.model, checkpoint, parsed.expert_episode_id, expert, store)
    score_seconds = time.perf_counter() - t0
    ctx.raise_if_cancelled()
    rel = Path(PLANS_DIR) / f"{ctx.job}.npz"
    _write_npz(Path(ctx.data_dir) / rel, arrays)
    # To the hub's data dir, where the studio reads it, when it is not this worker's.
    ctx.output(Path(ctx.data_dir) / rel)
    ctx.progress(3, 3, message="planned")
    return {
        "path": str(rel),
        "planning_time_s": seconds,
        "latent_images": decoded,
        "decoder": None if checkpoint == "oracle" else (str(find_decoder(checkpoint) or "") or None),
        "gripper_closed": [bool(g > 0.5) for g in arrays["waypoints_world"][:, 3]],
        "guidance": guidance,
        "demo_score": demo_score,
        "demo_score_time_s": score_seconds,
    }
