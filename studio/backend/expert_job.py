"""The ``expert`` job of a sim worker: record one scripted expert demonstration and store it.

The UI's *Imitate* panel offers "scripted" demonstrations next to recorded and uploaded ones; this job
makes one on a sim worker (the scene's scripted expert, the same recorder ``studio collect`` uses) and
stores it as an expert episode (source ``scripted``). A scripted expert that fails on the seed stores
nothing and fails the job with the reason, so the user can pick another seed.
"""

from __future__ import annotations

from typing import Any


def run_expert_job(ctx) -> dict[str, Any]:
    """Spec: ``task``, ``seed``, ``robot`` (default ``"sawyer"``). Returns the stored episode's id."""
    from studio.data.collect import DEFAULT_RECORDER, MIN_FRAMES, RECORDER_OF_SCENE, load_recorder
    from studio.data.store import EpisodeStore
    from studio.eval.planners import process_cached
    from studio.sim.env import default_image_size
    from studio.sim.tasks import get_task

    spec = dict(ctx.spec)
    missing = [k for k in ("task", "seed") if k not in spec]
    if missing:
        raise ValueError(f"expert job spec lacks {missing}")
    if ctx.data_dir is None:
        raise ValueError(
            "expert jobs need a worker started with --data-dir (the store to add the episode to)"
        )
    task = get_task(str(spec["task"]))
    robot = str(spec.get("robot", "sawyer"))
    seed = int(spec["seed"])
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
    ctx.progress(2, 2, message="stored")
    return {"episode_id": meta.id, "task": meta.task, "frames": meta.num_frames, "steps": meta.num_steps}
