"""The ``expert`` job of a sim worker: record one scripted expert demonstration and store it.

The UI's *Imitate* panel offers "scripted" demonstrations next to recorded and uploaded ones; this job
makes one on a sim worker (the scene's scripted expert, the same recorder ``studio collect`` uses) and
stores it as an expert episode (source ``scripted``). A scripted expert that fails on the seed stores
nothing and fails the job with the reason, so the user can pick another seed.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec


class ExpertJobSpec(msgspec.Struct, forbid_unknown_fields=True):
    """What an ``expert`` job records: the scripted ``robot`` expert on ``task`` with scene ``seed``."""

    task: Annotated[str, msgspec.Meta(min_length=1, max_length=200)]
    seed: Annotated[int, msgspec.Meta(ge=0, le=2**63 - 1)]
    robot: Literal["sawyer", "panda", "hand"] = "sawyer"


def parse_spec(spec: Any) -> ExpertJobSpec:
    """The spec as an :class:`ExpertJobSpec`; ``ValueError`` naming what is missing or wrong."""
    try:
        return msgspec.convert(spec, ExpertJobSpec)
    except msgspec.ValidationError as e:
        raise ValueError(f"invalid expert job spec: {e}") from None


def run_expert_job(ctx) -> dict[str, Any]:
    """Spec: :class:`ExpertJobSpec`. Returns the stored episode's id."""
    from studio.data.collect import DEFAULT_RECORDER, MIN_FRAMES, RECORDER_OF_SCENE, load_recorder
    from studio.data.store import EpisodeStore
    from studio.eval.planners import process_cached
    from studio.sim.env import default_image_size
    from studio.sim.tasks import get_task

    spec = parse_spec(dict(ctx.spec))
    if ctx.data_dir is None:
        raise ValueError(
            "expert jobs need a worker started with --data-dir (the store to add the episode to)"
        )
    task = get_task(spec.task)
    robot, seed = spec.robot, spec.seed
    record = load_recorder(RECORDER_OF_SCENE.get(task.scene, DEFAULT_RECORDER))
    ctx.progress(0, 2, message=f"scripted {robot} expert on {task.name}, seed {seed}")
    recording = record(task.scene, robot, task.name, seed, default_image_size(task.scene), MIN_FRAMES)
    ctx.raise_if_cancelled()
    if not recording.success:
        raise ValueError(
            f"the scripted expert did not succeed on {task.name} with seed {seed}; try another seed"
        )
    store = process_cached(("store", str(ctx.data_dir)), lambda: EpisodeStore(ctx.data_dir))
    ctx.progress(1, 2, message="storing the demonstration")
    meta = store.add_episode(recording, role="expert", source="scripted", extra={"job": ctx.job})
    ctx.output_episode(meta.id)  # to the hub's store, when the worker's data dir is its own
    ctx.progress(2, 2, message="stored")
    return {"episode_id": meta.id, "task": meta.task, "frames": meta.num_frames, "steps": meta.num_steps}
